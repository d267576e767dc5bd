"""The progressive engine of a whole clip: one more sample per pixel per frame each iteration.

Iteration ``i`` (1-based) renders sample ``i-1`` of every frame, filters every query time with its
neighbour frames in time (Gaussian weights) guided by the per-sample features at the bandwidth of the
schedule (``sigma_i^2 / sigma_{i-1}^2 = (i-1+a)/i``), and adds the result into a running average:

    ours_n = (1/n) sum_{i<=n} filter_i(samples_i)

As the bandwidth shrinks the filter tends to the identity, so the running average converges to the
true image like the raw average does (consistency), but starts from a far better estimate.

Memory is bounded by the time window: frames are rendered in order and held while a window needs them
(:class:`~torchmanifold.pipeline.sliding.SlidingFrames`, ``2r+1`` frames);
a query time is filtered as soon as the last frame of its window has arrived, and only its running
sums (ours, the raw average and the Gaussian-filtered baseline, 3 channels each) are kept.

The render job, the benchmarks and the demo all drive this one object:

- :meth:`ProgressiveRenderer.step` runs one iteration;
- :meth:`ProgressiveRenderer.estimate` reads the current estimate at any frame or in-between time;
- :meth:`ProgressiveRenderer.set_settings` and the :attr:`~ProgressiveRenderer.schedule` property
  change settings; changes take effect at the next step, the iterations done stay in the averages;
- :meth:`ProgressiveRenderer.track` / :meth:`~ProgressiveRenderer.untrack` add or drop query times,
  :meth:`ProgressiveRenderer.restart` drops all samples.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import torch
from torch import Tensor

from torchmanifold._threads import InOrder, caller_threads, serial
from torchmanifold.pipeline.denoise import DenoiseSettings, FrameState, denoise_window_states, prepare_frames
from torchmanifold.pipeline.footprint import footprint_width
from torchmanifold.pipeline.schedule import DEFAULT_ALPHA, BandwidthSchedule
from torchmanifold.pipeline.selection import ClipCache
from torchmanifold.pipeline.sliding import SlidingFrames
from torchmanifold.timewindow import frame_at, interpolate, window

__all__ = ["ProgressiveRenderer", "ProgressiveState", "gaussian_baseline", "ESTIMATES"]

#: the running estimates the engine keeps per query time, in this order
ESTIMATES = ("ours", "raw", "gaussian")
#: the loop's filter where it differs from :class:`DenoiseSettings`' defaults: neighbour frames join in
#: space-time; the cheaper tree height, since the estimate is filtered every iteration; a more decisive
#: bandwidth selection (softness 0.7), which keeps a thin caustic from being blended with the wide
#: candidates around it. Built-in scene against softness 1: 96x96 and 128x128 (4 frames, 10 iterations)
#: +0.03 / +0.03 dB, caustic energy 0.72 -> 0.78 / 0.75; the render job's default (256x256, 8 frames, 16
#: iterations) -0.02 dB. Softness 0.5: -0.04 / +0.04 / -0.07 dB, caustic 0.80 / 0.78. The window's candidates
#: alone: the tracer's features tell its frames apart, and each frame's own narrowest candidate beside them
#: measured -0.10 / -0.08 dB at 96x96 / 128x128 (caustic 0.868 -> 0.875, 0.785 -> 0.801). +-2 frames against
#: +-1, as the ``denoise`` command joins: 96x96 (4 frames, 10 iterations) 28.66 -> 28.83 dB, the render job's
#: default 31.57 -> 31.65 (inside the moving object +0.34, caustic energy 0.913 -> 0.932) in 40 s against 39
PROGRESSIVE_FILTER = dict(temporal_radius=2, mode="spacetime", tree_height=2, selection_softness=0.7,
                          frame_alone_bandwidths=())
#: how "ours" is built: filter the running mean of the samples at the shrinking bandwidth
#: ("accumulate"), or average filtered 1-spp iterations (the paper's scheme, "average")
SCHEMES = ("accumulate", "average")


def gaussian_baseline(color: Tensor, sigma: float) -> Tensor:
    """kornia ``gaussian_blur2d`` of ``(N, 3, H, W)`` radiance with ``sigma`` pixels (kernel +-3 sigma)."""
    import kornia

    if sigma <= 0.3:
        return color
    k = 2 * int(math.ceil(3 * sigma)) + 1
    return kornia.filters.gaussian_blur2d(color, (k, k), (sigma, sigma), border_type="replicate")


@dataclass
class ProgressiveState:
    """The clip after ``iteration`` iterations (all ``(Q, 3, H, W)`` at ``query_times``).

    Attributes:
        iteration: iterations done (= samples per pixel per frame).
        ours: running average of the adaptive-manifold-filtered iterations.
        raw: running average of the samples (plain progressive path tracing).
        gaussian: running average of Gaussian-filtered samples (same schedule, no features).
        sigma_s: spatial bandwidth used at this iteration.
        seconds: wall time of this iteration (render + filter), and ``render_seconds`` of it rendering.
        stats: counters from the filter (non-finite samples, firefly energy removed).
        query_times: the ``Q`` times of the rows.
    """

    iteration: int
    ours: Tensor
    raw: Tensor
    gaussian: Tensor
    sigma_s: float
    seconds: float
    render_seconds: float
    stats: dict
    query_times: list[float] = field(default_factory=list)


def _finite(name: str, v, lo: float) -> float:
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v < lo:
        raise ValueError(f"{name} must be a finite number >= {lo}, got {v!r}")
    return float(v)


class ProgressiveRenderer:
    """Progressive rendering + filtering of a clip, one iteration per :meth:`step`.

    Args:
        tracer: a :class:`~torchmanifold.render.PathTracer` (``render(times, spp, seed, sample_offset)``).
        times: the frame times to render (frame units, increasing).
        query_times: times to output (default ``times``); times between frames give in-between frames
            (rendered frames' samples and guides, interpolated by the temporal filter).
        settings: :class:`DenoiseSettings` of iteration 1 (sigma_s, guide sigmas, firefly, time window).
        alpha: the ``a`` of the bandwidth schedule.
        seed: RNG seed of the tracer.
        firefly_growth: the firefly clamp's multiple grows as ``k * i ** firefly_growth`` so the clamp's
            bias vanishes with iterations.
        gaussian_sigma: spatial sigma of the Gaussian baseline at iteration 1 (default 1 pixel,
            a good setting for it); it shrinks with the same schedule.
        progress: optional ``callable(n)`` called after each query time is filtered (progress bars).
        on_render: optional ``callable(frame_index, render_result)`` called for every frame rendered,
            e.g. to keep the mean of its feature buffers.
        range_scale: multiplier of every range sigma at iteration 1 (the schedule's ``sigma_r``); it
            shrinks with the same schedule.
        scheme: ``"accumulate"`` filters the running mean of each frame's samples (and of its features)
            at the iteration's bandwidth, so each iteration's filter sees n spp and the pixel-mean
            albedo; ``"average"`` is the paper's literal scheme, the running average of independently
            filtered 1-spp iterations. Both tend to the raw mean as the bandwidth shrinks (consistent);
            ``benchmarks/bench_progressive_schemes.py`` measures them against each other.

    Example:
        >>> pr = ProgressiveRenderer(PathTracer(default_scene(), 32, 32), times=[0, 1, 2])  # doctest: +SKIP
        >>> state = pr.step(); state.ours.shape                                               # doctest: +SKIP
        torch.Size([3, 3, 32, 32])
        >>> pr.set_settings(sigma_s=2.0); pr.estimate(0.5).shape                              # doctest: +SKIP
        torch.Size([3, 32, 32])
    """

    def __init__(self, tracer, times: Sequence[float], query_times: Sequence[float] | None = None,
                 settings: DenoiseSettings | None = None, alpha: float = DEFAULT_ALPHA, seed: int = 0,
                 firefly_growth: float = 0.5, gaussian_sigma: float | None = None,
                 progress: Callable[[int], object] | None = None,
                 on_render: Callable[[int, object], object] | None = None, range_scale: float = 1.0,
                 scheme: str = "accumulate"):
        if not hasattr(tracer, "render"):
            raise TypeError(f"tracer must have a render(times, spp, seed, sample_offset) method, got "
                            f"{type(tracer).__name__}")
        times = [float(t) for t in times]
        if not times or any(not math.isfinite(t) for t in times) or any(b <= a for a, b in zip(times, times[1:])):
            raise ValueError(f"times must be a non-empty increasing sequence of finite numbers, got {times}")
        self.tracer = tracer
        self.times = times
        self._query_times = list(times) if query_times is None else [float(q) for q in query_times]
        if not self._query_times or any(not math.isfinite(q) for q in self._query_times):
            raise ValueError("query_times must be a non-empty sequence of finite numbers")
        self._settings = (settings or DenoiseSettings(**PROGRESSIVE_FILTER)).check()
        self._schedule = BandwidthSchedule(self._settings.sigma_s, range_scale, alpha)
        self.gaussian_sigma = 1.0 if gaussian_sigma is None else _finite("gaussian_sigma", gaussian_sigma, 0.0)
        self.firefly_growth = _finite("firefly_growth", firefly_growth, 0.0)
        if scheme not in SCHEMES:
            raise ValueError(f"scheme: expected one of {SCHEMES}, got {scheme!r}")
        self.scheme = scheme
        self.seed = int(seed)
        self.progress = progress
        self.on_render = on_render
        self.restart()

    # -- settings -----------------------------------------------------------------------------------
    @property
    def settings(self) -> DenoiseSettings:
        """The :class:`DenoiseSettings` of the next step (``sigma_s`` is that of iteration 1)."""
        return self._settings

    @settings.setter
    def settings(self, settings: DenoiseSettings) -> None:
        self.set_settings(settings)

    @property
    def schedule(self) -> BandwidthSchedule:
        """The bandwidth schedule: ``sigma_s`` (pixels) and the range scale of every iteration."""
        return self._schedule

    @schedule.setter
    def schedule(self, schedule: BandwidthSchedule) -> None:
        if not isinstance(schedule, BandwidthSchedule):
            raise TypeError(f"schedule must be a BandwidthSchedule, got {type(schedule).__name__}")
        self._settings = replace(self._settings, sigma_s=schedule.sigma_s0).check()
        self._schedule = schedule

    @property
    def alpha(self) -> float:
        return self._schedule.alpha

    def set_settings(self, settings: DenoiseSettings | None = None, **changes) -> None:
        """Change settings from the next :meth:`step` on; the iterations done stay in the averages.

        Args:
            settings: a whole new :class:`DenoiseSettings` (optional).
            **changes: fields of :class:`DenoiseSettings` (``sigma_s``, ``temporal_radius``, ``guide``, ...)
                and of the engine: ``alpha``, ``range_scale`` (the schedule's ``sigma_r``),
                ``gaussian_sigma``, ``firefly_growth``.

        Raises:
            TypeError: an unknown setting (named); ValueError: a bad value (named). Nothing changes then.
        """
        new = self._settings if settings is None else settings
        if not isinstance(new, DenoiseSettings):
            raise TypeError(f"settings must be a DenoiseSettings, got {type(new).__name__}")
        engine = {k: changes.pop(k) for k in ("alpha", "range_scale", "gaussian_sigma", "firefly_growth")
                  if k in changes}
        known = {f.name for f in dataclasses.fields(DenoiseSettings)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise TypeError(f"set_settings: unknown setting(s) {unknown}; expected fields of DenoiseSettings "
                            f"{sorted(known)} or alpha, range_scale, gaussian_sigma, firefly_growth")
        new = replace(new, **changes).check()
        sched = {"sigma_s": new.sigma_s}
        if "alpha" in engine:
            sched["alpha"] = engine["alpha"]
        if "range_scale" in engine:
            sched["sigma_r"] = engine["range_scale"]
        schedule = self._schedule.replace(**sched)
        gs = _finite("gaussian_sigma", engine.get("gaussian_sigma", self.gaussian_sigma), 0.0)
        fg = _finite("firefly_growth", engine.get("firefly_growth", self.firefly_growth), 0.0)
        self._settings, self._schedule, self.gaussian_sigma, self.firefly_growth = new, schedule, gs, fg

    # -- query times --------------------------------------------------------------------------------
    @property
    def query_times(self) -> list[float]:
        """The times whose running estimates are kept (the rows of :class:`ProgressiveState`)."""
        return list(self._query_times)

    def track(self, t: float) -> None:
        """Keep a running estimate at time ``t`` from now on (nothing happens if it is kept already).

        A time joining after iteration ``n`` starts from :meth:`estimate` at ``t`` (the interpolation of
        the kept neighbours) weighted as the ``n`` iterations it missed; its own filtered iterations are
        added from the next step. For raw and Gaussian this start is exact when the neighbours are the
        frames bracketing ``t`` (both are linear in the frames); for ours it fades as n / (n + m) after
        m more iterations.
        """
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"t must be a finite time, got {t}")
        if frame_at(self._query_times, t) is not None:
            return
        if self._sums is not None:
            start = torch.stack([self._estimate64(t, kind) for kind in ESTIMATES]) * self.iteration
            self._sums = torch.cat([self._sums, start[None]])
        self._query_times.append(t)

    def untrack(self, t: float) -> None:
        """Stop keeping the running estimate at time ``t`` (a kept time; at least one must stay)."""
        j = frame_at(self._query_times, float(t))
        if j is None:
            raise ValueError(f"t: {t} is not a kept query time {self._query_times}")
        if len(self._query_times) == 1:
            raise ValueError("t: the last query time cannot be dropped")
        del self._query_times[j]
        if self._sums is not None:
            self._sums = torch.cat([self._sums[:j], self._sums[j + 1:]])

    def restart(self) -> None:
        """Drop all samples: the next step is iteration 1 again (settings and query times stay)."""
        self.iteration = 0
        self._sums: Tensor | None = None  # (Q, len(ESTIMATES), 3, H, W) float64 running sums
        self._frame_sums: dict[int, Tensor] = {}  # accumulate: frame -> sum of [colour, features, emission]
        self.history: list[ProgressiveState] = []

    # -- estimates ----------------------------------------------------------------------------------
    def _estimate64(self, t: float, kind: str) -> Tensor:
        if self._sums is None:
            raise RuntimeError("estimate: no iteration has run yet; call step() first")
        if kind not in ESTIMATES:
            raise ValueError(f"kind must be one of {ESTIMATES}, got {kind!r}")
        return interpolate(self._sums[:, ESTIMATES.index(kind)], self._query_times, float(t)) / self.iteration

    def estimate(self, t: float, kind: str = "ours") -> Tensor:
        """The current estimate ``(3, H, W)`` at time ``t``.

        Args:
            t: any time; at a kept query time its running average, between two kept times the linear
                interpolation of theirs (:func:`torchmanifold.timewindow.interpolate`), outside them
                the nearest end's. :meth:`track` ``t`` to filter at ``t`` itself from the next step.
            kind: ``"ours"``, ``"raw"`` or ``"gaussian"``.
        """
        return self._estimate64(t, kind).float()

    # -- the iteration ------------------------------------------------------------------------------
    def _needed(self, q: float) -> list[int]:
        return window(self.times, q, self._settings.query_radius)

    def _accumulate(self, k: int, res) -> None:
        parts = (res.color, res.features, res.emission)
        if k not in self._frame_sums:
            self._frame_sums[k] = torch.cat(parts, 1)[0].double()
            return
        total, c = self._frame_sums[k], 0
        for p in parts:  # in place, part by part: no concatenated copy of the frame
            total[c:c + p.shape[1]] += p[0]
            c += p.shape[1]

    def _render(self, k: int, i: int):
        res = self.tracer.render(times=[self.times[k]], spp=1, seed=self.seed, sample_offset=i - 1)
        if self.on_render is not None:
            self.on_render(k, res)
        return res

    def iteration_settings(self, i: int) -> DenoiseSettings:
        """The filter's settings at iteration ``i`` (1-based): every bandwidth shrinks with the schedule.

        The spatial sigma follows the schedule; the pixel footprint and the pooling of the bandwidth
        selection's errors are spatial bandwidths too and shrink by the same factor, so the filter tends
        to the identity (consistency) and each pixel's error estimate pools over fewer pixels as their
        samples grow. The time sigma shrinks by the square root of the factor: neighbour frames are most
        of the samples early on.
        """
        # measured on the built-in scene (benchmarks/validation/findings.md): time at the spatial rate lost
        # 0.6 dB after 10 iterations and not shrinking it gained 0.2; the selection's pooling at the spatial
        # rate gained 0.10-0.16 dB after 4 to 16 iterations (96x96 and 128x128, 4 frames) against 4 px fixed,
        # and lost 0.04 on the render job's default (256x256, 8 frames, 16 iterations)
        shrink = self._schedule.factor(i)
        return replace(self._settings, sigma_s=self._schedule.sigma_s(i),
                       footprint_sigma=footprint_width(self._settings, None) * shrink,
                       selection_blur=self._settings.selection_blur * shrink,
                       sigma_t=self._settings.sigma_t * shrink ** 0.5)

    @serial  # the C++ ops inside take the caller's threads (torchmanifold._threads)
    def step(self) -> ProgressiveState:
        """Run one iteration over the whole clip and return the updated :class:`ProgressiveState`."""
        i = self.iteration + 1
        t0 = time.perf_counter()
        render_s = 0.0
        settings = self.iteration_settings(i)
        sig_s = settings.sigma_s
        rscale = self._schedule.sigma_r(i)
        shrink = self._schedule.factor(i)
        k_ff = self._settings.firefly_k * i ** self.firefly_growth
        qt = self._query_times
        rows: list[Tensor | None] = [None] * len(qt)
        stats_all: dict = {}

        def render(k: int):
            nonlocal render_s
            tr = time.perf_counter()
            res = self._render(k, i)
            render_s += time.perf_counter() - tr
            if self.scheme == "accumulate":
                self._accumulate(k, res)
            return res

        def prepare(k: int, res) -> FrameState:
            if self.scheme == "accumulate":
                color, feats, emis = (self._frame_sums[k] / i).float()[None].split(
                    [3, len(res.feature_names), 3], 1)
            else:
                color, feats, emis = res.color, res.features, res.emission
            # the running estimate is a far better firefly pilot than one sample
            pilot = None if self._sums is None else self.estimate(self.times[k])[None]
            return prepare_frames(color, feats, list(res.feature_names), emis, settings, sig_s, rscale, pilot,
                                  k_ff, own_pixels=True)

        candidates = ClipCache()  # each query's candidates and the flows between frames, made once

        def filter_query(states: list, ft: list[float], q: float, samples: Tensor):
            y, state = denoise_window_states(states, settings, ft, q, sig_s, rscale, candidates)
            y = y.float()
            x = interpolate(samples, ft, q)
            gauss = gaussian_baseline(x[None], self.gaussian_sigma * shrink)[0]
            row = torch.empty((3, *x.shape), dtype=torch.float64)
            for r, img in zip(row, (y[0], x, gauss)):
                r.copy_(img)
            return row, state.stats()

        def collect(qi, row, st):  # in time order, so the stats sum in one order for any thread count
            rows[qi] = row
            for key, v in st.items():
                stats_all[key] = stats_all.get(key, 0) + v
            if self.progress is not None:
                self.progress(1)

        # Each frame is rendered and prepared once (sanitised, demodulated, guided, clamped) for every
        # window that holds it. Frames are independent once rendered, and query times once their frames
        # are prepared: with more than one thread both run side by side on worker threads that share the
        # caller's (the GL tracer stays on this one; a query waits on its frames' preparations, started
        # before it). The Python around a small frame's ops does not scale inside one call; across calls
        # it overlaps with the other's ops.
        with InOrder(caller_threads(), len(qt)) as pool:
            frames = SlidingFrames(render, lambda k, res: pool.ahead(prepare, k, res))
            for qi in sorted(range(len(qt)), key=lambda j: qt[j]):  # in time order: windows only move on
                q = qt[qi]
                need = self._needed(q)
                states = frames.prepared(need)
                ft = [self.times[k] for k in need]
                candidates.release_before(ft[0])  # the queries before this window lend it nothing
                samples = torch.cat([res.color for res in frames.frames(need)])
                for j, result in pool.submit(qi, filter_query, states, ft, q, samples):
                    collect(j, *result)
            for j, result in pool.drain():
                collect(j, *result)
        ours_row = ESTIMATES.index("ours")
        if self._sums is None:
            self._sums = torch.stack(rows)
        else:
            for total, row in zip(self._sums, rows):  # in place: no stacked copy of the clip
                total += row
        if self.scheme == "accumulate":  # "ours" is the latest filtered mean: i times itself in the sums
            for total, row in zip(self._sums, rows):
                torch.mul(row[ours_row], i, out=total[ours_row])
        self.iteration = i
        stats_all["firefly_energy_removed"] = stats_all.get("firefly_energy_removed", 0.0) / len(qt)
        avg = (self._sums / i).float()
        ours, raw, gauss = (avg[:, ESTIMATES.index(k)] for k in ("ours", "raw", "gaussian"))
        state = ProgressiveState(i, ours, raw, gauss, sig_s, time.perf_counter() - t0, render_s, stats_all,
                                 list(qt))
        self.history.append(state)
        return state

    def run(self, iterations: int) -> ProgressiveState:
        """Run ``iterations`` more iterations; returns the last state."""
        if not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"iterations must be an int >= 1, got {iterations!r}")
        for _ in range(iterations):
            state = self.step()
        return state

    @property
    def memory_frames(self) -> int:
        """Most rendered frames held at once (the time window), independent of the clip length."""
        return max(len(self._needed(q)) for q in self._query_times)
