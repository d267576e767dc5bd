"""Denoise Monte Carlo frames with the adaptive-manifold filter: the preprocessing that makes it win.

Plain joint filtering of 1-spp colour loses to a Gaussian blur on real renders (fireflies become
blobs, texture blurs, lights bleed). :func:`denoise_frames` wraps the filter op with:

1. **Sanitising**: non-finite colour or feature samples are counted and given zero weight (the filter
   runs on ``[w * colour, w]`` and divides, so they never enter any sum).
2. **Emission apart**: emitted radiance at the first hit (when the renderer gives it) is removed
   before filtering and added back unfiltered, so lights do not bleed into walls.
3. **Irradiance**: colour is divided by the first-hit albedo, filtered, and multiplied back by the
   same albedo, so texture stays sharp. Where the albedo is about 0 (delta BSDFs, black surfaces) the
   radiance itself is averaged, among those pixels only and each frame alone: their features do not
   show what a mirror or glass shows (:func:`_flat_average`).
4. **Fireflies**: a pilot estimate is filtered in the range-compressed ``log1p`` domain (where a
   firefly is just one more sample), samples brighter than ``firefly_k`` times the pilot are clamped
   to it, and the clamped samples are filtered linearly. The energy removed is measured and returned
   (``stats["firefly_energy_removed"]``).
5. **Guide**: each feature group gets its own range sigma (albedo, normals, world position or depth
   relative to each frame's extent, directions; see :func:`default_guide_sigmas`), and a log-radiance
   channel of the colour itself (:func:`_log_radiance`) separates what the features cannot: lights
   set in a surface, shadows, what glass shows. Where the pilot below is too noisy to trust, that
   channel and the albedo stop steering (:func:`_noise_widening`). Colour alone adds the pilot's
   chromaticity (:func:`_with_chromaticity`).
6. **Bandwidth from the data**: the filter runs at several spatial bandwidths and every pixel blends
   them by their error, estimated by cross-validation between two interleaved halves of the samples
   (see :func:`_select_bandwidth`): wide where the light is smooth and the samples noisy, narrow at
   detail the features do not show and where more samples make the input better. Where neighbouring
   pixels share samples (a renderer's reconstruction filter splats them), the halves are squares of
   pixels (:func:`_cv_cell`). Where no albedo guides, two narrower bandwidths join
   (:func:`adapt_to_features`): nothing else tells texture from noise.
7. **Time**: optionally neighbour frames within ``temporal_radius`` join with Gaussian weights in
   time, in the op's ``"spacetime"`` mode (no ghosts where things move) or ``"window"`` mode; with
   colour alone each frame is filtered alone (nothing tells a moving view's frames apart).
8. **Pixel footprint** (:mod:`torchmanifold.pipeline.footprint`): a 1-spp pixel shows one point of its
   area, so thin geometry comes out dotted and texture speckled; the result is averaged over a pixel-sized
   footprint, in a tone-mapped domain and only among pixels of similar brightness, so a light's edge does
   not bleed into the dark beside it. On a smooth surface the albedo, whose detail is texture, gets a
   narrower footprint than the light. Where the renderer gives world positions, the window's other frames
   add their samples of each pixel's albedo: a still view's of the same pixel, a moving view's that fall
   in the pixel's square.
9. **Sky**: where the camera ray left the scene (depth 0) the colour is the environment itself, with no
   Monte Carlo noise: those pixels keep their samples (:func:`_escaped`).

Every statistic comes from the frames of one query's window, so a clip gives the same bytes streamed,
sharded or all at once.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from torchmanifold import features as feature_table
from torchmanifold._checks import (MAX_TREE_HEIGHT, check_choice, check_int, check_nonnegative,
                                   check_positive, check_tree_height)
from torchmanifold._threads import serial
from torchmanifold.pipeline import _fast
from torchmanifold.pipeline.footprint import (_UNSEEN_BORDER, _footprint_albedo, _known_count,
                                              _normalised_blur, _position, _remodulate, _smooth_surface,
                                              _window_albedo, footprint_width)
from torchmanifold.pipeline.image import (_channel_means, _four_neighbours, _frame_mean, _gaussian_taps,
                                          footprint_blur, luminance)
from torchmanifold.timewindow import bracket, frame_at, interpolate, window

__all__ = [
    "DenoiseSettings",
    "denoise_frames",
    "prepare_frames",
    "denoise_prepared",
    "FrameState",
    "footprint_width",
    "spatial_sigma",
    "adapt_to_features",
    "Denoiser",
    "default_guide_sigmas",
    "feature_group",
    "luminance",
    "footprint_blur",
]

_ALBEDO = ("albedo.R", "albedo.G", "albedo.B")


def canonical_name(name: str) -> str:
    """Tracer (``Mr``), Mitsuba or Blender (``Denoising Albedo.R``) channel names mapped to the canonical
    EXR channel names (``albedo.R``) of :mod:`torchmanifold.features`; unknown names unchanged."""
    return feature_table.canonical_name(name)


def feature_group(name: str) -> str:
    """The group a feature channel belongs to (``albedo``, ``N``, ``P``, ``Z`` ..., see
    :mod:`torchmanifold.features`), or the part before the first dot for unknown channels."""
    return feature_table.group_of(name)


def _extent(x: Tensor, valid: Tensor) -> Tensor:
    """Robust spread (1st to 99th percentile, largest over channels) of each frame of ``(T, C, H, W)``
    where ``valid`` ``(T, 1, H, W)``: ``(T,)``, 1 where a frame has too few valid samples.

    Per frame, so a frame's guide never depends on which other frames share the call (streaming and
    sharded runs give the same frames)."""
    out = []
    for t in range(x.shape[0]):
        v = x[t][:, valid[t, 0]]  # (C, N)
        s = 0.0
        if v.shape[1] >= 2:
            if v.shape[1] > 200_000:  # quantile of a deterministic subsample is plenty
                v = v[:, :: v.shape[1] // 100_000]
            if _fast.enabled(v):
                lo, hi = _fast.quantiles(v, [0.01, 0.99])
            else:
                lo, hi = torch.quantile(v.double(), torch.tensor([0.01, 0.99], dtype=torch.float64), dim=1)
            s = float((hi - lo).max())
        out.append(s if s > 0 and math.isfinite(s) else 1.0)
    return torch.tensor(out, dtype=torch.float64)


#: the float32 guard's box, in spatial sigmas: the samples a pixel mixes lie almost all within it
#: (a Gaussian keeps 86% of its weight inside 2 sigma in 2-D), and a wider box bounds nothing
_GUARD_RADIUS = 2
#: ways of handling fireflies (see :class:`DenoiseSettings`)
FIREFLY_MODES = ("clamp", "log", "none")
#: guide-sigma key of the log-radiance channel the denoiser adds to the renderer's features
RADIANCE_GUIDE = "log_radiance"
#: the log-radiance guide's offset as a fraction of the frame's mean luminance (validation set: 0.1
#: separates shadows and lights as well as 0 does in bright scenes, without resolving noise in dark ones)
_LOG_RADIANCE_OFFSET = 0.1
#: the log-radiance guide's sigma from single samples (3x3 Kuwahara) relative to the pilot's
#: (validation set's tuning part: the pilot's at 0.5 with the samples' at 1.0 beat both at 1.0 by 0.14 dB
#: from 1 spp, and 0.22 dB over the whole set from 4 spp; the pilot's at 1.0 or 0.25 lost)
_SAMPLE_RADIANCE_WIDENING = 2.0
#: a bandwidth whose pooled cross-validated error is over this many times the least one's is left out,
#: whatever the evidence: one catastrophic residual widens its own standard error, so z alone would keep
#: it (frames 0-2 of the validation set: -0.01 / 0.00 dB from 1 / 4 spp, and it removed 20-700x bright
#: pixels from mi_glass_mirror, while the op centred values at their range's middle; since they are
#: centred nearest 0, without it 0.000 / -0.008, `bl_moving_metal` -0.07 from 4 spp)
_SELECTION_ERROR_CUT = 2.0
#: z^2 of a bandwidth left out (weight exp(-z^2 / 2) = 0)
_LEFT_OUT = 1e30


def _min_support(dtype: torch.dtype) -> float:
    """The least normalising weight ``den`` (1 at a fully supported pixel) whose ``num / den`` is taken;
    below it a pixel takes its fallback. The op's recursive sums round ``den`` to about eps (its peak is
    1), so ``100 eps`` keeps two digits (float32: 1.2e-5; not below 1e-8, float64's). Frames 0-2 of the
    validation set from 1 / 4 spp, PyTorch stages: 1e-8 / 1.2e-5 / 1.2e-4 all within 0.002 dB of each other,
    1.2e-5 within 0.002 of the best on every scene. The C++ kernels' ``min_support`` is the same."""
    return max(1e-8, 1e2 * torch.finfo(dtype).eps)


#: firefly clamp floor as a fraction of the frame's mean pilot luminance
_FIREFLY_FLOOR = 0.25
#: the largest share of a frame's samples the firefly clamp may take down: fireflies are rare. A scene lit
#: by bounce light alone, whose light reaches most pixels through rare bright paths that the log-domain
#: pilot sees as fireflies, had 8.6% of its samples clamped from 1 spp and lost half its energy; the other
#: scenes' frames had at most 1.6%. On the tuning part, frames 0-2, from 1 / 4 spp: 2% 27.318 / 30.603,
#: 1% 27.483 / 30.626, 0.5% 27.536 / 30.629, 0.25% 27.542 / 30.624, 0.1% 27.531 / 30.617
#: (``benchmarks/validation/findings.md``)
_FIREFLY_MAX_SHARE = 0.005

#: range sigmas of feature groups in their own units; ``P`` and ``Z`` are fractions of the scene extent
#: (the feature table's, see :mod:`torchmanifold.features` for where each figure comes from)
GROUP_SIGMAS = feature_table.GroupSigmas()


def default_guide_sigmas(names: Sequence[str], features: Tensor | None = None,
                         valid: Tensor | None = None) -> Tensor:
    """Range sigma of every guide channel in every frame, from its group (see ``GROUP_SIGMAS``).

    World position and depth have scene units, so their sigma is a fraction of the robust extent of
    each frame's data in ``features`` ``(T, D, H, W)`` (1 scene unit when not given).

    Returns:
        ``(T, D)`` float64 sigmas (``T = 1`` without ``features``).
    """
    T = 1 if features is None else features.shape[0]
    out = torch.empty(T, len(names), dtype=torch.float64)
    for k, n in enumerate(names):
        g = feature_group(n)
        if g not in GROUP_SIGMAS:
            raise ValueError(f"guide_sigmas: no default sigma for feature channel {n!r}; pass guide_sigmas "
                             f"explicitly (known groups: {sorted(GROUP_SIGMAS)})")
        out[:, k] = GROUP_SIGMAS[g]
    for g in {feature_group(n) for n in names}:
        if features is None or not feature_table.feature(g).sigma_of_extent:
            continue
        idx = [j for j, m in enumerate(names) if feature_group(m) == g]
        v = valid if valid is not None else torch.ones_like(features[:, :1], dtype=torch.bool)
        if feature_table.feature(g).zero_is_no_hit:  # depth 0 marks background
            v = v & (features[:, idx[0]:idx[0] + 1] > 0)
        out[:, idx] *= _extent(features[:, idx], v)[:, None]
    return out


@dataclass
class DenoiseSettings:
    """Settings of :func:`denoise_frames` (defaults measured on the tuning part of the validation set,
    ``benchmarks/validation``, unless said otherwise).

    Attributes:
        sigma_s: spatial sigma in pixels from 1 spp (the reference bandwidth: the pilot's, and the unit of
            ``bandwidths``); where the sample count n is known it is ``sigma_s * n ** -0.25``
            (:func:`spatial_sigma`), unless the caller passes a sigma itself.
        bandwidths: spatial sigmas tried at every pixel, as multiples of ``sigma_s``; each pixel blends
            them by their cross-validated error (see :func:`_select_bandwidth`). One value filters at that
            bandwidth alone. Factor-2 steps from 0.5 to 4 (2 to 16 px) measured best on the validation
            set's tuning part from 1 and 4 spp (``benchmarks/validation``): a 1-spp wall wants 16 px, a
            4-spp leaf edge 2.
        selection_blur: sigma (pixels) over which a pixel's cross-validated errors are pooled: one
            held-out sample is too noisy an error estimate (2 to 8 measured alike; 4 is the middle). It
            widens where the firefly pilot is noisy (:func:`_selection_pooling`).
        selection_softness: how sure the evidence must be before a bandwidth is left out: weights are
            ``exp(-z^2 / (2 softness^2))``, ``z`` a bandwidth's pooled error in excess of the least one's in
            standard errors of that excess (see :func:`_excess_error_z2`); 0 picks the least-error
            bandwidth alone. 1 is the plain likelihood that the excess is noise; against the earlier
            ``softmax(-err / (0.5 min err))``, which blended the bandwidths almost evenly because every
            error holds the sample's own variance, it measured -0.02 / +0.09 dB from 1 / 4 spp on the
            tuning part, +0.12 / +0.23 over the whole set and +0.40 dB in the progressive loop (96x96,
            4 frames, 10 iterations). Picking one alone flickers between progressive iterations.
        guide: feature channels that steer the filter (EXR or tracer names); ``None`` = albedo, normals
            and world position ``P`` (or depth ``Z`` without ``P``): the sampled directions ``D``/``S`` are
            one random draw per sample and only add noise to the range weights (measured).
        guide_sigmas: range sigma per guide channel (``{name: sigma}`` overrides); missing ones default.
        tree_height: manifold tree height at ``sigma_s``: 3 measured best on the tuning part (2: -0.13 dB, 4:
            the same; over the whole set from 1 / 4 spp, 3 beats 2 by 0.27 / 0.40 dB, at about twice the op's
            time).
        levels_per_doubling: levels the tree gains per doubling of a bandwidth beyond ``sigma_s``
            (:func:`tree_height_at`). A wider kernel mixes more of the pixels that lie far from every
            manifold, whose values it takes from the nearest manifolds': with one height for all, the
            widest candidate bled a cube's top face into its side (``findings.md``). 1 against 0, frames
            0-2 from 1 / 4 spp: the validation set +0.08 / +0.08 dB (``bl_moving_metal`` -0.11 / -0.07, no
            other scene below -0.02), five of its clips rendered at 256x256 +0.18 / +0.13; the frame step
            with +-1 frames takes 1.3 times as long on one thread, 1.13-1.18 times on two (``findings.md``).
        firefly: ``"clamp"`` (log-domain pilot, clamp, linear filter), ``"log"`` (the pilot alone,
            biased dark), or ``"none"``.
        firefly_k: clamp threshold as a multiple of the pilot's luminance (+ a floor). 5 since the blend
            weighs the bandwidths by evidence (it leaves out one that a firefly spoils), against 3 before:
            on frames 0-2 of the validation set +0.07 / -0.04 dB from 1 / 4 spp (+0.59 on the caustic
            scene, no other scene more than -0.12), the denoise command's default +0.10; caustic energy
            0.65 -> 0.70 and 0.66 -> 0.71, the caustic scene's light ring 0.88 -> 0.92 (8 and 16 gain
            no more on the caustic scene and lose more elsewhere). 2 removed 8% of the energy of
            exponentially distributed samples.
        footprint_sigma: sigma (pixels) of the pixel-footprint average of the result (see
            :mod:`~torchmanifold.pipeline.footprint`); 0 keeps each pixel's own sample position; ``None``
            (default) takes it from the samples per pixel when the caller knows them
            (:func:`footprint_width`).
        albedo_eps: albedo luminance below which a pixel is not demodulated (delta BSDFs and black
            surfaces, whose first-hit albedo says nothing about the light there).
        radiance_sigma: range sigma of the log-radiance guide channel, which keeps lights, shadows
            and what is seen through glass apart where the renderer's features cannot; 0 leaves it out.
            The channel comes from the firefly pilot where there is one, else from the samples
            (:func:`_log_radiance`, at twice this sigma). 0.5 measured best on the tuning part. Where the
            pilot's own noise is a quarter of it or more, the sigma widens (:func:`_noise_widening`).
        demodulate: divide by albedo when albedo channels are present.
        keep_sky: pixels whose camera ray left the scene keep their samples (:func:`_escaped`), unless
            their colour is noise (:func:`_noisy_sky`: a scene in a medium, where a ray that meets no surface
            also reads depth 0 and its colour is in-scattered light); ``False`` filters them always.
        temporal_radius: neighbour frames on each side that join the filter (0 = per frame); where a
            frame's pilot is too noisy to trust, every frame of ``window_radius`` (:func:`_noisy_window`).
        albedo_radius: with a time window (``temporal_radius`` > 0) and world positions from the
            renderer, the frames on each side whose samples of each pixel's albedo join it
            (:func:`~torchmanifold.pipeline.footprint._window_albedo`); it may reach beyond the filter's
            window, as texture holds still where light does not need to. Validation set, 1 spp, against 1: 2
            +0.09 dB on the tuning part (``cbox_glossy_tex`` +0.24), 3 +0.13 at twice the cost; no scene below
            -0.03 (``benchmarks/validation/findings.md``).
        sigma_t: temporal sigma in frames.
        mode: ``"spacetime"`` or ``"window"`` (see :func:`~torchmanifold.ops.temporal_adaptive_manifold_filter`).
        dtype: working precision; float32 (fast C++ paths) bounds each result by the range of the
            samples near it, float64 keeps S/S0 exact where the weights get tiny.
    """

    sigma_s: float = 4.0
    bandwidths: Sequence[float] = (0.5, 1.0, 2.0, 4.0)
    selection_blur: float = 4.0
    selection_softness: float = 1.0
    guide: Sequence[str] | None = None
    guide_sigmas: Mapping[str, float] = field(default_factory=dict)
    tree_height: int = 3
    levels_per_doubling: int = 1
    firefly: str = "clamp"
    firefly_k: float = 5.0
    footprint_sigma: float | None = None
    albedo_eps: float = 0.02
    radiance_sigma: float = 0.5
    demodulate: bool = True
    keep_sky: bool = True
    temporal_radius: int = 0
    albedo_radius: int = 2
    sigma_t: float = 1.0
    mode: str = "spacetime"
    dtype: torch.dtype = torch.float32

    def check(self) -> "DenoiseSettings":
        """Raise TypeError / ValueError (see :mod:`torchmanifold._checks`) on a bad setting; return self."""
        from torchmanifold.ops.temporal import MODES

        for name in ("sigma_s", "firefly_k", "albedo_eps", "sigma_t"):
            check_positive(name, getattr(self, name))
        if isinstance(self.bandwidths, (str, bytes)) or not isinstance(self.bandwidths, Sequence) or \
                not self.bandwidths:
            raise TypeError(f"bandwidths must be a non-empty sequence of numbers, got {self.bandwidths!r}")
        for k, b in enumerate(self.bandwidths):
            check_positive(f"bandwidths[{k}]", b)
        for name in ("radiance_sigma", "selection_blur", "selection_softness"):
            check_nonnegative(name, getattr(self, name))
        if self.footprint_sigma is not None:
            check_nonnegative("footprint_sigma", self.footprint_sigma)
        check_choice("firefly", self.firefly, FIREFLY_MODES)
        check_choice("mode", self.mode, MODES)
        check_int("temporal_radius", self.temporal_radius, min=0)
        check_int("albedo_radius", self.albedo_radius, min=0)
        check_int("levels_per_doubling", self.levels_per_doubling, min=0)
        check_tree_height(self.tree_height)
        for k, v in dict(self.guide_sigmas).items():
            check_positive(f"guide_sigmas[{k!r}]", v)
        return self

    @property
    def window_radius(self) -> int:
        """The frames on each side that a query's output depends on: the filter's window, and the
        albedo's where there is a time window (0 per frame)."""
        return max(self.temporal_radius, self.albedo_radius) if self.temporal_radius > 0 else 0


#: the spatial sigma shrinks as ``spp ** -0.25``: with noise variance ~ 1/spp, a kernel's error on a
#: piecewise-smooth image (bias linear in the width at edges) is least at width ~ variance^(1/4). On the
#: validation set's tuning part, frames 0-2 from 4 spp, sigma 2.5 / 3 / 3.5 beat 4 by +0.11 / +0.10 /
#: +0.06 dB (every scene within -0.04 or better; the held-out part +0.18 / +0.15 / +0.10); from 1 spp, 4
#: stays (3: -0.08, 5: +0.07 on the tuning part, -0.10 on the held-out part). The progressive loop's
#: schedule, measured best at a = 0.5 on its own, shrinks at the same rate: sigma_n^2 ~ n^(a - 1)
_SIGMA_SPP_EXPONENT = -0.25


def spatial_sigma(settings: DenoiseSettings, samples_per_pixel: float | None) -> float:
    """The filter's reference spatial sigma (pixels): ``settings.sigma_s`` (its 1-spp figure) times
    ``spp ** -0.25`` when the samples per pixel are known (4 -> 2.83 from 4 spp), else
    ``settings.sigma_s``."""
    if not _known_count(samples_per_pixel):
        return float(settings.sigma_s)
    return float(settings.sigma_s) * float(samples_per_pixel) ** _SIGMA_SPP_EXPONENT


#: Where no albedo channel guides (colour alone, a renderer's Combined pass; or geometry alone), the guide
#: cannot tell texture from noise, so the bandwidth selection reaches down to nearly no filtering: two more
#: candidates, a half and a quarter of the narrowest. Frames 0-2 of the validation set from 1 / 4 spp
#: (findings.md, "Without albedo"): colour alone +0.63 / +1.31 dB (an eighth as well: +0.06 / +0.04);
#: normals, depth and positions without albedo +0.60 / +1.12, no scene below -0.2. With albedo, a 1 px
#: candidate lost 0.14 dB from 1 spp.
_NO_ALBEDO_NARROWER = (0.25, 0.5)
#: the range sigma of the pilot's chromaticity guide channels, r / (r + g + b) and g / (r + g + b), where
#: colour alone guides: a red ball on green grass has the grass's luminance. The tuning part, colour alone,
#: each frame alone: +0.40 / +0.50 dB over none; 0.025 +0.14 / +0.13 more there but -0.3 / -0.4 on its room
#: lit by bounce light and -0.7 / -0.8 on the held-out one; 0.1 -0.23 / -0.23. Beside geometry without
#: albedo it gains +0.30 / +0.47 on the tuning part but loses 0.5 / 0.4 on its room: colour alone only.
_CHROMA_SIGMA = 0.05


def adapt_to_features(settings: DenoiseSettings,
                      feature_names: Sequence[str]) -> tuple[DenoiseSettings, str | None]:
    """``settings`` for frames with these feature channels, and a note where they changed.

    Where no albedo channel guides, the candidates reach down to a quarter of the narrowest
    (:data:`_NO_ALBEDO_NARROWER`). Where no feature channel guides at all (colour alone), each frame is
    also filtered alone: nothing tells a moving view's frames apart, and the +-1 window smeared a pan's
    moving ball (-1.2 / -1.4 dB from 4 spp on two validation scenes), though it gained 0.7-0.9 dB on still
    views and +0.21 / -0.16 on average (frames 0-2, from 1 / 4 spp, findings.md)."""
    names = list(feature_names)
    guide = [names[k] for k in _select_guide(names, settings)]
    if _albedo_guides(guide):
        return settings, None
    low = min(float(b) for b in settings.bandwidths)
    bandwidths = tuple(sorted({low * f for f in _NO_ALBEDO_NARROWER} | set(map(float, settings.bandwidths))))
    note = f"no albedo guides: bandwidths {list(bandwidths)} times sigma_s"
    if guide:
        return replace(settings, bandwidths=bandwidths), note
    return (replace(settings, bandwidths=bandwidths, temporal_radius=0),
            note + "; no feature channel guides: each frame filtered alone (nothing tells a moving view's "
                   "frames apart)")


def _albedo_guides(guide_names: Sequence[str]) -> bool:
    """Whether an albedo channel is among the guide's: the texture the guide can tell from noise."""
    return any(feature_group(n) == "albedo" for n in guide_names)


def _select_guide(names: Sequence[str], settings: DenoiseSettings) -> list[int]:
    if settings.guide is None:
        # the feature table says which groups guide (not D/S: one random draw per sample) and which
        # make others redundant (world position makes depth redundant)
        return [k for k, n in enumerate(names) if feature_table.guides_by_default(n, names)]
    canon = [canonical_name(n) for n in names]
    idx = []
    for g in settings.guide:
        c = canonical_name(g)
        if c not in canon:
            raise ValueError(f"guide: feature channel {g!r} not found; available: {list(names)}")
        idx.append(canon.index(c))
    return idx


def _box_max(x: Tensor, r: int) -> Tensor:
    """Max over a (2r+1)^2 box around every pixel of ``(N, C, H, W)``, separably; O(log r) per pixel
    (a sparse table: maxima over doubling spans, the box read as two overlapping spans)."""
    return _window_max(_window_max(x, r, 3), r, 2)


def _window_max(x: Tensor, r: int, dim: int) -> Tensor:
    n, width = x.shape[dim], 2 * r + 1
    pad = [0, 0] * (x.dim() - 1 - dim) + [r, r]
    m = torch.nn.functional.pad(x, pad, value=-math.inf)
    span = 1  # m[i] holds the max over [i, i + span) of the padded row
    while 2 * span <= width:
        m = torch.maximum(m.narrow(dim, 0, m.shape[dim] - span), m.narrow(dim, span, m.shape[dim] - span))
        span *= 2
    return torch.maximum(m.narrow(dim, 0, n), m.narrow(dim, width - span, n))


#: Largest output of the bandwidths filtered in one call, in elements (256 MB of float32: four 16-channel
#: bandwidths of a 1 MP frame); a larger frame filters one bandwidth at a time.
_BANDWIDTHS_AT_ONCE = 1 << 26
#: the doublings that add tree levels (:func:`tree_height_at`): up to the default's widest candidate, 4
#: times ``sigma_s``; wider ones were not measured, and every level doubles the op's time
_MAX_DOUBLINGS = 2


def tree_height_at(settings: DenoiseSettings, bandwidth: float) -> int:
    """The manifold tree's height for a spatial sigma of ``bandwidth`` times ``sigma_s``:
    ``settings.tree_height``, plus ``settings.levels_per_doubling`` for each whole doubling beyond 1
    (a half step rounds down), for at most :data:`_MAX_DOUBLINGS` doublings."""
    doublings = min(_MAX_DOUBLINGS, max(0, math.floor(math.log2(float(bandwidth)) + 1e-9)))
    return min(MAX_TREE_HEIGHT, settings.tree_height + settings.levels_per_doubling * doublings)


class _Filter:
    """The weighted (sample-mask) adaptive-manifold filter over a clip, at query times.

    A query at a frame time with no temporal radius is a plain spatial filter (batched); otherwise the
    frames within ``temporal_radius`` (time units) of the query join through the temporal op.
    """

    def __init__(self, guide: Tensor, sigmas: Tensor, settings: DenoiseSettings,
                 frame_times: list[float], query_times: list[float],
                 sigma_s: float | None = None, range_scale: float = 1.0, tree_height: int | None = None):
        self.g, self.gs, self.st = guide, sigmas * range_scale, settings
        self.sigma_s = settings.sigma_s if sigma_s is None else sigma_s
        self.tree_height = settings.tree_height if tree_height is None else tree_height
        self.ft, self.qt = frame_times, query_times

    def _window(self, q: float) -> list[int]:
        return window(self.ft, q, self.st.temporal_radius)

    def _sigmas_at(self, q: float) -> Tensor:
        """Range sigmas of the frame nearest ``q``: one scale for every frame joined at that query."""
        i0, i1, w = bracket(self.ft, q)
        return self.gs[i1 if w > 0.5 else i0]

    def apply(self, x: Tensor) -> Tensor:
        """The op on the channel stack ``x`` ``(T, C, H, W)`` at every query: ``(Q, C, H, W)``, unnormalised."""
        return _Filter.apply_each([self], x)[0]

    @staticmethod
    def apply_each(filters: "list[_Filter]", x: Tensor) -> list[Tensor]:
        """:meth:`apply` of filters that differ in ``sigma_s`` and ``tree_height`` alone: per query, one op
        call for all of them (on CPU their images share the threads; the bits of one call each), as many at
        once as ``_BANDWIDTHS_AT_ONCE`` allows."""
        from torchmanifold.ops import temporal_adaptive_manifold_filter
        from torchmanifold.ops.adaptive_manifold import _filter_bandwidths
        from torchmanifold.ops.temporal import _spacetime_bandwidths

        per_call = max(1, _BANDWIDTHS_AT_ONCE // max(1, x[0].numel()))
        if len(filters) > per_call:
            return [y for i in range(0, len(filters), per_call) for y in _Filter.apply_each(filters[i:i + per_call], x)]
        f0, st = filters[0], filters[0].st
        sigmas, heights = [f.sigma_s for f in filters], [f.tree_height for f in filters]
        outs = []  # per query (K, C, H, W)
        for q in f0.qt:
            k = frame_at(f0.ft, q)
            if st.temporal_radius == 0 and k is not None:
                y = _filter_bandwidths(x[k:k + 1], f0.g[k:k + 1], sigmas, 1.0, heights, f0.gs[k])[:, 0]
            else:
                ids = f0._window(q)
                xw, gw, ftw = _frames(x, ids)[None], _frames(f0.g, ids)[None], [f0.ft[i] for i in ids]
                if st.mode == "spacetime":
                    y = _spacetime_bandwidths(xw, gw, ftw, [q], sigmas, 1.0, st.sigma_t, heights,
                                              f0._sigmas_at(q))[:, 0, 0]
                else:  # the window mean, then the spatial filter, per bandwidth
                    y = torch.stack([temporal_adaptive_manifold_filter(
                        xw, gw, ftw, [q], s, 1.0, sigma_t=st.sigma_t, mode=st.mode, tree_height=h,
                        guide_sigmas=f0._sigmas_at(q))[0, 0] for s, h in zip(sigmas, heights)])
            outs.append(y)
        return list((outs[0][:, None] if len(outs) == 1 else torch.stack(outs, 1)).unbind(0))

    def normalise(self, num: Tensor, den: Tensor, values: Tensor, mask: Tensor,
                  bounds: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """``num / den`` at the queries; where no valid sample lies under the kernel, the interpolated
        (masked) input; guarded (see :meth:`_guard`). ``bounds``: :meth:`window_bounds` of ``values`` and
        ``mask`` where the caller holds them (they do not depend on the bandwidth)."""
        if _fast.enabled(num, den, values, mask):
            radius = 0 if values.dtype == torch.float64 else self._guard_radius()
            if self._per_frame():
                return _fast.normalise_guard(num, den, values, mask, radius)
            fallback = self.at_queries(values * mask)
            hi, nlo = (bounds or self.window_bounds(values, mask)) if radius else (fallback, fallback)
            return _fast.normalise_guard_bounds(num, den, fallback, hi, nlo, radius)
        ok = den > _min_support(den.dtype)
        out = torch.where(ok, num / torch.where(ok, den, 1.0), self.at_queries(values * mask))
        return self._guard(out, values, mask, bounds)

    def _per_frame(self) -> bool:
        """Every query is a frame and mixes that frame alone (at_queries and at_queries_max are identities)."""
        return self.qt == self.ft and (self.st.temporal_radius == 0 or all(
            self._window(q) == [k] for k, q in enumerate(self.qt)))

    def _guard_radius(self) -> int:
        return max(1, int(math.ceil(_GUARD_RADIUS * self.sigma_s)))

    def __call__(self, values: Tensor, mask: Tensor) -> Tensor:
        y = self.apply(torch.cat([values * mask, mask], 1))
        return self.normalise(y[:, :-1], y[:, -1:], values, mask)

    def with_held_out(self, values: Tensor, mask: Tensor, cell: int = 1) -> tuple[Tensor, Tensor]:
        """``self(values, mask)`` of 3-channel values, and each pixel's filter of the other checkerboard
        half's samples alone (NaN where that half has none under the kernel), from one op call of both
        halves (:func:`_halves_stack` of ``cell``)."""
        pred, num, den = _split_halves(self.apply(_halves_stack(values, mask, cell)), cell)
        return self.normalise(num, den, values, mask), pred

    def window_bounds(self, values: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """At each query, the largest valid value of its window's frames and the largest minus valid value
        (``-max`` of the dtype where none): what the guard's box maxima start from."""
        big = torch.finfo(values.dtype).max
        return (self.at_queries_max(torch.where(mask > 0, values, -big)),
                self.at_queries_max(torch.where(mask > 0, -values, -big)))

    def _guard(self, out: Tensor, values: Tensor, mask: Tensor,
               bounds: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """A normalised filter is a convex combination: keep the result inside the range of the valid
        samples near the pixel. In float32 a pixel far from every manifold (weights ~1e-38) can come back
        as garbage; this bounds it (float64 needs no guard)."""
        if values.dtype == torch.float64:
            return out
        r = self._guard_radius()
        big = torch.finfo(values.dtype).max
        # the window's largest first, then the box (max commutes): one box per query, not per frame
        hi, lo = bounds or self.window_bounds(values, mask)
        hi, lo = _box_max(hi, r), -_box_max(lo, r)
        ok = hi > -big / 2
        return torch.where(ok, torch.minimum(torch.maximum(out, lo), hi), out)

    def at_queries_max(self, x: Tensor) -> Tensor:
        """Largest of the window's frames around each query (the bound of what the filter may mix)."""
        outs = []
        for q in self.qt:
            k = frame_at(self.ft, q)
            ids = self._window(q) if self.st.temporal_radius > 0 or k is None else [k]
            outs.append(_frames(x, ids).amax(0))
        return torch.stack(outs)

    def at_queries(self, x: Tensor) -> Tensor:
        """Per-frame data ``(T, C, H, W)`` at the query times, linear between bracketing frames."""
        return self.at_frames_to_queries(x, self.ft, self.qt)

    @staticmethod
    def at_frames_to_queries(x: Tensor, ft: list[float], qt: list[float]) -> Tensor:
        if list(qt) == list(ft):
            return x
        at = [frame_at(ft, q) for q in qt]
        if all(k is not None for k in at):
            return _frames(x, at)
        return torch.stack([interpolate(x, ft, q) for q in qt])


def _frames(x: Tensor, ids: Sequence[int]) -> Tensor:
    """``x[ids]`` along the frame dimension: a view where the frames are consecutive (a window, one
    query's frame), a copy otherwise."""
    ids = list(ids)
    if ids and ids == list(range(ids[0], ids[0] + len(ids))):
        return x[ids[0]:ids[0] + len(ids)]
    return x[ids]


def _halves(shape, device, cell: int = 1) -> Tensor:
    """A checkerboard ``(1, 1, H, W)`` of ``cell`` x ``cell`` pixel squares: 1 on half the pixels, 0 on the
    other half."""
    H, W = shape[-2:]
    yy = torch.arange(H, device=device)[:, None] // cell
    xx = torch.arange(W, device=device)[None, :] // cell
    return ((yy + xx) % 2 == 0)[None, None]


#: Cross-validation takes each pixel's noise as its own. A reconstruction filter that splats each sample
#: into the pixels around (Mitsuba's default, a gaussian of 2 px radius) shares samples between
#: neighbours: the other half's prediction then holds part of the pixel's own noise and narrow
#: bandwidths look right. A bounce-lit room rendered so (mi_indirect_dof, gaussian) came out 2 dB under a
#: plain Gaussian blur from 1 spp. Where the noise is found correlated (:func:`_cv_cell`) the halves are a
#: checkerboard of squares this many pixels wide, so that most pixels (36 of 64) have no neighbour in the
#: other half. On six Mitsuba clips rendered so, 8 px scored best on four and within 0.06 dB of 4 px on the
#: fifth (that room: 2 / 4 / 8 px +1.3 / +3.7 / +5.0 dB); 8 px squares everywhere would cost the 12
#: box-filtered scenes 0.05 / 0.11 dB from 1 / 4 spp, at most 0.35 on one (benchmarks/validation/findings.md),
#: so they are only where the test finds them needed.
_CORRELATED_CELL = 8
#: the test: in rows (and columns) of four pixels on one plain surface, how often the differences of the
#: two adjacent pairs, x1 - x0 and x2 - x3, have one sign. Their covariance is the correlation of adjacent
#: pixels (less twice that of pixels two apart, and a plain surface's slope), so independent noise gives
#: them one sign half the time and splatted samples more often: 0.47-0.52 on every frame of the validation
#: clips that has the pairs (and of two Cycles clips with its Blackman-Harris filter), 0.557-0.63 on five
#: Mitsuba clips rendered with its gaussian (benchmarks/validation/findings.md); the bound lies between.
_CORRELATED_SIGNS = 0.535
#: a plain surface: albedo and normal within a quarter of their range sigmas over the four pixels
_PLAIN_SPAN = 0.25
#: the feature groups constant over a plain surface (depth and position run along it)
_PLAIN_GROUPS = ("albedo", "N", "Ncam")
#: pairs of differences the share needs (a frame with fewer says nothing): its standard error is then at
#: most 0.011, and the bound three of them above one half
_MIN_SIGN_PAIRS = 2000
#: Without albedo nothing marks a plain surface (normals alone take in texture, which pulls the share below
#: one half), so the test runs on every row of four pixels of the colour's residual about its own Gaussian
#: blur of this width (pixels): the blur takes out most of the texture and shading, and its taps give
#: independent noise a share a little under one half.
_RESIDUAL_BLUR = 1.0
#: the bound on the residuals' share: first frames of the validation clips from 1 and 4 spp 0.47-0.51, the
#: two Cycles clips with its Blackman-Harris filter 0.45-0.49, the six Mitsuba clips with its gaussian
#: 0.543-0.589 (benchmarks/validation/findings.md); the bound lies between
_CORRELATED_RESIDUAL_SIGNS = 0.525
#: the squares there: without albedo only the narrow candidates keep texture, and inside a square they have
#: no sample of the other half within reach, so they go unjudged. The six Mitsuba clips with its gaussian,
#: colour alone, from 1 / 4 spp: squares of 2 / 4 / 8 px 23.57 / 26.82, 24.25 / 27.00, 24.25 / 26.33 dB
#: (per-pixel halves 22.64 / 25.94); 8 px blurs `mi_still_textures` 2.5 dB under its raw frames from 4 spp,
#: 4 px leaves the bounce-lit room 3 / 2 dB under a Gaussian blur (7 with per-pixel halves)
_CORRELATED_CELL_NO_ALBEDO = 4


def _cv_cell(e: Tensor, valid: Tensor, features: Tensor, sigmas: Tensor) -> Tensor:
    """Each frame's cross-validation cell ``(T,)`` int64: :data:`_CORRELATED_CELL` where neighbouring pixels'
    noise is correlated, else 1. From the samples ``e`` ``(T, 3, H, W)`` at ``valid`` pixels (bool
    ``(T, 1, H, W)``) and the guide's albedo and normal channels ``(T, F, H, W)`` of range sigmas ``(T, F)``:
    in every row (column) of four valid pixels on one plain surface, whether ``x1 - x0`` and ``x2 - x3`` have
    one sign (a difference of 0, as between two black pixels, tells nothing). With no such channel (``F`` 0:
    no albedo guides), in every row of four valid pixels of the residual about a blur
    (:data:`_RESIDUAL_BLUR`, :data:`_CORRELATED_RESIDUAL_SIGNS`), and the squares are
    :data:`_CORRELATED_CELL_NO_ALBEDO` wide."""
    with torch.no_grad():
        T, _, H, W = e.shape
        out = torch.ones(T, dtype=torch.int64)
        x = luminance(torch.where(valid, e, 0.0))
        residual = features.shape[1] == 0
        if residual:
            x = x - footprint_blur(x, _RESIDUAL_BLUR)
        else:
            g = features / sigmas.to(features.dtype).clamp_min(1e-30)[:, :, None, None]
        agree, total = torch.zeros(T, dtype=torch.int64), torch.zeros(T, dtype=torch.int64)
        for dim in (-1, -2):
            n = x.shape[dim] - 3
            if n <= 0:
                continue
            at = [x.narrow(dim, k, n) for k in range(4)]
            near, far = torch.sign(at[1] - at[0]), torch.sign(at[2] - at[3])
            if residual:
                plain = torch.ones_like(near, dtype=torch.bool)
            else:
                four = [g.narrow(dim, k, n) for k in range(4)]
                hi = torch.maximum(torch.maximum(four[0], four[1]), torch.maximum(four[2], four[3]))
                lo = torch.minimum(torch.minimum(four[0], four[1]), torch.minimum(four[2], four[3]))
                plain = (hi - lo).amax(1, keepdim=True) < _PLAIN_SPAN
            for k in range(4):
                plain &= valid.narrow(dim, k, n)
            counted = plain & (near != 0) & (far != 0)
            agree += (counted & (near == far)).flatten(1).sum(1)
            total += counted.flatten(1).sum(1)
        bound = _CORRELATED_RESIDUAL_SIGNS if residual else _CORRELATED_SIGNS
        correlated = (total >= _MIN_SIGN_PAIRS) & (agree > bound * total)
        return torch.where(correlated, _CORRELATED_CELL_NO_ALBEDO if residual else _CORRELATED_CELL, out)


def _halves_stack(e: Tensor, mask: Tensor, cell: int = 1) -> Tensor:
    """The op's input for cross-validation, ``(T, 8, H, W)``: per checkerboard half ``h`` (:func:`_halves`
    of ``cell``, then its complement) ``[e m h, m h]``, for samples ``e`` ``(T, 3, H, W)`` of weights ``m``
    ``(T, 1, H, W)``. The op's output on it holds each half's filter apart (:func:`_split_halves`)."""
    if cell == 1 and _fast.enabled(e, mask):
        return _fast.cv_halves(e, mask)
    half = _halves(e.shape, e.device, cell).to(e.dtype)
    return torch.cat([x for h in (half, 1 - half) for x in (e * (mask * h), mask * h)], 1)


def _split_halves(y: Tensor, cell: int = 1) -> tuple[Tensor, Tensor, Tensor]:
    """The op's output on :func:`_halves_stack` ``(Q, 8, H, W)`` of the same ``cell`` -> each pixel's
    prediction from the other half's samples alone ``(Q, 3, H, W)`` (NaN where that half has no sample
    under the kernel: no support, no estimate), and both halves' sums ``num`` ``(Q, 3, H, W)``, ``den``
    ``(Q, 1, H, W)``: the unnormalised filter of all samples."""
    if cell == 1 and _fast.enabled(y):
        return _fast.cv_split(y)
    Q, _, H, W = y.shape
    half = _halves(y.shape, y.device, cell)
    y = y.view(Q, 2, 4, H, W)
    num, den = y[:, :, :3], y[:, :, 3:]
    # a pixel of the first half is predicted from the second half's samples and the other way round
    other_num = torch.where(half, num[:, 1], num[:, 0])
    other_den = torch.where(half, den[:, 1], den[:, 0])
    ok = other_den > _min_support(y.dtype)
    pred = torch.where(ok, other_num / torch.where(ok, other_den, 1.0), float("nan"))
    return pred, num.sum(1), den.sum(1)


def _select_bandwidth(e: Tensor, mask: Tensor, guide: Tensor, sigmas: Tensor,
                      settings: DenoiseSettings, ft: list[float], qt: list[float], sigma_s: float,
                      range_scale: float, level: Tensor | None, pooling: Tensor | None = None,
                      cell: int = 1) -> Tensor:
    """Filter ``e`` at every bandwidth of ``settings.bandwidths`` and blend them per pixel by their error.

    The error of a bandwidth at a pixel is estimated by cross-validation on two interleaved halves of
    the pixels (Rousselle et al. 2012): each sample is predicted by the filter of the other half's
    samples alone, whose noise is independent of it, so the squared difference is the prediction's
    error plus the sample's variance, the same for every bandwidth. The squared differences are
    weighted as relative errors (against ``level``, a radiance estimate, plus a tenth of the frame's
    mean) and pooled over ``selection_blur`` pixels; a bandwidth's weight is the likelihood that its
    excess over the least error is noise (:func:`_excess_error_z2`). Each bandwidth's own output uses
    all samples (the two halves' sums add up).

    Args:
        e: ``(T, 3, H, W)`` samples; mask ``(T, 1, H, W)`` their weights (0: not filtered here).
        level: ``(T, 3, H, W)`` radiance estimate at the frames, or ``None`` (then the output at
            ``sigma_s`` itself).
        pooling: ``(T,)`` the factor on ``selection_blur`` at each frame (``FrameState.pooling``), or
            ``None`` (1).
        cell: the halves' checkerboard squares, in pixels (:func:`_cv_cell`).

    Returns:
        ``(Q, 3, H, W)`` at the query times.
    """
    T = e.shape[0]
    st = settings
    # Where every query is a frame, cross-validate at the queries alone (a query's window is filtered
    # once, its halves' sums are its output); otherwise at every frame, the errors interpolated.
    query_frames = [frame_at(ft, q) for q in qt]
    at_frames = all(k is not None for k in query_frames)
    cv_times = qt if at_frames else ft
    idx = query_frames if at_frames else list(range(T))
    preds, fulls, cv_outs = [], [], []
    filters = [_Filter(guide, sigmas, st, ft, cv_times, sigma_s * float(b), range_scale,
                       tree_height_at(st, b)) for b in st.bandwidths]
    stack = _halves_stack(e, mask, cell)
    # the guard's window bounds hold for every bandwidth (per-frame queries bound inside the fused kernel)
    windowed = not filters[0]._per_frame() and e.dtype != torch.float64
    bounds = filters[0].window_bounds(e, mask) if windowed else None
    for b, filt, y in zip(st.bandwidths, filters, _Filter.apply_each(filters, stack)):
        pred, num, den = _split_halves(y, cell)
        cv_out = filt.normalise(num, den, e, mask, bounds)
        preds.append(pred)
        cv_outs.append(cv_out)
        if at_frames:
            fulls.append(cv_out)
        else:
            at_queries = _Filter(guide, sigmas, st, ft, qt, sigma_s * float(b), range_scale, filt.tree_height)
            fulls.append(at_queries(e, mask))
    if level is None:
        level = cv_outs[min(range(len(st.bandwidths)), key=lambda k: abs(math.log(st.bandwidths[k])))]
    else:
        level = _frames(level, idx)
    # the residuals in units of the brightest frame mean of each query's window (its prediction mixes the
    # window's frames), so that the z statistics, which square their squares, overflow float32 neither on
    # a clip of values about 1e10 nor on a black frame between lit ones; per window, not per call, so that
    # a frame's bytes do not depend on which other frames share the call (a unit: no gradient passes it)
    brightness = _frame_mean(luminance(e.detach()).clamp_min(0.0), mask)[:, 0, 0, 0]
    top = torch.stack([brightness[window(ft, t, st.temporal_radius)].amax() for t in cv_times]).view(-1, 1, 1, 1)
    scale = torch.where(top > 0, top, torch.ones_like(top))
    e, mask = _frames(e, idx), _frames(mask, idx)
    lum = luminance(level).clamp_min(0.0)
    mean = _frame_mean(lum, mask)
    # relative errors, in units of the frame's mean: a per-frame factor leaves every z unchanged, and
    # the weights stay at most 1 / offset^2 on a frame whose mean is tiny or 0 (a black frame)
    unit = torch.where(mean > 0, mean, torch.ones_like(mean))
    weight = mask / (lum / unit + _LOG_RADIANCE_OFFSET) ** 2
    e, preds = e / scale, [p / scale for p in preds]
    # each frame pools over its own width, widened at most to the widest candidate's (a candidate's bias
    # varies on its own scale: pooling wider mixes places where it differs); frames pool apart, so
    # frames of one width go in one call
    widest = sigma_s * max(st.bandwidths)
    blurs = [st.selection_blur if pooling is None else
             max(st.selection_blur, min(st.selection_blur * float(pooling[k]), widest)) for k in idx]
    groups = [list(range(len(idx)))] if len(set(blurs)) == 1 else [[i] for i in range(len(idx))]

    def part(xs: list, g: list) -> list:
        return [x if len(groups) == 1 else _frames(x, g) for x in xs]

    if at_frames and st.selection_softness > 0 and st.selection_blur > 0 and \
            _fast.enabled(e, weight, mask, *preds, *fulls):
        return torch.cat([_fast.cv_blend(part(preds, g), part(fulls, g), *part([e, weight, mask], g),
                                         blurs[g[0]], st.selection_softness, _SELECTION_ERROR_CUT)
                          for g in groups])
    z2 = torch.cat([_candidate_z2(part(preds, g), *part([e, weight, mask], g), blurs[g[0]])
                    for g in groups], 1)
    if not at_frames:
        z2 = torch.stack([_Filter.at_frames_to_queries(x, ft, qt) for x in z2])
    if st.selection_softness > 0:
        w = torch.softmax(-z2 / (2 * st.selection_softness ** 2), 0)
    else:  # the least error has z = 0
        w = torch.nn.functional.one_hot(z2.argmin(0)[:, :, 0], len(z2)).permute(3, 0, 1, 2)[:, :, None]
        w = w.to(e.dtype)
    return (torch.stack(fulls) * w).sum(0)


def _candidate_z2(preds: list, e: Tensor, weight: Tensor, mask: Tensor, blur: float) -> Tensor:
    """``z^2`` of each candidate's error in excess of the least one's (:func:`_excess_error_z2`), ``(K, T, 1,
    H, W)``, from its predictions ``preds`` of the samples ``e`` ``(T, 3, H, W)``, the squared residuals
    weighted by ``weight`` and pooled over ``blur`` pixels."""
    # a prediction with no sample of the other half under its kernel (NaN) tells nothing of its error: it
    # pools as the worst candidate's residual there, and its candidate is left out at that pixel (its
    # residual is taken as 0 first, so no NaN reaches a gradient)
    held = torch.stack([~torch.isnan(p).any(1, keepdim=True) for p in preds])  # (K, T, 1, H, W)
    sq = torch.stack([(torch.where(h, p - e, 0.0) ** 2).sum(1, keepdim=True) * weight
                      for p, h in zip(preds, held)])
    sq = torch.where(held, sq, math.nan)
    worst = torch.where(held, sq, -math.inf).amax(0, keepdim=True)
    sq = torch.where(held, sq, torch.where(torch.isfinite(worst), worst, 0.0))
    return _excess_error_z2(sq, mask, blur, held | ~held.any(0, keepdim=True))


def _filter_flat_apart(filt, values: Tensor, mask: Tensor, flat: Tensor, flat_sigma: float,
                       at_queries) -> Tensor:
    """``filt(values, mask)`` (a filter of frames to queries), except that flat pixels beside demodulated
    ones are left out of it (weight 0) and take :func:`_flat_average` at ``flat_sigma``, brought to the
    queries by ``at_queries``. A frame of flat pixels alone (no albedo) is filtered whole."""
    if not (bool(flat.any()) and not bool(flat.all())):
        return filt(values, mask)
    out = filt(values, mask * ~flat)
    own = _flat_average(values, mask * flat, flat_sigma)
    return torch.where(at_queries(flat.to(out.dtype)) > 0.5, at_queries(own), out)


def _flat_average(e: Tensor, weight: Tensor, sigma: float) -> Tensor:
    """Flat pixels' own estimate, ``(T, 3, H, W)``: the ``weight``-ed average of ``e`` under a Gaussian of
    ``sigma`` pixels, each frame alone (``e`` itself where no weight lies under it).

    Flat pixels beside demodulated ones are delta surfaces and black ones (:func:`_demodulation_albedo`).
    Their guide is the surface's own features, which do not show what a mirror or glass shows, nor how
    that moves between frames, so they are not guided, selected or joined in time: the result takes this
    average at the narrowest bandwidth, the firefly pilot at its own. On the validation set that did
    better than the guided, selected space-time filter of the other pixels, and the op no longer carries
    a second class's channels (``benchmarks/validation/findings.md``). It tends to the samples as
    ``sigma`` shrinks.
    """
    return _normalised_blur(e, weight, sigma)


def _excess_error_z2(sq: Tensor, mask: Tensor, blur: float, allowed: Tensor) -> Tensor:
    """How surely each candidate's error exceeds the least one's: ``z^2`` per candidate and pixel.

    ``sq`` ``(K, T, 1, H, W)`` holds each candidate's weighted squared cross-validation residuals; a pixel's
    error of candidate b is their mean under a Gaussian of ``blur`` pixels (weighted by ``mask``
    ``(T, 1, H, W)``). The excess D of b over the least-error candidate a is the pooled mean of the
    residual differences d = sq_b - sq_a, whose standard error comes from their spread under the same
    kernel: ``var = sum k^2 m (d - D)^2 / (sum k m)^2``. The residuals of two candidates share the sample's
    own noise, so d is far less noisy than either residual; a candidate is out only where the evidence
    says so. ``z^2 = D^2 / var``, 0 for the least-error candidate. Candidates not ``allowed`` (bool, like
    ``sq``) and those whose error exceeds ``_SELECTION_ERROR_CUT`` times the least are left out
    (``_LEFT_OUT``); the least-error allowed candidate never is.
    """
    K = sq.shape[0]
    pool = footprint_blur(mask, blur).clamp_min(1e-6)
    err = footprint_blur(sq.flatten(0, 1), blur).view_as(sq) / pool
    if blur > 0:  # sum_j k_j^2 f_j = (sum_i k1_i^2)^2 times the blur of f at sigma / sqrt(2)
        c, blur2 = float((_gaussian_taps(blur, torch.float64) ** 2).sum()) ** 2, blur / math.sqrt(2)
    else:
        c, blur2 = 1.0, 0.0
    inv = c / pool ** 2
    s1 = footprint_blur(sq.flatten(0, 1), blur2).view_as(sq) * inv
    m2 = footprint_blur(mask, blur2) * inv
    pairs = [(a, b) for a in range(K) for b in range(a + 1, K)]
    d2 = {}
    if pairs:
        T = sq.shape[1]
        blurred = footprint_blur(torch.cat([(sq[b] - sq[a]) ** 2 for a, b in pairs]), blur2)
        for k, (a, b) in enumerate(pairs):
            d2[a, b] = d2[b, a] = blurred[k * T:(k + 1) * T] * inv
    best = torch.where(allowed, err, math.inf).argmin(0)  # (T, 1, H, W)
    least = err.gather(0, best[None])[0]
    z2 = torch.zeros_like(err)
    for b in range(K):
        for a in range(K):
            if a != b:
                D = err[b] - err[a]
                var = d2[a, b] - 2 * D * (s1[b] - s1[a]) + D * D * m2
                z2[b] = torch.where(best == a, D.clamp_min(0) ** 2 / var.clamp_min(1e-30), z2[b])
    out = ~allowed | (err > _SELECTION_ERROR_CUT * least)
    keep = torch.arange(K, device=err.device).view(-1, 1, 1, 1, 1) == best
    return torch.where(out & ~keep, _LEFT_OUT, z2)


@serial
def denoise_frames(color: Tensor, features: Tensor | None = None, feature_names: Sequence[str] = (),
                   emission: Tensor | None = None, settings: DenoiseSettings | None = None,
                   sigma_s: float | None = None, range_scale: float = 1.0,
                   frame_times: Sequence[float] | None = None, query_times: Sequence[float] | None = None,
                   pilot: Tensor | None = None, firefly_k: float | None = None,
                   samples_per_pixel: float | None = None, return_stats: bool = False):
    """Denoise a clip of Monte Carlo frames guided by their per-sample features.

    Args:
        color: ``(T, 3, H, W)`` linear radiance (e.g. 1 sample per pixel).
        features: ``(T, D, H, W)`` feature channels of the same samples, or ``None``.
        feature_names: the D names (EXR names such as ``albedo.R``, ``N.X``, ``Z``, ``P.X`` or tracer
            names such as ``Mr``, ``Nx``); albedo is used to demodulate when present.
        emission: optional ``(T, 3, H, W)`` emitted radiance at the first hit, part of ``color``.
        settings: :class:`DenoiseSettings` (defaults when ``None``).
        sigma_s: overrides ``settings.sigma_s`` (the progressive loop shrinks it).
        range_scale: multiplies every range sigma (the progressive loop shrinks it).
        frame_times: ``(T,)`` times of the frames (default ``0..T-1``, in frames).
        query_times: ``(Q,)`` times to output, may fall between frames (default ``frame_times``).
        pilot: optional ``(T, 3, H, W)`` radiance estimate of the frames (e.g. the progressive running
            average) used for firefly clamping instead of the log-domain pilot filter.
        firefly_k: overrides ``settings.firefly_k``.
        samples_per_pixel: how many samples each pixel of ``color`` averages (a renderer's EXR header
            says; :func:`~torchmanifold.io.exr.exr_samples_per_pixel`): sets the spatial sigma when
            ``sigma_s`` is not given (:func:`spatial_sigma`) and the footprint width when
            ``settings.footprint_sigma`` is ``None``
            (:func:`~torchmanifold.pipeline.footprint.footprint_width`).
        return_stats: also return a dict of counts (non-finite samples, firefly energy removed).

    Returns:
        ``(Q, 3, H, W)`` denoised radiance in ``color``'s dtype (and the stats dict when asked).

    Raises:
        TypeError, ValueError: wrong types/shapes, names not matching ``features``, bad settings.

    Example:
        >>> c, f = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
        >>> denoise_frames(c, f, ["albedo.R", "albedo.G", "albedo.B"]).shape
        torch.Size([2, 3, 32, 32])
    """
    settings = (settings or DenoiseSettings()).check()
    if not isinstance(color, Tensor):
        raise TypeError(f"color must be a torch.Tensor, got {type(color).__name__}")
    if color.dim() != 4 or color.shape[1] != 3:
        raise ValueError(f"color must be (T, 3, H, W), got {tuple(color.shape)}")
    T, _, H, W = color.shape
    names = list(feature_names)
    if features is None:
        features = color.new_zeros(T, 0, H, W)
        if names:
            raise ValueError("feature_names given without features")
    if not isinstance(features, Tensor) or features.dim() != 4 or features.shape[0] != T or \
            features.shape[2:] != color.shape[2:]:
        raise ValueError(f"features must be (T, D, H, W) matching color {tuple(color.shape)}, got "
                         f"{tuple(features.shape) if isinstance(features, Tensor) else type(features).__name__}")
    if features.shape[1] != len(names):
        raise ValueError(f"feature_names must name the {features.shape[1]} feature channels, got {len(names)}")
    if emission is not None and (not isinstance(emission, Tensor) or emission.shape != color.shape):
        raise ValueError(f"emission must be a tensor shaped like color {tuple(color.shape)}")

    ft = [float(t) for t in (range(T) if frame_times is None else frame_times)]
    qt = ft if query_times is None else [float(t) for t in query_times]
    if len(ft) != T:
        raise ValueError(f"frame_times must have one time per frame (T={T}), got {len(ft)}")
    if not qt or not all(math.isfinite(t) for t in ft + qt):
        raise ValueError("frame_times and query_times must be non-empty and finite")
    if pilot is not None and (not isinstance(pilot, Tensor) or pilot.shape != color.shape):
        raise ValueError(f"pilot must be a tensor shaped like color {tuple(color.shape)}")
    settings = adapt_to_features(settings, names)[0]
    state = prepare_frames(color, features, names, emission, settings, sigma_s, range_scale, pilot, firefly_k,
                           samples_per_pixel)
    out = denoise_prepared(state, settings, ft, qt, sigma_s, range_scale).to(color.dtype)
    return (out, state.stats()) if return_stats else out


@dataclass
class FrameState:
    """What the frame step derives from each frame alone, made by :func:`prepare_frames`.

    Every tensor holds one entry per frame, ``(T, ...)``, and no entry depends on the other frames, so a
    streamed clip prepares each frame once and joins the states of a window with :meth:`cat`.

    Attributes:
        values: ``(T, 3, H, W)`` demodulated samples to filter (fireflies clamped).
        level: ``(T, 3, H, W)`` demodulated radiance estimate (the pilot), or ``None`` without one.
        mask: ``(T, 1, H, W)`` sample weights (0 where a sample was not finite).
        flat: ``(T, 1, H, W)`` bool, pixels filtered as radiance (not demodulated).
        albedo: ``(T, 3, H, W)`` the albedo the output is multiplied back by.
        smooth: ``(T, 1, H, W)`` in [0, 1], how smooth the surface is around each pixel (see
            :func:`~torchmanifold.pipeline.footprint._smooth_surface`), or ``None`` without geometry channels
            in the guide or without a known sample count (then
            :func:`~torchmanifold.pipeline.footprint._remodulate` averages the product alone).
        escaped: ``(T, 1, H, W)`` bool, pixels whose camera ray left the scene (see :func:`_escaped`) and
            whose colour is no noise (:func:`_noisy_sky`): they keep their samples.
        emission: ``(T, 3, H, W)`` emitted radiance added back after filtering, or ``None``.
        position: ``(T, 3, H, W)`` the samples' world positions (``P``), or ``None`` where the renderer
            gives none or no time window is used: they tell which samples of the window's other frames
            fall in a pixel (:func:`~torchmanifold.pipeline.footprint._window_albedo`).
        guide: ``(T, G, H, W)`` the filter's guide; sigmas ``(T, G)`` float64 its range sigmas.
        pooling: ``(T,)`` float64, the factor on ``selection_blur`` for each frame (1 but where the pilot is
            noisy, :func:`_selection_pooling`).
        cv_cell: ``(T,)`` int64, each frame's cross-validation checkerboard squares in pixels (1 but where
            neighbouring pixels' noise is correlated, :func:`_cv_cell`).
        pilot_only: the output is the pilot itself (``firefly="log"`` without a caller's pilot).
        point_samples: each pixel holds one sample (a known count of 1), so its features are one point of the
            pixel's footprint (:func:`~torchmanifold.pipeline.footprint._window_albedo` looks for other
            frames' points in it).
        counts: sums over the frames: non-finite samples, clamped samples, energy and energy clamped.
        footprint: the footprint average's sigma (pixels), from the settings and the sample count.
        sigma_s: the reference spatial sigma (pixels) the frames were prepared with: the caller's, or
            from the settings and the sample count (:func:`spatial_sigma`).
    """

    values: Tensor
    level: Tensor | None
    mask: Tensor
    flat: Tensor
    albedo: Tensor
    smooth: Tensor | None
    escaped: Tensor
    emission: Tensor | None
    position: Tensor | None
    guide: Tensor
    sigmas: Tensor
    pooling: Tensor
    cv_cell: Tensor
    pilot_only: bool
    point_samples: bool
    counts: dict
    footprint: float
    sigma_s: float

    @staticmethod
    def cat(states: Sequence["FrameState"]) -> "FrameState":
        """The states of consecutive frames as one state."""
        def join(name):
            xs = [getattr(s, name) for s in states]
            return None if xs[0] is None else torch.cat(xs)
        counts = {k: sum(s.counts[k] for s in states) for k in states[0].counts}
        tensors = ("values", "level", "mask", "flat", "albedo", "smooth", "escaped", "emission", "position",
                   "guide", "sigmas", "pooling", "cv_cell")
        return FrameState(*(join(n) for n in tensors), states[0].pilot_only, states[0].point_samples, counts,
                          states[0].footprint, states[0].sigma_s)

    def stats(self) -> dict:
        """Non-finite samples, masked pixels, clamped samples, the fraction of energy clamped and the frames
        whose sky was filtered as noise (``noisy_sky_frames``)."""
        c = dict(self.counts)
        removed, total = c.pop("firefly_energy"), c.pop("energy")
        return {**c, "firefly_energy_removed": removed / max(total, 1e-30)}


@serial
def prepare_frames(color: Tensor, features: Tensor, feature_names: Sequence[str], emission: Tensor | None,
                   settings: DenoiseSettings, sigma_s: float | None = None, range_scale: float = 1.0,
                   pilot: Tensor | None = None, firefly_k: float | None = None,
                   samples_per_pixel: float | None = None, own_pixels: bool = False) -> FrameState:
    """Sanitise, demodulate, guide and clamp fireflies, each frame on its own (arguments as
    :func:`denoise_frames`, already checked there; ``own_pixels``: the caller knows that each pixel holds
    its own samples, as our tracer's do, so the frames are not tested for correlated noise)."""
    names = list(feature_names)
    dt = settings.dtype
    k_ff = settings.firefly_k if firefly_k is None else float(firefly_k)
    base = spatial_sigma(settings, samples_per_pixel) if sigma_s is None else float(sigma_s)
    em = None if emission is None else emission.to(dt)
    c, f, mask, em, counts = _sanitize(color.to(dt), features.to(dt), em)
    alb, flat = _demodulation_albedo(f, names, settings)
    sky = _escaped(f, names)
    lone = _lone_flat_samples(c, flat & ~sky)
    if bool(lone.any()):
        f = _from_neighbours(f, lone, ~flat)
        alb, flat = _demodulation_albedo(f, names, settings)
        sky = _escaped(f, names)  # a repaired pixel may take depth 0 from sky beside it
    noisy_sky = _noisy_sky(c, sky & (mask > 0))
    counts["noisy_sky_frames"] = int(noisy_sky.sum())
    kept = sky & ~noisy_sky & settings.keep_sky
    # a sky that is filtered is light, not a surface: it has no albedo to divide by (Mitsuba writes 0,
    # Cycles in fog the medium's colour, noisy) nor surface features; it is divided by 1, its features are 0
    # (Mitsuba's convention), which keep it apart from the surfaces, and it is filtered with them, not
    # averaged apart as flat
    lit = sky & ~kept
    alb, flat, f = torch.where(lit, 1.0, alb), flat & ~lit, torch.where(lit, 0.0, f)
    escaped = kept & (mask > 0)
    e = c / alb
    guide, sig, gnames = _guide(f, names, e, mask, settings)
    # texture gets its own footprint where the sample count, hence the samples' jitter, is known
    geometry = [k for k, n in enumerate(gnames) if feature_group(n) != "albedo"]
    known = settings.footprint_sigma is None and _known_count(samples_per_pixel)
    smooth = _smooth_surface(guide[:, geometry], sig[:, geometry]) if geometry and known else None
    counts.update(firefly_clamped_samples=0, firefly_energy=0.0, energy=0.0)
    fp = footprint_width(settings, samples_per_pixel)
    position = _position(f, names) if settings.temporal_radius > 0 else None  # used by a window alone
    point = _known_count(samples_per_pixel) and float(samples_per_pixel) == 1
    # the demodulated pixels; every pixel of a frame that has no albedo to demodulate by
    demodulated = ~flat | flat.flatten(1).all(1).view(-1, 1, 1, 1)
    # a plain surface needs its albedo: normals alone take in texture
    plain = [k for k, n in enumerate(gnames) if feature_group(n) in _PLAIN_GROUPS] if _albedo_guides(gnames) \
        else []
    cell = torch.ones(c.shape[0], dtype=torch.int64) if own_pixels else \
        _cv_cell(e, (mask > 0) & demodulated, guide[:, plain], sig[:, plain])
    state = FrameState(e, None, mask, flat, alb, smooth, escaped, em, position, guide, sig,
                       torch.ones(c.shape[0], dtype=torch.float64), cell, False, point, counts, fp, base)
    if settings.firefly == "none":
        return state
    ft = [float(t) for t in range(c.shape[0])]
    if pilot is not None:
        pe = pilot.to(dt)
        pe = torch.where(torch.isfinite(pe), pe, 0.0)
        if em is not None:
            pe = pe - em
        pe = pe.clamp_min(0.0) / _footprint_albedo(alb, flat, fp)  # a pixel average
    else:  # log-domain pilot at the frames themselves (spatial only: cheap, fireflies compressed)
        pf = _Filter(guide, sig, replace(settings, temporal_radius=0), ft, ft, base, range_scale)
        # the log domain compresses what is bright for the frame, whatever the exposure
        level = _frame_mean(luminance(e), mask).clamp_min(1e-30)
        x = torch.log1p(e.clamp_min(0.0) / level)
        held = {}

        def pilot_filter(values, weights):  # keeps the held-out estimate (flat pixels apart have none)
            out, held["x"] = pf.with_held_out(values, weights, int(cell.max()))
            return out
        pe = level * torch.expm1(_filter_flat_apart(pilot_filter, x, mask, flat, base, pf.at_queries))
    state.level = pe
    if settings.firefly == "log" and pilot is None:
        state.pilot_only = True
        return state
    state.values = _clamp_fireflies(e, alb, pe, mask, k_ff, counts, escaped)
    if pilot is None:  # a caller's pilot is a past result: guiding by it would lock its errors in
        noise = _pilot_noise(pe, level * torch.expm1(held["x"]), (mask > 0) & demodulated)
        state.guide, state.sigmas = _radiance_from_pilot(guide, sig, pe, mask, settings, noise)
        if not gnames:  # colour alone: its hue tells apart what its luminance does not
            state.guide, state.sigmas = _with_chromaticity(state.guide, state.sigmas, pe, mask)
        state.sigmas = _albedo_widened(state.sigmas, gnames, noise)
        state.level = _trusted_level(pe, mask, _pilot_trust(noise / _PILOT_NOISE_SCALE))
        state.pooling = _selection_pooling(noise / _PILOT_NOISE_SCALE)
    return state


@serial
def denoise_prepared(state: FrameState, settings: DenoiseSettings, frame_times: Sequence[float],
                     query_times: Sequence[float], sigma_s: float | None = None,
                     range_scale: float = 1.0) -> Tensor:
    """Filter prepared frames at the query times: ``(Q, 3, H, W)`` in ``settings.dtype`` (arguments as
    :func:`denoise_frames`). At a query whose frame's pilot is too noisy to trust, the time window joins
    every frame the albedo's window holds (:func:`_noisy_window`)."""
    ft, qt = list(frame_times), list(query_times)
    wide = _noisy_window(state, settings, ft, qt)
    if any(wide):
        if not all(wide):  # each query with its own window: a frame's bytes do not depend on the others'
            return torch.cat([denoise_prepared(state, settings, ft, [q], sigma_s, range_scale) for q in qt])
        settings = replace(settings, temporal_radius=settings.window_radius)
    base = state.sigma_s if sigma_s is None else float(sigma_s)
    s = state

    def at_queries(x: Tensor) -> Tensor:
        return _Filter.at_frames_to_queries(x, ft, qt)

    if s.pilot_only:
        out = at_queries(s.level)
    else:
        if len(settings.bandwidths) == 1:
            b = float(settings.bandwidths[0])
            filt = _Filter(s.guide, s.sigmas, settings, ft, qt, base * b, range_scale,
                           tree_height_at(settings, b))
        else:
            def filt(values, mask):
                return _select_bandwidth(values, mask, s.guide, s.sigmas, settings, ft, qt, base, range_scale,
                                         s.level, s.pooling, int(s.cv_cell.max()))
        out = _filter_flat_apart(filt, s.values, s.mask, s.flat, base * min(settings.bandwidths), at_queries)
    if bool(s.escaped.any()):  # what the camera sees of the environment has no noise to filter
        out = torch.where(at_queries(s.escaped.to(out.dtype)) > 0.5, at_queries(s.values), out)
    albedo, counts = at_queries(s.albedo), None
    if s.position is not None and settings.temporal_radius > 0:
        albedo, counts = _window_albedo(albedo, s, ft, qt, settings.albedo_radius)
    out = _remodulate(out, albedo, at_queries(s.flat.to(out.dtype)) > 0.5,
                      None if s.smooth is None else at_queries(s.smooth), s.footprint, counts,
                      1 + 2 * settings.albedo_radius, _UNSEEN_BORDER if s.point_samples else 0.0)
    if s.emission is not None:  # the renderer's emission is added back exactly as rendered
        out = out + at_queries(s.emission)
    return out


def _noisy_window(state: FrameState, settings: DenoiseSettings, ft: list[float],
                  qt: list[float]) -> list[bool]:
    """Per query, whether its time window widens to every frame the albedo's window holds
    (``settings.window_radius``): where the query is a frame whose firefly pilot is too noisy to trust
    (``state.pooling`` above 1, :func:`_selection_pooling`), as the selection's pooling widens there. Only
    the two rooms lit by bounce light alone are that noisy: frames 0-5 from 1 / 4 spp, ``mi_indirect_dof``
    (tuning part) +0.15 / +0.11 dB and ``bl_indirect_dof`` (held out) +0.11 / +0.14 with +-2 frames against
    +-1 (for 5/3 of the op's time there); every other scene keeps its bits."""
    if settings.temporal_radius == 0 or settings.window_radius <= settings.temporal_radius:
        return [False] * len(qt)
    at = [frame_at(ft, q) for q in qt]
    return [k is not None and float(state.pooling[k]) > 1.0 for k in at]


def _sanitize(c: Tensor, f: Tensor, em: Tensor | None):
    """Zero non-finite samples and mark them with weight 0; take emission out of the colour."""
    if _fast.enabled(c, f):
        c, f, mask, stats = _fast.sanitize(c, f)
    else:
        mask = (torch.isfinite(c).all(1, keepdim=True) & torch.isfinite(f).all(1, keepdim=True)).to(c.dtype)
        stats = {"nonfinite_color": int((~torch.isfinite(c)).sum()),
                 "nonfinite_features": int((~torch.isfinite(f)).sum()),
                 "masked_pixels": int((mask == 0).sum())}
        c = torch.where(torch.isfinite(c), c, 0.0)
        f = torch.where(torch.isfinite(f), f, 0.0)
    if em is not None:
        em = torch.where(torch.isfinite(em), em, 0.0)
        c = (c - em).clamp_min(0.0)
    return c, f, mask, em, stats


def _demodulation_albedo(f: Tensor, names: Sequence[str], settings: DenoiseSettings) -> tuple[Tensor, Tensor]:
    """The albedo the colour is divided by, ``(T, 3, H, W)``, and where it is flat (1), ``(T, 1, H, W)``.

    A first-hit albedo darker than ``albedo_eps`` says nothing about the light there: renderers give 0 on
    delta BSDFs (Mitsuba's glass and mirrors) and on black surfaces. Dividing by a clamped tiny albedo
    and multiplying back by a blurred one draws bright rims, so such pixels are not demodulated at all.
    """
    canon = [canonical_name(n) for n in names]
    T, _, H, W = f.shape
    if not (settings.demodulate and all(a in canon for a in _ALBEDO)):
        return f.new_ones(T, 3, H, W), f.new_ones(T, 1, H, W, dtype=torch.bool)
    alb = torch.stack([f[:, canon.index(a)] for a in _ALBEDO], 1).clamp_min(0.0)
    flat = luminance(alb) < settings.albedo_eps
    return torch.where(flat, 1.0, alb.clamp_min(settings.albedo_eps)), flat


def _lone_flat_samples(c: Tensor, flat: Tensor) -> Tensor:
    """Flat pixels ``(T, 1, H, W)`` that are sample events, not surfaces: no adjacent pixel is flat, and the
    colour ``c`` ``(T, 3, H, W)`` is darker than the four adjacent pixels' mean.

    A delta surface or a black one covers connected pixels. A flat pixel alone among demodulated ones,
    and dark, is a path that left neither albedo nor light: Cycles' denoising albedo looks through glass,
    and a 1-spp path that ends inside it writes albedo 0 and colour 0, so a glass ball showed black dots
    where the reference is the wall behind it. A lone flat pixel brighter than its surroundings stays flat
    (a light one or two pixels wide has no albedo in Mitsuba's AOVs); one with a flat neighbour may be the
    edge of a delta surface (``benchmarks/validation/findings.md``)."""
    if not bool(flat.any()):
        return flat
    alone = flat & (_four_neighbours(flat.to(c.dtype)) == 0)
    lum = luminance(c).clamp_min(0.0)
    return alone & (lum * _four_neighbours(torch.ones_like(lum)) < _four_neighbours(lum))


def _from_neighbours(f: Tensor, where: Tensor, source: Tensor) -> Tensor:
    """Features ``f`` ``(T, D, H, W)`` with the pixels ``where`` replaced by the mean of their adjacent
    ``source`` pixels (both bool ``(T, 1, H, W)``), where they have any."""
    w = source.to(f.dtype)
    total, n = _four_neighbours(f * w), _four_neighbours(w)
    return torch.where(where & (n > 0), total / n.clamp_min(1.0), f)


def _escaped(f: Tensor, names: Sequence[str]) -> Tensor:
    """Pixels whose camera ray left the scene, ``(T, 1, H, W)`` bool: 0 in every channel whose 0 means
    no hit (``zero_is_no_hit`` in :mod:`torchmanifold.features`: depth ``Z``, ``Zplane``), or where no depth
    is given, in the unit normals (``unit``: a pixel's average of unit vectors is 0 only where no sample
    hit; without depth or positions, `mi_env_thin` +1.10 / +0.81 dB from 1 / 4 spp, frames 0-2, back to its
    score with them); none without either.

    Such a pixel's colour is the environment seen directly: a 1-spp pixel is exact up to the spread of
    the environment over the pixel, which the footprint average takes. Filtering it only blurs the sky:
    on the validation set ``mi_env_thin`` (40% sky) gains 0.45 / 0.58 dB from 1 / 4 spp, every other
    scene stays within 0.01 dB (``benchmarks/validation/findings.md``).
    """
    table = [feature_table.feature_of(n) for n in names]
    depth = [k for k, row in enumerate(table) if getattr(row, "zero_is_no_hit", False)]
    if not depth:  # the normals, where no depth is given: 0 only where every sample left the scene
        depth = [k for k, row in enumerate(table) if getattr(row, "unit", False)]
    if not depth:
        return f.new_zeros(f.shape[0], 1, *f.shape[2:], dtype=torch.bool)
    missed = (f[:, depth] == 0).all(1, keepdim=True)
    # a frame whose depth is 0 everywhere holds a placeholder, not a view of the sky alone
    return missed & ~missed.flatten(1).all(1).view(-1, 1, 1, 1)


#: A sky pixel keeps its samples because the environment seen directly has no noise. In a medium (fog) a ray
#: that meets no surface reads depth 0 as well, and its colour is in-scattered light, as noisy as any. Kept,
#: the validation set's probes in fog scored 19.2 / 20.2 dB from 1 / 4 spp (Mitsuba, ``mi_fog``; OIDN 33.4 /
#: 35.6) and 21.6 / 30.5 (Cycles, ``bl_fog``; OIDN 31.8 / 34.3, a Gaussian blur 22.4 / 32.0). Noise is told
#: from the environment's own detail by R, the mean square of the sky's differences between adjacent pixels
#: over that of pixels two apart (rows and columns of three sky pixels, on the luminance tone-mapped by the
#: sky's mean): independent noise gives 1, a smooth gradient 1/4, an edge 1/2, stripes a pixel wide more
#: than 1. Per frame, from 1 and 4 spp: the validation set's skies (Mitsuba's and Cycles', 128x128 and
#: 256x256) 0.24-0.31, the two fog clips 0.97-1.03. The sky is noise within a factor sqrt(2) of 1
#: (``benchmarks/validation/findings.md``).
_NOISY_SKY = (2.0 ** -0.5, 2.0 ** 0.5)
#: the largest differences left out of both means: a small sun's rim or a few stars are points, which a
#: smooth sky around them would make look like noise
_SKY_OUTLIERS = 0.01
#: rows of three sky pixels the test needs: for independent noise R's standard error is then about 0.09
_MIN_SKY_TRIPLETS = 500


def _noisy_sky(c: Tensor, sky: Tensor) -> Tensor:
    """Per frame, whether the colour ``c`` ``(T, 3, H, W)`` of the sky pixels ``sky`` (bool ``(T, 1, H, W)``,
    :func:`_escaped`) is noise: ``(T, 1, 1, 1)`` bool, by the ratio of :data:`_NOISY_SKY` (a frame with fewer
    than :data:`_MIN_SKY_TRIPLETS` rows of three sky pixels, or a black sky, is not). In NumPy float64, whose
    sums do not depend on the thread count."""
    out = torch.zeros(c.shape[0], 1, 1, 1, dtype=torch.bool)
    with torch.no_grad():
        lum = luminance(c.detach()).double().clamp_min(0.0)[:, 0].cpu().numpy()
        masks = sky[:, 0].cpu().numpy()
    lo, hi = _NOISY_SKY
    for t, (x, s) in enumerate(zip(lum, masks)):
        if int(s.sum()) < _MIN_SKY_TRIPLETS:
            continue
        y = x / np.maximum(x + x[s].mean(), 1e-300)
        near, far = [], []
        for a, b, d, m in ((y[:, :-2], y[:, 1:-1], y[:, 2:], s[:, :-2] & s[:, 1:-1] & s[:, 2:]),
                           (y[:-2], y[1:-1], y[2:], s[:-2] & s[1:-1] & s[2:])):
            near.append((a - b)[m] ** 2)
            far.append((a - d)[m] ** 2)
        near, far = np.concatenate(near), np.concatenate(far)
        if near.size < _MIN_SKY_TRIPLETS:
            continue
        keep = near.size - int(_SKY_OUTLIERS * near.size)  # the largest 1% left out of each
        near_sum = np.partition(near, keep - 1)[:keep].sum()
        far_sum = np.partition(far, keep - 1)[:keep].sum()
        out[t] = bool(lo * far_sum < near_sum < hi * far_sum)
    return out


def _log_radiance(e: Tensor, mask: Tensor) -> Tensor:
    """Log luminance of the demodulated colour, ``(T, 1, H, W)``: a guide channel that tells lights from
    the surface they sit in (no renderer AOV does), shadows from lit ground and what is seen through glass.

    ``log(L + 0.1 mean(L))`` is the same for any exposure and does not resolve noise far below the
    frame's level; each pixel takes the mean of the least varying of the four 3x3 windows that hold it
    in a corner (a Kuwahara filter), so a pixel on the edge of a light still reads as the light.
    """
    L = luminance(e).clamp_min(0.0)
    mean = _frame_mean(L, mask)
    lg = torch.log(L + _LOG_RADIANCE_OFFSET * mean.clamp_min(1e-30))
    if _fast.enabled(lg):
        return _fast.kuwahara3(lg)
    H, W = lg.shape[-2:]
    moments = torch.nn.functional.pad(torch.cat([lg, lg * lg], 1), (2, 2, 2, 2), mode="replicate")
    moments = torch.nn.functional.avg_pool2d(moments, 3, 1)
    best_v = best_m = None
    for dy in (0, 2):
        for dx in (0, 2):
            mu = moments[:, 0:1, dy:dy + H, dx:dx + W]
            v = moments[:, 1:2, dy:dy + H, dx:dx + W] - mu * mu
            if best_v is None:
                best_v, best_m = v, mu
            else:
                take = v < best_v
                best_v, best_m = torch.where(take, v, best_v), torch.where(take, mu, best_m)
    return best_m


def _guide(f: Tensor, names: Sequence[str], e: Tensor, mask: Tensor, settings: DenoiseSettings):
    """The guide ``(T, G, H, W)``, its range sigmas ``(T, G)`` per frame and the names of its feature
    channels, its first ones (the log-radiance channel, when there is one, comes last)."""
    T, _, H, W = e.shape
    gi = _select_guide(names, settings)
    gnames = [names[k] for k in gi]
    parts, sig = [], []
    if gi:
        guide = f[:, gi]
        s = default_guide_sigmas(gnames, guide, mask > 0)
        over = {canonical_name(k): float(v) for k, v in dict(settings.guide_sigmas).items()}
        unknown = [k for k in over if k not in [canonical_name(n) for n in gnames] + [RADIANCE_GUIDE]]
        if unknown:
            raise ValueError(f"guide_sigmas: channels {unknown} are not guide channels {gnames + [RADIANCE_GUIDE]}")
        for k, n in enumerate(gnames):
            if canonical_name(n) in over:
                s[:, k] = over[canonical_name(n)]
        # (guide is a copy: f indexed by a list)
        ai = [k for k, n in enumerate(gnames) if feature_group(n) == "albedo"]
        if ai:  # renderer albedo may exceed 1 (conductors); the guide only needs its colour
            guide[:, ai] = guide[:, ai].clamp(0.0, 1.0)
        # scene units: centred on each frame's mean, which leaves every range difference as it is, so that
        # a scene far from the origin (positions of 1e30) does not overflow the filter's float32 squares
        xi = [k for k, n in enumerate(gnames) if feature_table.feature(feature_group(n)).sigma_of_extent]
        if xi:
            guide[:, xi] = (guide[:, xi].double() - _channel_means(guide[:, xi], mask)).to(guide.dtype)
        parts.append(guide)
        sig.append(s)
    rs = _radiance_sigma(settings)
    if rs > 0:  # from single samples: noisier than the pilot's that replaces it, so wider
        parts.append(_log_radiance(e, mask))
        sig.append(torch.full((T, 1), _SAMPLE_RADIANCE_WIDENING * rs, dtype=torch.float64))
    if not parts:
        return e.new_zeros(T, 1, H, W), torch.ones(T, 1, dtype=torch.float64), gnames
    return torch.cat(parts, 1), torch.cat(sig, 1), gnames


def _radiance_sigma(settings: DenoiseSettings) -> float:
    return float(dict(settings.guide_sigmas).get(RADIANCE_GUIDE, settings.radiance_sigma))


def _radiance_from_pilot(guide: Tensor, sigmas: Tensor, pilot: Tensor, mask: Tensor,
                         settings: DenoiseSettings, noise: Tensor | None = None):
    """The guide with its log-radiance channel (the last, see :func:`_guide`) taken from the pilot
    estimate ``(T, 3, H, W)`` instead of the samples: it tells a light, a shadow or what glass shows from
    their surroundings without resolving the noise of single samples. ``noise`` ``(T,)``: the pilot's own
    noise in the channel's units (:func:`_pilot_noise`); where it reaches a quarter of the channel's
    sigma the sigma widens, and at half of it the channel no longer steers (:func:`_noise_widening`)."""
    rs = _radiance_sigma(settings)
    if rs <= 0:
        return guide, sigmas
    L = luminance(pilot).clamp_min(0.0)
    mean = _frame_mean(L, mask)
    guide = torch.cat([guide[:, :-1], _log_radiance_of(L, mean)], 1)
    sigmas = sigmas.clone()
    sigmas[:, -1] = rs if noise is None else rs * _noise_widening(noise.to(sigmas.dtype) / rs)
    return guide, sigmas


def _with_chromaticity(guide: Tensor, sigmas: Tensor, pilot: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """The guide ``(T, G, H, W)`` and its sigmas ``(T, G)`` with two more channels: the chromaticity of the
    pilot ``(T, 3, H, W)``, ``r / (r + g + b)`` and ``g / (r + g + b)`` (the sum offset by a thousandth of
    the frame's mean luminance, so black pixels stay near 0), at :data:`_CHROMA_SIGMA`."""
    p = pilot.clamp_min(0.0)
    total = p.sum(1, keepdim=True) + 1e-3 * _frame_mean(luminance(p), mask).clamp_min(1e-30)
    chroma = torch.full((guide.shape[0], 2), _CHROMA_SIGMA, dtype=sigmas.dtype)
    return torch.cat([guide, (p[:, :2] / total).to(guide.dtype)], 1), torch.cat([sigmas, chroma], 1)


def _log_radiance_of(L: Tensor, mean: Tensor) -> Tensor:
    """The log-radiance guide channel of luminance ``L`` ``(T, 1, H, W)`` whose frame means are ``mean``."""
    return torch.log(L + _LOG_RADIANCE_OFFSET * mean.clamp_min(1e-30))


#: the widening of the log-radiance channel's sigma where the pilot is noisy; its largest value leaves
#: the channel without effect
_RADIANCE_OFF = 1e6
#: the pilot's noise (log units) that the selection's level is judged by: the default log-radiance sigma
_PILOT_NOISE_SCALE = 0.5


#: the pilot's noise, in units of a range sigma, up to which it is trusted whole (two pixels of the same
#: radiance then differ by a third of the sigma, typically, and weigh each other 0.94) and from which not at
#: all (they differ by 0.7 of the sigma: the pilot steers by noise)
_PILOT_TRUSTED, _PILOT_UNTRUSTED = 0.25, 0.5


def _pilot_trust(relative_noise: Tensor) -> Tensor:
    """How far the pilot is trusted, in [0, 1], from its noise in units of a range sigma: 1 up to
    :data:`_PILOT_TRUSTED`, falling linearly to 0 at :data:`_PILOT_UNTRUSTED`."""
    return ((_PILOT_UNTRUSTED - relative_noise) / (_PILOT_UNTRUSTED - _PILOT_TRUSTED)).clamp(0.0, 1.0)


def _selection_pooling(relative_noise: Tensor) -> Tensor:
    """The factor on the bandwidth selection's pooling width (``selection_blur``) for the pilot's noise in
    units of a range sigma: 1 where the pilot is trusted whole (up to :data:`_PILOT_TRUSTED`), and the
    noise over that beyond it. The pooled errors' standard error goes as the noise over the square root of
    the pixels pooled, so the width grows as the noise: the selection tells the candidates apart as surely
    as at a trusted pilot (up to the widest candidate's bandwidth, :func:`_select_bandwidth`). Only the two
    rooms lit by bounce light alone are that noisy (0.23-0.36 against at most 0.11, ``findings.md``): over
    all frames from 1 / 4 spp, ``mi_indirect_dof`` (tuning part) +0.08 / +0.28 dB and ``bl_indirect_dof``
    (held out) +0.21 / +0.25; every other scene keeps its bits."""
    return (relative_noise.to(torch.float64) / _PILOT_TRUSTED).clamp_min(1.0)


def _noise_widening(relative_noise: Tensor) -> Tensor:
    """The factor on a guide channel's sigma for the pilot's noise in units of a range sigma: 1 over
    :func:`_pilot_trust`, up to :data:`_RADIANCE_OFF` where it is not trusted at all (the log-radiance
    channel's, :func:`_radiance_from_pilot`; the albedo's, :func:`_albedo_widened`). Where the pilot is
    that noisy, its sample is the larger part of it at a bright sample: such a sample lands far from every
    manifold and its light is lost (the validation set: the pilot's noise is at most 0.11 on every scene
    but one, lit by bounce light alone, where it is 0.26 and the channel cost 1.9 / 3.1 dB from 1 / 4 spp;
    ``findings.md``)."""
    w = _pilot_trust(relative_noise)
    return torch.where(w > 0, 1.0 / w.clamp_min(1.0 / _RADIANCE_OFF), _RADIANCE_OFF)


def _albedo_widened(sigmas: Tensor, names: Sequence[str], noise: Tensor) -> Tensor:
    """The guide's range sigmas ``(T, G)`` with those of its albedo channels (named by ``names``, the
    guide's first channels) widened for the pilot's noise ``(T,)`` as the log-radiance channel's are
    (:func:`_noise_widening`, in units of :data:`_PILOT_NOISE_SCALE`).

    The filtered values are demodulated: on a diffuse surface they do not depend on the albedo, which
    there only tells texture apart, and a textured surface split by its albedo averages each part's
    samples alone. Where the pilot is too noisy to trust, the samples are too few for that: the two rooms
    lit by bounce light alone (textured walls and floors, the pilot's noise 0.26-0.36, at most 0.11 on every
    other scene) gain 0.3 / 0.8 dB (``mi_indirect_dof``, tuning part) and 0.8 / 1.3 dB (``bl_indirect_dof``,
    held out) from 1 / 4 spp, every other scene keeps its bits (``findings.md``)."""
    ai = [k for k, n in enumerate(names) if feature_group(n) == "albedo"]
    if not ai:
        return sigmas
    out = sigmas.clone()
    out[:, ai] *= _noise_widening(noise.to(sigmas.dtype) / _PILOT_NOISE_SCALE)[:, None]
    return out


def _trusted_level(pilot: Tensor, mask: Tensor, trust: Tensor) -> Tensor:
    """The level the bandwidth selection weighs its errors by (relative errors, :func:`_select_bandwidth`):
    the pilot where it is trusted, the frame's mean where not (absolute errors), blended by ``trust``
    ``(T,)``. A noisy pilot, dark where its samples are sparse, would weigh a few pixels' errors far above
    the rest (``mi_indirect_dof``: +0.44 / +0.89 dB with absolute errors; ``findings.md``)."""
    w = trust.to(pilot.dtype).view(-1, 1, 1, 1)
    if bool((w >= 1).all()):
        return pilot
    return w * pilot + (1 - w) * _channel_means(pilot, mask).to(pilot.dtype)


def _pilot_noise(pilot: Tensor, held_out: Tensor, valid: Tensor) -> Tensor:
    """The pilot's noise per frame in the log-radiance channel's units, ``(T,)``: the robust spread
    (1.4826 times the median absolute deviation) of the channel of ``pilot`` ``(T, 3, H, W)`` minus that of
    ``held_out``, each pixel's estimate from the other checkerboard half alone, over the ``valid``
    ``(T, 1, H, W)`` pixels where both exist. The pilot is about the mean of the two halves' estimates, so
    the difference is half the halves' difference: its spread is the pilot's own. 0 where a frame has
    no such pixel."""
    with torch.no_grad():
        L, Lh = luminance(pilot).clamp_min(0.0), luminance(held_out).clamp_min(0.0)
        mean = _frame_mean(L, valid.to(L.dtype))
        d = _log_radiance_of(L, mean) - _log_radiance_of(Lh, mean)
        ok = valid & torch.isfinite(d)
        out = []
        for t in range(d.shape[0]):
            v = d[t][ok[t]].double()
            out.append(1.4826 * float((v - v.median()).abs().median()) if v.numel() else 0.0)
        return torch.tensor(out, dtype=torch.float64)


def _clamp_fireflies(e: Tensor, alb: Tensor, pe: Tensor, mask: Tensor, k: float, stats: dict,
                     keep: Tensor) -> Tensor:
    """Scale samples brighter than ``k`` times the pilot ``pe`` (plus a floor) down to that bound, except
    where ``keep`` (bool ``(T, 1, H, W)``); the energy, the energy removed and the samples clamped are added
    to ``stats``. The floor is a quarter of the frame's mean pilot luminance, so dark regions next to
    noise-free black do not clamp every lit sample (measured on shared/data; on the validation set's
    tuning part 0.1 to 1 are within 0.05 dB). Where more than :data:`_FIREFLY_MAX_SHARE` of a frame's
    samples exceed it, the frame's bound rises until no more do (:func:`_clamp_scale`): so many
    "fireflies" are the light itself."""
    lp = luminance(pe).clamp_min(0.0)
    floor = _FIREFLY_FLOOR * _frame_mean(lp, mask)
    thr = k * (lp + floor)
    L = luminance(e)
    thr = thr * _clamp_scale(torch.where(~keep & (mask > 0), L / thr, 0.0), mask)
    scale = torch.where((L > thr) & ~keep, thr / L.clamp_min(1e-30), torch.ones_like(L))
    ec = e * scale
    with torch.no_grad():  # counts, not part of a gradient
        stats["energy"] += float(((e * alb) * mask).sum())
        stats["firefly_energy"] += float((((e - ec) * alb) * mask).sum())
        stats["firefly_clamped_samples"] += int(((scale < 1) & (mask > 0)).sum())
    return ec


def _clamp_scale(ratio: Tensor, mask: Tensor) -> Tensor:
    """Per frame, the least factor ``s >= 1`` by which the clamp's bound must rise so that at most
    :data:`_FIREFLY_MAX_SHARE` of the frame's valid samples (at least one) exceed it: ``(T, 1, 1, 1)``.
    ``ratio`` ``(T, 1, H, W)`` is each sample's luminance over its bound (0 where none applies)."""
    with torch.no_grad():
        r = ratio.detach().flatten(1)
        out = torch.ones(r.shape[0], dtype=r.dtype, device=r.device)
        for t in range(r.shape[0]):
            allowed = max(1, int(_FIREFLY_MAX_SHARE * float((mask[t] > 0).sum())))
            if int((r[t] > 1).sum()) > allowed:  # the (allowed + 1)-th largest: `allowed` lie above it
                out[t] = torch.topk(r[t], allowed + 1).values[-1].clamp_min(1.0)
        return out.view(-1, 1, 1, 1)


class Denoiser(nn.Module):
    """Module form of :func:`denoise_frames`; stores a :class:`DenoiseSettings`.

    Shape:
        - color ``(T, 3, H, W)``, features ``(T, D, H, W)`` -> ``(T, 3, H, W)``
    """

    def __init__(self, feature_names: Sequence[str] = (), settings: DenoiseSettings | None = None, **kwargs):
        super().__init__()
        self.feature_names = list(feature_names)
        self.settings = (settings or DenoiseSettings(**kwargs)).check()

    def forward(self, color: Tensor, features: Tensor | None = None, emission: Tensor | None = None) -> Tensor:
        return denoise_frames(color, features, self.feature_names, emission, self.settings)

    def extra_repr(self) -> str:
        s = self.settings
        return (f"sigma_s={s.sigma_s}, firefly={s.firefly!r}, firefly_k={s.firefly_k}, "
                f"temporal_radius={s.temporal_radius}, mode={s.mode!r}, features={self.feature_names}")
