"""A time window's frames brought to one frame's pixels by matching the samples' features.

Where the view moves, a neighbour frame's pixel holds another point of the scene than the query frame's pixel,
and only the filter's range weights keep the two apart: where no feature differs (a sun patch's border, a
shadow, what a mirror shows) they blend. Each other frame is gathered to the query frame's pixels by an
integer flow found from features that do not change with the view (:func:`frame_flow`): world positions
``P``, or without them the albedo, normals and depth: the pair's dominant offset, and each pixel's own near it
where its surface moves otherwise. A pixel whose source lies outside the other frame gets no weight. A pair
whose dominant offset is 0 (a still view) is left as it is, bit for bit: there the range weights keep a moving
object's samples apart, and per-pixel offsets drew a still camera's defocused pixels to random neighbours
(``benchmarks/validation/findings.md``).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmanifold.pipeline import _fast
from torchmanifold.pipeline.footprint import _box_mean
from torchmanifold.timewindow import window

__all__ = ["Flow", "frame_flow", "gather", "WindowAlignment"]

#: the farthest the view moves in one frame, pixels: the validation set's clips pan up to 6 px a frame at
#: 256x256 (`mi_glass_mirror`); a pan beyond it finds a poor dominant offset, whose matches the range weights
#: reject as they do without alignment
_REACH = 8
#: the most grid pixels whose median cost picks the dominant offset (every fourth pixel of a 256x256 frame;
#: every eighth lost `mi_yard` 0.02 / 0.08 dB from 1 / 4 spp: its parallax leaves the dominant offset a close
#: call)
_GRID_PIXELS = 4096
#: the offsets whose median is taken over every grid pixel, the best over a quarter of them
_FINALISTS = 9
#: positions are averaged over this many pixels each way before matching: a 1-spp sample's jitter in its
#: pixel averages out
_BOX = 3
#: without positions, the share of the surface's grid pixels whose median cost picks the dominant offset:
#: those where the features vary most (the Cycles clips' pans match at 0.02-0.5 of no move's median cost
#: there; a half or a tenth scored within 0.03 dB of a quarter on the four panning Cycles clips, from 1 / 4
#: spp)
_VARYING_SHARE = 0.25
#: Each pixel's offset: within :data:`_REFINE` px of the dominant one, the one of least cost averaged over
#: :data:`_POOL` px each way, where that is under :data:`_MARGIN` times the dominant one's cost (without the
#: margin a still camera's depth of field drew a third of `mi_indirect_dof`'s pixels to random neighbours);
#: farther, the one a coarse-to-fine search over :data:`_LEVELS` halvings finds, where its cost is under
#: :data:`_FAR_MARGIN` times the near one's. A near floor moves against the wall behind it (`mi_yard`,
#: `mi_window`: -8 px against +2), beyond the near search; but a free search finds wrong matches in repeated
#: structure (a pergola's slats). The far margin on those two probes, all frames from 1 / 4 spp, against the
#: near search alone: 0.5 -0.05 / -0.10 and +0.12 / +0.10 dB, 0.25 -0.01 / -0.02 and +0.11 / +0.11, 0.1
#: +0.01 / +0.01 and +0.07 / +0.07 (``benchmarks/validation/findings.md``)
_REFINE = 2
_POOL = 7
_MARGIN = 0.5
_LEVELS = 2
_FAR_MARGIN = 0.25
#: the cost of a pixel whose source lies outside the frame (its neighbours' costs leave it out)
_OUTSIDE = 1e30


@dataclass
class Flow:
    """Where each pixel of one frame finds its samples in another: ``index`` ``(H * W,)`` int64, the other
    frame's flat pixel index, and ``inside`` ``(H, W)`` bool, whether that pixel lies in the frame (outside,
    the index is the nearest border pixel's)."""

    index: Tensor
    inside: Tensor


def _box(x: Tensor, size: int) -> Tensor:
    """The mean of ``x`` ``(C, H, W)`` over ``size`` x ``size`` pixels, those in the frame alone."""
    x = F.avg_pool2d(x[:, None], (1, size), 1, (0, size // 2), count_include_pad=False)
    return F.avg_pool2d(x, (size, 1), 1, (size // 2, 0), count_include_pad=False)[:, 0]


def _nearest_first(offsets: list[tuple[int, int]], centre: tuple[int, int]) -> list[tuple[int, int]]:
    """``offsets`` nearest ``centre`` first: an equal cost picks the smallest move."""
    return sorted(offsets, key=lambda o: ((o[0] - centre[0]) ** 2 + (o[1] - centre[1]) ** 2, o))


def _least_median_cost(to: Tensor, source: Tensor, ys: Tensor, xs: Tensor,
                       offsets: list[tuple[int, int]]) -> tuple[int, int]:
    """The offset whose median L1 difference over the grid pixels ``ys, xs`` is least (the first on a tie):
    the :data:`_FINALISTS` best over every fourth grid pixel, then those over all."""
    if len(offsets) > _FINALISTS and len(ys) >= 4 * _FINALISTS:
        median = _median_costs(to, source, ys[::4], xs[::4], offsets, keep=_FINALISTS).tolist()
        best = sorted(range(len(offsets)), key=lambda i: (median[i], i))[:_FINALISTS]
        offsets = [offsets[i] for i in sorted(best)]
    return offsets[int(_median_costs(to, source, ys, xs, offsets).argmin())]


def _median_costs(to: Tensor, source: Tensor, ys: Tensor, xs: Tensor,
                  offsets: list[tuple[int, int]], keep: int = 0) -> Tensor:
    """Each offset's median L1 difference over the grid pixels ``ys, xs`` that it keeps in the frame (inf
    where none): ``(O,)``. ``keep`` > 0: the C++ kernel may give inf for offsets whose median certainly lies
    above ``keep`` others' (the ``keep`` least, by median then order, stay exact), skipping their
    selection."""
    if _fast.enabled(to, source):
        median = _fast.median_offset_costs(to, source, ys, xs, offsets, keep)
    else:
        H, W = source.shape[-2:]
        pad = max(max(abs(dy), abs(dx)) for dy, dx in offsets)
        padded = F.pad(source[None], (pad, pad, pad, pad), value=float("nan"))[0].flatten(1)
        off = torch.tensor(offsets, device=ys.device)
        index = (ys[None] + pad + off[:, :1]) * (W + 2 * pad) + xs[None] + pad + off[:, 1:]
        cost = (to[:, ys, xs][:, None] - padded[:, index]).abs().sum(0)  # (offsets, grid pixels)
        median = torch.nan_to_num(cost.nanmedian(1).values, nan=math.inf)
    return median


def _varying(x: Tensor, hit: Tensor) -> Tensor:
    """The pixels of ``hit`` where ``x`` ``(C, H, W)`` varies most: of those where it varies at all, the top
    :data:`_VARYING_SHARE` by the L1 length of its central differences (where features are piecewise constant,
    a plain wall's albedo and normal, a floor's depth along a row, a move along them matches as well as
    none)."""
    change = torch.zeros(x.shape[-2:], dtype=x.dtype, device=x.device)
    change[:, 1:-1] += (x[:, :, 2:] - x[:, :, :-2]).abs().sum(0)
    change[1:-1, :] += (x[:, 2:, :] - x[:, :-2, :]).abs().sum(0)
    varies = hit & (change > 0)
    if not bool(varies.any()):
        return hit
    values = change[varies]
    least = values.kthvalue(max(1, math.ceil((1.0 - _VARYING_SHARE) * values.numel()))).values
    return varies & (change >= least)


def _dominant_offset(to: Tensor, source: Tensor, hit: Tensor, distance: int) -> tuple[int, int]:
    """The offset that moves most of ``to``'s surface (``hit``) onto ``source``'s: a search over multiples
    of ``distance`` within ``distance`` frames' reach, then the offsets between around the best; the smaller
    move on a tie (a flat guide matches every offset alike)."""
    H, W = to.shape[-2:]
    step = max(1, math.ceil(math.sqrt(H * W / _GRID_PIXELS)))
    grid = hit[step // 2::step, step // 2::step].nonzero()
    if len(grid) == 0:  # no surface to match
        return 0, 0
    ys, xs = grid[:, 0] * step + step // 2, grid[:, 1] * step + step // 2
    steps = min(_REACH * distance, H // 2, W // 2) // distance
    coarse = [(a * distance, b * distance) for a, b in _square(steps)]  # nearest first, as the square
    best = _least_median_cost(to, source, ys, xs, coarse)
    if distance > 1:
        fine = [(best[0] + a, best[1] + b) for a in range(1 - distance, distance)
                for b in range(1 - distance, distance)]
        best = _least_median_cost(to, source, ys, xs, _nearest_first(fine, (0, 0)))
    return best


def _moved(dy: Tensor, dx: Tensor) -> Flow:
    """The flow that moves each pixel by its own ``(dy, dx)`` (``(H, W)`` int64)."""
    H, W = dy.shape
    y = torch.arange(H, device=dy.device)[:, None] + dy
    x = torch.arange(W, device=dy.device)[None, :] + dx
    inside = (y >= 0) & (y < H) & (x >= 0) & (x < W)
    return Flow((y.clamp(0, H - 1) * W + x.clamp(0, W - 1)).flatten(), inside)


def _pooled_cost(to: Tensor, source: Tensor, dy: Tensor, dx: Tensor) -> Tensor:
    """The L1 difference of each pixel's features and those of its source moved by ``(dy, dx)``, averaged
    over :data:`_POOL` pixels each way, those whose source lies in the frame: ``(H, W)``, :data:`_OUTSIDE`
    where the pixel's own does not."""
    flow = _moved(dy, dx)
    inside = flow.inside
    cost, count = torch.where(inside, (to - gather(source, flow)).abs().sum(0), 0.0), inside.to(to.dtype)
    return torch.where(inside, _box(cost[None], _POOL)[0] / _box(count[None], _POOL)[0], _OUTSIDE)


def _least_cost(to: Tensor, source: Tensor, dy: Tensor, dx: Tensor,
                offsets: list[tuple[int, int]]) -> tuple[Tensor, Tensor, Tensor]:
    """Per pixel, the offset of ``(dy, dx) + offsets`` (the first wins a tie) of least pooled cost: its
    ``dy``, ``dx`` and cost."""
    if _fast.enabled(to, source):
        return _fast.least_offset_cost(to, source, dy, dx, offsets, _POOL // 2)
    best = pick_y = pick_x = None
    for a, b in offsets:
        cost = _pooled_cost(to, source, dy + a, dx + b)
        if best is None:
            best, pick_y, pick_x = cost, dy + a, dx + b
            continue
        better = cost < best
        best = torch.where(better, cost, best)
        pick_y, pick_x = torch.where(better, dy + a, pick_y), torch.where(better, dx + b, pick_x)
    return pick_y, pick_x, best


def _square(r: int) -> list[tuple[int, int]]:
    """The offsets within ``r`` each way, nearest first."""
    return list(_square_once(r))


@functools.lru_cache(maxsize=None)
def _square_once(r: int) -> tuple[tuple[int, int], ...]:
    return tuple(_nearest_first([(a, b) for a in range(-r, r + 1) for b in range(-r, r + 1)], (0, 0)))


def _searched(to: Tensor, source: Tensor, distance: int) -> tuple[Tensor, Tensor, Tensor]:
    """Each pixel's offset of least pooled cost within ``distance`` frames' reach, searched coarse to fine
    over :data:`_LEVELS` halvings, each finer level within a pixel of the coarser one's: ``dy``, ``dx``,
    cost."""
    H, W = to.shape[-2:]
    levels = max(0, min(_LEVELS, int(math.log2(min(H, W) / _POOL)) - 1))
    pyramid = [(to, source)]
    for _ in range(levels):
        pyramid.append(tuple(F.avg_pool2d(x[None], 2, ceil_mode=True)[0] for x in pyramid[-1]))
    t, src = pyramid[-1]
    zero = torch.zeros(t.shape[-2:], dtype=torch.int64, device=t.device)
    dy, dx, cost = _least_cost(t, src, zero, zero, _square(math.ceil(_REACH * distance / 2 ** levels)))
    for t, src in pyramid[-2::-1]:
        h, w = t.shape[-2:]
        dy, dx = ((2 * x).repeat_interleave(2, 0).repeat_interleave(2, 1)[:h, :w] for x in (dy, dx))
        dy, dx, cost = _least_cost(t, src, dy, dx, _square(1))
    return dy, dx, cost


def _pixel_offsets(to: Tensor, source: Tensor, dominant: tuple[int, int],
                   distance: int) -> tuple[Tensor, Tensor]:
    """Each pixel's offset ``(dy, dx)``, two ``(H, W)`` int64: near the dominant one, or farther where that
    matches clearly better (the rule at :data:`_REFINE`)."""
    zero = torch.zeros(to.shape[-2:], dtype=torch.int64, device=to.device)
    own_y, own_x = zero + dominant[0], zero + dominant[1]
    own = _least_cost(to, source, own_y, own_x, [(0, 0)])[2]
    near_y, near_x, near = _least_cost(to, source, own_y, own_x, _square(_REFINE))
    clear = near < _MARGIN * own
    near_y, near_x, near = torch.where(clear, near_y, own_y), torch.where(clear, near_x, own_x), \
        torch.where(clear, near, own)
    far_y, far_x, far = _searched(to, source, distance)
    clear = far < _FAR_MARGIN * near
    return torch.where(clear, far_y, near_y), torch.where(clear, far_x, near_x)


def frame_flow(to: Tensor, source: Tensor, distance: int = 1, varying_only: bool = False) -> Flow | None:
    """Where each pixel of a frame finds its surface's samples in another, from features that do not change
    with the view.

    Args:
        to: ``(C, H, W)`` the features of the frame whose pixels the flow serves: world positions, or
            channels in comparable units (0 where no surface).
        source: ``(C, H, W)`` the other frame's.
        distance: frames between the two (the search reaches :data:`_REACH` pixels a frame).
        varying_only: the dominant offset from the pixels where the features vary most
            (:data:`_VARYING_SHARE`): piecewise constant ones match a move along them as well as none.

    Returns:
        the :class:`Flow` from ``to``'s pixels into ``source``'s, or ``None`` where the dominant offset is 0
        (a still view: each pixel keeps its own).

    Example:
        >>> y, x = torch.meshgrid(torch.arange(32.), torch.arange(32.), indexing="ij")
        >>> p = torch.stack([x, y, torch.ones_like(x)])
        >>> flow = frame_flow(p, p + torch.tensor([3.0, 0.0, 0.0])[:, None, None])
        >>> flow.index.view(32, 32)[10, 10].item() == 10 * 32 + 7
        True
    """
    return _flow_onto(_surface(to, varying_only), source, distance)


@dataclass
class _Surface:
    """A frame's features as the flows from its pixels match them (:func:`_surface`): ``field`` ``(C, H, W)``
    centred and averaged over :data:`_BOX` px, ``centre`` what was taken off (``(C, 1, 1)`` or 0), ``pixels``
    ``(H, W)`` bool, those whose median cost picks the dominant offset."""

    field: Tensor
    centre: Tensor | float
    pixels: Tensor


def _surface(to: Tensor, varying_only: bool) -> _Surface:
    """What every flow from the pixels of the frame with features ``to`` ``(C, H, W)`` matches, made once for
    all of them (:func:`frame_flow`'s arguments)."""
    to = to.detach()  # a flow picks pixels: no gradient passes it
    hit = to.abs().sum(0) > 0
    # about the surface's middle: float32 keeps the small differences of positions far from the origin
    centre = to[:, hit].mean(1)[:, None, None] if bool(hit.any()) else 0.0
    field = _box_mean(to - centre, _BOX // 2)
    return _Surface(field, centre, _varying(field, hit) if varying_only else hit)


def _flow_onto(surface: _Surface, source: Tensor, distance: int) -> Flow | None:
    """:func:`frame_flow` from a frame's :func:`_surface`."""
    source = _box_mean(source.detach() - surface.centre, _BOX // 2)
    dominant = _dominant_offset(surface.field, source, surface.pixels, max(1, int(distance)))
    if dominant == (0, 0):
        return None
    return _moved(*_pixel_offsets(surface.field, source, dominant, max(1, int(distance))))


def gather(x: Tensor, flow: Flow | None, weights: bool = False) -> Tensor:
    """``x`` ``(..., H, W)`` of the other frame at the pixels of the frame ``flow`` serves (``x`` itself
    without a flow); ``weights``: 0 where the source lies outside the frame."""
    if flow is None:
        return x
    out = torch.index_select(x.flatten(-2), -1, flow.index).view(x.shape)
    return out * flow.inside.to(out.dtype) if weights else out


class WindowAlignment:
    """The flows between the frames of a clip, each found once (:func:`frame_flow`).

    Args:
        field: ``(T, C, H, W)`` what the flows match (world positions, or features).
        frame_times: ``(T,)`` their times.
        radius: the frames on each side of a frame that are brought to its pixels (others stay as they are).
        memo: a store shared by a clip's calls (a :class:`~torchmanifold.pipeline.selection.ClipCache`) for
            the flows and each frame's side of them (:func:`_surface`), or ``None`` (this object's own).
        varying_only: as :func:`frame_flow` (features without positions).
    """

    def __init__(self, field: Tensor, frame_times: Sequence[float], radius: float, memo=None,
                 varying_only: bool = False):
        self.field, self.frame_times, self.radius, self.memo = field, list(frame_times), radius, memo
        self.varying_only = varying_only
        self._made: dict = {}  # what this object has made or taken from the memo: flows and surfaces

    def flow(self, k: int, j: int) -> Flow | None:
        """The flow from frame ``k``'s pixels into frame ``j``'s (``None``: each pixel keeps its own)."""
        if j == k:
            return None
        key = (self.frame_times[k], self.frame_times[j])
        distance = max(1, round(abs(key[1] - key[0])))
        return self._once(key, lambda: _flow_onto(self._surface(k), self.field[j], distance))

    def _surface(self, k: int) -> _Surface:
        """Frame ``k``'s side of its flows to the other frames, made once."""
        return self._once((self.frame_times[k], "surface"),
                          lambda: _surface(self.field[k], self.varying_only))

    def _once(self, key: tuple, make):
        """``make()`` for ``key``, made once: here, or by whichever call of the clip's memo came first."""
        if key not in self._made:
            self._made[key] = make() if self.memo is None else self.memo.get([key], lambda keys: [make()])[0]
        return self._made[key]

    def _others(self, k: int) -> list[int]:
        return [j for j in window(self.frame_times, self.frame_times[k], self.radius) if j != k]

    def moves(self, k: int) -> bool:
        """Whether any frame within ``radius`` of frame ``k`` moves against it."""
        return any(self.flow(k, j) is not None for j in self._others(k))

    def frames(self, x: Tensor, k: int, weights: bool = False, ids: Sequence[int] | None = None) -> Tensor:
        """``x`` ``(T, ..., H, W)`` with the frames within ``radius`` of frame ``k`` brought to its pixels
        (:func:`gather`; ``weights``: 0 where a source lies outside its frame); ``ids``: those frames alone,
        in that order (``(len(ids), ..., H, W)``), else all."""
        near = set(self._others(k))
        ids = range(x.shape[0]) if ids is None else ids
        flows = [self.flow(k, j) if j in near else None for j in ids]
        if x.requires_grad and torch.is_grad_enabled():
            return torch.stack([gather(x[j], flow, weights) for j, flow in zip(ids, flows)])
        out = torch.empty((len(flows), *x.shape[1:]), dtype=x.dtype, device=x.device)  # each frame in place
        for i, (j, flow) in enumerate(zip(ids, flows)):
            if flow is None:
                out[i].copy_(x[j])
                continue
            torch.index_select(x[j].flatten(-2), -1, flow.index, out=out[i].flatten(-2))
            if weights:
                out[i].mul_(flow.inside.to(out.dtype))
        return out

    def frame(self, x: Tensor, k: int, j: int) -> Tensor:
        """``x`` ``(..., H, W)`` of frame ``j`` at frame ``k``'s pixels (:func:`gather`)."""
        return gather(x, self.flow(k, j))
