"""What a pixel's footprint holds, the last stage of the frame step (:mod:`torchmanifold.pipeline.denoise`).

A pixel of the reference averages its whole area; a pixel of n samples shows n points of it. The filtered
irradiance is multiplied back by the albedo and averaged over a footprint whose width follows the samples per
pixel (:func:`footprint_width`), in a tone-mapped domain and among pixels of similar brightness, so that a
light's border does not bleed into the dark beside it (:func:`_footprint_average`). On a smooth surface the
albedo, whose detail is texture, gets a narrower footprint than the light (:func:`_remodulate`). Along an
edge the footprint reaches further, as far as the few samples' share of either side is noisy
(:func:`_along_edges`), and across a sure edge it starts part-way back from the footprint average
(:func:`_before_footprint`). Where the renderer gives world positions the window's other frames add their
samples of each pixel's albedo: a still view's of the same pixel, a moving view's that fall in the pixel's
square (:func:`_window_albedo`); where they scatter across a surface against the pixel grid (a defocused
texture), the albedo itself is averaged before the frame step reads it (:func:`_scattered_albedo`); without
world positions, where the albedo is salt and pepper over one smooth surface (:func:`_speckled`). Where a lens
or a shutter mixes two surfaces in each pixel at random, beside the surface it blurs, the result is averaged
over the blend's wider footprint (:func:`_mixed_layers`).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import torch
from torch import Tensor

from torchmanifold import features as feature_table
from torchmanifold.pipeline import _fast
from torchmanifold.pipeline.image import _four_neighbours, _frame_mean, footprint_blur, luminance
from torchmanifold.timewindow import frame_at, window

if TYPE_CHECKING:
    from torchmanifold.pipeline.denoise import DenoiseSettings, FrameState


#: the footprint width's square is ``a + b / spp``: the part of a pixel's area its samples leave
#: unseen shrinks as 1/spp. Fitted to the validation set's best widths, the same on every scene's
#: frames 0-2 but two (findings.md): 0.7 px from 1 spp (+0.41 dB over 0.5), 0.5 from 4 spp (0.6: -0.35)
_FOOTPRINT_A, _FOOTPRINT_B = 0.17, 0.32
#: the width when the sample count is unknown: the 4-spp best, the safe side (0.7 from 4 spp: -1 dB)
_FOOTPRINT_UNKNOWN = 0.5


def _known_count(samples_per_pixel: float | None) -> bool:
    """Whether the caller knows how many samples each pixel averages (a missing, 0 or NaN count is none)."""
    return samples_per_pixel is not None and samples_per_pixel > 0


def footprint_width(settings: DenoiseSettings, samples_per_pixel: float | None) -> float:
    """The footprint average's sigma (pixels): ``settings.footprint_sigma`` when set, else from the
    samples per pixel, ``sqrt(0.17 + 0.32 / spp)`` (0.7 from 1 spp, 0.5 from 4, 0.41 in the limit),
    else 0.5."""
    if settings.footprint_sigma is not None:
        return float(settings.footprint_sigma)
    if not _known_count(samples_per_pixel):
        return _FOOTPRINT_UNKNOWN
    return math.sqrt(_FOOTPRINT_A + _FOOTPRINT_B / float(samples_per_pixel))


def _unseen(sigma: float) -> float:
    """The part of a footprint of ``sigma``'s square that its samples leave unseen, ``sigma^2 - a`` (``b /
    spp``, :func:`footprint_width`); 0 for a footprint at or under the limit's."""
    return max(sigma * sigma - _FOOTPRINT_A, 0.0)


def _footprint_albedo(alb: Tensor, flat: Tensor, sigma: float) -> Tensor:
    """The albedo to multiply back: its average over the pixel footprint, from demodulated pixels only
    (a normalised blur), and 1 where the colour was not demodulated."""
    if sigma <= 0:
        return alb
    return torch.where(flat, 1.0, _normalised_blur(alb, (~flat).to(alb.dtype), sigma))


def _normalised_blur(x: Tensor, weight: Tensor, sigma: float) -> Tensor:
    """``blur(x w) / blur(w)`` for ``x`` ``(T, C, H, W)`` and weights ``w`` ``(T, 1, H, W)``: a Gaussian of
    ``sigma`` pixels (:func:`footprint_blur`) over the weighted pixels alone; ``x`` itself where no weight
    lies under the kernel. A pixel of weight 0 takes nothing of its value, NaN or inf included."""
    if _fast.enabled(x, weight) and weight.shape == (x.shape[0], 1, *x.shape[2:]) and sigma > 0:
        return _fast.normalised_blur(x, weight, sigma)
    y = footprint_blur(torch.cat([torch.where(weight != 0, x * weight, 0.0), weight], 1), sigma)
    den = y[:, -1:]
    return torch.where(den > 1e-8, y[:, :-1] / den.clamp_min(1e-8), x)


#: the footprint average's tone-mapping knee, in frame-mean luminances (validation set's tuning part: 3
#: beats 1 by 0.15 dB and 10 by 0.05 dB)
_FOOTPRINT_KNEE = 3.0
#: the footprint average's range sigma on tone-mapped luminance: an 8-pixel ring around a light set in
#: a ceiling keeps its energy within 2.5% (0.4: 5%, no range term: 29% too bright; see the tests), while
#: pixels within a factor of about 2 of each other still average (0.3 dB below no range term on the
#: validation set's tuning part)
_FOOTPRINT_RANGE = 0.3


#: where each pixel holds one sample, how far the range weight gives way between a light and a dim pixel
#: beside it that has no other lit neighbour: the light's border may run through that pixel unseen (a
#: renderer that samples the pixel's centre shows a border a third of the way in nowhere), and the
#: reference, far above display white there, shows it lit. Frames 0-2 of the validation set from 1 spp,
#: the `denoise` default, against 0: 0.25 / 0.5 / 0.75 / 1 gain +0.035 / +0.043 / +0.034 / +0.013 dB on the
#: tuning part (its scenes at 128x128 and 256x256); from 4 spp 0.25 and 0.5 lose there (-0.01 / -0.06): the
#: samples show the border (benchmarks/validation/findings.md)
_UNSEEN_BORDER = 0.5


def _light_share(ly: Tensor) -> Tensor:
    """How much of a light a pixel of tone-mapped luminance ``ly`` is: 0 up to the footprint's knee
    (``ly = 0.5``), 1 from three times the knee (``ly = 0.75``), continuous in between so that no rounding
    flips it. Frames 0-2 of the validation set against a step at the knee: -0.005 / -0.007 dB; rising to
    ``ly = 1`` instead: -0.011 / -0.021, and the test's border row shows 0.83 in display range (0.99 here,
    1.00 with the step)."""
    return (4.0 * ly - 2.0).clamp(0.0, 1.0)


def _light_neighbours(ly: Tensor) -> Tensor:
    """The light shares (:func:`_light_share`) of each pixel's four adjacent pixels summed (``ly``
    ``(T, 1, H, W)`` the tone-mapped luminance; none beyond the border)."""
    return _four_neighbours(_light_share(ly))


def _footprint_average(x: Tensor, sigma: float, unseen_border: float = 0.0) -> Tensor:
    """Each pixel of ``(T, 3, H, W)`` radiance averaged over a pixel-sized Gaussian footprint of ``sigma``.

    A box-filtered reference pixel is the mean over its area; a filtered 1-spp pixel is the radiance at
    its one sample's point, so a post a third of a pixel wide is either all there or not at all, and
    texture is speckled. The average runs on ``y = x / (k + x)`` (``k`` a few times the frame's mean
    luminance) and maps back, with a range weight on the difference of ``y``'s luminance: radiance of
    the same order averages almost linearly, while a light (``y`` near 1) and the dark beside it
    (``y`` near 0) do not mix, so lights neither bleed a halo nor lose their edges.

    A pixel through which a light's border runs holds part of the light, many times brighter than the
    wall, and its one sample shows all of it or none: such a border looks jagged, and in a display-range
    image every pixel of it should show the light. Two adjacent pixels, one of them a light (far above
    the knee ``y = 0.5``), therefore average without the range weight where the dimmer of them has two
    adjacent lights: the border runs through its row or column. Beside a border that runs between two
    rows of pixels the dim pixels have one such neighbour and keep the range weight (no halo). How much of
    a light each pixel is rises continuously above the knee (:func:`_light_share`), and the range weight
    gives way by the pair's share times the dimmer's lit neighbours beyond one, so rounding never flips it.
    Frames 0-2 of the validation set, the ``denoise`` default, from 1 / 4 spp: +0.06 / +0.07 dB, no scene
    below -0.01 (``mi_dark_glossy`` +0.29 / +0.18, ``mi_ceiling_light`` +0.25 / +0.25; rendered at 256x256
    +0.67 / +0.39). Without the neighbours, at a range sigma of 0.6: +0.08 / +0.04 and a 1-px halo where a
    border runs between rows; for every adjacent pair: ``bl_moving_metal``'s checkered floor -0.23 from
    1 spp (``benchmarks/validation/findings.md``).

    ``unseen_border`` (0 to 1) is where the dimmer pixel has one lit neighbour alone: how far the range
    weight gives way there all the same, for pixels of one sample each, whose border may run through the
    dim pixel without its sample showing it (:data:`_UNSEEN_BORDER`).
    """
    if sigma <= 0:
        return x
    x = x.clamp_min(0.0)
    k = _knee(x)
    if _fast.enabled(x, k):
        return _fast.footprint_average(x, k, sigma, _FOOTPRINT_RANGE, unseen_border)
    y = _tone_mapped(x, k)
    ly = luminance(y)
    count = _light_neighbours(ly)
    r = max(1, int(math.ceil(3 * sigma)))
    H, W = x.shape[-2:]
    yp = torch.nn.functional.pad(torch.cat([y, ly, count], 1), (r, r, r, r), mode="replicate")
    num, den = torch.zeros_like(y), torch.zeros_like(ly)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            nb = yp[:, :, r + dy:r + dy + H, r + dx:r + dx + W]
            w = torch.exp(-(nb[:, 3:4] - ly) ** 2 / (2 * _FOOTPRINT_RANGE ** 2))
            if abs(dx) + abs(dy) == 1:  # a light's border through the dimmer one: no range weight
                dimmer = torch.where(nb[:, 3:4] < ly, nb[:, 4:5], count)
                over = (dimmer - 1.0 + unseen_border).clamp(0.0, 1.0)
                border = _light_share(torch.maximum(nb[:, 3:4], ly)) * over
                w = w + (1.0 - w) * border
            w = math.exp(-(dx * dx + dy * dy) / (2 * sigma * sigma)) * w
            num += w * nb[:, :3]
            den += w
    y = num / den
    return k * y / (1.0 - y).clamp_min(1e-6)


#: the footprint along an edge: a pixel that an edge crosses shows its few samples' share of either side, and
#: its neighbours along the edge hold about the same share. The share's variance falls as 1 / n with the n
#: samples, as the part ``b / spp`` of the footprint's square does (:func:`footprint_width`), so the average
#: along the edge has the square ``_ALONG_EDGE * b / n``: 2 px from 1 spp, 1 from 4, none in the limit. The
#: tuning part of the validation set and `mi_ceiling_light` at 256x256, frames 0-2 of the `denoise` default,
#: 1 / 4 spp: 4.7 / 6.5 / 9 with taps of any surety +0.15 / +0.14, +0.16 / +0.16, +0.16 / +0.18 dB; 12 with
#: taps weighed by theirs +0.15 / +0.16, and by brightness too, lights apart, +0.13 / +0.15; with the least
#: surety on the way, 18 instead: 0.00 / +0.02 (findings.md)
_ALONG_EDGE = 12.0
#: the structure tensor's smoothing (pixels) that finds an edge's direction: 0.7 / 1 / 1.5 / 2.5 px gained
#: +0.13 / +0.18 / +0.18 / +0.12 dB from 4 spp on that part (an average of 1 px on our output)
_EDGE_TENSOR_SIGMA = 1.0
#: how surely a pixel lies on one edge: its coherence ((l1 - l2) / (l1 + l2), 0 to 1) to this power; a
#: corner or texture of many directions has a low one. 6 instead (before the brightness weight): +0.09 /
#: +0.10 on that part, the held-out 64x64 clips' worst -0.07 instead of -0.18 dB (a checkered floor, 1 spp).
#: Once the average started back before the footprint average (:func:`_before_footprint`), 2 / 1.5 / 1.25 / 1
#: against 3, summed over the tuning part and `mi_ceiling_light` at 256x256 from 1 / 4 spp: +0.20 / +0.29 /
#: +0.31 / +0.29 and +0.29 / +0.46 / +0.55 / +0.63 dB, worst clip -0.002 / -0.02 / -0.05 / -0.08; held
#: out (ten clips) 2 / 1.5: +0.21 / +0.29 and +0.33 / +0.51, worst -0.06 / -0.12 (the checkered 64x64 and
#: 80x80 clips)
_EDGE_COHERENCE_POWER = 2.0
#: across a sure edge the footprint average mixes the far side into a pixel whose share of it only its own
#: samples and its neighbours' along the edge tell; there the average along the edge starts part-way back
#: towards the product before the footprint average: the surety to :data:`_EDGE_RAW_POWER` times a share
#: of the way that grows with the n samples per pixel, the footprint average keeping this much over sqrt(n)
#: (:func:`_raw_share`). Not all of it: a renderer that samples every pixel at the same place (Cycles from
#: 1 spp) gives the neighbours along an axis-aligned edge no new sample of it (a rod a third of a pixel wide
#: showed whole: `bl_env_thin` -0.56 dB all the way). The tuning part and `mi_ceiling_light` at 256x256,
#: frames 0-2, summed over the six clips' gains from 1 / 4 spp, one share for both (the coherence then cubed):
#: 0.4 / 0.5 / 0.6 / 0.7 at power 3 +0.53 / +0.57 / +0.57 / +0.52 and +0.35 / +0.41 / +0.47 / +0.51 dB, worst
#: clip -0.006 / -0.008 / -0.011 / -0.078; power 2 / 4 at 0.5: +0.56 / +0.55 and +0.44 / +0.38, worst -0.029 /
#: -0.002. Then 0.75 from 4 spp (this rule): +0.12 more there, the held-out clips +0.20 (ten, worst -0.008)
#: (findings.md)
_EDGE_FOOTPRINT_KEPT = 0.5
_EDGE_RAW_POWER = 3.0


def _edge_directions(x: Tensor, tensor_sigma: float = _EDGE_TENSOR_SIGMA) -> Tensor:
    """Each pixel's edge direction in ``(T, 3, H, W)`` radiance and how surely it lies on one edge:
    ``(T, 3, H, W)`` of ``(surety, tx, ty)``. The direction is the minor eigenvector of the structure tensor
    of the tone-mapped luminance (smoothed over ``tensor_sigma`` px), the surety the tensor's coherence to
    :data:`_EDGE_COHERENCE_POWER`: a corner or texture of many directions has a low one."""
    k = _knee(x)
    if _fast.enabled(x, k):
        return _fast.edge_directions(x, k, tensor_sigma, _EDGE_COHERENCE_POWER)
    ly = luminance(_tone_mapped(x, k))
    gx, gy = torch.zeros_like(ly), torch.zeros_like(ly)
    gx[..., 1:-1] = (ly[..., 2:] - ly[..., :-2]) / 2
    gy[..., 1:-1, :] = (ly[..., 2:, :] - ly[..., :-2, :]) / 2
    jxx, jxy, jyy = footprint_blur(torch.cat([gx * gx, gx * gy, gy * gy], 1), tensor_sigma).unbind(1)
    spread = torch.sqrt((jxx - jyy) ** 2 + 4 * jxy * jxy)
    coherence = (spread / (jxx + jyy).clamp_min(1e-30)).clamp(0.0, 1.0) ** _EDGE_COHERENCE_POWER
    across = 0.5 * torch.atan2(2 * jxy, jxx - jyy)  # the gradient's direction
    return torch.stack([coherence, -torch.sin(across), torch.cos(across)], 1)


def _knee(x: Tensor) -> Tensor:
    """The footprint average's tone-mapping knee ``(T, 1, 1, 1)`` of ``(T, 3, H, W)`` radiance: a few times
    each frame's mean luminance (``x`` clamped at 0)."""
    lum = luminance(x.clamp_min(0.0))
    return _FOOTPRINT_KNEE * _frame_mean(lum, torch.ones_like(lum)).clamp_min(1e-30)


def _tone_mapped(x: Tensor, k: Tensor) -> Tensor:
    """``x / (k + x)`` of ``(T, 3, H, W)`` radiance clamped at 0, ``k`` its knee (:func:`_knee`)."""
    x = x.clamp_min(0.0)
    return x / (k + x)


def _along_edges(images: Sequence[Tensor], widths: Sequence[Tensor], directions: Tensor) -> list[Tensor]:
    """Each ``(T, 3, H, W)`` radiance of ``images`` averaged along the edges of ``directions``
    (:func:`_edge_directions`), over a Gaussian of its ``widths`` pixels (``(T, 1, H, W)``, each pixel its
    own; 0 leaves a pixel as it is).

    A pixel that a silhouette, a light's border or a texture's edge crosses shows the share of its few
    samples that fell on either side, a noisy estimate of the area it covers; its neighbours along the
    edge cover about the same share. The average along the edge (bilinear taps) blends in by the
    direction's surety, so flat regions, corners and many-directional texture keep what they are. It runs
    in the footprint average's tone-mapped domain with its range weight; lights (:func:`_light_share`) keep
    their value, and their borders are the footprint average's.
    """
    reach = max((float(w.max()) for w in widths if w.numel()), default=0.0)
    if reach <= 0:
        return list(images)
    knees = [_knee(x) for x in images]
    if _fast.enabled(*images, *knees, *widths, directions):
        out = _fast.along_edges(torch.stack(list(images)), torch.stack(knees), torch.stack(list(widths)),
                                directions, _FOOTPRINT_RANGE)
        return list(out.unbind(0))
    return [_along_edges_reference(x, k, w, directions, reach) for x, k, w in zip(images, knees, widths)]


def _along_edges_reference(x: Tensor, k: Tensor, sigma: Tensor, directions: Tensor, reach: float) -> Tensor:
    """:func:`_along_edges` of one image of knee ``k``, its taps out to 2 ``reach`` (the widest width)."""
    y = _tone_mapped(x, k)
    coherence, tx, ty = directions.unbind(1)
    T, _, H, W = x.shape
    ly = luminance(y)
    # a tap weighs by the least surety met on the way to it: beyond a corner, or among pixel-sized texture,
    # the edge does not go on; and, as in the footprint average, by its brightness
    yc = torch.cat([y, coherence[:, None]], 1)
    rows = torch.arange(H, dtype=x.dtype, device=x.device).view(1, H, 1)
    cols = torch.arange(W, dtype=x.dtype, device=x.device).view(1, 1, W)
    inv = 1.0 / (2.0 * sigma * sigma).clamp_min(1e-30)
    num, den = y.clone(), torch.ones_like(sigma)
    reach_min = {1: torch.ones_like(sigma), -1: torch.ones_like(sigma)}
    for t in range(1, max(1, int(math.ceil(2.0 * reach))) + 1):
        w = torch.where(sigma > 0, torch.exp(-t * t * inv), 0.0)
        for s in (t, -t):
            grid = torch.stack([(cols + s * tx + 0.5) * (2.0 / W) - 1,
                                (rows + s * ty + 0.5) * (2.0 / H) - 1], -1)
            tap = torch.nn.functional.grid_sample(yc, grid, mode="bilinear", padding_mode="border",
                                                  align_corners=False)
            way = 1 if s > 0 else -1
            reach_min[way] = torch.minimum(reach_min[way], tap[:, 3:])
            brightness = torch.exp(-(luminance(tap[:, :3]) - ly) ** 2 / (2 * _FOOTPRINT_RANGE ** 2))
            wt = w * reach_min[way] * brightness
            num = num + wt * tap[:, :3]
            den = den + wt
    # a light keeps its own value: near its display white a tap a few percent into the dark beside it would
    # take a tenth of its radiance
    y = y + coherence[:, None] * (1.0 - _light_share(ly)) * (num / den - y)
    return k * y / (1.0 - y).clamp_min(1e-6)


def _raw_share(sigma: float) -> float:
    """How far :func:`_before_footprint` goes back at a sure edge for a footprint of ``sigma``:
    ``1 - _EDGE_FOOTPRINT_KEPT / sqrt(n)``, ``1 / n`` the unseen part of the footprint's square over ``b``
    (:func:`footprint_width`): 0.5 from 1 spp, 0.75 from 4 (and where the count is unknown), all the way in
    the limit."""
    return min(1.0, max(0.0, 1.0 - _EDGE_FOOTPRINT_KEPT * math.sqrt(_unseen(sigma) / _FOOTPRINT_B)))


def _before_footprint(averaged: Tensor, product: Tensor, directions: Tensor, share: float) -> Tensor:
    """The footprint average ``averaged`` ``(T, 3, H, W)`` taken back towards the ``product`` it averaged,
    ``share`` (:func:`_raw_share`) of the way times the edges' surety (:func:`_edge_directions`) to
    :data:`_EDGE_RAW_POWER`: what :func:`_along_edges` averages across a sure edge."""
    return averaged + share * directions[:, :1] ** _EDGE_RAW_POWER * (product - averaged)


def _edge_width(sigma: float, counts: Tensor | None, like: Tensor) -> Tensor:
    """The width of :func:`_along_edges` ``(T, 1, H, W)`` for a footprint of ``sigma`` whose pixels hold
    ``counts`` times the frame's samples (``None``: once): :data:`_ALONG_EDGE` times the unseen part of the
    footprint's square (``sigma^2 - a``, that is ``b / spp``) over the count."""
    share = _unseen(sigma) * _ALONG_EDGE
    if counts is None:
        return like.new_full((like.shape[0], 1, *like.shape[2:]), math.sqrt(share))
    return (share / counts.clamp_min(1.0)).sqrt()


#: where the surface is smooth, the albedo's footprint is this fraction of the radiance's: texture
#: is sharper than lighting. Frames 0-2 of the validation set, +-1 default, from 1 / 4 spp: +0.09 / +0.04 dB
#: (tuning part +0.15 / +0.05; `cbox_glossy_tex`'s striped wall +0.47 / +0.14; no scene below -0.02); 0.7:
#: -0.02 / -0.06 against 0.8 (each frame alone); 1, 0.8 or 0.7 for every pixel: -0.7 to -1.0 dB. Only where
#: the sample count is known: on 1-spp frames whose count is not, 0.8 of the safe 0.5 px lost 0.56 dB
_TEXTURE_FOOTPRINT = 0.8
#: the 3x3 variance of the geometry channels (in units of their range sigmas, squared) at which a surface
#: counts as smooth with weight 1/e: 0.1 to 0.3 measured alike (within 0.01 dB from 1 spp, 0.03 from 4)
_SMOOTH_VARIANCE = 0.1


def _smooth_surface(geometry: Tensor, sigmas: Tensor) -> Tensor:
    """How smooth the surface is around each pixel, ``(T, 1, H, W)`` in (0, 1]: ``exp(-v / 0.1)``
    (:data:`_SMOOTH_VARIANCE`), ``v`` the variance over the pixel's 3x3 neighbourhood of the geometry guide
    channels (normals, position or depth: ``(T, G, H, W)`` with range sigmas ``(T, G)``), summed over
    channels in units of the sigmas. 1 on a plane or a gently curved surface, near 0 across a silhouette
    or a crease."""
    g = geometry / sigmas.to(geometry.dtype)[:, :, None, None]
    m1, m2 = _box_mean(torch.cat([g, g * g], 1), 1).chunk(2, 1)
    v = (m2 - m1 * m1).clamp_min(0.0).sum(1, keepdim=True)
    return torch.exp(-v / _SMOOTH_VARIANCE)


def _position(f: Tensor, names: Sequence[str]) -> Tensor | None:
    """The world position channels ``P.X/Y/Z`` of features ``f`` ``(T, D, H, W)`` named ``names``, in that
    order: ``(T, 3, H, W)``, or ``None`` where they are not all there."""
    canon = [feature_table.canonical_name(n) for n in names]
    want = feature_table.feature("P").channels
    if not all(c in canon for c in want):
        return None
    return torch.stack([f[:, canon.index(c)] for c in want], 1)


#: Where a pixel's samples spread over more than its square (a thin lens's circle of confusion), their world
#: positions scatter across the surface against the pixel grid, and each sample's albedo is another point of a
#: texture that the reference shows averaged: a defocused post in `mi_indirect_dof` kept its samples' salt and
#: pepper. A pixel scatters where the second differences of its position along x and along y, less their part
#: in depth, exceed :data:`_SCATTER_SPACINGS` pixel spacings at its depth (1-spp jitter alone gives up to 2
#: along an axis), and depth holds at most :data:`_SCATTER_ALONG_DEPTH` of them: a depth jump is a silhouette
#: or a rod thinner than a pixel, which keep their albedo. In that clip a defocused surface's second
#: difference is about 3.7 spacings, a third of it in depth; in the set's thin-rod clips nearly all of it is.
#: Frames 0-2 of `mi_indirect_dof` from 1 / 4 spp: the post's features blurred by hand gained +1.1 / +1.0 dB,
#: the albedo alone +0.9 / +0.9 (findings.md); this rule, before the bound on depth below, +0.88 / +0.49 (0.7
#: / 0.9 of it in depth: +0.82 / +0.44, +0.90 / +0.53). Every other Mitsuba clip of the set, of the probes and
#: at 256x256 keeps its bits: its scatter never fills the window below. Without world positions (our tracer,
#: Blender without its Position pass) the albedo alone tells it, less surely (:data:`_SPECKLE_BOX`).
_SCATTER_SPACINGS = 3.0
_SCATTER_ALONG_DEPTH = 0.8
#: and depth's own second difference stays under this many spacings: one surface at about one depth. Under a
#: lens it is 0.3-2 spacings (the quartiles, both rooms, 1 and 4 spp); where a pixel's 4 samples mix a
#: wireframe ball and the ground far behind it (`bl_env_thin` rendered with Blender's Position pass) 11-59,
#: and without this bound the rule cost that clip 0.16 dB from 4 spp. All frames of `mi_indirect_dof` from 1 /
#: 4 spp, 4 / 6 / 8 / none: 24.34 / 26.94, 24.47 / 26.99, 24.52 / 27.00, 24.54 / 27.01 dB (23.74 / 26.52
#: without the rule)
_SCATTER_DEPTH_SPACINGS = 8.0
#: the share of a 5x5 window's pixels that scatter from which the albedo starts to average (all of it from
#: halfway to 1): scatter over an area, not the two columns beside an edge. 0.3 / 0.6 on the clip above
#: (frames 0-2, before the bound on depth): +0.92 / +0.60 and +0.72 / +0.25 dB
_SCATTER_DENSITY = 0.4
#: the averaged albedo's Gaussian, pixels: the hand-blurred post gained as much at 2 and 3 px, 0.2 dB less
#: at 1
_SCATTERED_ALBEDO_SIGMA = 2.0

#: Without world positions (Blender writes none in the set's layout) a lens's scatter shows in the albedo
#: alone: neighbouring pixels' albedos are independent points of the texture, white noise at the pixel scale,
#: which a single frame shares with a rod's partial coverage and a texture near the pixels' scale. The tests
#: that tell a lens's: the ratio of the squared differences of pixels 1 apart to those of pixels 2 apart over
#: a (2 :data:`_SPECKLE_BOX` + 1)^2 box (1 for white noise, about 0.5 across an edge, 0.25 on a gradient; the
#: weight rises from :data:`_SPECKLE_RATIO`'s first value to its second), with the albedo's spread there over
#: :data:`_SPECKLE_SPREAD` of its mean; an area, cores that survive an erosion of the mask by a
#: (2 :data:`_SPECKLE_AREA` + 1)^2 square (edges, rods and a checker's corners are lines and points) on one
#: smooth surface, every depth within :data:`_SPECKLE_REACH` px within :data:`_SPECKLE_DEPTH` of its 3x3
#: median (a wireframe before the ground far behind it, a horizon, are not), grown by
#: :data:`_SPECKLE_GROWTH`; no texture (:data:`_SPECKLE_LAGS`). Set on the tuning clips read without their
#: positions, all frames from 1 / 4 spp, with the area the opening's alone and no texture test:
#: `mi_indirect_dof` (its defocused post) +0.49 / +0.26 dB, `mi_ceiling_light` -0.02 / 0.00; the ratio's ramp
#: from 0.7 / 0.65 gained the post 0.08 / 0.10 and 0.12 / 0.15 more but lost the room 0.10 / 0.04 and 0.25 /
#: 0.13; a 7x7 opening lost `bl_glass_caustic` 0.03 / 0.01 (points by its checker's corners and in its glass).
#: The whole rule: `mi_indirect_dof` without positions +0.81 / +0.67, `mi_ceiling_light` -0.01 / 0.00; held
#: out, `bl_indirect_dof` at 128x128 +0.87 / +0.59, at 256x256 +1.26 / +1.14; every other Blender clip within
#: 0.04 dB (findings.md).
_SPECKLE_BOX = 3
_SPECKLE_RATIO = (0.75, 0.95)
_SPECKLE_SPREAD = 0.05
_SPECKLE_AREA = 4
_SPECKLE_DEPTH, _SPECKLE_REACH = 0.05, 2
#: Without depth (a renderer's albedo and normals alone, OIDN's own inputs) one smooth surface is where each
#: unit normal is within this of its 3x3 median's (1 - cos, 0.1: 26 degrees). The tuning clips read with albedo
#: and normals alone, all frames from 1 / 4 spp, against no test: 0.01 / 0.02 / 0.05 / 0.1 / 0.2 / 0.4
#: +0.02 / +0.05, +0.02 / +0.11, +0.12 / +0.12, +0.16 / +0.13, +0.16 / +0.13, +0.16 / +0.13 dB (the mean of
#: five; `mi_indirect_dof` +0.78 / +0.63 at 0.1); the smallest that reaches it (findings.md)
_SPECKLE_BEND = 0.1
#: A fine texture that the pixel grid aliases reads as white by the ratio too (`mi_still_textures` read
#: without its positions lost 0.24 / 0.84 dB to the tests above: its fine checkers and stripes were averaged
#: away). Unlike a lens's scatter it repeats or runs one way. Over more than :data:`_SPECKLE_PLAIN` of the
#: area's box, a lens's pixels keep the squared differences at each lag of :data:`_SPECKLE_LAGS` pixels along
#: each axis above :data:`_SPECKLE_REPEAT` of those of adjacent pixels (medians in the flagged areas: 0.75 on
#: the defocused posts, 0.48 / 0.62 on that clip's textures from 4 / 1 spp), and the horizontal share of the
#: adjacent differences within :data:`_SPECKLE_ALONG` of a half (0.50 on the posts, 0.64 / 0.59 on the
#: textures). Set on the tuning clips read without positions: `mi_indirect_dof` +0.41 / +0.21 (+0.49 / +0.26
#: without this test), `mi_ceiling_light` -0.005 / 0.00; 0.6 of the box, or the share within 0.08 and the
#: lags' least above 0.55: within 0.04 dB of it. `mi_still_textures` without positions: -0.08 / +0.03 against
#: the rule off; per pixel instead of over the box, the posts kept only half their gain.
_SPECKLE_LAGS = (2, 3, 4)
_SPECKLE_REPEAT, _SPECKLE_ALONG, _SPECKLE_PLAIN = 0.5, 0.1, 0.5
#: The opening's cores lie where the test is surest, on the surface itself; the lens's salt and pepper reaches
#: on around them, and past the silhouette into the band where each pixel mixes the surface with what lies
#: behind (its depth no longer smooth): the area grows :data:`_SPECKLE_GROWTH` px from its cores, the ratio's
#: weight still applying to each pixel. `mi_indirect_dof` read without positions (tuning), from 1 / 4 spp, the
#: area the opening's own 4 px and no further than the smooth depth / grown 4 / 8 / 16 / 24 / 32 px: 23.87 /
#: 26.45, 23.97 / 26.52, 24.19 / 26.75, 24.27 / 26.91, 24.28 / 26.94, 24.28 / 26.94 dB; `mi_ceiling_light`
#: without positions 29.804 down to 29.800 at 16 and 29.795 at 32 from 1 spp (the same from 4).
_SPECKLE_GROWTH = 16


def _precision(position: Tensor) -> Tensor:
    """Per frame, ``(T, 1, 1, 1)``, the relative step of the float format world positions ``(T, 3, H, W)``
    were stored in: half's where every finite value of the frame is a half (the set's EXR files; a scene far
    from the origin then cannot tell finer steps), else single's (a position 1000 units out still tells a
    pixel's scatter). Each frame alone, so a frame's bytes do not depend on the others in the call."""
    exact = (position == position.half().to(position.dtype)) | ~torch.isfinite(position)
    half = exact.flatten(1).all(1).view(-1, 1, 1, 1)
    return torch.where(half, 2.0 ** -10, 2.0 ** -23).to(position.dtype)


def _scattered(position: Tensor, depth: Tensor, valid: Tensor | None = None) -> Tensor:
    """How surely each pixel's samples scatter over an area, ``(T, 1, H, W)`` in [0, 1], from world positions
    ``(T, 3, H, W)`` and depth ``(T, 1, H, W)`` (0: no hit), where ``valid`` (bool, like depth; all by
    default) marks the pixels whose features are samples (not sanitised non-finite ones): a second
    difference counts where its three pixels are hit and valid. A frame's pixel spacing per unit of depth is
    the median of the horizontal neighbours' distance over their depth; at least the precision the positions
    were stored with (:func:`_precision`). 0 in a frame with no such pair."""
    if min(position.shape[-2:]) < 3:  # no second difference
        return torch.zeros_like(depth)
    hit = _hits(depth, valid)
    pairs = hit[..., :, 1:] & hit[..., :, :-1]
    # sums of squares: torch's vector norm over the channels is several times slower here
    step = (position[..., :, 1:] - position[..., :, :-1]).square().sum(1, keepdim=True).sqrt()
    step = step / depth[..., :, 1:].clamp_min(1e-30)
    angle = torch.stack([step[t][pairs[t]].median() if bool(pairs[t].any()) else step.new_zeros(())
                         for t in range(step.shape[0])]).view(-1, 1, 1, 1)
    floor = position.square().sum(1, keepdim=True).sqrt() * _precision(position)
    spacing = torch.maximum(depth * angle, floor)

    def second(axis: int) -> tuple[Tensor, Tensor]:
        # the squared second differences of position and depth along an image axis; 0 at the border and
        # where one of the three pixels is no hit or no sample (no evidence along that axis)
        n, pad = position.shape[axis], (1, 1, 0, 0) if axis == 3 else (0, 0, 1, 1)
        d2 = [x.narrow(axis, 2, n - 2) + x.narrow(axis, 0, n - 2) - 2 * x.narrow(axis, 1, n - 2)
              for x in (position, depth)]
        h = hit.to(position.dtype)
        ok = h.narrow(axis, 2, n - 2) * h.narrow(axis, 0, n - 2) * h.narrow(axis, 1, n - 2)
        return (torch.nn.functional.pad(d2[0].square().sum(1, keepdim=True) * ok, pad),
                torch.nn.functional.pad(d2[1].square() * ok, pad))
    (px, zx), (py, zy) = second(3), second(2)
    across = (px - zx).clamp_min(0.0).sqrt() + (py - zy).clamp_min(0.0).sqrt()
    along = zx.sqrt() + zy.sqrt()
    flag = hit & (angle > 0) & (across > _SCATTER_SPACINGS * spacing) & \
        (along < _SCATTER_ALONG_DEPTH * (px.sqrt() + py.sqrt())) & (along < _SCATTER_DEPTH_SPACINGS * spacing)
    density = _box_mean(flag.to(position.dtype), 2)
    return ((density - _SCATTER_DENSITY) / (0.5 * (1 - _SCATTER_DENSITY))).clamp(0.0, 1.0)


def _ratio_of(a: Tensor, b: Tensor) -> Tensor:
    """``a / b`` where ``b > 0``, else 0."""
    return torch.where(b > 0, a / torch.where(b > 0, b, 1.0), 0.0)


def _lag_squares(x: Tensor, h: Tensor, lags: int) -> dict:
    """The squared differences of the pixels of ``x`` ``(T, 1, H, W)`` 1 to ``lags`` apart along each image
    axis (``(axis, k)``: 2 down, 3 across), counted where both pixels have ``h`` (``x``'s dtype, 0 or 1; 0
    past the end), each averaged over the (2 :data:`_SPECKLE_BOX` + 1)^2 box."""
    def squared_differences(k: int, axis: int) -> Tensor:
        n = x.shape[axis]
        if k >= n:  # no pair that far apart in a frame this small
            return torch.zeros_like(x)
        d = (x.narrow(axis, k, n - k) - x.narrow(axis, 0, n - k)).square()
        d = d * h.narrow(axis, k, n - k) * h.narrow(axis, 0, n - k)
        return torch.nn.functional.pad(d, (0, k, 0, 0) if axis == 3 else (0, 0, 0, k))
    return {(axis, k): _box_mean(squared_differences(k, axis), _SPECKLE_BOX)
            for axis in (2, 3) for k in range(1, lags + 1)}


def _whiteness(lag: dict) -> tuple[Tensor, Tensor]:
    """From :func:`_lag_squares`: the squared differences of adjacent pixels over those of pixels 2 apart
    (1 for white noise, about 0.5 across an edge, 0.25 on a gradient), and how far the horizontal share of the
    adjacent ones lies from a half (0 where no axis is preferred)."""
    ratio = _ratio_of(lag[3, 1] + lag[2, 1], lag[3, 2] + lag[2, 2])
    return ratio, (_ratio_of(lag[3, 1], lag[3, 1] + lag[2, 1]) - 0.5).abs()


def _hits(depth: Tensor, valid: Tensor | None) -> Tensor:
    """Where the depth ``(T, 1, H, W)`` is a hit (above 0) and, where ``valid`` (bool, like depth) is given,
    a sample."""
    return (depth > 0) if valid is None else (depth > 0) & valid


def _box_spread(x: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """The mean and the standard deviation of ``x`` ``(T, 1, H, W)`` (0 where ``h`` is 0) over the pixels of
    ``h`` in the (2 :data:`_SPECKLE_BOX` + 1)^2 box; 0 where the box holds none."""
    count = _box_mean(h, _SPECKLE_BOX)
    mean = _ratio_of(_box_mean(x, _SPECKLE_BOX), count)
    return mean, (_ratio_of(_box_mean(x.square(), _SPECKLE_BOX), count) - mean.square()).clamp_min(0.0).sqrt()


def _surface_breaks(depth: Tensor | None, normal: Tensor | None, valid: Tensor | None) -> tuple[Tensor, Tensor]:
    """Where each pixel is a hit, and where one smooth surface breaks (a depth jump or a fold, no hit, no
    sample), bool ``(T, 1, H, W)`` each: from the depth (0: no hit) within :data:`_SPECKLE_DEPTH` of its 3x3
    median, or without depth from the normals (0: no hit) within :data:`_SPECKLE_BEND` of theirs."""
    if depth is not None:
        hit = _hits(depth, valid)
        median = _median3x3(depth)
        return hit, ~hit | ((depth - median).abs() > _SPECKLE_DEPTH * median.abs())
    length = normal.square().sum(1, keepdim=True).sqrt()
    hit = _hits(length, valid)
    n = normal / torch.where(length > 0, length, 1.0)
    median = _median3x3(n)  # per component
    median = median / median.square().sum(1, keepdim=True).sqrt().clamp_min(1e-30)
    return hit, ~hit | (1.0 - (n * median).sum(1, keepdim=True) > _SPECKLE_BEND)


def _speckled(albedo: Tensor, depth: Tensor | None, valid: Tensor | None = None,
              normal: Tensor | None = None) -> Tensor:
    """How surely each pixel's albedo is a lens's salt and pepper over one smooth surface, ``(T, 1, H, W)`` in
    [0, 1], from the albedo ``(T, 3, H, W)`` and depth ``(T, 1, H, W)`` alone (0: no hit), or without depth
    (``None``) the normals ``(T, 3, H, W)`` (0: no hit), where ``valid`` (bool, ``(T, 1, H, W)``; all by
    default) marks the pixels whose features are samples (the tests above :data:`_SPECKLE_BOX`). 0 in a frame
    too small for a difference of pixels 2 apart."""
    if min(albedo.shape[-2:]) < 3:
        return albedo.new_zeros(albedo.shape[0], 1, *albedo.shape[2:])
    # the statistics of the surface's samples alone: no sky's or sanitised pixel's albedo enters them
    hit, rough = _surface_breaks(depth, normal, valid)
    h = hit.to(albedo.dtype)
    lum = albedo.mean(1, keepdim=True) * h
    # in units of each frame's largest, so that the squares of squares neither overflow nor underflow: every
    # test is a ratio
    top = lum.detach().abs().amax((1, 2, 3), keepdim=True)
    lum = lum / torch.where(top > 0, top, torch.ones_like(top))

    lag = _lag_squares(lum, h, max(_SPECKLE_LAGS))
    ratio, along = _whiteness(lag)
    lo, hi = _SPECKLE_RATIO
    mean, spread = _box_spread(lum, h)
    w = ((ratio - lo) / (hi - lo)).clamp(0.0, 1.0) * (spread > _SPECKLE_SPREAD * mean.abs()).to(lum.dtype)
    # no texture: no lag along either axis where the albedo repeats, no direction it runs along, over most of
    # the area's box
    repeats = torch.stack([_ratio_of(lag[axis, k], lag[axis, 1])
                           for axis in (2, 3) for k in _SPECKLE_LAGS]).amin(0)
    plain = ((repeats > _SPECKLE_REPEAT) & (along < _SPECKLE_ALONG)).to(lum.dtype)
    # an area: what survives an erosion by the square on one smooth surface, grown from there, also into the
    # band past its silhouette where the lens mixes it with what lies behind
    core = ~_any_within(w <= 0.5, _SPECKLE_AREA) & ~_any_within(rough, _SPECKLE_REACH)
    area = _any_within(core, _SPECKLE_GROWTH) & (_box_mean(plain, _SPECKLE_AREA) > _SPECKLE_PLAIN)
    return w * (area & hit).to(lum.dtype)


#: Where a lens or a shutter mixes two surfaces within each pixel (a defocused post before a wall, a ball
#: blurred by its motion), each sample's features are one surface's, picked at random: the guide keeps the
#: surfaces apart and a pixel shows the surface its samples hit, salt and pepper where the reference shows
#: their blend. The depth tells it (:func:`_mixed_layers`): its log's squared differences of pixels 1 apart
#: against those 2 apart, as the albedo's test (:data:`_SPECKLE_BOX`), the weight rising from
#: :data:`_MIX_RATIO`'s first value to its second (lower than the albedo's: a lens's mix of two depths is
#: white where it is dense and sparse at the band's rims); the log depth's spread over :data:`_MIX_SPREAD`; no
#: axis along which the differences run (:data:`_MIX_ALONG`); every pixel of the box a hit; an area, cores of
#: a (2 :data:`_SPECKLE_AREA` + 1)^2 square grown by :data:`_MIX_GROWTH` px. A wireframe ball before the
#: ground passes these (its wires, under a pixel, are as random as a lens); unlike a lens's band it lies
#: beside no solid surface of its near depth. The band holds where, within :data:`_MIX_CORE` px, a pixel of
#: one surface (its log depth's spread under half of :data:`_MIX_SPREAD`, every neighbour a hit) lies within
#: :data:`_MIX_DEPTH` of the band's nearest depth in the box, and :data:`_MIX_REACH` px on from there within
#: the band. Found on `bl_indirect_dof` rendered at 256x256 (not in the set), set on the tuning part's
#: `mi_indirect_dof` and `bl_env_thin` (the wireframe ball, which the core test is for; findings.md).
_MIX_RATIO = (0.6, 0.85)
_MIX_SPREAD, _MIX_ALONG = 0.05, 0.2
_MIX_GROWTH = 2
_MIX_CORE, _MIX_DEPTH, _MIX_REACH = 6, 0.05, 8
#: the mixed band's footprint (pixels): the blend of the surfaces a pixel's lens or shutter covers; 1 / 2 / 3
#: px on the defocused rooms from 1 spp gained 0.35-0.42 / 0.44-0.52 / 0.45-0.54 dB, a motion-blurred ball's
#: narrow band +0.05 / -0.03 / -0.14 (findings.md)
_MIX_FOOTPRINT = 1.5


def _mixed_layers(depth: Tensor, valid: Tensor | None = None) -> Tensor:
    """How surely each pixel's samples mix two surfaces at random (a lens's or a shutter's blend, see
    :data:`_MIX_RATIO`), ``(T, 1, H, W)`` in [0, 1], from the depth ``(T, 1, H, W)`` (0: no hit), where
    ``valid`` (bool, like depth; all by default) marks the pixels whose features are samples. 0 in a frame too
    small for a difference of pixels 2 apart."""
    if min(depth.shape[-2:]) < 3:
        return torch.zeros_like(depth)
    hit = _hits(depth, valid)
    h = hit.to(depth.dtype)
    log_depth = torch.where(hit, depth, 1.0).log() * h
    ratio, along = _whiteness(_lag_squares(log_depth, h, 2))
    _, spread = _box_spread(log_depth, h)
    lo, hi = _MIX_RATIO
    w = ((ratio - lo) / (hi - lo)).clamp(0.0, 1.0) * ((spread > _MIX_SPREAD) & (along < _MIX_ALONG)
                                                      & ~_any_within(~hit, _SPECKLE_BOX)).to(depth.dtype)
    core = ~_any_within(w <= 0.5, _SPECKLE_AREA)
    w = w * _any_within(core, _SPECKLE_AREA + _MIX_GROWTH).to(w.dtype)
    if not bool((w > 0).any()):
        return w
    # the band's nearest depth, and one surface's pixels within reach at it; searched over the band's box
    far = torch.finfo(depth.dtype).max
    nearest = -torch.nn.functional.max_pool2d(-torch.where(hit, log_depth, far), 2 * _SPECKLE_BOX + 1, 1,
                                              _SPECKLE_BOX)
    solid = torch.where(hit & (spread < 0.5 * _MIX_SPREAD) & ~_any_within(~hit, 1), log_depth, far)
    band, r = w > 0, _MIX_CORE
    rows = band.any(-1).flatten(0, -2).any(0).nonzero()[:, 0]
    cols = band.any(-2).flatten(0, -2).any(0).nonzero()[:, 0]
    y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    padded = torch.nn.functional.pad(solid, (r, r, r, r), value=far)[..., y0:y1 + 2 * r, x0:x1 + 2 * r]
    at, H, W = nearest[..., y0:y1, x0:x1], y1 - y0, x1 - x0
    beside = torch.zeros_like(hit)
    inside = beside[..., y0:y1, x0:x1]  # a view: the search writes into beside
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy * dy + dx * dx <= r * r:
                inside |= (padded[..., r + dy:r + dy + H, r + dx:r + dx + W] - at).abs() < _MIX_DEPTH
    held = beside & band
    for _ in range(_MIX_REACH):
        held = _any_within(held, 1) & band
    return w * held.to(w.dtype)


def _mixed_pixels(f: Tensor, names: Sequence[str], mask: Tensor | None = None) -> Tensor | None:
    """:func:`_mixed_layers` of features ``f`` ``(T, D, H, W)`` named ``names``, among the pixels of nonzero
    ``mask`` ``(T, 1, H, W)`` (all by default); ``None`` without depth."""
    canon = [feature_table.canonical_name(n) for n in names]
    (depth,) = feature_table.feature("Z").channels
    if depth not in canon:
        return None
    return _mixed_layers(f[:, canon.index(depth)][:, None], None if mask is None else mask > 0)


def _mixed_footprint(x: Tensor, mixed: Tensor) -> Tensor:
    """``x`` ``(Q, C, H, W)`` averaged over :data:`_MIX_FOOTPRINT` px where its pixels mix two surfaces,
    by ``mixed`` ``(Q, 1, H, W)`` (:func:`_mixed_layers`)."""
    return x + mixed * (footprint_blur(x, _MIX_FOOTPRINT) - x)


def _any_within(mask: Tensor, r: int) -> Tensor:
    """Where bool ``mask`` ``(..., H, W)`` holds anywhere in the (2r+1)^2 box around a pixel (its binary
    dilation, no pixel beyond the border): a box mean above 0, exact for counts."""
    return _box_mean(mask.to(torch.float32), r) > 0


#: compare-exchanges whose 5th output is the median of 9 (Paeth's network, as in Devillard's ``opt_med9``)
_MEDIAN_OF_9 = ((1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 3), (5, 8),
                (4, 7), (3, 6), (1, 4), (2, 5), (4, 7), (4, 2), (6, 4), (4, 2))


def _median3x3(x: Tensor) -> Tensor:
    """The median of each pixel's 3x3 box of ``(..., H, W)``, the border replicated: 19 elementwise
    compare-exchanges (``torch.median`` over unfolded boxes takes 20x longer)."""
    H, W = x.shape[-2:]
    p = torch.nn.functional.pad(x, (1, 1, 1, 1), mode="replicate")
    v = [p[..., dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)]
    for i, j in _MEDIAN_OF_9:
        v[i], v[j] = torch.minimum(v[i], v[j]), torch.maximum(v[i], v[j])
    return v[4]


def _scattered_albedo(f: Tensor, names: Sequence[str], mask: Tensor | None = None) -> Tensor:
    """Features ``f`` ``(T, D, H, W)`` named ``names`` with the albedo averaged over
    :data:`_SCATTERED_ALBEDO_SIGMA` pixels where the samples scatter over an area (:func:`_scattered`, among
    the pixels of nonzero ``mask`` ``(T, 1, H, W)``, all by default), or without world positions where the
    albedo is salt and pepper over one smooth surface (:func:`_speckled`; without depth, or in a frame whose
    depth is a placeholder of zeros, the normals tell the surface); ``f`` itself without albedo, without depth
    and normals, or where nothing scatters."""
    canon = [feature_table.canonical_name(n) for n in names]
    position = _position(f, names)
    albedo = [canon.index(c) for c in feature_table.feature("albedo").channels if c in canon]
    normal = [canon.index(c) for c in feature_table.feature("N").channels if c in canon]
    (depth,) = feature_table.feature("Z").channels
    valid = None if mask is None else mask > 0
    if len(albedo) != 3:
        return f
    normals = f[:, normal] if len(normal) == 3 else None
    if depth in canon:
        z = f[:, canon.index(depth)][:, None]
        w = _speckled(f[:, albedo], z, valid) if position is None else _scattered(position, z, valid)
        placeholder = ~(z > 0).flatten(1).any(1).view(-1, 1, 1, 1)  # a frame whose depth is 0 everywhere
        if normals is not None and bool(placeholder.any()):
            w = torch.where(placeholder, _speckled(f[:, albedo], None, valid, normals), w)
    elif normals is not None:  # the normals tell one smooth surface
        w = _speckled(f[:, albedo], None, valid, normals)
    else:
        return f
    if not bool((w > 0).any()):
        return f
    a = f[:, albedo]
    f = f.clone()
    f[:, albedo] = a + w * (footprint_blur(a, _SCATTERED_ALBEDO_SIGMA) - a)
    return f


#: how far (pixels, along each image axis) a sample of another frame may lie from a pixel's own sample to
#: count as a sample of that pixel: two samples of one pixel of a still view differ by the difference of
#: their jitters, under a pixel (frames 0-2, the ``denoise`` default, from 1 / 4 spp, the gains of the two
#: still views summed: 0.75 +0.78 / +1.43, 1 +0.90 / +1.46, 1.5 +0.92 / +1.51 dB; every other scene within
#: 0.001 dB)
_SAME_PIXEL = 1.0
#: the largest mean offset (pixels) of a neighbourhood's samples from the other frame's that still counts
#: as a still view, and the neighbourhood's radius (frames 0-2, the ``denoise`` default, from 1 / 4 spp:
#: without it ``mi_env_thin``, whose camera dollies, lost 0.11 / 0.12 dB and ``cbox_glossy_tex``, a pan,
#: 0.04 / 0.09; with it every scene but the still views within 0.001 dB; 0.15 / 0.35: the two still views
#: +0.76 / +1.43 and +0.91 / +1.51 dB summed, against +0.90 / +1.46 at 0.25, the middle)
_STILL, _STILL_RADIUS = 0.25, 2


def _window_albedo(albedo: Tensor, s: FrameState, ft: list[float], qt: list[float],
                   radius: int) -> tuple[Tensor, Tensor]:
    """The albedo ``(Q, 3, H, W)`` at the queries averaged with the samples of the window's other frames
    that land in the pixel, on the same surface, each of equal weight, and how many samples each pixel's
    average holds, ``(Q, 1, H, W)`` (1: its own alone).

    A 1-spp pixel's albedo is one point of its area, and the reference is the pixel's average: texture
    under the footprint is the error left where the light is clean. Where the view is still, each frame
    samples the pixel at another point, so the window holds a few samples of every pixel's albedo
    (:func:`_same_pixel`). Where it moves and each pixel holds one sample (``s.point_samples``), the other
    frames' samples that fall in the pixel's footprint are points of the same area too
    (:func:`_footprint_samples`), on smooth surfaces (:func:`_smooth_surface` at least 1/e), where the
    footprint's position is known. An n-spp pixel's albedo already averages its own footprint, and another
    frame's pixel averages another one. Either way a surface that slides within itself keeps its positions
    while its texture moves: another frame's samples count only where its texture held
    (:func:`_texture_held`). Only at queries that are frames; flat pixels (not demodulated) and pixels
    without a valid sample keep their own."""
    out, counted = [], []
    for qi, q in enumerate(qt):
        k = frame_at(ft, q)
        a = albedo[qi]
        if k is None:
            out.append(a)
            counted.append(torch.ones_like(a[:1]))
            continue
        own = (s.mask[k] > 0) & ~s.flat[k]
        total, count = a.clone(), torch.ones_like(a[:1])
        others = [j for j in window(ft, q, radius) if j != k]
        valid = [(s.mask[j] > 0) & ~s.flat[j] for j in others]
        sames = _same_pixel(s.position[k], [s.position[j] for j in others])
        # (a moving view's pixels find no still sample: nothing to test)
        held = _texture_held(s.albedo[k], own, [s.albedo[j] for j in others], valid, not s.point_samples) \
            if any(bool(m.any()) for m in sames) else sames
        in_squares = s.point_samples and s.smooth is not None and bool(others)  # a moving view's samples
        if in_squares:  # searched where no still view's sample of the pixel was found
            search = own & (s.smooth[k] >= math.exp(-1.0))
            sums, counts = _footprint_samples(s.position[k], torch.stack([s.position[j] for j in others]),
                                              torch.stack([s.albedo[j] for j in others]),
                                              torch.stack(valid)[:, 0].to(a.dtype),
                                              torch.stack([search & ~(ok_j & same) for ok_j, same in
                                                           zip(valid, sames)])[:, 0])
            # the samples found in a pixel's square hold its texture too, unless it slid within its surface
            found_held = _texture_held(s.albedo[k], own, list(sums / counts.clamp_min(1.0)),
                                       list(counts > 0))
        for n, (j, same, ok_j, still) in enumerate(zip(others, sames, valid, held)):
            ok = own & ok_j & same & still  # the still view's sample of the pixel, else those in its square
            found, found_n = ((sums[n] * found_held[n], counts[n] * found_held[n]) if in_squares
                              else (0.0, 0.0))
            total += torch.where(ok, s.albedo[j], found)
            count += torch.where(ok, 1.0, found_n)
        out.append(total / count)
        counted.append(count)
    return torch.stack(out), torch.stack(counted)


#: a texture holds still where the other frame's albedo samples of the pixels around differ from the own ones
#: by at most this many times what neighbouring pixels' samples differ by (:func:`_texture_held`). A still
#: texture's ratio is about 0.5 with detail at the pixel scale and 1 where it is finer (both samples are
#: draws of the pixel's mix); the margin keeps 97% of such pixels over the 5x5 pool. Frames 0-5, the
#: ``denoise`` default, from 1 / 4 spp, the scenes with a still view and world positions (the others keep
#: their bits): c = 1 / 1.5 / 2, `mi_ceiling_light` (tuning part, a box moving under a still camera) at
#: 256x256 -0.06 / +0.11, +0.01 / +0.07, 0.00 / +0.04 dB; its 128x128 frames and `mi_indirect_dof`
#: -0.07 to -0.05, -0.02 to 0.00, 0.00; held out, `mi_still_textures` (a box sliding under a still camera)
#: at 256x256 +0.24 / +1.17, +0.37 / +1.15, +0.16 / +0.93, at 64x64 -0.20 / +0.01, -0.01 / +0.06,
#: +0.01 / +0.06
_TEXTURE_HELD = 1.5
#: where pixels average several samples, a texture also counts as slid where the other frame's samples match
#: the own ones better one pixel over than in place, by more than this many times the mean squared difference
#: between 4-neighbours: a slide of a pixel or two a frame, which the ratio above lets through
#: (:func:`_texture_held`). A checkered ball turning in place under a still camera (the probe `mi_spin`,
#: render_mitsuba.py, from 4 spp): inside the moving objects' mask the window albedo cost 1.5 dB against none
#: (28.26 against 29.76); 0.5 takes back 0.83 of it, the whole frame +0.20 dB (on a first render with 256-spp
#: references k = 0.5 / 0.75 / 1 took back 1.03 / 0.48 / 0.15 of 1.6). Frames 0-2 from 4 spp at 0.5, the
#: still views with world positions: `mi_ceiling_light` -0.001 (+0.008 at 256x256), `mi_indirect_dof` -0.021,
#: held out `mi_still_textures` +0.011; the other clips keep their bits. From 1 spp one sample a pixel makes
#: the test too noisy (k = 0.5: the mask +0.15, the tuning part -0.11 summed): it is not taken there.
_SLID = 0.5


def _texture_held(a: Tensor, own: Tensor, others: Sequence[Tensor], valid: Sequence[Tensor],
                  pixel_averages: bool = False) -> list[Tensor]:
    """Where the texture under each pixel holds still in each other frame: one ``(1, H, W)`` bool per frame.

    World positions cannot see a surface slide within itself (a box sliding on the floor, a ball spinning
    in place): its points keep their positions, its texture moves. Two samples of one pixel of a still
    texture lie within the pixel, nearer each other than samples of neighbouring pixels, so their albedos
    differ by less, or by as much where the texture is finer than a pixel; a texture that slid further
    than its detail differs by more. Over the pixels around (:data:`_STILL_RADIUS`), the mean squared
    difference of the other frame's albedo from the own must stay at most :data:`_TEXTURE_HELD` times the
    mean squared difference between 4-neighbours' own samples (where both are 0, on a plain surface, it
    holds). A slide of about a pixel passes that test. Where the pixels average several samples
    (``pixel_averages``), whose noise is lower, a slide also shows as a better match one pixel over: the least
    mean squared difference over the 8 neighbouring offsets must not undercut the one in place by more than
    :data:`_SLID` times the 4-neighbours' mean squared difference."""
    if not others:
        return []
    w = own.to(a.dtype)
    H, W = a.shape[-2:]
    near, pairs = torch.zeros_like(a[:1]), torch.zeros_like(a[:1])
    for dy, dx in ((0, 1), (1, 0)):
        d = ((a[:, dy:, dx:] - a[:, :H - dy, :W - dx]) ** 2).sum(0, keepdim=True)
        both = w[:, dy:, dx:] * w[:, :H - dy, :W - dx]
        near[:, dy:, dx:] += d * both
        near[:, :H - dy, :W - dx] += d * both
        pairs[:, dy:, dx:] += both
        pairs[:, :H - dy, :W - dx] += both
    spread = _box_mean(torch.stack([near, pairs]), _STILL_RADIUS)
    out = []
    for b, ok in zip(others, valid):
        m = w * ok.to(a.dtype)
        moved = _box_mean(torch.stack([((b - a) ** 2).sum(0, keepdim=True) * m, m]), _STILL_RADIUS)
        # mean over the box of each: moved[0] / moved[1] <= c spread[0] / spread[1]
        held = moved[0] * spread[1] <= _TEXTURE_HELD * spread[0] * moved[1]
        if pixel_averages:
            # one pixel over, each way
            bp = torch.nn.functional.pad(b[None], (1, 1, 1, 1), mode="replicate")[0]
            shifted = [bp[:, 1 + dy:1 + dy + H, 1 + dx:1 + dx + W] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                       if dy or dx]
            over = torch.stack([((x - a) ** 2).sum(0, keepdim=True) * m for x in shifted])
            better = moved[0] - _box_mean(over, _STILL_RADIUS).amin(0)
            held = held & (better * spread[1] <= _SLID * spread[0] * moved[1])
        out.append(held)
    return out


def _box_mean(x: Tensor, r: int) -> Tensor:
    """Mean of ``(..., H, W)`` over the (2r+1)^2 box around each pixel, the border replicated: sums of
    shifted views along x, then along y (about 10x faster than ``avg_pool2d`` for these small boxes),
    divided once, in the order the C++ kernel of :func:`_same_pixel` sums them; on CPU that kernel, bit for
    bit."""
    if _fast.enabled(x):
        return _fast.box_mean(x, r)
    for dim in (-1, -2):
        n = x.shape[dim]
        xp = torch.cat([x.narrow(dim, 0, 1)] * r + [x] + [x.narrow(dim, n - 1, 1)] * r, dim)
        total = xp.narrow(dim, 0, n)
        for k in range(1, 2 * r + 1):
            total = total + xp.narrow(dim, k, n)
        x = total
    return x / float((2 * r + 1) ** 2)


def _same_pixel(p: Tensor, others: Sequence[Tensor]) -> list[Tensor]:
    """Where each world position of ``others`` (``(3, H, W)``, samples of other frames) lies within
    :data:`_SAME_PIXEL` pixels of ``p`` along each image axis, on its surface, where the view is still:
    one ``(1, H, W)`` bool per other frame.

    The image axes in world units are the position's derivatives along x and y (central differences,
    averaged over 3x3 against the samples' jitter); an offset is taken into those axes by least squares,
    and what is left of it, off the surface, must stay under half a pixel. Across a moving surface or a
    moving view, the samples of one pixel lie on another part of the surface; their offsets, averaged
    over the pixels around (:data:`_STILL_RADIUS`), where the jitters cancel, show it: that mean must stay
    under :data:`_STILL` pixels. On CPU a C++ kernel takes the same steps, bit for bit."""
    if others and _fast.enabled(p, *others):
        stacked = torch.stack(list(others))
        return list(_fast.same_pixel(p, stacked, _SAME_PIXEL, _STILL, _STILL_RADIUS).unbind(0))
    axes = _image_axes(p)
    out = []
    for other in others:
        u, v, on_surface = _in_image_axes(other - p, axes)
        mean = _mean_offset(u, v, on_surface.to(u.dtype))
        n = mean[0].clamp_min(1e-6)
        still = (mean[1].abs() < _STILL * n) & (mean[2].abs() < _STILL * n)
        out.append((on_surface & still & (u.abs() < _SAME_PIXEL) & (v.abs() < _SAME_PIXEL))[None])
    return out


def _mean_offset(u: Tensor, v: Tensor, w: Tensor) -> Tensor:
    """The means of ``w``, ``u w`` and ``v w`` ``(H, W)`` over the pixels around (:data:`_STILL_RADIUS`):
    ``(3, H, W)``, the mean offset being the last two over the first."""
    return _box_mean(torch.stack([w, u * w, v * w]), _STILL_RADIUS)


def _dot3(a: Tensor, b: Tensor) -> Tensor:
    """``a . b`` over the 3 coordinates of ``(3, H, W)`` vectors."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _image_axes(p: Tensor) -> tuple:
    """The image axes of world positions ``p`` ``(3, H, W)`` in world units: their derivatives along x and
    y (central differences, 0 on the border columns / rows, averaged over 3x3 against the samples'
    jitter), with what :func:`_in_image_axes` solves by: ``(gx, gy, a11, a12, a22, det, solvable)``."""
    gx, gy = torch.zeros_like(p), torch.zeros_like(p)
    gx[:, :, 1:-1] = (p[:, :, 2:] - p[:, :, :-2]) / 2
    gy[:, 1:-1, :] = (p[:, 2:, :] - p[:, :-2, :]) / 2
    gx, gy = _box_mean(gx, 1), _box_mean(gy, 1)
    a11, a12, a22 = _dot3(gx, gx), _dot3(gx, gy), _dot3(gy, gy)
    det = a11 * a22 - a12 * a12
    solvable = det > 1e-12 * (a11 + a22) ** 2
    return gx, gy, a11, a12, a22, torch.where(solvable, det, 1.0), solvable


def _in_image_axes(d: Tensor, axes: tuple) -> tuple[Tensor, Tensor, Tensor]:
    """World offsets ``d`` ``(3, H, W)`` along the image axes (:func:`_image_axes`), by least squares:
    ``u, v`` in pixels, and whether what is left, off the surface, stays under half a pixel."""
    gx, gy, a11, a12, a22, det, solvable = axes
    b1, b2 = _dot3(gx, d), _dot3(gy, d)
    u, v = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
    rest = d - u * gx - v * gy
    return u, v, solvable & (_dot3(rest, rest) < 0.125 * (a11 + a22))


def _footprint_samples(p: Tensor, others: Tensor, albedo: Tensor, valid: Tensor,
                       search: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The samples of other frames that fall in each pixel's footprint: the sum of their ``albedo`` and
    their count, ``(K, 3, H, W)`` and ``(K, 1, H, W)``, for world positions ``p`` ``(3, H, W)`` of one
    sample per pixel and ``others`` ``(K, 3, H, W)`` of the other frames' samples, ``valid`` ``(K, H, W)``
    (1: usable), at the pixels ``search`` (bool ``(K, H, W)``; ``None``: every pixel) and 0 elsewhere.

    The footprint is the pixel's square, half a pixel each way along the image axes (:func:`_image_axes`)
    about the pixel's centre, the mean of the 3x3 samples around it (their jitters cancel). Where the
    footprint went between the frames is the mean offset of the other frame's samples at the same pixels
    over the pixels around (:data:`_STILL_RADIUS`), as in the still test of :func:`_same_pixel`, rounded to
    a pixel; the samples of the 3x3 pixels there are tested. A sample counts when it lies in the square and
    on the surface. On CPU a C++ kernel takes the same steps, bit for bit."""
    if search is None:
        search = torch.ones(valid.shape, dtype=torch.bool, device=valid.device)
    if _fast.enabled(p, others, albedo, valid):
        return _fast.footprint_samples(p, others, albedo, valid, search, _STILL_RADIUS)
    H, W = p.shape[-2:]
    axes = _image_axes(p)
    centre = _box_mean(p, 1)
    yy = torch.arange(H, device=p.device).view(H, 1).expand(H, W)
    xx = torch.arange(W, device=p.device).view(1, W).expand(H, W)
    sums, counts = [], []
    for other, alb, ok, where in zip(others, albedo, valid, search):
        u, v, on = _in_image_axes(other - centre, axes)
        mean = _mean_offset(u, v, torch.where(on, ok, 0.0))
        n = mean[0].clamp_min(1e-6)
        # the other frame's samples at the same pixels lie at -flow from the footprint (none where the
        # positions overflow; beyond the image nothing is inside)
        fx = torch.where(mean[0] > 0, torch.round(mean[1] / n), 0.0)
        fy = torch.where(mean[0] > 0, torch.round(mean[2] / n), 0.0)
        qx = xx - torch.where(torch.isfinite(fx), fx, 0.0).clamp(-W - 1, W + 1).long()
        qy = yy - torch.where(torch.isfinite(fy), fy, 0.0).clamp(-H - 1, H + 1).long()
        total, count = torch.zeros_like(alb), torch.zeros_like(ok)[None]
        flat_p, flat_a, flat_ok = other.reshape(3, -1), alb.reshape(3, -1), ok.reshape(-1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                sx, sy = qx + dx, qy + dy
                inside = (sx >= 0) & (sx < W) & (sy >= 0) & (sy < H)
                idx = (sy.clamp(0, H - 1) * W + sx.clamp(0, W - 1)).reshape(-1)
                u, v, on = _in_image_axes(flat_p[:, idx].view(3, H, W) - centre, axes)
                hit = inside & on & (flat_ok[idx].view(H, W) > 0) & (u.abs() < 0.5) & (v.abs() < 0.5)
                hit = hit & where
                total += torch.where(hit, flat_a[:, idx].view(3, H, W), 0.0)
                count += hit.to(count.dtype)
        sums.append(total)
        counts.append(count)
    return torch.stack(sums), torch.stack(counts)


def _remodulate(irradiance: Tensor, albedo: Tensor, flat: Tensor, smooth: Tensor | None, sigma: float,
                counts: Tensor | None = None, most: int = 1, unseen_border: float = 0.0) -> Tensor:
    """The filtered irradiance ``(Q, 3, H, W)`` times the albedo, averaged over the pixel footprint.

    Across a silhouette, light and albedo change together within a pixel: the product is averaged
    (:func:`_footprint_average`). On a smooth surface (``smooth`` near 1) only the albedo has detail below
    the footprint, texture: the irradiance is averaged alone and the albedo over a narrower footprint
    (:data:`_TEXTURE_FOOTPRINT`), which keeps a texture's stripes that the full footprint washes out.
    The two blend by ``smooth``; flat-shaded pixels (``flat``, not demodulated) take the product.

    Where the albedo already averages ``counts`` ``(Q, 1, H, W)`` samples of the pixel
    (:func:`_window_albedo`), its footprint is the width of that many times the samples
    (:func:`footprint_width`: its square is ``a + b / spp``): a blend of the footprints of one count and
    of ``most``, whose variance is that square exactly for every count in between. ``unseen_border``: as
    :func:`_footprint_average` takes it.

    Last, each of the product, the light and the albedo is averaged along the result's edges
    (:func:`_along_edges`), over a width from the samples per pixel (:func:`_edge_width`; the albedo's from
    its ``counts``); across a sure edge each starts part-way back from its footprint average
    (:func:`_before_footprint`).
    """
    product = irradiance * albedo
    out = _footprint_average(product, sigma, unseen_border)
    width = _edge_width(sigma, None, out)
    edges = bool((width > 0).any())
    if smooth is None or sigma <= 0:
        if not edges:
            return out
        directions = _edge_directions(out)
        feed = _before_footprint(out, product, directions, _raw_share(sigma))
        return _along_edges([feed], [width], directions)[0]
    w = smooth * (~flat).to(smooth.dtype)
    texture = _footprint_albedo(albedo, flat, _TEXTURE_FOOTPRINT * sigma)
    if counts is not None and most > 1 and bool((counts > 1).any()):
        # sigma^2 = a + b / spp, so with n times the samples: a + (sigma^2 - a) / n
        narrow = math.sqrt(_FOOTPRINT_A + _unseen(sigma) / most)
        f = ((1.0 / counts - 1.0 / most) / (1.0 - 1.0 / most)).clamp(0.0, 1.0)
        texture = f * texture + (1 - f) * _footprint_albedo(albedo, flat, _TEXTURE_FOOTPRINT * narrow)
    light = _footprint_average(irradiance, sigma, unseen_border)
    if not edges:
        return out + w * (light * texture - out)
    # the edges are the result's; the albedo's own samples, counts times the frame's, set its width
    directions = _edge_directions(out + w * (light * texture - out))
    share = _raw_share(sigma)
    images = [_before_footprint(x, before, directions, share)
              for x, before in ((out, product), (light, irradiance), (texture, albedo))]
    out, light, texture = _along_edges(images, [width, width, _edge_width(sigma, counts, out)], directions)
    return out + w * (light * texture - out)
