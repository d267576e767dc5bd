"""The demo driven by the project's own progressive pipeline (``torchmanifold.pipeline.ProgressiveRenderer``).

Same interface as :class:`demo.progression.Progression`, so the window shows the product's loop
(its preprocessing: footprint albedo, pilot-based firefly clamp, per-group guide sigmas) with the
demo's live controls mapped onto :class:`~torchmanifold.pipeline.DenoiseSettings`:

- sigma_s -> ``settings.sigma_s``; sigma_r -> a multiplier of every per-group range sigma (the
  schedule's ``sigma_r``); a -> the schedule's ``alpha``; time window -> ``temporal_radius`` and
  ``sigma_t``; temporal mode -> ``mode``; tree height; feature set -> ``settings.guide``;
  clamp on/off -> ``firefly = "clamp" | "none"`` (the clamp's threshold is the pipeline's own).
- In-between times are query times of the renderer: showing a new one restarts the progression
  with it added (the pipeline keeps one running sum per query time).
"""
from __future__ import annotations

import torch

from demo.progression import FilterParams, Progression, StepTiming, psnr, torch_threads


class _FeatureTap:
    """Forwards ``render`` to the tracer and keeps per-frame sums of the features it returned, so the
    feature views work while the pipeline drives the tracer."""

    def __init__(self, tracer):
        self.tracer = tracer
        self.width, self.height = tracer.width, tracer.height
        self.reset()

    def reset(self) -> None:
        self.sums: dict[float, torch.Tensor] = {}
        self.counts: dict[float, int] = {}
        self.feature_names: list[str] = []

    def render(self, times, spp, seed, sample_offset):
        res = self.tracer.render(times=times, spp=spp, seed=seed, sample_offset=sample_offset)
        self.feature_names = list(res.feature_names)
        for k, t in enumerate(times):
            t = float(t)
            f = res.features[k].float() * spp
            self.sums[t] = f if t not in self.sums else self.sums[t] + f
            self.counts[t] = self.counts.get(t, 0) + spp
        return res


class PipelineProgression(Progression):
    """:class:`~demo.progression.Progression` whose iterations run ``ProgressiveRenderer.step()``."""

    #: the pipeline's raw / Gaussian at an in-between time: linear between the bracketing frames
    raw_in_between = "lerp"

    def __init__(self, tracer, frame_times, params: FilterParams | None = None, seed: int = 0,
                 reference: torch.Tensor | None = None, max_extra_times: int = 4, threads: int | None = None):
        self._tap = _FeatureTap(tracer)
        self._query_times: list[float] = [float(t) for t in frame_times]
        self._state = None
        super().__init__(tracer, frame_times, params, seed=seed, reference=reference,
                         max_extra_times=max_extra_times, threads=threads)

    # ------------------------------------------------------------------------------ the renderer
    def settings(self):
        from torchmanifold.pipeline import DenoiseSettings

        p = self.params
        guide = self.guide_channels()
        return DenoiseSettings(
            sigma_s=p.sigma_s, tree_height=p.tree_height, temporal_radius=p.time_window,
            sigma_t=max(p.time_window / 2.0, 0.5), mode=p.temporal_mode,
            guide=guide or None, firefly="clamp" if p.clamp > 0 else "none",
        ).check()

    def restart(self, params: FilterParams | None = None) -> None:
        from torchmanifold.pipeline import BandwidthSchedule
        from torchmanifold.pipeline.progressive import ProgressiveRenderer

        super().restart(params)
        self._tap.reset()
        self._state = None
        p = self.params
        self._renderer = ProgressiveRenderer(self._tap, self.frame_times, query_times=self._query_times,
                                             settings=self.settings(), alpha=p.a, seed=self.seed)
        # sigma_r scales every per-group range sigma; it shrinks with the same schedule
        self._renderer.schedule = BandwidthSchedule(p.sigma_s, p.sigma_r / FilterParams().sigma_r, p.a)

    def guide_channels(self) -> list[str]:
        # The pipeline has no colour-guided mode ("colour" falls back to its default guide), and
        # cannot guide by time T (no default sigma for it, and an override is checked too late).
        names = [c for c in super().guide_channels() if c != "T"]
        return names or [c for c in self.feature_names if c != "T"]

    def step(self) -> StepTiming:
        with torch_threads(self.threads):
            self._state = self._renderer.step()
        self.iteration = self._state.iteration
        self.feature_names = list(self._tap.feature_names)
        self.version += 1
        s = self._state
        self.timing = StepTiming(s.render_seconds * 1e3, (s.seconds - s.render_seconds) * 1e3)
        if self.reference is not None:
            self._record_errors()
        return self.timing

    # ------------------------------------------------------------------------------------- views
    def _q(self, t: float) -> int:
        return self._query_times.index(float(t))

    def track(self, t: float) -> None:
        t = float(t)
        if t in self._query_times:
            return
        if not self.frame_times[0] <= t <= self.frame_times[-1]:
            raise ValueError(f"t: expected a time in [{self.frame_times[0]}, {self.frame_times[-1]}], got {t}")
        extras = [q for q in self._query_times if q not in self.frame_times]
        if len(extras) >= self.max_extra_times:
            extras.pop(0)
        self._query_times = sorted(set(self.frame_times) | set(extras) | {t})
        self.restart()

    def _image(self, which: str, t: float) -> torch.Tensor:
        t = float(t)
        if t not in self._query_times:
            self.track(t)
        if self._state is None:
            return torch.zeros(3, self.tracer.height, self.tracer.width)
        return getattr(self._state, which)[self._q(t)]

    def raw(self, t: float) -> torch.Tensor:
        return self._image("raw", t)

    def gaussian(self, t: float) -> torch.Tensor:
        return self._image("gaussian", t)

    def ours(self, t: float) -> torch.Tensor:
        return self._image("ours", t)

    def _feature_mean(self, frame: int) -> torch.Tensor:
        t = self.frame_times[frame]
        return self._tap.sums[t] / self._tap.counts[t]

    def _record_errors(self) -> None:
        idx = [self._q(t) for t in self.frame_times]
        s = self._state
        for name in ("raw", "gaussian", "ours"):
            self.history[name].append((self.iteration, psnr(getattr(s, name)[idx], self.reference)))
