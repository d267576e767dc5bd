"""The demo's session: the window's controls on the one progressive engine, plus what only the window needs.

The iterations are :class:`torchmanifold.pipeline.progressive.ProgressiveRenderer` steps, exactly what
``torchmanifold render`` runs. :func:`engine_settings` maps every control of :class:`FilterParams` onto
the engine's :meth:`~ProgressiveRenderer.set_settings`; a scrubbed in-between time is
:meth:`~ProgressiveRenderer.track` -ed and joins without a restart. Kept here beside the engine: the
PSNR curves against the reference, the mean feature buffers for the feature views (from the engine's
``on_render`` hook), the stage times and the torch thread count.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from demo.controls import FEATURE_GROUPS, FEATURE_SETS, SIGMA_R_UNSCALED, FilterParams
from torchmanifold import features as feature_table
from torchmanifold._threads import torch_threads
from torchmanifold.metrics import psnr
from torchmanifold.pipeline import DenoiseSettings
from torchmanifold.pipeline.progressive import ESTIMATES, ProgressiveRenderer
from torchmanifold.timewindow import frame_at, interpolate


def guide_channels(feature_set: str, feature_names) -> list[str]:
    """The channels of ``feature_set`` the scene provides that have a range sigma (not time ``T`` nor the
    ``caustic`` share); the ``"colour"`` set (no channels) guides by every such feature."""
    can_guide = [c for c in feature_names if feature_table.default_sigma(c) is not None]
    names = [c for g in FEATURE_SETS[feature_set] for c in FEATURE_GROUPS[g] if c in can_guide]
    return names or can_guide


def engine_settings(p: FilterParams, feature_names) -> dict:
    """The engine's :meth:`~ProgressiveRenderer.set_settings` arguments for the demo's controls."""
    return dict(
        sigma_s=p.sigma_s,
        range_scale=p.sigma_r / SIGMA_R_UNSCALED,
        alpha=p.a,
        temporal_radius=p.time_window,
        # a quarter of the window (2 sigma) each side; 0.5 frame floors it so an in-between time with
        # radius 0 still weighs its two neighbours
        sigma_t=max(p.time_window / 2.0, 0.5),
        mode=p.temporal_mode,
        tree_height=p.tree_height,
        guide=guide_channels(p.feature_set, feature_names) or None,
        firefly="clamp" if p.clamp > 0 else "none",
        bandwidths=DenoiseSettings().bandwidths if p.adaptive else (1.0,),
        **({"firefly_k": p.clamp} if p.clamp > 0 else {}),
    )


@dataclass
class StepTiming:
    """Milliseconds of one iteration.

    trace_ms: rendering one sample of every clip frame (in the tracer process when it runs ahead).
    trace_wait_ms: how long the iteration waited for the tracer (all of ``trace_ms`` without look-ahead).
    filter_ms: the engine's filtering and accumulation plus the error curves: the iteration's wall time
        without the wait.
    """

    trace_ms: float = 0.0
    trace_wait_ms: float = 0.0
    filter_ms: float = 0.0


class DemoSession:
    """The object the demo window drives: one :class:`ProgressiveRenderer` over a short clip.

    Args:
        tracer: a ``torchmanifold.render.PathTracer``.
        frame_times: clip frame times in frame units, e.g. ``[0, 1, 2, 3]``.
        params: :class:`FilterParams`.
        seed: sample seed; the same seed gives the same progression.
        reference: optional ``(T, 3, H, W)`` converged frames at ``frame_times`` for the error curves.
        max_extra_times: in-between times kept at once (the oldest is dropped for a new one).
        threads: torch threads for the filtering (None = torch's setting). At demo sizes one thread
            beats two on a shared CPU: OpenMP barriers wait on descheduled threads, and the tracer's
            llvmpipe threads want a core too.
    """

    def __init__(self, tracer, frame_times, params: FilterParams | None = None, seed: int = 0,
                 reference: torch.Tensor | None = None, max_extra_times: int = 4, threads: int | None = None):
        self.tracer = tracer
        self.frame_times = [float(t) for t in frame_times]
        if not self.frame_times:
            raise ValueError("frame_times: expected at least one frame time")
        if sorted(self.frame_times) != self.frame_times or len(set(self.frame_times)) != len(self.frame_times):
            raise ValueError(f"frame_times: expected strictly increasing times, got {self.frame_times}")
        if reference is not None:
            expected = (len(self.frame_times), 3, tracer.height, tracer.width)
            if tuple(reference.shape) != expected:
                raise ValueError(f"reference: expected shape {expected}, got {tuple(reference.shape)}")
        self.reference = reference
        self.max_extra_times = max_extra_times
        if threads is not None and not (isinstance(threads, int) and threads >= 1):
            raise ValueError(f"threads: expected an int >= 1 or None, got {threads!r}")
        self.threads = threads
        self.feature_names: list[str] = list(tracer.feature_names)
        self.engine = ProgressiveRenderer(tracer, self.frame_times, seed=seed, on_render=self._keep_features)
        self.params = params or FilterParams()
        self.version = 0  # changes whenever any shown result may have changed
        self.restart()

    # ----------------------------------------------------------------------------------- state
    @property
    def iteration(self) -> int:
        return self.engine.iteration

    @property
    def spp(self) -> int:
        return self.engine.iteration

    def restart(self, params: FilterParams | None = None) -> None:
        """Drop all samples and start again at iteration 0 (optionally with new parameters)."""
        if params is not None:
            self.params = params
        self.engine.set_settings(**engine_settings(self.params, self.feature_names))
        self.engine.restart()
        if hasattr(self.tracer, "drop_lookahead"):  # samples rendered ahead are those of the old progression
            self.tracer.drop_lookahead()
        self.state = None  # the engine's ProgressiveState of the last iteration
        self.version += 1
        self.history: dict[str, list[tuple[int, float]]] = {k: [] for k in ("raw", "gaussian", "ours")}
        self.timing = StepTiming()
        self._feat_sum = torch.zeros(len(self.frame_times), len(self.feature_names), self.tracer.height,
                                     self.tracer.width)

    def guide_channels(self) -> list[str]:
        """The channels that steer the filter now."""
        return list(self.engine.settings.guide or [])

    def bandwidth(self) -> tuple[float, float]:
        """(sigma_s, sigma_r) of the current iteration (of the next one before the first step)."""
        i, schedule = max(self.iteration, 1), self.engine.schedule
        return schedule.sigma_s(i), self.params.sigma_r * schedule.factor(i)

    def track(self, t: float) -> None:
        """Filter at time ``t`` from the next iteration on (clip frames always are); it joins at once."""
        t = float(t)
        if not self.frame_times[0] <= t <= self.frame_times[-1]:
            raise ValueError(f"t: expected a time in [{self.frame_times[0]}, {self.frame_times[-1]}], got {t}")
        if frame_at(self.engine.query_times, t) is not None:
            return
        extras = [q for q in self.engine.query_times if frame_at(self.frame_times, q) is None]
        while len(extras) >= self.max_extra_times:
            self.engine.untrack(extras.pop(0))
        self.engine.track(t)
        self.version += 1

    # ------------------------------------------------------------------------------------ step
    def step(self) -> StepTiming:
        """One iteration: 1 more spp for every clip frame, filter, accumulate, record errors."""
        t0 = time.perf_counter()
        with torch_threads(self.threads):
            state = self.engine.step()
            self.state = state
            self.version += 1
            if self.reference is not None:
                rows = [self.engine.query_times.index(t) for t in self.frame_times]
                for kind in ESTIMATES:
                    self.history[kind].append((self.iteration, psnr(getattr(state, kind)[rows], self.reference)))
        wall = time.perf_counter() - t0
        # a TracerProcess renders ahead in its own process: its trace time is its own, the step only waits
        trace = self.tracer.trace_seconds if getattr(self.tracer, "prefetch", False) else state.render_seconds
        self.timing = StepTiming(trace * 1e3, state.render_seconds * 1e3, (wall - state.render_seconds) * 1e3)
        return self.timing

    def planes(self, rows: Sequence[int] | None = None) -> torch.Tensor:
        """The last iteration's estimates of ``rows`` (indices into :attr:`row_times`; None: every row) as
        float32 ``(len(rows), 3, H, W, 3)`` (raw, gaussian, ours; RGB last, the texture's texel layout):
        what the display uploads, in one copy."""
        s = self.state
        pick = slice(None) if rows is None else list(rows)
        return torch.stack([x[pick].permute(0, 2, 3, 1) for x in (s.raw, s.gaussian, s.ours)], 1)

    @property
    def row_times(self) -> list[float]:
        """The times of the rows of :meth:`planes`."""
        return list(self.state.query_times) if self.state is not None else []

    def _keep_features(self, frame: int, res) -> None:
        self._feat_sum[frame] += res.features[0].float()

    # ------------------------------------------------------------------------------------ views
    def estimate(self, t: float, kind: str) -> torch.Tensor:
        """The engine's current ``kind`` estimate ``(3, H, W)`` at ``t`` (black before the first step)."""
        if self.iteration == 0:
            return torch.zeros(3, self.tracer.height, self.tracer.width)
        return self.engine.estimate(t, kind)

    def raw(self, t: float) -> torch.Tensor:
        return self.estimate(t, "raw")

    def gaussian(self, t: float) -> torch.Tensor:
        return self.estimate(t, "gaussian")

    def ours(self, t: float) -> torch.Tensor:
        return self.estimate(t, "ours")

    def feature_view(self, t: float, group: str) -> torch.Tensor | None:
        """Display-ready ``(3,H,W)`` in [0,1] of the mean feature ``group`` at ``t``, None if absent."""
        chans = [c for c in FEATURE_GROUPS[group] if c in self.feature_names]
        if not chans or self.iteration == 0:
            return None
        means = self._feat_sum[:, [self.feature_names.index(c) for c in chans]] / self.iteration
        x = interpolate(means, self.frame_times, t)
        if group == "Z":
            finite = x[x.isfinite() & (x > 0)]
            top = float(finite.max()) if finite.numel() else 1.0
            x = (x / top).clamp(0, 1)
        elif group in ("N", "D", "S"):  # unit vectors
            x = 0.5 + 0.5 * x
        elif group == "T":
            x = 0.5 + (x - t)  # the sample's time inside the shutter around the shown time, centred on grey
        x = x.expand(3, -1, -1) if x.shape[0] == 1 else x
        return x.clamp(0, 1)
