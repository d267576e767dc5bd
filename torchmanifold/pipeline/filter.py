"""The weighted adaptive-manifold filter over a clip as the frame step (:mod:`torchmanifold.pipeline.denoise`)
calls it: per query one op call for every bandwidth (a frame alone, a space-time window or the window's
mean), normalised by the filtered weights, bounded by the samples around in float32 (the guard), and run on
two checkerboard halves of the samples at once where the bandwidth selection cross-validates."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import torch
from torch import Tensor

from torchmanifold._checks import MAX_TREE_HEIGHT
from torchmanifold.pipeline import _fast
from torchmanifold.timewindow import bracket, frame_at, interpolate, window

if TYPE_CHECKING:
    from torchmanifold.pipeline.denoise import DenoiseSettings


#: the float32 guard's box, in spatial sigmas: the samples a pixel mixes lie almost all within it
#: (a Gaussian keeps 86% of its weight inside 2 sigma in 2-D), and a wider box bounds nothing
_GUARD_RADIUS = 2


def _min_support(dtype: torch.dtype) -> float:
    """The least normalising weight ``den`` (1 at a fully supported pixel) whose ``num / den`` is taken;
    below it a pixel takes its fallback. The op's recursive sums round ``den`` to about eps (its peak is
    1), so ``100 eps`` keeps two digits (float32: 1.2e-5; not below 1e-8, float64's). Frames 0-2 of the
    validation set from 1 / 4 spp, PyTorch stages: 1e-8 / 1.2e-5 / 1.2e-4 all within 0.002 dB of each other,
    1.2e-5 within 0.002 of the best on every scene. The C++ kernels' ``min_support`` is the same."""
    return max(1e-8, 1e2 * torch.finfo(dtype).eps)


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

#: the bandwidth (times ``sigma_s``) below which the tree has one level fewer: the candidates that reach the
#: samples' own detail where no albedo guides (a quarter and an eighth), whose fine grids make them the
#: costliest. Colour alone, every frame of the validation set from 1 / 4 spp: +0.005 / +0.006 dB, geometry
#: alone +0.006 / -0.002, for 190 -> 168 ms a 256x256 frame (one thread); below 1, the default's 2 px
#: candidate lost 0.12 / 0.06 dB with every feature
_FEWER_LEVELS_BELOW = 0.5


def tree_height_at(settings: DenoiseSettings, bandwidth: float) -> int:
    """The manifold tree's height for a spatial sigma of ``bandwidth`` times ``sigma_s``:
    ``settings.tree_height``, plus ``settings.levels_per_doubling`` for each whole doubling beyond 1
    (a half step rounds down), for at most :data:`_MAX_DOUBLINGS` doublings; one level fewer below
    :data:`_FEWER_LEVELS_BELOW` (at least 1)."""
    doublings = min(_MAX_DOUBLINGS, max(0, math.floor(math.log2(float(bandwidth)) + 1e-9)))
    height = settings.tree_height + settings.levels_per_doubling * doublings
    if float(bandwidth) < _FEWER_LEVELS_BELOW:
        height = max(1, height - 1)
    return min(MAX_TREE_HEIGHT, height)


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
        ids = [self._max_frames(q) for q in self.qt]
        if _fast.enabled(values, mask) and all(map(_consecutive, ids)):
            return _fast.window_bounds(values, mask, [f[0] for f in ids], [len(f) for f in ids])
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
        return torch.stack([_frames(x, self._max_frames(q)).amax(0) for q in self.qt])

    def _max_frames(self, q: float) -> list[int]:
        """The frames :meth:`at_queries_max` takes the largest of at query ``q``."""
        k = frame_at(self.ft, q)
        return self._window(q) if self.st.temporal_radius > 0 or k is None else [k]

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
    if _consecutive(ids):
        return x[ids[0]:ids[0] + len(ids)]
    return x[ids]


def _consecutive(ids: list[int]) -> bool:
    """``ids`` is a non-empty run of consecutive frames (a window, one query's frame)."""
    return bool(ids) and ids == list(range(ids[0], ids[0] + len(ids)))


def _halves(shape, device, cell: int = 1) -> Tensor:
    """A checkerboard ``(1, 1, H, W)`` of ``cell`` x ``cell`` pixel squares: 1 on half the pixels, 0 on the
    other half."""
    H, W = shape[-2:]
    yy = torch.arange(H, device=device)[:, None] // cell
    xx = torch.arange(W, device=device)[None, :] // cell
    return ((yy + xx) % 2 == 0)[None, None]


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
