"""Denoise Monte Carlo frames with the adaptive-manifold filter: the preprocessing that makes it win.

Plain joint filtering of 1-spp colour loses to a Gaussian blur on real renders (fireflies become
blobs, texture blurs, lights bleed). :func:`denoise_frames` wraps the filter op with:

1. **Sanitising**: non-finite colour or feature samples are counted and given zero weight (the filter
   runs on ``[w * colour, w]`` and divides, so they never enter any sum); an infinite depth or position is
   a ray that left the scene, read as 0 (:func:`_infinite_as_no_hit`).
2. **Emission apart**: emitted radiance at the first hit (when the renderer gives it) is removed
   before filtering and added back unfiltered, so lights do not bleed into walls.
3. **Irradiance**: colour is divided by the first-hit albedo, filtered, and multiplied back by the
   same albedo, so texture stays sharp. Where the albedo is about 0 (delta BSDFs, black surfaces) the
   radiance itself is averaged, among those pixels only and guided by their colour: their features do
   not show what a mirror or glass shows (:func:`_flat_average`, :func:`_flat_filters`). Where the
   samples' world positions scatter across a surface (a lens's circle of confusion), each sample's albedo
   is another point of a texture the reference shows averaged, and the albedo is averaged first
   (:func:`~torchmanifold.pipeline.footprint._scattered_albedo`).
4. **Fireflies**: a pilot estimate is filtered in the range-compressed ``log1p`` domain (where a
   firefly is just one more sample), samples brighter than ``firefly_k`` times the pilot are clamped
   to it, and the clamped samples are filtered linearly. The energy removed is measured and returned
   (``stats["firefly_energy_removed"]``); where the pilot is too noisy to trust, it comes back after
   filtering, in proportion to the result over a wide reach (:func:`_give_back`). Elsewhere what lone
   fireflies took (a caustic's rare paths) comes back as far as enough of them fall within the reach to
   know its mean (:func:`_lone_fireflies`).
5. **Guide**: each feature group gets its own range sigma (albedo, normals, world position or depth
   relative to each frame's extent, directions; see :func:`default_guide_sigmas`), and a log-radiance
   channel of the colour itself (:func:`_log_radiance`) separates what the features cannot: lights
   set in a surface, shadows, what glass shows; it is taken from the pilot below, averaged along its own
   edges (:func:`_pilot_along_edges`). Where the pilot is too noisy to trust, that channel and the albedo
   stop steering (:func:`_noise_widening`). Without albedo the chromaticity guides
   too, the pilot's from the samples' (:func:`_chromaticity_from_pilot`).
6. **Bandwidth from the data**: the filter runs at several spatial bandwidths and every pixel blends them by
   their error, estimated by cross-validation between two interleaved halves of the samples (see
   :func:`~torchmanifold.pipeline.selection._select_bandwidth`): wide where the light is smooth and the
   samples noisy, narrow at detail the features do not show and where more samples make the input better.
   Where neighbouring pixels share samples (a renderer's reconstruction filter splats them), the halves are
   squares of pixels (:func:`~torchmanifold.pipeline.selection._cv_cell`). Where no albedo guides, two
   narrower bandwidths join (:func:`adapt_to_features`): nothing else tells texture from noise.
7. **Time**: optionally neighbour frames within ``temporal_radius`` join with Gaussian weights in
   time, in the op's ``"spacetime"`` mode (no ghosts where things move) or ``"window"`` mode; each frame
   is also filtered alone at the narrow bandwidths, and the bandwidth selection keeps it where the window's
   frames disagree (a pan's edges; with colour alone nothing else tells a moving view's frames apart).
   Where the view moves, the window's frames are first brought to the query frame's pixels by a flow found
   from the renderer's world positions, or without them from its albedo, normals and depth
   (:mod:`~torchmanifold.pipeline.align`), and so is the evidence its neighbours lend its bandwidth selection.
8. **Pixel footprint** (:mod:`torchmanifold.pipeline.footprint`): a 1-spp pixel shows one point of its
   area, so thin geometry comes out dotted and texture speckled; the result is averaged over a pixel-sized
   footprint, in a tone-mapped domain and only among pixels of similar brightness, so a light's edge does
   not bleed into the dark beside it. On a smooth surface the albedo, whose detail is texture, gets a
   narrower footprint than the light. A pixel that an edge crosses shows its few samples' share of either
   side; its neighbours along the edge share it, so the footprint reaches along edges, by the sample count.
   Where the renderer gives world positions, the window's other frames add their samples of each pixel's
   albedo: a still view's of the same pixel, a moving view's that fall in the pixel's square. Where a lens
   or a shutter mixes two surfaces in each pixel at random (the depth tells it), the footprint is the
   blend's (:func:`~torchmanifold.pipeline.footprint._mixed_layers`).
9. **Sky**: where the camera ray left the scene (depth 0) the colour is the environment itself, with no
   Monte Carlo noise: those pixels keep their samples (:func:`_escaped`), unless their colour is noise, as
   in fog (:func:`_noisy_sky`): then they are filtered with the rest, with no albedo or feature of their own.
   So do a frame's flat pixels (no albedo beside pixels that have one) where their colour is surely no noise,
   as on a picture on an emitter whose surface is black (:func:`_exact_flat`).

Every statistic comes from the frames of one query's window, so a clip gives the same bytes streamed,
sharded or all at once.
"""
from __future__ import annotations

import math
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from torchmanifold import features as feature_table
from torchmanifold._checks import (check_choice, check_int, check_nonnegative, check_positive,
                                   check_tree_height)
from torchmanifold._threads import InOrder, caller_threads, serial
from torchmanifold.pipeline import _fast
from torchmanifold.pipeline.align import WindowAlignment
from torchmanifold.pipeline.footprint import (_UNSEEN_BORDER, _along_edges, _any_within, _edge_directions,
                                              _footprint_albedo, _known_count, _mixed_footprint,
                                              _mixed_pixels, _normalised_blur, _position, _remodulate,
                                              _scattered_albedo, _smooth_surface, _window_albedo,
                                              footprint_width)
from torchmanifold.pipeline.filter import _Filter, tree_height_at
from torchmanifold.pipeline.image import (_LOG_RADIANCE_OFFSET, _channel_means, _eight_neighbours_max,
                                          _four_neighbours, _frame_mean, _gaussian_taps, luminance)
from torchmanifold.pipeline.selection import (_PLAIN_GROUPS, ClipCache, _caustic_light, _cv_cell,
                                             _pooled_selection, _select_bandwidth, _select_flat_width)
from torchmanifold.timewindow import frame_at, index_window, window, windows_span

__all__ = [
    "DenoiseSettings",
    "denoise_frames",
    "prepare_frames",
    "denoise_prepared",
    "FrameState",
    "footprint_width",
    "spatial_sigma",
    "radiance_sigma_at",
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


#: ways of handling fireflies (see :class:`DenoiseSettings`)
FIREFLY_MODES = ("clamp", "log", "none")
#: guide-sigma key of the log-radiance channel the denoiser adds to the renderer's features
RADIANCE_GUIDE = "log_radiance"
#: the log-radiance guide's sigma from single samples (3x3 Kuwahara) relative to the pilot's
#: (validation set's tuning part: the pilot's at 0.5 with the samples' at 1.0 beat both at 1.0 by 0.14 dB
#: from 1 spp, and 0.22 dB over the whole set from 4 spp; the pilot's at 1.0 or 0.25 lost)
#: The samples' chromaticity, where colour alone guides, takes the same widening (the tuning part, colour
#: alone, from 1 / 4 spp, against none in the pilot's guide: 1 +0.02 / -0.01 dB, 1.5 +0.11 / +0.05, 2 +0.16 /
#: +0.06, 3 +0.18 / +0.09, 4 +0.16 / +0.10)
_SAMPLE_RADIANCE_WIDENING = 2.0


#: firefly clamp floor as a fraction of the frame's mean pilot luminance
_FIREFLY_FLOOR = 0.25
#: the largest share of a frame's samples the firefly clamp may take down: fireflies are rare. A scene lit
#: by bounce light alone, whose light reaches most pixels through rare bright paths that the log-domain
#: pilot sees as fireflies, had 8.6% of its samples clamped from 1 spp and lost half its energy; the other
#: scenes' frames had at most 1.6%. On the tuning part, frames 0-2, from 1 / 4 spp: 2% 27.318 / 30.603,
#: 1% 27.483 / 30.626, 0.5% 27.536 / 30.629, 0.25% 27.542 / 30.624, 0.1% 27.531 / 30.617
#: (``benchmarks/validation/findings.md``)
_FIREFLY_MAX_SHARE = 0.005
#: where the pilot is too noisy to trust, how far (in sigmas of the widest candidate bandwidth) the energy
#: the clamp took goes back (:func:`_give_back`). The rooms lit by bounce light alone came out 7% dark from
#: 1 spp, their light clamped as fireflies. Frames 0-2, the ``denoise`` default, from 1 / 4 spp:
#: ``mi_indirect_dof`` (tuning part) 0.5 / 2 / 4: +0.14 / -0.05, +0.16 / -0.02, +0.10 / -0.02 dB;
#: ``bl_indirect_dof`` (held out) -0.01 / +0.02, +0.18 / +0.03, +0.23 / +0.02. Given back in every frame,
#: the pilots that can be trusted lose: from 4 spp ``mi_dark_glossy`` -6 dB (its small lights' real
#: highlights spread over the floor), ``mi_still_textures`` -1.5 (``benchmarks/validation/findings.md``).
_GIVE_BACK_REACH = 2.0
#: where the pilot can be trusted, lone clamped samples (:func:`_lone_fireflies`) are light that reaches a
#: surface through rare paths (a caustic under glass); their energy comes back over this reach (in sigmas
#: of the widest candidate bandwidth), in full only where many of them fall within it: the share is
#: ``n / (n + count)``, ``n`` their effective number under the kernel (:func:`_effective_count`). A few
#: lone fireflies (a small light's rare paths) would come back as a halo. From 1 / 4 spp, count 8 / 16 /
#: 32 / 64 at reach 1: the probe ``mi_glass_room`` (256x256) +0.75 / +0.39, +0.66 / +0.34, +0.52 / +0.26,
#: +0.36 / +0.18 dB; the tuning part's ``bl_glass_caustic`` from 1 spp +0.08 at 16, +0.06 at 32; the held-out
#: ``mi_dark_glossy`` from 4 spp -0.34, -0.09, -0.01, +0.01 (its small lights' rare paths). Reach 2, count
#: 16: the room +0.57 / +0.31. Halos around lights and highlights where clustered clamped samples come back
#: too (count 16: ``mi_dark_glossy`` -1.51 from 4 spp, the room +0.73 / +0.42) or lone ones without a count
#: (-2.82). A clamped sample beside one as bright (a small light's rim) is no lone firefly either: through
#: the set's progressive iterations without that test ``mi_dark_glossy`` lost 0.14 / 0.57 / 0.23 dB after 2
#: / 4 / 8, its lights' rims spread as halos (``benchmarks/validation/findings.md``)
_FIREFLY_BACK_REACH = 1.0
_FIREFLY_BACK_COUNT = 16.0

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
        bandwidths: spatial sigmas tried at every pixel, as multiples of ``sigma_s``; each pixel blends them
            by their cross-validated error (see :func:`~torchmanifold.pipeline.selection._select_bandwidth`).
            One value filters at that bandwidth alone. Factor-2 steps from 0.5 to 4 (2 to 16 px) measured best
            on the validation set's tuning part from 1 and 4 spp (``benchmarks/validation``): a 1-spp wall
            wants 16 px, a 4-spp leaf edge 2.
        selection_blur: sigma (pixels) over which a pixel's cross-validated errors are pooled in a frame
            ``selection_side`` pixels across: one held-out sample is too noisy an error estimate (on the set
            3 / 4 / 5 / 6 within 0.03 dB, 4 the best). It widens where the firefly pilot is noisy
            (:func:`_selection_pooling`).
        selection_side: the frame side (pixels) at which ``selection_blur`` holds; a frame whose shorter side
            is larger pools wider, by the square root of the ratio (:func:`_frame_pooling`; the set's 128x128
            frames, where ``selection_blur`` was measured). ``None``: the same width in every frame, as where
            no albedo guides (:func:`adapt_to_features`).
        selection_softness: how sure the evidence must be before a bandwidth is left out: weights are
            ``exp(-z^2 / (2 softness^2))``, ``z`` a bandwidth's pooled error in excess of the least one's in
            standard errors of that excess (see :func:`~torchmanifold.pipeline.selection._excess_error_z2`); 0
            picks the least-error bandwidth alone. 1 is the plain likelihood that the excess is noise; against
            the earlier ``softmax(-err / (0.5 min err))``, which blended the bandwidths almost evenly because
            every error holds the sample's own variance, it measured -0.02 / +0.09 dB from 1 / 4 spp on the
            tuning part, +0.12 / +0.23 over the whole set and +0.40 dB in the progressive loop (96x96, 4
            frames, 10 iterations). Picking one alone flickers between progressive iterations.
        guide: feature channels that steer the filter (EXR or tracer names); ``None`` = albedo, normals
            and world position ``P`` (or depth ``Z`` without ``P``): the sampled directions ``D``/``S`` are
            one random draw per sample and only add noise to the range weights (measured).
        guide_sigmas: range sigma per guide channel (``{name: sigma}`` overrides); missing ones default.
        tree_height: manifold tree height at ``sigma_s``: 3 measured best on the tuning part (2: -0.13 dB, 4:
            the same; over the whole set from 1 / 4 spp, 3 beats 2 by 0.27 / 0.40 dB, at about twice the op's
            time).
        levels_per_doubling: levels the tree gains per doubling of a bandwidth beyond ``sigma_s``
            (:func:`~torchmanifold.pipeline.filter.tree_height_at`). A wider kernel mixes more of the pixels
            that lie far from every manifold, whose values it takes from the nearest manifolds': with one
            height for all, the widest candidate bled a cube's top face into its side (``findings.md``). 1
            against 0, frames 0-2 from 1 / 4 spp: the validation set +0.08 / +0.08 dB (``bl_moving_metal``
            -0.11 / -0.07, no other scene below -0.02), five of its clips rendered at 256x256 +0.18 / +0.13;
            the frame step with +-1 frames takes 1.3 times as long on one thread, 1.13-1.18 times on two
            (``findings.md``).
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
            (:func:`~torchmanifold.pipeline.footprint.footprint_width`).
        albedo_eps: albedo luminance below which a pixel is not demodulated (delta BSDFs and black
            surfaces, whose first-hit albedo says nothing about the light there).
        albedo_floor: the least albedo a demodulated pixel is divided by, per channel (and multiplied
            back by). A dark surface's colour divided by its own albedo carries its noise many times over
            into the filter, and where a renderer's albedo does not scale the light (Mitsuba's rough
            glass: a small albedo rising to the ball's middle over light that does not) the division
            draws rings. Frames 0-2, the ``denoise`` default, from 1 / 4 spp, the validation set's clips
            and four at 256x256 summed against 0.02 (``albedo_eps``): 0.05 +0.05 / +0.11 dB (worst clip
            -0.015), 0.07 +0.39 / +0.23 (worst -0.07, ``mi_still_textures`` from 4 spp), 0.1 +0.29 /
            -0.06 (worst -0.15, ``cbox_glossy_tex`` from 1 spp); a rough-glass probe +0.09 / +0.16 at
            0.07 (``benchmarks/validation/findings.md``).
        radiance_sigma: range sigma of the log-radiance guide channel, which keeps lights, shadows
            and what is seen through glass apart where the renderer's features cannot; 0 leaves it out.
            The channel comes from the firefly pilot where there is one, else from the samples
            (:func:`_log_radiance`, at twice this sigma). 0.5 measured best on the tuning part. Where the
            pilot's own noise is a quarter of it or more, the sigma widens (:func:`_noise_widening`); beyond 4
            samples per pixel it narrows (:func:`radiance_sigma_at`).
        demodulate: divide by albedo when albedo channels are present.
        keep_sky: pixels whose camera ray left the scene keep their samples (:func:`_escaped`), unless
            their colour is noise (:func:`_noisy_sky`: a scene in a medium, where a ray that meets no surface
            also reads depth 0 and its colour is in-scattered light); ``False`` filters them always.
        temporal_radius: neighbour frames on each side that join the filter (0 = per frame); where a
            frame's pilot is too noisy to trust, every frame of ``joined_radius`` (:func:`_noisy_window`).
        align_frames: with a time window, each query frame's window is brought to its pixels where the view
            moves (:mod:`~torchmanifold.pipeline.align`): the other frames' samples, guides and albedo, and
            its neighbours' lent evidence, gathered by a flow found from the renderer's world positions, or
            without them from its albedo, normals and depth. All frames from 1 / 4 spp, against leaving the
            windows as they are: the panning clips of the validation set `mi_dark_glossy` +0.39 / +0.59 dB,
            `mi_glass_mirror` +0.39 / +0.58, `bl_glass_caustic` +0.17 / +0.49, `bl_motion_blur` +0.05 / +0.08,
            the thin rods against the sky `mi_env_thin` -0.02 / -0.03 and `bl_env_thin` +0.04 / 0.00; at
            256x256 +0.42 / +0.65, +0.32 / +0.50, +0.22 / +0.38, +0.04 / +0.11, -0.06 / -0.04, +0.03 / -0.02;
            the sunlit probes `mi_yard` +0.42 / +0.61, `mi_window` +0.27 / +0.33, `bl_window` +0.28 / +0.31;
            no clip below -0.06, every still view keeps its bits (``benchmarks/validation/findings.md``). The
            frame step of a panning 256x256 clip takes 1.4-1.6 times as long (two threads), of a still one
            1.05-1.1.
        albedo_radius: with a time window (``temporal_radius`` > 0) and world positions from the
            renderer, the frames on each side whose samples of each pixel's albedo join it
            (:func:`~torchmanifold.pipeline.footprint._window_albedo`); it may reach beyond the filter's
            window, as texture holds still where light does not need to. Validation set, 1 spp, against 1: 2
            +0.09 dB on the tuning part (``cbox_glossy_tex`` +0.24), 3 +0.13; no scene below -0.03. All
            frames from 1 / 4 spp, against 2: 3 the eleven 128x128 clips +0.05 / +0.04 (``mi_still_textures``
            +0.25 / +0.23, no clip below 0), the six Mitsuba clips at 256x256 with 12 frames +0.10 / +0.07
            (Blender's, without positions, the same), 4 the same as 3; the ``denoise`` command on the shared
            clip 7% slower on one thread, 2% on two (``benchmarks/validation/findings.md``).
        evidence_radius: with a time window, the frames on each side whose queries lend their cross-validated
            residuals to a query's bandwidth selection, where their guides agree with its own
            (:func:`~torchmanifold.pipeline.selection._pooled_selection`): a candidate's bias at a place
            persists from frame to frame, the noise of its error estimate does not. 1 against 0, all frames
            from 1 / 4 spp: the validation set +0.08 / +0.07 dB, no clip below -0.01; its clips at 256x256
            with 12 frames +0.07 / +0.07 (six Mitsuba) and +0.08 / +0.07 (four Cycles); the progressive loop's
            caustic 0.83 -> 0.87 (``benchmarks/validation/findings.md``). 2 against 1, with each residual
            measured against its own half's average
            (:func:`~torchmanifold.pipeline.selection._own_half_reference`): the set +0.019 / +0.013, the
            256x256 clips +0.011 / +0.005 and +0.019 / +0.010, the fifteen probes +0.027 / +0.015, no clip
            below -0.03, at the same time a frame (a 12-frame 256x256 clip, one thread). Frames of another
            window kind (:func:`_noisy_window`) lend none; with one bandwidth there is nothing to lend.
        frame_alone_bandwidths: with a time window, bandwidths (multiples of ``sigma_s``) at which each
            query's frame is also filtered alone; the bandwidth selection blends them with the window's
            candidates by their cross-validated error, so that where the window's frames disagree (a moving
            view, and little in the guide that tells them apart) a pixel keeps its own frame. ``None``
            (default): the ``bandwidths`` narrower than ``sigma_s``, except where the window widens for a
            noisy pilot (:func:`_noisy_window`: a frame's own narrow candidate is its noise); ``()``: none.
            Every frame of the validation set from 1 / 4 spp against none: +0.03 / +0.07 dB, no clip below
            -0.05 (the pans ``mi_env_thin`` and ``bl_env_thin`` +0.09 to +0.37); from colour alone, where
            nothing else tells a pan's frames apart, +0.60 / +0.57 (``findings.md``).
        sigma_t: temporal sigma in frames: the Gaussian weight of a window's other frames (the space-time
            guide keeps what moved apart). All frames from 1 / 4 spp, 1 / 1.5 / 2 / 3: the set's eleven
            128x128 clips 26.92 / 29.94, 26.99 / 29.99, 27.01 / 30.00, 27.02 / 30.00 dB (2: the bounce-lit
            rooms, whose noisy pilot's window joins +-3, +0.37 / +0.29 and +0.40 / +0.26, every other clip
            within -0.01 to +0.05; inside the moving objects +0.06 on average, none below -0.03); the Cycles
            and Mitsuba clips at 256x256 +0.06 / +0.05 and +0.05 / +0.02 at 2 and 3 alike; 0.7 lost 0.1. 2,
            the smallest that reaches the plateau (``benchmarks/validation/findings.md``).
        mode: ``"spacetime"`` or ``"window"`` (see :func:`~torchmanifold.ops.temporal_adaptive_manifold_filter`).
        dtype: working precision; float32 (fast C++ paths) bounds each result by the range of the
            samples near it, float64 keeps S/S0 exact where the weights get tiny.
    """

    sigma_s: float = 4.0
    bandwidths: Sequence[float] = (0.5, 1.0, 2.0, 4.0)
    selection_blur: float = 4.0
    selection_side: float | None = 128.0
    selection_softness: float = 1.0
    guide: Sequence[str] | None = None
    guide_sigmas: Mapping[str, float] = field(default_factory=dict)
    tree_height: int = 3
    levels_per_doubling: int = 1
    firefly: str = "clamp"
    firefly_k: float = 5.0
    footprint_sigma: float | None = None
    albedo_eps: float = 0.02
    albedo_floor: float = 0.07
    radiance_sigma: float = 0.5
    demodulate: bool = True
    keep_sky: bool = True
    temporal_radius: int = 0
    align_frames: bool = True
    albedo_radius: int = 3
    evidence_radius: int = 2
    frame_alone_bandwidths: Sequence[float] | None = None
    sigma_t: float = 2.0
    mode: str = "spacetime"
    dtype: torch.dtype = torch.float32

    def check(self) -> "DenoiseSettings":
        """Raise TypeError / ValueError (see :mod:`torchmanifold._checks`) on a bad setting; return self."""
        from torchmanifold.ops.temporal import MODES

        for name in ("sigma_s", "firefly_k", "albedo_eps", "albedo_floor", "sigma_t"):
            check_positive(name, getattr(self, name))
        if isinstance(self.bandwidths, (str, bytes)) or not isinstance(self.bandwidths, Sequence) or \
                not self.bandwidths:
            raise TypeError(f"bandwidths must be a non-empty sequence of numbers, got {self.bandwidths!r}")
        for k, b in enumerate(self.bandwidths):
            check_positive(f"bandwidths[{k}]", b)
        alone = self.frame_alone_bandwidths
        if alone is not None and (isinstance(alone, (str, bytes)) or not isinstance(alone, Sequence)):
            raise TypeError(f"frame_alone_bandwidths must be None or a sequence of numbers, got {alone!r}")
        for k, b in enumerate(alone or ()):
            check_positive(f"frame_alone_bandwidths[{k}]", b)
        for name in ("radiance_sigma", "selection_blur", "selection_softness"):
            check_nonnegative(name, getattr(self, name))
        if self.selection_side is not None:
            check_positive("selection_side", self.selection_side)
        if self.footprint_sigma is not None:
            check_nonnegative("footprint_sigma", self.footprint_sigma)
        check_choice("firefly", self.firefly, FIREFLY_MODES)
        check_choice("mode", self.mode, MODES)
        check_int("temporal_radius", self.temporal_radius, min=0)
        check_int("albedo_radius", self.albedo_radius, min=0)
        check_int("evidence_radius", self.evidence_radius, min=0)
        check_int("levels_per_doubling", self.levels_per_doubling, min=0)
        check_tree_height(self.tree_height)
        for k, v in dict(self.guide_sigmas).items():
            check_positive(f"guide_sigmas[{k!r}]", v)
        return self

    @property
    def joined_radius(self) -> int:
        """The frames on each side that a query's filter or albedo joins: the filter's window, and the
        albedo's where there is a time window (0 per frame)."""
        return max(self.temporal_radius, self.albedo_radius) if self.temporal_radius > 0 else 0

    @property
    def lending_radius(self) -> int:
        """The neighbouring frames on each side whose queries lend a query their evidence: ``evidence_radius``
        where there is a time window and bandwidths to choose among, else 0."""
        return self.evidence_radius if self.temporal_radius > 0 and self.candidates > 1 else 0

    @property
    def frame_alone(self) -> tuple[float, ...]:
        """The bandwidths at which a query's frame is also filtered alone: ``frame_alone_bandwidths``
        (``None``: the bandwidths under 1) where there is a time window, else none (every candidate is of the
        frame alone)."""
        if self.temporal_radius == 0:
            return ()
        if self.frame_alone_bandwidths is None:
            return tuple(float(b) for b in self.bandwidths if b < 1)
        return tuple(map(float, self.frame_alone_bandwidths))

    @property
    def candidates(self) -> int:
        """How many filters the bandwidth selection blends."""
        return len(self.bandwidths) + len(self.frame_alone)

    @property
    def query_radius(self) -> int:
        """The frames on each side whose samples a query's filter and its neighbours' lending evidence join
        (the albedo's window aside; 0 per frame): what the progressive loop renders around a query."""
        return self.temporal_radius + self.lending_radius

    @property
    def window_radius(self) -> int:
        """The frames on each side that a query's output depends on: what it joins, and what its
        neighbours lending evidence join (0 per frame)."""
        return self.joined_radius + self.lending_radius


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


#: the most samples per pixel at which the log-radiance channel keeps ``radiance_sigma`` (measured best at
#: 1 and 4 spp); beyond, the pilot is cleaner and a narrower channel keeps the shading that no feature
#: shows, so the sigma shrinks as the spatial one, ``(spp / 4) ** -0.25``: 0.42 from 8 spp, 0.35 from 16.
#: The set through progressive iterations (``benchmarks/validation/iterations.py``), frames 0-2 of eleven
#: clips, summed against 0.5: +0.32 / +1.66 dB from 8 / 16 spp, no clip below -0.07 (``mi_dark_glossy`` and
#: ``mi_still_textures`` from 8; ``bl_env_thin`` +0.18 / +0.50, ``mi_indirect_dof`` +0.04 / +0.46);
#: 0.5 * spp ** -0.25 from every count cost those two textured clips 0.2 dB from 4 spp (``findings.md``)
_RADIANCE_SPP = 4


def radiance_sigma_at(settings: DenoiseSettings, samples_per_pixel: float | None) -> float:
    """The log-radiance channel's range sigma for frames of ``samples_per_pixel``: ``settings.radiance_sigma``
    (or its ``guide_sigmas`` entry, which is taken as given) up to :data:`_RADIANCE_SPP` samples, then
    shrinking as ``(spp / 4) ** -0.25``."""
    rs = _radiance_sigma(settings)
    if RADIANCE_GUIDE in dict(settings.guide_sigmas) or not _known_count(samples_per_pixel):
        return rs
    return rs * max(1.0, float(samples_per_pixel) / _RADIANCE_SPP) ** _SIGMA_SPP_EXPONENT


#: Where no albedo channel guides (colour alone, a renderer's Combined pass; or geometry alone), the guide
#: cannot tell texture from noise, so the bandwidth selection reaches down to nearly no filtering: two more
#: candidates, a half and a quarter of the narrowest. Frames 0-2 of the validation set from 1 / 4 spp
#: (findings.md, "Without albedo"): colour alone +0.63 / +1.31 dB (an eighth as well: +0.06 / +0.04);
#: normals, depth and positions without albedo +0.60 / +1.12, no scene below -0.2. With albedo, a 1 px
#: candidate lost 0.14 dB from 1 spp.
_NO_ALBEDO_NARROWER = (0.25, 0.5)
#: the factor on ``radiance_sigma`` where no albedo guides (with colour alone the log-radiance channel is the
#: one edge beside the chromaticity). The validation set's tuning part from 1 / 4 spp, colour alone, every
#: frame, against 1: 0.5 +0.18 / +0.19 dB, 0.6 +0.26 / +0.23, 0.7 +0.28 / +0.24, 0.8 +0.21 / +0.18, 1.4
#: -0.22 / -0.18; geometry alone, 0.7: -0.01 / +0.08
_NO_ALBEDO_RADIANCE = 0.7
#: the range sigma of the pilot's chromaticity guide channels, r / (r + g + b) and g / (r + g + b), where no
#: albedo guides: a red ball on green grass has the grass's luminance. The tuning part, colour alone, each
#: frame alone: +0.40 / +0.50 dB over none; 0.025 +0.14 / +0.13 more there but -0.3 / -0.4 on its room lit by
#: bounce light and -0.7 / -0.8 on the held-out one; 0.1 -0.23 / -0.23. Beside geometry without albedo the
#: whole set +0.40 / +0.45 (the glass clips +2.1 to +3.1) but the rooms lit by bounce light -0.4 / -0.5 until
#: the sigma widens with the pilot's noise as the albedo's does (+0.44 / +0.47, every room within 0.1 dB);
#: 1.5 / 2 times as wide, -0.04 / -0.06 and -0.06 / -0.06
_CHROMA_SIGMA = 0.05


def adapt_to_features(settings: DenoiseSettings,
                      feature_names: Sequence[str]) -> tuple[DenoiseSettings, str | None]:
    """``settings`` for frames with these feature channels, and a note where they changed.

    Where no albedo channel guides (colour alone, or geometry alone), the guide cannot tell texture from noise
    nor, on glass, what it shows: the candidates reach down to a quarter of the narrowest
    (:data:`_NO_ALBEDO_NARROWER`), and so, with a time window, does each frame's own filter (by default at
    the candidates narrower than ``sigma_s``, ``frame_alone_bandwidths``), and the log-radiance channel
    narrows by :data:`_NO_ALBEDO_RADIANCE` (the guide also holds the colour's chromaticity, :func:`_guide`);
    the selection pools over ``selection_blur`` in any frame size (``selection_side``: the narrow candidates'
    errors vary on the texture's scale).
    Nothing in colour alone tells a moving view's frames apart (the +-1 window smeared a pan's moving ball,
    -1.2 / -1.4 dB from 4 spp on two validation scenes, and gained 0.7-0.9 dB on still views): the bandwidth
    selection keeps a pixel's own frame where the window's disagree. The validation set from 1 / 4 spp,
    colour alone: each frame alone 24.42 / 27.42 dB, the window alone 24.90 / 27.45, both 25.02 / 27.99 (each
    frame alone at all six candidates: 24.96 / 27.94), with the narrower channel 25.13 / 28.10 (every clip
    up but ``mi_dark_glossy``, -0.06 / -0.11); geometry alone, with the chromaticity, 25.74 / 28.36 -> 25.74
    / 28.57 (findings.md)."""
    names = list(feature_names)
    guide = [names[k] for k in _select_guide(names, settings)]
    if _albedo_guides(guide):
        return settings, None
    low = min(float(b) for b in settings.bandwidths)
    bandwidths = tuple(sorted({low * f for f in _NO_ALBEDO_NARROWER} | set(map(float, settings.bandwidths))))
    adapted = replace(settings, bandwidths=bandwidths,
                      radiance_sigma=settings.radiance_sigma * _NO_ALBEDO_RADIANCE, selection_side=None)
    note = (f"no albedo guides: bandwidths {list(bandwidths)} times sigma_s, radiance sigma "
            f"{adapted.radiance_sigma:g}, the colour's chromaticity guides, the selection pools over "
            f"{adapted.selection_blur:g} px in any frame size")
    if adapted.frame_alone:
        note += f", each frame also filtered alone at bandwidths {list(adapted.frame_alone)}"
    if not guide:
        note += "; no feature channel guides"
    return adapted, note


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


#: the fewest flat pixels (those that keep no samples) a frame needs to blend their widths: below, the flat
#: average's width alone. The blend costs about 25 ms a 256x256 frame (one thread) however few they are,
#: and the shared clip's 190 scattered dark pixels a frame gained nothing from it (within 0.001 dB from 1
#: and 4 spp)
_MIN_FLAT_PIXELS = 500


def _filter_flat_apart(filt, values: Tensor, mask: Tensor, flat: Tensor, flat_sigma: float,
                       at_queries, average=None) -> Tensor:
    """``filt(values, mask)`` (a filter of frames to queries), except that flat pixels beside demodulated
    ones are left out of it (weight 0) and take ``average(values, weights, flat_sigma)`` (default
    :func:`_flat_average`), brought to the queries by ``at_queries``. A frame of flat pixels alone (no
    albedo, or a medium's) is filtered whole; beside frames that have demodulated pixels, by the filter of the
    flat pixels alone (radiance and irradiance do not mix)."""
    whole = _flat_frames(flat)
    if not (bool(flat.any()) and not bool(whole.all())):
        return filt(values, mask)
    out = filt(values, mask * ~flat)
    beside = flat & ~whole  # the whole frames' flat pixels take no average: they are filtered below
    own = (average or _flat_average)(values, mask * beside, flat_sigma)
    out = torch.where(at_queries(flat.to(out.dtype)) > 0.5, at_queries(own), out)
    if bool(whole.any()):
        whole = at_queries(whole.to(out.dtype)) > 0.5
        out = torch.where(whole, filt(values, mask * flat), out)
    return out


def _flat_frames(flat: Tensor) -> Tensor:
    """``(T, 1, 1, 1)`` bool: the frames whose pixels are all flat (``flat`` ``(T, 1, H, W)``), which have no
    albedo to demodulate by and are filtered whole as radiance."""
    return flat.flatten(1).all(1).view(-1, 1, 1, 1)


def _flat_average(e: Tensor, weight: Tensor, sigma: float) -> Tensor:
    """Flat pixels' own estimate, ``(T, 3, H, W)``: the ``weight``-ed average of ``e`` under a Gaussian of
    ``sigma`` pixels, each frame alone (``e`` itself where no weight lies under it).

    Flat pixels beside demodulated ones are delta surfaces and black ones (:func:`_demodulation_albedo`).
    Their features do not show what a mirror or glass shows, nor how that moves between frames, so the
    other pixels' guide does not steer them: where a frame holds enough of them, their result blends
    filters at a few widths about the narrowest bandwidth, chosen per pixel by cross-validation
    (:func:`~torchmanifold.pipeline.selection._select_flat_width`), guided by their own colour and joined in
    time (:func:`_flat_filters`); elsewhere, and in the firefly pilot, this average at its own width. On
    the validation set that did better than the guided, selected space-time filter of the other pixels,
    and the op no longer carries a second class's channels (``benchmarks/validation/findings.md``). It
    tends to the samples as ``sigma`` shrinks.
    """
    return _normalised_blur(e, weight, sigma)


#: the tree height of flat pixels' colour-guided filter: its guide has three channels (the glass probes and
#: `mi_glass_mirror`, from 1 / 4 spp: height 3 within 0.02 dB of 2)
_FLAT_TREE_HEIGHT = 2
#: flat pixels' widths from which the op filters (narrower ones are Gaussians of the query's frame alone):
#: a Gaussian under 0.6 px keeps about half its weight on the pixel itself, and the op's grid is finest
#: there (the glass probes and `mi_glass_mirror`, from 1 / 4 spp, against the op at every width: +0.00 /
#: +0.02 dB; from 1 px: +0.00 / -0.02)
_FLAT_OP_WIDTH = 0.6


def _flat_guide(e: Tensor, mask: Tensor, settings: DenoiseSettings) -> tuple[Tensor, Tensor]:
    """The guide of flat pixels ``(T, 3, H, W)`` and its range sigmas ``(T, 3)``: the chromaticity and the
    log radiance of the values ``e`` ``(T, 3, H, W)`` (:func:`_colour_channels`), the chromaticity at its
    sigma from samples as where no albedo guides (:func:`_guide`), the log radiance at the pilot's sigma,
    ``radiance_sigma``, not widened for samples (the three glass scenes of ``findings.md``, from 1 / 4 spp,
    summed against 0.5: 0.25 -0.24 / -0.07 dB, 0.35 -0.09 / -0.02, 1 +0.02 / -0.17: once frames join, what
    moved is told apart by the narrower channel)."""
    parts, sig = _colour_channels(e, mask, True, _radiance_sigma(settings))
    return torch.cat(parts, 1), torch.cat(sig, 1)


def _flat_filters(e: Tensor, mask: Tensor, settings: DenoiseSettings, frame_times: list[float],
                  query_times: list[float], range_scale: float):
    """The filter of flat pixels at each width for
    :func:`~torchmanifold.pipeline.selection._select_flat_width`: ``guided(stack, widths)`` -> one
    ``(Q, C, H, W)`` per width, the op on the channel stack ``(T, C, H, W)`` at ``query_times`` (frame
    times), guided by the samples' colour (:func:`_flat_guide`) and joined in space-time over the time
    window; widths under :data:`_FLAT_OP_WIDTH` are Gaussians of the query's frame alone. Features of glass
    or a mirror say nothing of what it shows; its colour does, and a sample whose colour differs (what glass
    showed elsewhere a frame before) lands on no manifold near the query's."""
    guide, sigmas = _flat_guide(e, mask, settings)
    st = replace(settings, mode="spacetime")
    at = [frame_at(frame_times, q) for q in query_times]

    def guided(stack: Tensor, widths: list[float]) -> list[Tensor]:
        filters = [_Filter(guide, sigmas, st, frame_times, query_times, w, range_scale, _FLAT_TREE_HEIGHT)
                   for w in widths if w >= _FLAT_OP_WIDTH]
        wide = iter(_Filter.apply_each(filters, stack) if filters else [])
        ones = stack.new_ones(len(at), 1, *stack.shape[-2:])
        return [next(wide) if w >= _FLAT_OP_WIDTH else _normalised_blur(stack[at], ones, w) for w in widths]
    return guided


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
    threads = caller_threads()
    grad = torch.is_grad_enabled() and any(x is not None and x.requires_grad
                                            for x in (color, features, emission, pilot))
    # with a gradient, one graph: the per-query graphs would sum a frame's gradient in another order
    if grad or len(qt) < _SIDE_BY_SIDE * threads:
        state = prepare_frames(color, features, names, emission, settings, sigma_s, range_scale, pilot,
                               firefly_k, samples_per_pixel)
        out = denoise_prepared(state, settings, ft, qt, sigma_s, range_scale)
    else:
        out, state = _side_by_side(threads, color, features, names, emission, settings, sigma_s, range_scale,
                                   ft, qt, pilot, firefly_k, samples_per_pixel)
    out = out.to(color.dtype)
    return (out, state.stats()) if return_stats else out


#: queries per thread from which :func:`denoise_frames` runs frames and queries side by side rather than each
#: op on every thread: 12 / 6 / 5 / 4 / 3 / 2 frames of the shared clip (256x256, the default's +-1), two
#: threads, three interleaved runs: 118 / 125 / 139 / 130 / 150 / 140 ms a frame side by side against 135 /
#: 138 / 141 / 131 / 121 / 112 in one call (one thread: 200 ms); a last round with a worker idle, or a query
#: whose op would have had both threads, costs more than the overlap gives
_SIDE_BY_SIDE = 3


def _side_by_side(threads: int, color: Tensor, features: Tensor, names: list[str], emission: Tensor | None,
                  settings: DenoiseSettings, sigma_s: float | None, range_scale: float, ft: list[float],
                  qt: list[float], pilot: Tensor | None, firefly_k: float | None,
                  samples_per_pixel: float | None) -> tuple[Tensor, FrameState]:
    """:func:`denoise_frames`'s frame step as the command and the render loop run it on several threads:
    each frame prepared alone, then each query filtered over its window's frames, side by side on workers
    that share ``threads`` torch threads, one each (the Python around a frame's ops does not scale inside
    one call; across frames it overlaps with the other's ops). The bytes of one call over the whole clip: a
    frame's state is its own, and a query's output depends on its window alone."""
    def one(x: Tensor | None, k: int) -> Tensor | None:
        return None if x is None else x[k:k + 1]

    def prepare(k: int) -> FrameState:
        return prepare_frames(color[k:k + 1], features[k:k + 1], names, one(emission, k), settings, sigma_s,
                              range_scale, one(pilot, k), firefly_k, samples_per_pixel)

    candidates = ClipCache()  # each query's candidates and the flows between frames, made once

    def filter_query(q: float) -> Tensor:
        ids = window(ft, q, settings.window_radius)
        return denoise_window_states([states[k] for k in ids], settings, [ft[k] for k in ids], q, sigma_s,
                                     range_scale, candidates)[0]

    with InOrder(threads, max(len(ft), len(qt))) as pool:  # a query waits on frames started before it
        states = [pool.ahead(prepare, k) for k in range(len(ft))]
        outs = [pool.ahead(filter_query, q) for q in qt]
        out = torch.cat([o.result() for o in outs])
    return out, FrameState.cat([s.result() for s in states])


@dataclass
class FrameState:
    """What the frame step derives from each frame alone, made by :func:`prepare_frames`.

    Every tensor holds one entry per frame, ``(T, ...)``, and no entry depends on the other frames, so a
    streamed clip prepares each frame once and joins the states of a window with :meth:`cat`.

    Attributes:
        values: ``(T, 3, H, W)`` demodulated samples to filter (fireflies clamped).
        level: ``(T, 3, H, W)`` demodulated radiance estimate (the pilot), or ``None`` without one or with a
            caller's (a past result, which sets the firefly clamp alone).
        mask: ``(T, 1, H, W)`` sample weights (0 where a sample was not finite).
        flat: ``(T, 1, H, W)`` bool, pixels filtered as radiance (not demodulated).
        albedo: ``(T, 3, H, W)`` the albedo the output is multiplied back by.
        smooth: ``(T, 1, H, W)`` in [0, 1], how smooth the surface is around each pixel (see
            :func:`~torchmanifold.pipeline.footprint._smooth_surface`), or ``None`` without geometry channels
            in the guide or without a known sample count (then
            :func:`~torchmanifold.pipeline.footprint._remodulate` averages the product alone).
        keep_samples: ``(T, 1, H, W)`` bool, pixels that keep their samples: where the camera ray left the
            scene (:func:`_escaped`) and the colour is no noise (:func:`_noisy_sky`), and a frame's flat
            pixels beside demodulated ones whose colour is no noise (:func:`_exact_flat`).
        emission: ``(T, 3, H, W)`` emitted radiance added back after filtering, or ``None``.
        position: ``(T, 3, H, W)`` the samples' world positions (``P``), or ``None`` where the renderer
            gives none or no time window is used: they tell which samples of the window's other frames
            fall in a pixel (:func:`~torchmanifold.pipeline.footprint._window_albedo`).
        flow_field: ``(T, C, H, W)`` what the flows between a window's frames match
            (:mod:`~torchmanifold.pipeline.align`): ``position``, or where the renderer gives none, the
            guide's feature channels (albedo, normals, depth) over their range sigmas; ``None`` without a time
            window.
        guide: ``(T, G, H, W)`` the filter's guide; sigmas ``(T, G)`` float64 its range sigmas.
        pooling: ``(T,)`` float64, the factor on ``selection_blur`` for each frame (1 but where the pilot is
            noisy, :func:`_selection_pooling`).
        cv_cell: ``(T,)`` int64, each frame's cross-validation checkerboard squares in pixels (1 but where
            neighbouring pixels' noise is correlated, :func:`~torchmanifold.pipeline.selection._cv_cell`).
        clamped: ``(T, 1, H, W)`` the luminance of the radiance the firefly clamp took (0 without a clamp).
        lone: ``(T, 1, H, W)`` the part of ``clamped`` that lone fireflies took (:func:`_lone_fireflies`).
        mixed: ``(T, 1, H, W)`` in [0, 1], how surely a pixel's samples mix two surfaces at random (a lens's
            or a shutter's, :func:`~torchmanifold.pipeline.footprint._mixed_layers`), or ``None`` without
            depth.
        caustic: ``(T, 1, H, W)`` in [0, 1], the narrowest bandwidth's weight where caustic light lands
            (:func:`_caustic_light`), or ``None`` without the ``caustic`` feature.
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
    keep_samples: Tensor
    emission: Tensor | None
    position: Tensor | None
    flow_field: Tensor | None
    guide: Tensor
    sigmas: Tensor
    pooling: Tensor
    cv_cell: Tensor
    clamped: Tensor
    lone: Tensor
    mixed: Tensor | None
    caustic: Tensor | None
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
        tensors = ("values", "level", "mask", "flat", "albedo", "smooth", "keep_samples", "emission",
                   "position", "flow_field", "guide", "sigmas", "pooling", "cv_cell", "clamped", "lone",
                   "mixed", "caustic")
        joined = {n: join(n) for n in tensors if n != "flow_field"}
        # the flows match the positions themselves where there are any: joined once
        same = all(s.flow_field is s.position for s in states)
        joined["flow_field"] = joined["position"] if same else join("flow_field")
        first = states[0]
        return FrameState(*(joined[n] for n in tensors), first.pilot_only, first.point_samples, counts,
                          first.footprint, first.sigma_s)

    def stats(self) -> dict:
        """Non-finite samples, masked pixels, clamped samples, the fraction of energy clamped, the frames
        whose sky was filtered as noise (``noisy_sky_frames``) and the infinite depths and positions read as
        no hit (``infinite_as_no_hit``)."""
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
    settings = replace(settings, radiance_sigma=radiance_sigma_at(settings, samples_per_pixel))
    em = None if emission is None else emission.to(dt)
    f, infinite = _infinite_as_no_hit(features.to(dt), names)
    c, f, mask, em, counts = _sanitize(color.to(dt), f, em)
    counts["infinite_as_no_hit"] = infinite
    f = _scattered_albedo(f, names, mask)  # a defocused texture's samples: the reference shows the average
    mixed = _mixed_pixels(f, names, mask)  # and where a lens mixes two surfaces, their blend
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
    if bool(lit.any()):
        scattered = _scattered_before_surfaces(sky, lit)
        if bool(scattered.any()):  # samples of the surface behind: its features and albedo, from beside
            f = _from_neighbours(f, scattered, ~sky)
            alb_s, flat_s = _demodulation_albedo(f, names, settings)
            alb, flat = torch.where(scattered, alb_s, alb), torch.where(scattered, flat_s, flat)
            lit = lit & ~scattered
    if bool(lit.any()):
        # a frame with no albedo to demodulate by is filtered whole, its sky with its surfaces: apart, the
        # surfaces would take the flat pixels' narrow average
        whole = _flat_frames(flat)
        alb, flat = _sky_share_albedo(alb, flat, f, names, lit, settings)
        alb, flat, f = torch.where(lit, 1.0, alb), flat & (whole | ~lit), torch.where(lit, 0.0, f)
    # in a medium (a frame whose sky is noise) the colour is largely light scattered on the way, which no
    # surface's albedo scales: such a frame is not demodulated but filtered whole as radiance (the albedo
    # still guides); divided by the albedo, the surfaces' texture was drawn into the fog's light
    medium = noisy_sky.flatten(1).any(1).view(-1, 1, 1, 1)
    alb, flat = torch.where(medium, 1.0, alb), flat | medium
    e = c / alb
    guide, sig, gnames = _guide(f, names, e, mask, settings)
    # texture gets its own footprint where the sample count, hence the samples' jitter, is known
    geometry = [k for k, n in enumerate(gnames) if feature_group(n) != "albedo"]
    known = settings.footprint_sigma is None and _known_count(samples_per_pixel)
    smooth = _smooth_surface(guide[:, geometry], sig[:, geometry]) if geometry and known else None
    counts.update(firefly_clamped_samples=0, firefly_energy=0.0, energy=0.0)
    fp = footprint_width(settings, samples_per_pixel)
    position = _position(f, names) if settings.temporal_radius > 0 else None  # used by a window alone
    flow_field = position  # what the flows between a window's frames match, where there is a window
    if flow_field is None and settings.temporal_radius > 0 and gnames:
        flow_field = guide[:, :len(gnames)] / sig[:, :len(gnames), None, None].to(guide.dtype)
    point = _known_count(samples_per_pixel) and float(samples_per_pixel) == 1
    # the demodulated pixels; every pixel of a frame that has no albedo to demodulate by
    demodulated = ~flat | _flat_frames(flat)
    # a plain surface needs its albedo: normals alone take in texture
    plain = [k for k, n in enumerate(gnames) if feature_group(n) in _PLAIN_GROUPS] if _albedo_guides(gnames) \
        else []
    cell = torch.ones(c.shape[0], dtype=torch.int64) if own_pixels else \
        _cv_cell(e, (mask > 0) & demodulated, guide[:, plain], sig[:, plain])
    # flat pixels beside demodulated ones whose colour is no noise keep it (a frame that is flat alone,
    # with no albedo, is filtered whole)
    beside = flat & ~sky & (mask > 0) & ~demodulated
    kept_flat = beside & _exact_flat(c, beside)
    counts["kept_flat_frames"] = int(kept_flat.flatten(1).any(1).sum())
    keep_samples = (kept & (mask > 0)) | kept_flat
    pooling = torch.ones(c.shape[0], dtype=torch.float64)
    state = FrameState(e, None, mask, flat, alb, smooth, keep_samples, em, position, flow_field, guide, sig,
                       pooling, cell, torch.zeros_like(mask), torch.zeros_like(mask), mixed,
                       _caustic_light(f, names, mask), False, point, counts, fp, base)
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
    if settings.firefly == "log" and pilot is None:
        state.level, state.pilot_only = pe, True
        return state
    # a caller's pilot (a past result) only sets the clamp: as the bandwidth selection's error level its blur
    # would lock itself in where the samples now resolve more (the progressive loop's caustic, findings.md)
    state.values, state.clamped = _clamp_fireflies(e, alb, pe, mask, k_ff, counts, keep_samples)
    state.lone = _lone_fireflies(state.clamped, luminance(e * alb) * mask)
    if pilot is None:  # a caller's pilot is a past result: guiding by it would lock its errors in
        noise = _pilot_noise(pe, level * torch.expm1(held["x"]), (mask > 0) & demodulated)
        state.guide, state.sigmas = _radiance_from_pilot(guide, sig, _pilot_along_edges(pe, base), mask,
                                                         settings, noise)
        if not _albedo_guides(gnames):
            # beside geometry a noisy pilot's hue steers by noise, as its albedo would; colour alone has no
            # other guide to fall back on
            hue_noise = noise if gnames else None
            state.guide, state.sigmas = _chromaticity_from_pilot(state.guide, state.sigmas, pe, mask,
                                                                 len(gnames), hue_noise)
        state.sigmas = _albedo_widened(state.sigmas, gnames, noise)
        state.level = _trusted_level(pe, mask, _pilot_trust(noise / _PILOT_NOISE_SCALE))
        state.pooling = _selection_pooling(noise / _PILOT_NOISE_SCALE)
    return state


def denoise_window_states(states: Sequence[Future], settings: DenoiseSettings, frame_times: Sequence[float],
                          query: float, sigma_s: float | None = None, range_scale: float = 1.0,
                          cache: ClipCache | None = None) -> tuple[Tensor, FrameState]:
    """One query's output from its time window's frames, each prepared alone (:func:`prepare_frames`; futures
    of their states, waited on here): ``(1, 3, H, W)`` in ``settings.dtype`` and the window's joined state.
    Every front end (a whole clip side by side, the streamed files, the progressive loop) filters a window
    through here, on any thread, with its clip's ``cache`` (see :func:`denoise_prepared`)."""
    state = FrameState.cat([s.result() for s in states])
    return denoise_prepared(state, settings, frame_times, [query], sigma_s, range_scale, cache), state


@serial
def denoise_prepared(state: FrameState, settings: DenoiseSettings, frame_times: Sequence[float],
                     query_times: Sequence[float], sigma_s: float | None = None,
                     range_scale: float = 1.0, cache: ClipCache | None = None) -> Tensor:
    """Filter prepared frames at the query times: ``(Q, 3, H, W)`` in ``settings.dtype`` (arguments as
    :func:`denoise_frames`). At a query whose frame's pilot is too noisy to trust, the time window joins
    every frame the albedo's window holds (:func:`_noisy_window`) and, in large frames, wider candidates join
    (:func:`_noisy_bandwidths`). A query at a frame borrows evidence from
    its neighbours' queries (``settings.lending_radius``), filtered here unless ``cache`` (one per clip and
    settings, shared by a clip's calls) holds them."""
    ft, qt = list(frame_times), list(query_times)
    base = state.sigma_s if sigma_s is None else float(sigma_s)
    wide, kinds = _noisy_window(state, settings, ft, qt), _noisy_window(state, settings, ft, ft)
    between = sum(frame_at(ft, q) is None for q in qt)  # a query at a frame borrows evidence, one between not
    align = _alignment(state, settings, ft, cache, any(wide))
    moving = [align is not None and frame_at(ft, q) is not None and align.moves(frame_at(ft, q)) for q in qt]
    if len(qt) > 1 and (0 < sum(wide) < len(qt) or (settings.lending_radius > 0 and 0 < between < len(qt))
                        or any(moving)):
        # each query with its own window and evidence: a frame's bytes do not depend on the other queries
        if any(moving) and cache is None:  # the flows between frames, found once
            cache = ClipCache()
        return torch.cat([denoise_prepared(state, settings, ft, [q], sigma_s, range_scale, cache)
                          for q in qt])
    if any(wide):
        # the window's candidates alone: a frame's own narrow candidate is its noise there; wider ones where
        # the frame is large enough for them
        settings = replace(settings, temporal_radius=settings.joined_radius, frame_alone_bandwidths=(),
                           bandwidths=_noisy_bandwidths(settings, base, min(state.values.shape[-2:])))
    pooled = settings.selection_blur * _frame_pooling(*state.values.shape[-2:], settings.selection_side)
    settings = replace(settings, selection_blur=pooled)
    # s: each frame at its own pixels, for what a query takes from its own frame; w: the window brought to
    # the query's pixels where the view moves, for what joins the frames (the filters, the albedo's window)
    s, query = state, frame_at(ft, qt[0])
    w = _AlignedState(state, align, query) if moving[0] else state

    def at_queries(x: Tensor) -> Tensor:
        return _Filter.at_frames_to_queries(x, ft, qt)

    def joined(x: Tensor, weights: bool = False, ids: range | None = None) -> Tensor:
        # a tensor of s's frames as w's (``ids``: those frames alone)
        if moving[0]:
            return align.frames(x, query, weights, ids)
        return x if ids is None else x[ids.start:ids.stop]

    if s.pilot_only:
        out = at_queries(s.level)
    else:
        if settings.candidates == 1:
            b = float(settings.bandwidths[0])
            op = _Filter(w.guide, w.sigmas, settings, ft, qt, base * b, range_scale,
                         tree_height_at(settings, b))

            def filt(values, mask):
                return op(joined(values), joined(mask, True))
        else:
            neighbours = _lenders(kinds, settings, ft, qt)
            caustic = None if s.caustic is None else at_queries(s.caustic)

            def filt(values, mask):
                if neighbours is None:
                    return _select_bandwidth(joined(values), joined(mask, True), w.guide, w.sigmas, settings,
                                             ft, qt, base, range_scale, w.level, w.pooling,
                                             int(w.cv_cell.max()), caustic)
                # each query's window and its neighbours' brought to their own pixels there
                return _pooled_selection(values, mask, s.guide, s.sigmas, settings, ft, qt, base, range_scale,
                                         s.level, s.pooling, int(s.cv_cell.max()), neighbours, cache,
                                         align if any(moving) else None, caustic)

        def flat_widths(e: Tensor, weight: Tensor, sigma: float) -> Tensor:
            # averaged, or blended where they hold enough flat pixels that keep no samples (a clear sky does),
            # at the frames the queries take it from (all where a query lies between frames); the other
            # frames are not read
            at = [frame_at(ft, q) for q in qt]
            read = sorted(set(at)) if None not in at else list(range(len(ft)))
            if len(read) == len(ft):
                out = _flat_average(e, weight, sigma)
            else:
                out = e.new_zeros(e.shape)
                out[read] = _flat_average(e[read], weight[read], sigma)
            ids = [k for k in read if int(((weight[k] > 0) & ~s.keep_samples[k]).sum()) >= _MIN_FLAT_PIXELS]
            if ids:  # from the frames their filters read alone
                r = windows_span(ft, [ft[k] for k in ids], settings.temporal_radius)
                e, weight = joined(e, ids=r), joined(weight, True, r)
                guided = _flat_filters(e, w.mask[r.start:r.stop], settings, ft[r.start:r.stop],
                                       [ft[k] for k in ids], range_scale)
                out[ids] = _select_flat_width(e, weight, sigma, int(s.cv_cell.max()), settings.selection_blur,
                                              settings.selection_softness, guided, [k - r.start for k in ids])
            return out
        out = _filter_flat_apart(filt, s.values, s.mask, s.flat, base * min(settings.bandwidths), at_queries,
                                 flat_widths)
    kept = at_queries(s.keep_samples.to(out.dtype)) > 0.5
    if bool(kept.any()):  # the environment seen directly, a picture on a light: nothing to filter
        out = torch.where(kept, at_queries(s.values), out)
    albedo, counts = at_queries(s.albedo), None
    if s.position is not None and settings.temporal_radius > 0:
        albedo, counts = _window_albedo(albedo, w, ft, qt, settings.albedo_radius)
    out = _remodulate(out, albedo, at_queries(s.flat.to(out.dtype)) > 0.5,
                      None if s.smooth is None else at_queries(s.smooth), s.footprint, counts,
                      1 + 2 * settings.albedo_radius, _UNSEEN_BORDER if s.point_samples else 0.0)
    if s.mixed is not None and bool((s.mixed > 0).any()):
        out = _mixed_footprint(out, at_queries(s.mixed))
    noisy, widest = _noisy_pilot(s, ft, qt), base * max(settings.bandwidths)

    def window_mean(x: Tensor) -> Tensor:  # what the clamp took, held still from frame to frame
        return torch.stack([x[window(ft, q, settings.temporal_radius)].mean(0) for q in qt])
    if bool(noisy.any()):
        out = _give_back(out, window_mean(w.clamped), noisy, _GIVE_BACK_REACH * widest, kept)
    if not bool(noisy.all()) and bool((s.lone > 0).any()):
        reach = _FIREFLY_BACK_REACH * widest
        out = _give_back(out, window_mean(w.lone), ~noisy, reach, kept, _FIREFLY_BACK_COUNT)
    if s.emission is not None:  # the renderer's emission is added back exactly as rendered
        out = out + at_queries(s.emission)
    return out


def _alignment(state: FrameState, settings: DenoiseSettings, ft: list[float], cache: ClipCache | None,
               wide: bool) -> WindowAlignment | None:
    """The flows that bring a window's frames to a query frame's pixels (:mod:`~torchmanifold.pipeline.align`;
    a query between frames has no frame's pixels and keeps the window as it is): where
    ``settings.align_frames`` asks and there is a time window and features to match (``state.flow_field``).
    The frames brought: those the albedo's window joins where there are world positions or the filter's window
    widens (``wide``, :func:`_noisy_window`), else the filter's. ``cache`` keeps the flows for the clip."""
    if not settings.align_frames or state.flow_field is None or settings.temporal_radius == 0:
        return None
    radius = settings.joined_radius if state.position is not None or wide else settings.temporal_radius
    # without positions the features are piecewise constant: a move along a plain wall matches as well as none
    return WindowAlignment(state.flow_field, ft, radius, cache, varying_only=state.position is None)


#: the per-pixel fields of a :class:`FrameState` that a query joins from the window's other frames (the
#: filters' guide and error level, the albedo's window, what the firefly clamp took)
_JOINED_FIELDS = ("mask", "flat", "albedo", "position", "guide", "level", "clamped", "lone")


class _AlignedState:
    """``state`` (a :class:`FrameState`, read as one) with the frames within ``align``'s radius of frame ``k``
    brought to its pixels in the fields a query joins from them (:data:`_JOINED_FIELDS`), the sample weights 0
    where a source lies outside its frame; frame ``k`` is as it was. Each field is gathered when first read:
    a query reads some of them only, by its settings (the default reads neither the guide nor the level)."""

    def __init__(self, state: FrameState, align: WindowAlignment, k: int):
        self._state, self._align, self._k = state, align, k

    def __getattr__(self, name: str):
        if name.startswith("_"):  # not a field (and not this object's own, before they are set)
            raise AttributeError(name)
        x = getattr(self._state, name)
        if name in _JOINED_FIELDS and x is not None:
            x = self._align.frames(x, self._k, name == "mask")
        setattr(self, name, x)  # read once: later reads find it here
        return x


def _lenders(kinds: list[bool], settings: DenoiseSettings, ft: list[float], qt: list[float]) -> list | None:
    """Per query, the frames whose queries lend it their cross-validated residuals: those within
    ``settings.lending_radius`` of its frame whose window is of its kind (``kinds``: per frame,
    :func:`_noisy_window`); ``None`` where a query lies between frames or there is no time window (each
    query's evidence is its own)."""
    at = [frame_at(ft, q) for q in qt]
    r = settings.lending_radius
    if r == 0 or None in at:
        return None
    return [[n for n in index_window(len(ft), k, r) if n != k and kinds[n] == kinds[k]] for k in at]


def _noisy_window(state: FrameState, settings: DenoiseSettings, ft: list[float],
                  qt: list[float]) -> list[bool]:
    """Per query, whether its time window widens to every frame the albedo's window holds
    (``settings.joined_radius``): where the query is a frame whose firefly pilot is too noisy to trust
    (``state.pooling`` above 1, :func:`_selection_pooling`), as the selection's pooling widens there. Only
    the two rooms lit by bounce light alone are that noisy: frames 0-5 from 1 / 4 spp, ``mi_indirect_dof``
    (tuning part) +0.15 / +0.11 dB and ``bl_indirect_dof`` (held out) +0.11 / +0.14 with +-2 frames against
    +-1 (for 5/3 of the op's time there); every other scene keeps its bits. With the albedo's +-3 (all frames,
    against +-2, the albedo's window included): ``mi_indirect_dof`` +0.09 / +0.09, ``bl_indirect_dof`` +0.02 /
    +0.01."""
    if settings.temporal_radius == 0 or settings.joined_radius <= settings.temporal_radius:
        return [False] * len(qt)
    return _noisy_pilot(state, ft, qt).tolist()


#: Where the pilot is too noisy to trust (a room lit by bounce light alone, whose walls show splotches), one
#: candidate twice the widest joins where it stays within this share of the frame's shorter side: the tuned
#: widest, 16 px from 1 spp, is an eighth of the set's 128x128 frames. The two such rooms at 256x256, every
#: frame from 1 / 4 spp: `bl_indirect_dof` +0.12 / +0.10 dB, `mi_indirect_dof` +0.05 / 0.00; at 128x128 the
#: same candidate lost `bl_indirect_dof` 0.06 / 0.01 (findings.md). One step, as far as it was measured.
_NOISY_WIDEST_SHARE = 1.0 / 8.0


def _noisy_bandwidths(settings: DenoiseSettings, sigma_s: float, side: int) -> tuple[float, ...]:
    """The candidates (multiples of ``sigma_s`` pixels) of a window whose pilot is too noisy to trust, in
    frames whose shorter side is ``side`` pixels: ``settings.bandwidths``, and twice the widest where that is
    within :data:`_NOISY_WIDEST_SHARE` of ``side``."""
    out = tuple(float(b) for b in settings.bandwidths)
    wider = 2.0 * max(out)
    if len(out) == 1 or wider * sigma_s > _NOISY_WIDEST_SHARE * side:  # one bandwidth a caller chose: kept
        return out
    return out + (wider,)


def _noisy_pilot(state: FrameState, ft: list[float], qt: list[float]) -> Tensor:
    """Per query, whether it is a frame whose firefly pilot is too noisy to trust (``state.pooling`` above
    1, :func:`_selection_pooling`): bool ``(Q,)``."""
    at = [frame_at(ft, q) for q in qt]
    return torch.tensor([k is not None and float(state.pooling[k]) > 1.0 for k in at], dtype=torch.bool)


def _infinite_as_no_hit(f: Tensor, names: Sequence[str]) -> tuple[Tensor, int]:
    """Features ``f`` ``(T, D, H, W)`` named ``names`` with the infinite values of their geometry (depth and
    positions, ``sigma_of_extent`` in :mod:`torchmanifold.features`) read as 0, a ray that left the scene
    (ours, Mitsuba's and Blender's, once read, write 0 there; other renderers an infinite depth), and how many
    there were. Taken for bad samples, they dropped an open scene's sky from the filter (`mi_env_thin` with
    an infinite background, frame 1: 31.40 -> 29.02 dB)."""
    geometry = [k for k, n in enumerate(names)
                if (row := feature_table.feature_of(n)) is not None and row.sigma_of_extent]
    if not geometry:
        return f, 0
    x = f[:, geometry]
    infinite = torch.isinf(x)
    count = int(infinite.sum())
    if count == 0:
        return f, 0
    f = f.clone()
    f[:, geometry] = torch.where(infinite, 0.0, x)
    return f, count


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


def _albedo(f: Tensor, names: Sequence[str]) -> Tensor | None:
    """The renderer's albedo ``(T, 3, H, W)`` from features ``f`` named ``names`` (any alias), negatives
    taken as 0; ``None`` where the three channels are not all there."""
    canon = [canonical_name(n) for n in names]
    if not all(a in canon for a in _ALBEDO):
        return None
    return torch.stack([f[:, canon.index(a)] for a in _ALBEDO], 1).clamp_min(0.0)


def _demodulation_albedo(f: Tensor, names: Sequence[str], settings: DenoiseSettings) -> tuple[Tensor, Tensor]:
    """The albedo the colour is divided by, ``(T, 3, H, W)``, and where it is flat (1), ``(T, 1, H, W)``.

    A first-hit albedo darker than ``albedo_eps`` says nothing about the light there: renderers give 0 on
    delta BSDFs (Mitsuba's glass and mirrors) and on black surfaces. Dividing by a clamped tiny albedo
    and multiplying back by a blurred one draws bright rims, so such pixels are not demodulated at all.
    The others are divided by their albedo, each channel at least ``albedo_floor`` (:func:`_divisor`).
    """
    T, _, H, W = f.shape
    alb = _albedo(f, names) if settings.demodulate else None
    if alb is None:
        return f.new_ones(T, 3, H, W), f.new_ones(T, 1, H, W, dtype=torch.bool)
    flat = luminance(alb) < settings.albedo_eps
    return torch.where(flat, 1.0, _divisor(alb, settings)), flat


def _divisor(alb: Tensor, settings: DenoiseSettings) -> Tensor:
    """What a demodulated pixel of albedo ``alb`` ``(T, 3, H, W)`` is divided by: each channel at least
    ``albedo_floor`` (and ``albedo_eps``)."""
    return alb.clamp_min(max(settings.albedo_eps, settings.albedo_floor))


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
#: from the environment's own detail by R, the mean square of the sky's differences between pixels two
#: apart over that of pixels four apart (rows and columns of five sky pixels, on the luminance tone-mapped
#: by the sky's mean): noise gives 1, a smooth gradient 1/4, an edge 1/2, stripes two pixels wide more than
#: 1. Two apart, not adjacent: a reconstruction filter that splats each sample over its neighbours
#: (Mitsuba's default gaussian) correlates adjacent pixels' noise, and their differences' ratio to those two
#: apart fell to 0.48-0.59 on the Mitsuba fog probe rendered that way, where two against four apart gives
#: 0.88-0.98. Per frame, from 1 and 4 spp: the validation set's skies (Mitsuba's and Cycles', 128x128 and
#: 256x256) 0.25-0.28, the fog probes 0.96-1.03 with box filters. The sky is noise where R is within a
#: factor sqrt(2) of 1 and adjacent pixels differ by no more than sqrt(2) times as much as pixels two apart:
#: noise, splatted or not, differs less, stripes a pixel wide (which R cannot see) differ more
#: (``benchmarks/validation/findings.md``). The same test tells a frame's flat pixels (glass, mirrors, black
#: surfaces: no albedo, averaged apart) whose colour is no noise, :func:`_exact_flat`: a picture on an emitter
#: whose surface is black (the ``mi_screen`` probe: 26.60 / 29.19 -> 28.46 / 31.76 dB from 1 / 4 spp when
#: they keep their samples, OIDN 26.86 / 30.46), where glass and mirrors showing lit surfaces are noise (every
#: clip of the set, its iterations, the Mitsuba probes and four Mitsuba clips at 256x256 keep their bits).
_NOISE_RATIOS = (2.0 ** -0.5, 2.0 ** 0.5)
#: the pixel spacings the differences are taken at (see :data:`_NOISE_RATIOS`)
_NOISE_LAGS = (1, 2, 4)
#: the largest differences left out of both means: a small sun's rim or a few stars are points, which a
#: smooth sky around them would make look like noise
_NOISE_OUTLIERS = 0.01
#: rows of five pixels the test needs: for independent noise R's standard error is then about 0.09
_MIN_NOISE_RUNS = 500
#: Flat pixels keep their samples only where most adjacent ones differ by less than this (luminance
#: tone-mapped as above: about 1% of a colour near the pixels' mean). More than :data:`_EQUAL_NEIGHBOURS` of
#: them do on ``mi_screen`` (0.69-0.72 from 1 spp); on the glass and mirror of ``mi_glass_mirror`` 0.06-0.11
#: from 1 to 16 spp, where the ratios alone came near their bound (adjacent against two apart 0.74-0.78 and
#: two apart against four apart 0.65-0.70 from 16 spp: kept there, those pixels lost that clip 0.78 dB),
#: rough glass (``mi_frost``) 0.11-0.13, smoke (``mi_smoke``) 0.15-0.18
_EQUAL_DIFFERENCE = 0.0025
_EQUAL_NEIGHBOURS = 0.5


def _difference_ratios(c: Tensor, pixels: Tensor) -> Tensor:
    """Per frame, how the colour ``c`` ``(T, 3, H, W)`` of ``pixels`` (bool ``(T, 1, H, W)``: the sky,
    :func:`_escaped`, or flat pixels) differs at the spacings of :data:`_NOISE_LAGS`: ``(T, 3)`` float64, the
    mean square of the differences between adjacent pixels over that of pixels two apart, and of pixels two
    apart over four apart (1 and 1 for noise, see :data:`_NOISE_RATIOS`), and the share of adjacent pixels
    that differ by less than :data:`_EQUAL_DIFFERENCE`; NaN for a frame with fewer than
    :data:`_MIN_NOISE_RUNS` rows of five such pixels, or whose differences are all 0 once the largest are left
    out (black, or a few bright samples on black). In NumPy float64, whose sums do not depend on the thread
    count."""
    out = torch.full((c.shape[0], 3), float("nan"), dtype=torch.float64)
    span = _NOISE_LAGS[-1]
    # most frames have no such pixels to judge: they skip the copy into NumPy
    for t in torch.nonzero(pixels.flatten(1).sum(1) >= _MIN_NOISE_RUNS).flatten().tolist():
        with torch.no_grad():
            x = luminance(c[t:t + 1].detach()).double().clamp_min(0.0)[0, 0].cpu().numpy()
            s = pixels[t, 0].cpu().numpy()
        y = x / np.maximum(x + x[s].mean(), 1e-300)
        diffs = {lag: [] for lag in _NOISE_LAGS}
        for yy, ss in ((y, s), (y.T, s.T)):  # rows, then columns
            n = ss.shape[1] - span  # runs start at columns 0..n-1
            if n <= 0:
                continue
            run = ss[:, :n].copy()  # every pixel of the run is one of them
            for k in range(1, span + 1):
                run &= ss[:, k:n + k]
            for lag, d in diffs.items():
                d.append((yy[:, :n] - yy[:, lag:n + lag])[run] ** 2)
        count = sum(d.size for d in diffs[span])
        if count < _MIN_NOISE_RUNS:
            continue
        keep = count - int(_NOISE_OUTLIERS * count)  # the largest 1% left out of each mean
        adjacent, near, far = (np.partition(np.concatenate(diffs[lag]), keep - 1)[:keep].sum()
                               for lag in _NOISE_LAGS)
        if far > 0:
            equal = (np.concatenate(diffs[1]) < _EQUAL_DIFFERENCE ** 2).mean()
            out[t] = torch.tensor([adjacent / max(near, 1e-300), near / far, equal], dtype=torch.float64)
    return out


def _noisy_sky(c: Tensor, sky: Tensor) -> Tensor:
    """Per frame, whether the colour ``c`` ``(T, 3, H, W)`` of the sky pixels ``sky`` (bool ``(T, 1, H, W)``,
    :func:`_escaped`) is noise, ``(T, 1, 1, 1)`` bool: two apart against four apart within
    :data:`_NOISE_RATIOS` and adjacent against two apart under its upper bound (:func:`_difference_ratios`; a
    frame with too few sky pixels, or a black sky, is not)."""
    lo, hi = _NOISE_RATIOS
    adjacent, near = _difference_ratios(c, sky)[:, :2].unbind(1)  # NaN compares false
    return ((near > lo) & (near < hi) & (adjacent < hi)).view(-1, 1, 1, 1)


def _exact_flat(c: Tensor, flat: Tensor) -> Tensor:
    """Per frame, whether the colour ``c`` ``(T, 3, H, W)`` of flat pixels ``flat`` (bool ``(T, 1, H, W)``) is
    surely no noise, ``(T, 1, 1, 1)`` bool (:func:`_difference_ratios`): most adjacent pixels alike
    (:data:`_EQUAL_NEIGHBOURS`), and both ratios under the lower bound of :data:`_NOISE_RATIOS`, as edges
    and gradients give and noise, splatted or sparse on black, does not. Stricter than the sky's test, which
    keeps what is not surely noise: kept, what glass shows would stay noise; a frame with too few flat pixels
    to judge is filtered."""
    lo = _NOISE_RATIOS[0]
    adjacent, near, equal = _difference_ratios(c, flat).unbind(1)
    return ((equal > _EQUAL_NEIGHBOURS) & (adjacent < lo) & (near < lo)).view(-1, 1, 1, 1)


#: a frame's filtered sky lies among its surfaces where at least this share of its pixels have half their
#: eight neighbours or more on surfaces: from 1 spp, Cycles' fog probe (a path scattered in the medium reads
#: depth 0 wherever it is) 0.32 per frame, Mitsuba's (a ray that meets no surface, whatever the medium)
#: 0.014-0.019 with a box filter and with its gaussian; from 4 spp (a pixel reads 0 only where every sample
#: did) 0.016-0.025
_SCATTERED_AMONG_SURFACES = 0.1
#: in such a frame, a sky pixel with at least this many of its eight neighbours on surfaces is a path
#: scattered before the surface behind it. ``bl_fog`` frames 0-3 from 1 spp (29.59 dB without): 4 / 3 / 2 / 1
#: give 30.96 / 31.61 / 31.85 / 31.73 (OIDN 31.80 over all frames)
_SCATTERED_NEIGHBOURS = 2


def _scattered_before_surfaces(sky: Tensor, lit: Tensor) -> Tensor:
    """The pixels of the filtered sky ``lit`` (bool ``(T, 1, H, W)``; ``sky`` every pixel of depth 0) that
    are paths scattered in a medium before the surface behind them, ``(T, 1, H, W)`` bool.

    Cycles writes a path that scatters in fog as depth 0 wherever it is, so from 1 spp the fog's ground is
    half ground samples and half such pixels, and filtered apart the two showed as dark and light speckle
    where the reference is their mean. Such a pixel is a sample of the surface behind it: where a frame's
    filtered sky lies among its surfaces (:data:`_SCATTERED_AMONG_SURFACES`), its pixels with
    :data:`_SCATTERED_NEIGHBOURS` or more neighbours on surfaces, one of them adjacent, are. Mitsuba writes
    the first surface a ray meets whatever the medium, so its sky pixels are where rays left the scene, in
    regions, and none is taken."""
    surface = (~sky).to(torch.float32)
    # the eight neighbours on surfaces (none beyond the border)
    around = nn.functional.avg_pool2d(nn.functional.pad(surface, (1, 1, 1, 1)), 3, 1, divisor_override=1)
    around = around - surface
    adjacent = _four_neighbours(surface) > 0
    among = (lit & (around >= 4)).flatten(1).sum(1) >= _SCATTERED_AMONG_SURFACES * lit.flatten(1).sum(1)
    return lit & adjacent & (around >= _SCATTERED_NEIGHBOURS) & among.view(-1, 1, 1, 1)


#: how far (pixels) from a sky pixel a pixel may mix sky samples into its mean: a reconstruction filter that
#: splats samples reaches 2 px (Mitsuba's default gaussian), a box filter keeps them in their own pixel
_SKY_MIX_RADIUS = 2


def _sky_share_albedo(alb: Tensor, flat: Tensor, f: Tensor, names: Sequence[str], lit: Tensor,
                      settings: DenoiseSettings) -> tuple[Tensor, Tensor]:
    """The demodulation albedo ``alb`` ``(T, 3, H, W)`` and flat pixels ``flat`` ``(T, 1, H, W)``
    (:func:`_demodulation_albedo`) with the share of each pixel's samples that met no surface divided by 1,
    as a filtered sky is (``lit`` ``(T, 1, H, W)``: the sky pixels of frames whose sky is noise,
    :func:`_noisy_sky`).

    A pixel beside such a sky averages samples that met a surface and samples that did not, which renderers
    write with no normal and an albedo of their own (Mitsuba 0, Cycles in fog the medium's colour), while
    their colour is scattered light like the sky's. Divided by its surface samples' albedo alone, the pixel
    reads many times too bright and the filter spreads that into the sky: Mitsuba's fog probe, rendered with
    its default gaussian filter, came out twice as bright as the reference around the horizon. The share
    ``s`` of sky samples is what the mean normal lacks of unit length, taken only within
    :data:`_SKY_MIX_RADIUS` of the sky (elsewhere a normal is also shorter where its samples' normals
    differ); the albedo becomes ``a + s (1 - a0)``, ``a`` the renderer's albedo and ``a0`` the frame's mean
    albedo over its sky pixels (the sky samples' part of ``a``). A pixel flat for its small albedo whose
    albedo so reaches ``albedo_eps`` was mostly sky, and is demodulated. A frame without normals
    keeps its albedo."""
    canon = [canonical_name(n) for n in names]
    unit = next((g for g in feature_table.FEATURES if g.unit and all(c in canon for c in g.channels)), None)
    raw = _albedo(f, names) if settings.demodulate else None
    if unit is None or raw is None:
        return alb, flat
    normal = torch.stack([f[:, canon.index(c)] for c in unit.channels], 1)
    share = (1.0 - torch.linalg.vector_norm(normal, dim=1, keepdim=True)).clamp(0.0, 1.0)
    sky = lit.to(f.dtype)
    near = _any_within(lit, _SKY_MIX_RADIUS)
    sky_albedo = (raw * sky).sum((2, 3), keepdim=True) / sky.sum((2, 3), keepdim=True).clamp_min(1.0)
    mixed_albedo = raw + share * (1.0 - sky_albedo).clamp_min(0.0)
    mixed = near & ~lit & (share > 0) & (luminance(mixed_albedo) >= settings.albedo_eps)
    return torch.where(mixed, _divisor(mixed_albedo, settings), alb), flat & ~mixed


def _log_radiance(e: Tensor, mask: Tensor) -> Tensor:
    """Log luminance of the demodulated colour, ``(T, 1, H, W)``: a guide channel that tells lights from
    the surface they sit in (no renderer AOV does), shadows from lit ground and what is seen through glass.

    ``log(L + 0.1 mean(L))`` is the same for any exposure and does not resolve noise far below the
    frame's level; each pixel takes the mean of the least varying of the four 3x3 windows that hold it
    in a corner (a Kuwahara filter), so a pixel on the edge of a light still reads as the light.
    """
    L = luminance(e).clamp_min(0.0)
    return _log_radiance_of(L, _frame_mean(L, mask), kuwahara=True)


def _kuwahara3(x: Tensor) -> Tensor:
    """Each channel of ``x`` ``(T, C, H, W)`` at each pixel: the mean of the least varying of the four 3x3
    windows that hold the pixel in a corner (replicate-padded), so that an edge stays sharp."""
    if _fast.enabled(x):
        return _fast.kuwahara3(x)
    C, H, W = x.shape[-3:]
    moments = torch.nn.functional.pad(torch.cat([x, x * x], 1), (2, 2, 2, 2), mode="replicate")
    moments = torch.nn.functional.avg_pool2d(moments, 3, 1)
    best_v = best_m = None
    for dy in (0, 2):
        for dx in (0, 2):
            mu = moments[:, :C, dy:dy + H, dx:dx + W]
            v = moments[:, C:, dy:dy + H, dx:dx + W] - mu * mu
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
    # from single samples: noisier than the pilot's that replaces them, so wider
    # without albedo, the samples' hue tells apart what luminance and geometry do not
    colour, colour_sig = _colour_channels(e, mask, not _albedo_guides(gnames),
                                          _SAMPLE_RADIANCE_WIDENING * _radiance_sigma(settings))
    parts += colour
    sig += colour_sig
    if not parts:
        return e.new_zeros(T, 1, H, W), torch.ones(T, 1, dtype=torch.float64), gnames
    return torch.cat(parts, 1), torch.cat(sig, 1), gnames


def _colour_channels(e: Tensor, mask: Tensor, chroma: bool, radiance_sigma: float) -> tuple[list, list]:
    """Guide channels of the samples' colour ``e`` ``(T, 3, H, W)`` and their range sigmas ``(T, k)``
    float64, as lists: the chromaticity (3x3 Kuwahara, :func:`_chromaticity`) at
    :data:`_SAMPLE_RADIANCE_WIDENING` times :data:`_CHROMA_SIGMA` where ``chroma``, then the log radiance
    (:func:`_log_radiance`) at ``radiance_sigma`` where it is positive (frame means over ``mask``)."""
    T = e.shape[0]
    parts, sig = [], []
    if chroma:
        parts.append(_kuwahara3(_chromaticity(e, mask)))
        sig.append(torch.full((T, 2), _SAMPLE_RADIANCE_WIDENING * _CHROMA_SIGMA, dtype=torch.float64))
    if radiance_sigma > 0:
        parts.append(_log_radiance(e, mask))
        sig.append(torch.full((T, 1), radiance_sigma, dtype=torch.float64))
    return parts, sig


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


#: the pilot's average along its own edges, for the log-radiance channel: its width and the structure
#: tensor's smoothing that finds the edges, in units of the pilot's spatial sigma. All frames from 1 / 4 spp,
#: against the pilot as it is: the two held-out sunlit rooms +0.09 / +0.01 dB, the set's eleven clips +0.003 /
#: +0.007, six Mitsuba and five Cycles clips at 256x256 +0.009 / +0.011 and +0.005 / +0.003, fifteen probes
#: +0.004 / +0.017, no clip below -0.03; 3 and 1 instead: the rooms +0.12 / +0.04, the set 0.000 / +0.004, the
#: 256x256 clips +0.009 / +0.009 and +0.003 / +0.001 (``benchmarks/validation/findings.md``)
_PILOT_ALONG_EDGES, _PILOT_EDGE_TENSOR = 1.5, 0.5


def _pilot_along_edges(pilot: Tensor, sigma: float) -> Tensor:
    """The pilot ``(T, 3, H, W)`` averaged along its own edges
    (:func:`~torchmanifold.pipeline.footprint._along_edges`), ``sigma`` its spatial sigma. Where no feature
    parts a shadow's or a sun patch's border, the pilot alone draws it, and the pilot's noise bends the
    contour its channel steers by, which the filter then draws at every bandwidth; along the border the
    light is the same, so the average straightens the contour and keeps the step across it."""
    directions = _edge_directions(pilot, _PILOT_EDGE_TENSOR * sigma)
    return _along_edges([pilot], [torch.full_like(pilot[:, :1], _PILOT_ALONG_EDGES * sigma)], directions)[0]


def _chromaticity(x: Tensor, mask: Tensor) -> Tensor:
    """``r / (r + g + b)`` and ``g / (r + g + b)`` of colours ``x`` ``(T, 3, H, W)``, ``(T, 2, H, W)`` (the
    sum offset by a thousandth of the frame's mean luminance over ``mask``, so black pixels stay near 0)."""
    p = x.clamp_min(0.0)
    return p[:, :2] / (p.sum(1, keepdim=True) + 1e-3 * _frame_mean(luminance(p), mask).clamp_min(1e-30))


def _chromaticity_from_pilot(guide: Tensor, sigmas: Tensor, pilot: Tensor, mask: Tensor, at: int,
                             noise: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The guide ``(T, G, H, W)`` without albedo and its sigmas ``(T, G)`` with the chromaticity channels (the
    two from channel ``at``, see :func:`_guide`) taken from the pilot ``(T, 3, H, W)`` instead of the samples,
    at :data:`_CHROMA_SIGMA`, widened for the pilot's ``noise`` ``(T,)`` where given, as the albedo's are
    (:func:`_albedo_widened`)."""
    sigmas = sigmas.clone()
    sigmas[:, at:at + 2] = _CHROMA_SIGMA
    if noise is not None:
        sigmas = _noise_widened(sigmas, [at, at + 1], noise)
    chroma = _chromaticity(pilot, mask).to(guide.dtype)
    return torch.cat([guide[:, :at], chroma, guide[:, at + 2:]], 1), sigmas


def _log_radiance_of(L: Tensor, mean: Tensor, kuwahara: bool = False) -> Tensor:
    """The log-radiance guide channel of luminance ``L`` ``(T, 1, H, W)`` whose frame means are ``mean``,
    through :func:`_kuwahara3` where ``kuwahara``."""
    m = mean.clamp_min(1e-30)
    # relative to the frame's mean until its log is added back: the Kuwahara's variances, computed on values
    # near log(exposure), would lose the bits that choose its window (and the choice would follow exposure)
    x = torch.log(L / m + _LOG_RADIANCE_OFFSET)
    return (_kuwahara3(x) if kuwahara else x) + torch.log(m)


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


def _frame_pooling(height: int, width: int, side: float | None) -> float:
    """The factor on ``selection_blur`` for a frame of ``height`` x ``width`` pixels: the square root of its
    shorter side over ``side`` (``DenoiseSettings.selection_side``), at least 1 (smaller frames pool as at
    ``side``); 1 where ``side`` is ``None``.

    A candidate's bias varies on the scene's scale, which grows with the frame, and the noise on the pixel's,
    which does not. All frames from 1 / 4 spp, ``selection_blur`` 3 / 4 / 5 / 5.66 / 6 / 8 (the set's
    128x128 frames: 3 / 4 / 5 / 6): the five Cycles clips at 256x256 (not in the set) 29.39 / 33.04, 29.46 /
    33.09, 29.49 / 33.10, 29.49 / 33.10, 29.49 / 33.09, 29.47 / 33.06 dB; the six Mitsuba clips at 256x256
    with 12 frames 29.62 / 32.02, 29.70 / 32.07, 29.74 / 32.09, 29.75 / 32.09, 29.75 / 32.08, 29.75 / 32.06;
    the set 26.85 / 29.90, 26.87 / 29.90, 26.86 / 29.89, 26.84 / 29.87 (eleven clips; ``findings.md``).
    Without albedo (colour alone) the 256x256 clips pooled at 5.66 lost up to 0.05 dB, the shared clip
    0.15."""
    if side is None:
        return 1.0
    return max(1.0, math.sqrt(min(height, width) / side))


def _selection_pooling(relative_noise: Tensor) -> Tensor:
    """The factor on the bandwidth selection's pooling width (``selection_blur``) for the pilot's noise in
    units of a range sigma: 1 where the pilot is trusted whole (up to :data:`_PILOT_TRUSTED`), and the
    noise over that beyond it. The pooled errors' standard error goes as the noise over the square root of
    the pixels pooled, so the width grows as the noise: the selection tells the candidates apart as surely
    as at a trusted pilot (up to the widest candidate's bandwidth,
    :func:`~torchmanifold.pipeline.selection._select_bandwidth`). Only the two rooms lit by bounce light alone
    are that noisy (0.23-0.36 against at most 0.11, ``findings.md``): over all frames from 1 / 4 spp,
    ``mi_indirect_dof`` (tuning part) +0.08 / +0.28 dB and ``bl_indirect_dof`` (held out) +0.21 / +0.25;
    every other scene keeps its bits."""
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
    return _noise_widened(sigmas, ai, noise) if ai else sigmas


def _noise_widened(sigmas: Tensor, channels: list[int], noise: Tensor) -> Tensor:
    """The range sigmas ``(T, G)`` with those of ``channels`` widened for the pilot's noise ``(T,)``
    (:func:`_noise_widening`, in units of :data:`_PILOT_NOISE_SCALE`)."""
    out = sigmas.clone()
    out[:, channels] *= _noise_widening(noise.to(sigmas.dtype) / _PILOT_NOISE_SCALE)[:, None]
    return out


def _trusted_level(pilot: Tensor, mask: Tensor, trust: Tensor) -> Tensor:
    """The level the bandwidth selection weighs its errors by (relative errors,
    :func:`~torchmanifold.pipeline.selection._select_bandwidth`): the pilot where it is trusted, the frame's
    mean where not (absolute errors), blended by ``trust`` ``(T,)``. A noisy pilot, dark where its samples are
    sparse, would weigh a few pixels' errors far above the rest (``mi_indirect_dof``: +0.44 / +0.89 dB with
    absolute errors; ``findings.md``)."""
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
                     keep: Tensor) -> tuple[Tensor, Tensor]:
    """Scale samples brighter than ``k`` times the pilot ``pe`` (plus a floor) down to that bound, except
    where ``keep`` (bool ``(T, 1, H, W)``): the clamped samples, and the luminance of the radiance taken
    (``(T, 1, H, W)``, the samples times ``alb``); the energy, the energy removed and the samples clamped
    are added to ``stats``. The floor is a quarter of the frame's mean pilot luminance, so dark regions
    next to noise-free black do not clamp every lit sample (measured on shared/data; on the validation set's
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
    taken = ((e - ec) * alb) * mask
    with torch.no_grad():  # counts, not part of a gradient; summed frame by frame, as frames prepared alone
        for key, x in (("energy", (e * alb) * mask), ("firefly_energy", taken)):
            for frame_sum in x.flatten(1).sum(1, dtype=torch.float64).tolist():
                stats[key] += frame_sum
        stats["firefly_clamped_samples"] += int(((scale < 1) & (mask > 0)).sum())
    return ec, luminance(taken)


def _give_back(out: Tensor, clamped: Tensor, queries: Tensor, sigma: float, kept: Tensor | None = None,
               count: float | None = None) -> Tensor:
    """The output ``out`` ``(Q, 3, H, W)`` with the radiance the firefly clamp took given back at the
    ``queries`` (bool ``(Q,)``): each pixel scaled by ``1 + blur(clamped) / blur(lum(out))`` under a
    Gaussian of ``sigma`` pixels, so that what the clamp took around a pixel comes back in proportion to
    what the filter left there. ``clamped`` ``(Q, 1, H, W)``: the luminance the clamp took, averaged over
    each query's time window, so that the gain holds still from frame to frame. Pixels ``kept`` (bool
    ``(Q, 1, H, W)``) keep their samples exactly and take nothing. With a ``count``, a share
    ``n / (n + count)`` of it comes back, ``n`` the effective number of clamped pixels under the kernel
    (``(sum w x)^2 / sum w^2 x^2``): a mean known from a few fireflies is mostly their noise.

    Where the pilot is too noisy to trust, the light that reaches most pixels through rare bright paths
    looks like fireflies to it, and the clamp takes real light: the rooms lit by bounce light alone came out
    7% dark. Spread out as it was taken, that energy draws blotches; in proportion to the result over a
    wide reach it changes the brightness alone. Where the pilot can be trusted, what the clamp took is
    mostly fireflies and bright detail: only lone fireflies' energy comes back there, with a ``count``
    (:func:`_lone_fireflies`): where many of them fall together, they are light (a caustic)."""
    q = queries.nonzero().flatten()
    both = torch.cat([clamped[q], luminance(out[q]).clamp_min(0.0)], 1)
    blurred = _normalised_blur(both, torch.ones_like(both[:, :1]), sigma)
    taken, left = blurred[:, :1], blurred[:, 1:]
    if count is not None:
        taken = taken * _effective_count(clamped[q], sigma, count)
    # out / blur(lum(out)) first: it stays under the inverse of the kernel's centre weight (over the least
    # luminance coefficient), so the product stays finite however little light the filter left
    back = torch.where(left > 0, out[q] / torch.where(left > 0, left, 1.0) * taken, 0.0)
    if kept is not None:
        back = torch.where(kept[q], 0.0, back)
    return out.index_copy(0, q, out[q] + back)


def _effective_count(x: Tensor, sigma: float, count: float) -> Tensor:
    """``n / (n + count)`` per pixel of ``x`` ``(T, 1, H, W)`` (at least 0), ``n = (sum w x)^2 / sum w^2 x^2``
    the effective number of nonzero pixels under a Gaussian ``w`` of ``sigma`` pixels (no terms beyond the
    border, so a firefly by the border does not count as many)."""
    w = _gaussian_taps(sigma, x.dtype, x.device)  # n is the same for any scale of w
    r = (w.numel() - 1) // 2
    conv, pad = torch.nn.functional.conv2d, torch.nn.functional.pad

    def sums(v: Tensor, taps: Tensor) -> Tensor:  # frame by frame: a batch would change the bits
        return torch.cat([conv(pad(conv(pad(f, (r, r, 0, 0)), taps.view(1, 1, 1, -1)), (0, 0, r, r)),
                               taps.view(1, 1, -1, 1)) for f in v.split(1)])

    x = x / x.amax((1, 2, 3), keepdim=True).clamp_min(1e-30)  # n is the same at any scale; x^2 stays finite
    s1, s2 = sums(x, w), sums(x * x, w * w)
    n = torch.where(s2 > 0, s1 * s1 / torch.where(s2 > 0, s2, 1.0), 0.0)
    return n / (n + count)


def _lone_fireflies(clamped: Tensor, radiance: Tensor) -> Tensor:
    """``clamped`` ``(T, 1, H, W)`` (the luminance the clamp took) at spikes: pixels none of whose eight
    neighbours was clamped and whose sample is brighter than each of theirs (``radiance``, like ``clamped``:
    the samples' luminance before the clamp); else 0. A clamped pixel beside another, or beside a sample as
    bright, is bright detail the pilot blurred (a small light and its rim, a highlight): its energy belongs
    where it is, not spread around."""
    beside_clamped = _eight_neighbours_max((clamped > 0).to(clamped.dtype)) > 0
    return torch.where(beside_clamped | (_eight_neighbours_max(radiance) >= radiance), 0.0, clamped)


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
