"""The progressive loop the demo shows: one more sample per pixel for every clip frame per step.

A thin loop over the tracer and the adaptive-manifold op (the paper's steps): every iteration renders
1 spp of every clip frame, accumulates neighbour frames with Gaussian weights in time around each
shown time, filters the result guided by the features with the current bandwidth, and adds it into a
running buffer. Bandwidths shrink as sigma_{i+1}^2 / sigma_i^2 = (i + a) / (i + 1). Beside it the
raw progressive average and a Gaussian-filtered average (same bandwidth schedule) are kept for the
comparison panels, and their errors against a reference are recorded after every iteration.
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from torchmanifold import features as feature_table
from torchmanifold.pipeline.schedule import DEFAULT_ALPHA

#: Feature groups the tracer makes (the feature table's groups and tracer channel names); the guide
#: of a feature set is made of the groups the scene provides.
FEATURE_GROUPS = {g: feature_table.tracer_channels(g) for g in feature_table.groups()
                  if feature_table.tracer_channels(g)}

#: Selectable guides (which channels steer the filter). "colour" guides by the noisy image itself.
FEATURE_SETS = {
    "all": tuple(FEATURE_GROUPS),
    "albedo+normal+depth": ("Z", "albedo", "N"),
    "albedo+normal": ("albedo", "N"),
    "normal+depth": ("Z", "N"),
    "colour": (),
}

#: How neighbour frames are combined: mean of the window then filter, or joint space-time filter.
TEMPORAL_MODES = ("window", "spacetime")

#: Feature buffers that can be shown instead of the raw image (time last: the least telling to look at).
FEATURE_VIEWS = (*[g for g in FEATURE_GROUPS if g != "T"], "T")


@dataclass(frozen=True)
class FilterParams:
    """What the user can change live. Bandwidths are those of the first iteration.

    sigma_s: spatial sigma in pixels. sigma_r: range sigma in units of the normalised guide
    (depth relative to its median, albedo, unit normals/directions, time in frames).
    a: bandwidth reduction in (0, 1). time_window: radius in frames of the temporal Gaussian window
    (0 = each frame alone; sigma_t = radius / 2). tree_height: manifold tree height.
    clamp: firefly clamp on 1-spp irradiance at iteration 1 (0 = off); it grows as sqrt(iteration),
    so its bias fades and the running result stays consistent. temporal_mode: "window" (average the
    window, then filter: the paper's accumulation) or "spacetime" (joint filter, no ghosts of moving
    objects; slower).
    """

    sigma_s: float = 3.0
    sigma_r: float = 0.3
    a: float = DEFAULT_ALPHA  # the pipeline's measured default
    time_window: int = 1
    tree_height: int = 2
    feature_set: str = "albedo+normal+depth"
    clamp: float = 4.0
    temporal_mode: str = "window"

    def __post_init__(self):
        if not self.sigma_s >= 1.0:
            raise ValueError(f"sigma_s: expected >= 1 pixel, got {self.sigma_s}")
        if not self.sigma_r > 0.0:
            raise ValueError(f"sigma_r: expected > 0, got {self.sigma_r}")
        if not 0.0 < self.a < 1.0:
            raise ValueError(f"a: expected a value in (0, 1), got {self.a}")
        if not (isinstance(self.time_window, int) and self.time_window >= 0):
            raise ValueError(f"time_window: expected an int >= 0 (frames), got {self.time_window!r}")
        if not (isinstance(self.tree_height, int) and 1 <= self.tree_height <= 8):
            raise ValueError(f"tree_height: expected an int in [1, 8], got {self.tree_height!r}")
        if not self.clamp >= 0.0:
            raise ValueError(f"clamp: expected >= 0 (0 = off), got {self.clamp}")
        if self.temporal_mode not in TEMPORAL_MODES:
            raise ValueError(f"temporal_mode: expected one of {TEMPORAL_MODES}, got {self.temporal_mode!r}")
        if self.feature_set not in FEATURE_SETS:
            raise ValueError(f"feature_set: expected one of {sorted(FEATURE_SETS)}, got {self.feature_set!r}")

    def bandwidth(self, iteration: int) -> tuple[float, float]:
        """(sigma_s, sigma_r) of 1-based ``iteration``: sigma_{i+1}^2 = sigma_i^2 (i + a) / (i + 1)."""
        ratio = math.exp(0.5 * sum(math.log((i + self.a) / (i + 1)) for i in range(1, iteration)))
        return max(1.0, self.sigma_s * ratio), self.sigma_r * ratio

    def with_(self, **changes) -> "FilterParams":
        return replace(self, **changes)


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean PSNR on clamped sRGB over the batch, the project's score (:func:`torchmanifold.metrics.psnr`)."""
    from torchmanifold.metrics import psnr as _psnr

    return float(_psnr(img, ref))


@contextlib.contextmanager
def torch_threads(n: int | None):
    """Run the block with ``n`` torch intra-op threads (None = unchanged), then restore the count."""
    if n is None:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@dataclass
class _Track:
    """Running state of one shown time (a clip frame or an in-between time)."""

    ours_sum: torch.Tensor
    count: int


@dataclass
class StepTiming:
    trace_ms: float = 0.0
    filter_ms: float = 0.0


class Progression:
    """Progressive rendering + filtering of a short clip, the object the demo window drives.

    Args:
        tracer: a ``torchmanifold.render.PathTracer`` (its ``render(times, spp, seed, sample_offset)``).
        frame_times: clip frame times in frame units, e.g. ``[0, 1, 2, 3]``.
        params: :class:`FilterParams`.
        seed: sample seed; the same seed gives the same progression.
        reference: optional ``(T, 3, H, W)`` converged frames at ``frame_times`` for the error curves.
        threads: torch threads for the filtering (None = torch's setting). At demo sizes one thread
            beats two on a shared CPU: OpenMP barriers wait on descheduled threads, and the tracer's
            llvmpipe threads want a core too.

    Memory: one running sum per clip frame and per tracked in-between time, plus the last samples.
    """

    #: what raw / Gaussian show at an in-between time: the nearest rendered frame
    raw_in_between = "nearest"

    def __init__(self, tracer, frame_times, params: FilterParams | None = None, seed: int = 0,
                 reference: torch.Tensor | None = None, max_extra_times: int = 4, threads: int | None = None):
        self.tracer = tracer
        self.frame_times = [float(t) for t in frame_times]
        if not self.frame_times:
            raise ValueError("frame_times: expected at least one frame time")
        if sorted(self.frame_times) != self.frame_times or len(set(self.frame_times)) != len(self.frame_times):
            raise ValueError(f"frame_times: expected strictly increasing times, got {self.frame_times}")
        self.params = params or FilterParams()
        self.seed = int(seed)
        if reference is not None:
            expected = (len(self.frame_times), 3, tracer.height, tracer.width)
            if tuple(reference.shape) != expected:
                raise ValueError(f"reference: expected shape {expected}, got {tuple(reference.shape)}")
        self.reference = reference
        self.max_extra_times = max_extra_times
        if threads is not None and not (isinstance(threads, int) and threads >= 1):
            raise ValueError(f"threads: expected an int >= 1 or None, got {threads!r}")
        self.threads = threads
        self.feature_names: list[str] = list(getattr(tracer, "feature_names", []))
        self.restart()

    # ----------------------------------------------------------------------------------- state
    def restart(self, params: FilterParams | None = None) -> None:
        """Drop all samples and start again at iteration 0 (optionally with new parameters)."""
        if params is not None:
            self.params = params
        self.version = getattr(self, "version", 0) + 1  # changes whenever any result may have changed
        self.iteration = 0
        self.raw_sum = None       # (T,3,H,W) sum of 1-spp colour
        self.feat_sum = None      # (T,D,H,W) sum of 1-spp features
        self.emis_sum = None      # (T,3,H,W) sum of 1-spp emission seen at the first hit
        self.tracks: dict[float, _Track] = {}
        self.history: dict[str, list[tuple[int, float]]] = {"raw": [], "gaussian": [], "ours": []}
        self.timing = StepTiming()
        self._gauss_cache: dict[int, torch.Tensor] = {}

    @property
    def spp(self) -> int:
        return self.iteration

    def track(self, t: float) -> None:
        """Start keeping a running result for time ``t`` (clip frames are always kept).

        An in-between time joining late starts from the filtered raw average of its window, weighted
        as the iterations it missed, so it shows a converged-looking image at once.
        """
        t = float(t)
        if t in self.tracks or t in self.frame_times:
            return
        if not self.frame_times[0] <= t <= self.frame_times[-1]:
            raise ValueError(f"t: expected a time in [{self.frame_times[0]}, {self.frame_times[-1]}], got {t}")
        extras = [k for k in self.tracks if k not in self.frame_times]
        while len(extras) >= self.max_extra_times:
            del self.tracks[extras.pop(0)]
        if self.iteration == 0:
            self.tracks[t] = _Track(None, 0)
            return
        raw = self.raw_sum / self.iteration
        feats = self.feat_sum / self.iteration
        emis = self.emis_sum / self.iteration if self.emis_sum is not None else None
        with torch_threads(self.threads):
            out = self._filter([t], raw, feats, self.params.bandwidth(self.iteration), emis, clamp=False)
        self.tracks[t] = _Track(out[0] * self.iteration, self.iteration)

    # ------------------------------------------------------------------------------------ step
    def step(self) -> StepTiming:
        """One iteration: 1 more spp for every clip frame, filter, accumulate, record errors."""
        i = self.iteration
        t0 = time.perf_counter()
        res = self.tracer.render(times=self.frame_times, spp=1, seed=self.seed, sample_offset=i)
        color, feats = res.color.float(), res.features.float()
        self.feature_names = list(res.feature_names)
        emission = res.emission.float() if getattr(res, "emission", None) is not None else None
        t1 = time.perf_counter()
        self.iteration = i + 1
        self.version += 1
        self._gauss_cache.clear()
        self.raw_sum = color.clone() if self.raw_sum is None else self.raw_sum + color
        self.feat_sum = feats.clone() if self.feat_sum is None else self.feat_sum + feats
        if emission is not None:
            self.emis_sum = emission.clone() if self.emis_sum is None else self.emis_sum + emission
        for t in self.frame_times:
            self.tracks.setdefault(t, _Track(None, 0))
        times = list(self.tracks)
        with torch_threads(self.threads):
            out = self._filter(times, color, feats, self.params.bandwidth(self.iteration), emission)
        for k, t in enumerate(times):
            tr = self.tracks[t]
            tr.ours_sum = out[k].clone() if tr.ours_sum is None else tr.ours_sum + out[k]
            tr.count += 1
        t2 = time.perf_counter()
        self.timing = StepTiming((t1 - t0) * 1e3, (t2 - t1) * 1e3)
        if self.reference is not None:
            self._record_errors()
        return self.timing

    # --------------------------------------------------------------------------------- filtering
    def _window(self, t: float) -> tuple[list[int], torch.Tensor]:
        """Clip frames inside the temporal window around ``t`` and their normalised Gaussian weights."""
        radius = self.params.time_window
        times = torch.tensor(self.frame_times, dtype=torch.float64)
        dist = (times - t).abs()
        inside = (dist <= radius + 1e-9).nonzero().flatten().tolist()
        if not inside:  # an in-between time with radius 0: its nearest frame
            inside = [int(dist.argmin())]
        sigma_t = max(radius / 2.0, 0.5)
        w = torch.exp(-0.5 * (dist[inside] / sigma_t) ** 2)
        return inside, (w / w.sum()).float()

    def guide_channels(self) -> list[str]:
        """Channels of the current feature set that the scene provides (empty = colour-guided)."""
        names = []
        for group in FEATURE_SETS[self.params.feature_set]:
            names += [c for c in FEATURE_GROUPS[group] if c in self.feature_names]
        return names

    def _guide(self, feats: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        names = self.guide_channels()
        if not names:
            # colour-guided: a log-compressed copy of the values, so fireflies don't dominate ranges
            return torch.log1p(values.clamp_min(0.0))
        idx = [self.feature_names.index(c) for c in names]
        guide = feats[:, idx].clone()
        if "Z" in names:
            # depth relative to its median so sigma_r means "percent of depth"
            z = names.index("Z")
            guide[:, z] = guide[:, z] / guide[:, z].flatten(1).median(1).values.clamp_min(1e-6)[:, None, None]
        return guide

    def _filter(self, times, color, feats, bandwidth, emission=None, clamp=True) -> torch.Tensor:
        """Temporal window + adaptive-manifold filter for each time in ``times`` -> ``(len(times), 3, H, W)``.

        Colour is filtered as irradiance: emission seen at the first hit is kept apart and the albedo
        divided out per frame, both put back at the shown time after filtering, so lights don't bleed
        and texture stays sharp.
        """
        from torchmanifold import adaptive_manifold_filter, temporal_adaptive_manifold_filter

        sigma_s, sigma_r = bandwidth
        names = self.feature_names
        if all(c in names for c in FEATURE_GROUPS["albedo"]):
            albedo = feats[:, [names.index(c) for c in FEATURE_GROUPS["albedo"]]].clamp_min(1e-3)
        else:
            albedo = torch.ones_like(color)
        if emission is None:
            emission = torch.zeros_like(color)
        irr = (color - emission).clamp_min(0.0) / albedo
        if clamp and self.params.clamp > 0:
            # fireflies: a bright 1-spp sample would become a blob; the limit grows with the
            # iteration so the bias vanishes as samples accumulate
            irr = irr.clamp_max(self.params.clamp * math.sqrt(self.iteration))
        guide = self._guide(feats, irr)
        height = self.params.tree_height
        if self.params.temporal_mode == "window":
            # the paper's accumulation: Gaussian-weighted mean of the frames in the window, then one
            # spatial filter per shown time (batched)
            ws = [self._window(t) for t in times]
            mix = lambda x: torch.stack([(x[i] * w.view(-1, 1, 1, 1)).sum(0) for i, w in ws])  # noqa: E731
            out = adaptive_manifold_filter(mix(irr), mix(guide), sigma_s, sigma_r, tree_height=height)
            return out * mix(albedo) + mix(emission)
        outs = []
        for t in times:
            # space-time: samples of other frames only count where their guide matches the shown
            # frame's, so moving objects don't leave ghosts
            idx, _ = self._window(t)
            frame_times = [self.frame_times[i] for i in idx]
            sigma_t = max(self.params.time_window / 2.0, 0.5)
            out = temporal_adaptive_manifold_filter(
                irr[idx][None], guide[idx][None], frame_times, [t], sigma_s, sigma_r, sigma_t=sigma_t,
                mode="spacetime", tree_height=height)[0, 0]
            outs.append(out * self._interpolate(albedo, t) + self._interpolate(emission, t))
        return torch.stack(outs)

    def _interpolate(self, x: torch.Tensor, t: float) -> torch.Tensor:
        """``x`` (T, C, H, W) at time ``t``: linear between the frames bracketing it."""
        ft = self.frame_times
        k = int(np.searchsorted(ft, t, side="right")) - 1
        if k < 0 or k >= len(ft) - 1 or ft[k] == t:
            return x[min(max(k, 0), len(ft) - 1)]
        s = (t - ft[k]) / (ft[k + 1] - ft[k])
        return torch.lerp(x[k], x[k + 1], s)

    # ------------------------------------------------------------------------------------ views
    def _nearest_frame(self, t: float) -> int:
        return int(np.argmin([abs(ft - t) for ft in self.frame_times]))

    def raw(self, t: float) -> torch.Tensor:
        """Raw progressive average ``(3,H,W)`` of the clip frame nearest to ``t``."""
        if self.iteration == 0:
            return torch.zeros(3, self.tracer.height, self.tracer.width)
        return self.raw_sum[self._nearest_frame(t)] / self.iteration

    def gaussian(self, t: float) -> torch.Tensor:
        """Raw average blurred with a Gaussian of a third of the current spatial bandwidth ``(3,H,W)``
        (the pipeline's baseline setting, its best on the built-in scene)."""
        from kornia.filters import gaussian_blur2d

        frame = self._nearest_frame(t)
        if frame not in self._gauss_cache:  # once per iteration, not once per displayed frame
            sigma_s = self.params.bandwidth(max(self.iteration, 1))[0] / 3.0
            k = 2 * int(math.ceil(3 * sigma_s)) + 1
            self._gauss_cache[frame] = gaussian_blur2d(self.raw(t)[None], (k, k), (sigma_s, sigma_s),
                                                       border_type="reflect")[0]
        return self._gauss_cache[frame]

    def ours(self, t: float) -> torch.Tensor:
        """Our running result ``(3,H,W)`` at ``t`` (tracked from now on if it was not)."""
        t = float(t)
        if t not in self.tracks:
            self.track(t)
        tr = self.tracks[t]
        if tr.ours_sum is None:
            return torch.zeros(3, self.tracer.height, self.tracer.width)
        return tr.ours_sum / tr.count

    def _feature_mean(self, frame: int) -> torch.Tensor:
        """Mean features ``(D,H,W)`` of clip frame index ``frame`` over the samples so far."""
        return self.feat_sum[frame] / self.iteration

    def feature_view(self, t: float, group: str) -> torch.Tensor | None:
        """Display-ready ``(3,H,W)`` in [0,1] of feature ``group`` at the nearest frame, None if absent."""
        chans = [c for c in FEATURE_GROUPS[group] if c in self.feature_names]
        if not chans or self.iteration == 0:
            return None
        f = self._feature_mean(self._nearest_frame(t))
        x = f[[self.feature_names.index(c) for c in chans]]
        if group == "Z":
            finite = x[x.isfinite() & (x > 0)]
            top = float(finite.max()) if finite.numel() else 1.0
            x = (x / top).clamp(0, 1)
        elif group in ("N", "D", "S"):  # unit vectors
            x = 0.5 + 0.5 * x
        elif group == "T":
            # the sample's time inside the shutter around the frame time, centred on grey
            x = 0.5 + (x - self.frame_times[self._nearest_frame(t)])
        x = x.expand(3, -1, -1) if x.shape[0] == 1 else x
        return x.clamp(0, 1)

    def _record_errors(self) -> None:
        ref = self.reference
        T = len(self.frame_times)
        raw = self.raw_sum / self.iteration
        gauss = torch.stack([self.gaussian(t) for t in self.frame_times])
        ours = torch.stack([self.ours(t) for t in self.frame_times])
        for name, img in (("raw", raw), ("gaussian", gauss), ("ours", ours)):
            self.history[name].append((self.iteration, psnr(img[:T], ref)))
