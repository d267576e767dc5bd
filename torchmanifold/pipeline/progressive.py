"""The progressive loop of a whole clip: one more sample per pixel per frame each iteration.

Iteration ``i`` (1-based) renders sample ``i-1`` of every frame, filters every frame with its
neighbours in time (Gaussian weights) guided by the per-sample features at the bandwidth of the
schedule (``sigma_i^2 / sigma_{i-1}^2 = (i-1+a)/i``), and adds the result into a running average:

    ours_n = (1/n) sum_{i<=n} filter_i(samples_i)

As the bandwidth shrinks the filter tends to the identity, so the running average converges to the
true image like the raw average does (consistency), but starts from a far better estimate.

Memory is bounded by the time window: frames are rendered in order into a ring of ``2r+1`` frames;
frame ``t`` is filtered as soon as frame ``t+r`` has arrived, and only its running sums (ours, the raw
average and the Gaussian-filtered baseline, 3 channels each) are kept per frame.
"""
from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Sequence

import torch
from torch import Tensor

from torchmanifold.pipeline.denoise import DenoiseSettings, denoise_frames
from torchmanifold.pipeline.schedule import DEFAULT_ALPHA, BandwidthSchedule

__all__ = ["ProgressiveRenderer", "ProgressiveState", "gaussian_baseline"]


def gaussian_baseline(color: Tensor, sigma: float) -> Tensor:
    """kornia ``gaussian_blur2d`` of ``(N, 3, H, W)`` radiance with ``sigma`` pixels (kernel +-3 sigma)."""
    import kornia

    if sigma <= 0.3:
        return color
    k = 2 * int(math.ceil(3 * sigma)) + 1
    return kornia.filters.gaussian_blur2d(color, (k, k), (sigma, sigma), border_type="replicate")


@dataclass
class ProgressiveState:
    """The clip after ``iteration`` iterations (all ``(Q, 3, H, W)`` at the query times).

    Attributes:
        iteration: iterations done (= samples per pixel per frame).
        ours: running average of the adaptive-manifold-filtered iterations.
        raw: running average of the samples (plain progressive path tracing).
        gaussian: running average of Gaussian-filtered samples (same schedule, no features).
        sigma_s: spatial bandwidth used at this iteration.
        seconds: wall time of this iteration (render + filter), and ``render_seconds`` of it rendering.
        stats: counters from the filter (non-finite samples, firefly energy removed).
    """

    iteration: int
    ours: Tensor
    raw: Tensor
    gaussian: Tensor
    sigma_s: float
    seconds: float
    render_seconds: float
    stats: dict


class ProgressiveRenderer:
    """Progressive rendering + filtering of a clip, one iteration per :meth:`step`.

    Args:
        tracer: a :class:`~torchmanifold.render.PathTracer` (``render(times, spp, seed, sample_offset)``).
        times: the frame times to render (frame units, increasing, spaced 1 apart for the window).
        query_times: times to output (default ``times``); times between frames give in-between frames
            (rendered frames' samples and guides, interpolated by the temporal filter).
        settings: :class:`DenoiseSettings` of iteration 1 (sigma_s, guide sigmas, firefly, time window).
        alpha: the ``a`` of the bandwidth schedule.
        seed: RNG seed of the tracer.
        firefly_growth: the firefly clamp's multiple grows as ``k * i ** firefly_growth`` so the clamp's
            bias vanishes with iterations.
        gaussian_sigma: spatial sigma of the Gaussian baseline at iteration 1 (default 1 pixel,
            a good setting for it); it shrinks with the same schedule.

    Example:
        >>> pr = ProgressiveRenderer(PathTracer(default_scene(), 32, 32), times=[0, 1, 2])  # doctest: +SKIP
        >>> state = pr.step(); state.ours.shape                                               # doctest: +SKIP
        torch.Size([3, 3, 32, 32])
    """

    def __init__(self, tracer, times: Sequence[float], query_times: Sequence[float] | None = None,
                 settings: DenoiseSettings | None = None, alpha: float = DEFAULT_ALPHA, seed: int = 0,
                 firefly_growth: float = 0.5, gaussian_sigma: float | None = None, progress=None):
        if not hasattr(tracer, "render"):
            raise TypeError(f"tracer must have a render(times, spp, seed, sample_offset) method, got "
                            f"{type(tracer).__name__}")
        times = [float(t) for t in times]
        if not times or any(not math.isfinite(t) for t in times) or any(b <= a for a, b in zip(times, times[1:])):
            raise ValueError(f"times must be a non-empty increasing sequence of finite numbers, got {times}")
        self.tracer = tracer
        self.times = times
        self.query_times = times if query_times is None else [float(q) for q in query_times]
        if not self.query_times or any(not math.isfinite(q) for q in self.query_times):
            raise ValueError("query_times must be a non-empty sequence of finite numbers")
        self.settings = (settings or DenoiseSettings(temporal_radius=1, mode="spacetime")).check()
        self.schedule = BandwidthSchedule(self.settings.sigma_s, 1.0, alpha)
        self.gaussian_sigma = 1.0 if gaussian_sigma is None else float(gaussian_sigma)
        self.seed = int(seed)
        self.firefly_growth = float(firefly_growth)
        self.iteration = 0
        self.progress = progress  # optional callable(frames_done) for progress bars
        self._sum_ours: Tensor | None = None
        self._sum_raw: Tensor | None = None
        self._sum_gauss: Tensor | None = None
        self.history: list[ProgressiveState] = []

    # -- queries to the frames they need --------------------------------------------------------------
    def _needed(self, q: float) -> list[int]:
        r = self.settings.temporal_radius
        ids = [k for k, t in enumerate(self.times) if abs(t - q) <= r + 1e-9]
        below = [k for k, t in enumerate(self.times) if t <= q]
        above = [k for k, t in enumerate(self.times) if t >= q]
        if below:
            ids.append(below[-1])
        if above:
            ids.append(above[0])
        return sorted(set(ids))

    def _render(self, k: int, i: int):
        res = self.tracer.render(times=[self.times[k]], spp=1, seed=self.seed, sample_offset=i - 1)
        return res

    def step(self) -> ProgressiveState:
        """Run one iteration over the whole clip and return the updated :class:`ProgressiveState`."""
        i = self.iteration + 1
        t0 = time.perf_counter()
        render_s = 0.0
        sig_s = self.schedule.sigma_s(i)
        rscale = self.schedule.sigma_r(i)
        settings = replace(self.settings, sigma_s=sig_s)
        k_ff = self.settings.firefly_k * i ** self.firefly_growth
        ours, raw, gauss = [], [], []
        ring: "OrderedDict[int, object]" = OrderedDict()  # frame index -> render result (bounded window)
        stats_all: dict = {}
        prev = None if self._sum_ours is None else self._sum_ours / (i - 1)
        for qi, q in enumerate(self.query_times):
            need = self._needed(q)
            for k in need:
                if k not in ring:
                    tr = time.perf_counter()
                    ring[k] = self._render(k, i)
                    render_s += time.perf_counter() - tr
            for k in [k for k in ring if k < need[0]]:  # frames behind the window are done
                del ring[k]
            rs = [ring[k] for k in need]
            color = torch.cat([r.color for r in rs])
            feats = torch.cat([r.features for r in rs])
            emis = torch.cat([r.emission for r in rs])
            names = list(rs[0].feature_names)
            pilot = None
            if prev is not None:  # the running estimate is a far better firefly pilot than one sample
                pilot = torch.stack([self._pilot_at(prev, k) for k in need])
            y, st = denoise_frames(color, feats, names, emis, settings, sigma_s=sig_s, range_scale=rscale,
                                   frame_times=[self.times[k] for k in need], query_times=[q], pilot=pilot,
                                   firefly_k=k_ff, return_stats=True)
            for key, v in st.items():
                stats_all[key] = stats_all.get(key, 0) + v
            ours.append(y[0])
            x = self._at(color, [self.times[k] for k in need], q)
            raw.append(x)
            gauss.append(gaussian_baseline(x[None], self.gaussian_sigma * self.schedule.factor(i))[0])
            if self.progress is not None:
                self.progress(1)
        ours, raw, gauss = torch.stack(ours), torch.stack(raw), torch.stack(gauss)
        if self._sum_ours is None:
            self._sum_ours, self._sum_raw, self._sum_gauss = ours.double(), raw.double(), gauss.double()
        else:
            self._sum_ours += ours
            self._sum_raw += raw
            self._sum_gauss += gauss
        self.iteration = i
        n_q = len(self.query_times)
        stats_all["firefly_energy_removed"] = stats_all.get("firefly_energy_removed", 0.0) / n_q
        state = ProgressiveState(i, (self._sum_ours / i).float(), (self._sum_raw / i).float(),
                                 (self._sum_gauss / i).float(), sig_s, time.perf_counter() - t0, render_s,
                                 stats_all)
        self.history.append(state)
        return state

    def _pilot_at(self, prev: Tensor, k: int) -> Tensor:
        """The running estimate at frame k (nearest query; queries usually are the frames)."""
        t = self.times[k]
        j = min(range(len(self.query_times)), key=lambda m: abs(self.query_times[m] - t))
        return prev[j].float()

    @staticmethod
    def _at(x: Tensor, ft: list[float], q: float) -> Tensor:
        """A frame of ``x`` (N, C, H, W) at time q: the frame itself or a lerp of the bracketing two."""
        if q in ft:
            return x[ft.index(q)]
        below = [k for k, t in enumerate(ft) if t <= q]
        above = [k for k, t in enumerate(ft) if t >= q]
        if not below or not above:
            return x[(below or above)[-1 if below else 0]]
        i0, i1 = below[-1], above[0]
        return torch.lerp(x[i0], x[i1], (q - ft[i0]) / (ft[i1] - ft[i0]))

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
        return max(len(self._needed(q)) for q in self.query_times)
