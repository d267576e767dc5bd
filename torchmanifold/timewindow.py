"""Which frames surround a time ``t``, and with what weights: the one rule of the project.

Frames carry times (in frame units, any order, duplicates allowed); a query time ``t`` may fall on a
frame, between two frames, or outside the clip. Every part of the project that needs frames around a
time (the temporal filter op, the denoiser, the progressive engine, the demo) asks this module:

- :func:`frame_at`: the frame that stands at ``t`` (within :data:`TIME_TOL`), or ``None``.
- :func:`bracket`: the two frames that bracket ``t`` and the linear weight between them.
- :func:`interpolate`: per-frame data at ``t``, linear between the bracketing frames.
- :func:`window`: the frames within a radius of ``t``, plus the bracketing pair.
- :func:`index_window`: the same for a clip's frame ``k`` when frames stand one time unit apart.
- :func:`time_weights`: Gaussian weights of frames around query times.

Ties: among frames with the same time the lowest index wins. Ends: a time before the first frame (or
after the last) is clamped to that frame.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

__all__ = ["TIME_TOL", "frame_at", "bracket", "interpolate", "window", "windows_span", "index_window",
           "time_weights"]

#: Two times closer than this (in frame units) are the same time. Times are built by sums such as
#: ``t + k / (n + 1)`` (the render job's in-between frames) or ``round(4 t) / 4`` (the demo's scrub);
#: their float64 rounding error is below 1e-12 for clips up to 10^4 frames, and no two distinct times
#: the project makes are closer than 1e-3 frames, so any tolerance in between is safe.
TIME_TOL = 1e-9


def _times(frame_times) -> list[float]:
    ft = frame_times.tolist() if isinstance(frame_times, Tensor) else [float(x) for x in frame_times]
    if not ft:
        raise ValueError("frame_times: expected at least one frame time, got none")
    return ft


def frame_at(frame_times: Sequence[float] | Tensor, t: float) -> int | None:
    """Index of the frame at time ``t`` (within :data:`TIME_TOL`; the lowest index among equal times),
    or ``None`` when no frame stands there.

    Example:
        >>> frame_at([0.0, 1.0, 1.0], 1.0 + 1e-12), frame_at([0.0, 1.0], 0.5)
        (1, None)
    """
    ft = _times(frame_times)
    best = min(range(len(ft)), key=lambda k: (abs(ft[k] - t), k))
    return best if abs(ft[best] - t) <= TIME_TOL else None


def bracket(frame_times: Sequence[float] | Tensor, t: float) -> tuple[int, int, float]:
    """The frames around time ``t`` and the weight of the later one.

    Args:
        frame_times: ``(T,)`` frame times, any order.
        t: the query time.

    Returns:
        ``(i0, i1, w)``: data at ``t`` is ``(1 - w) * x[i0] + w * x[i1]``. On a frame (within
        :data:`TIME_TOL`) and outside the clip (clamped to the end frame) ``i0 == i1`` and ``w == 0``;
        otherwise ``i0`` is the latest frame before ``t``, ``i1`` the earliest after it, ``0 < w < 1``.

    Example:
        >>> bracket([0.0, 1.0, 2.0], 1.25)
        (1, 2, 0.25)
    """
    ft = _times(frame_times)
    k = frame_at(ft, t)
    if k is not None:
        return k, k, 0.0
    below = [k for k in range(len(ft)) if ft[k] < t]
    above = [k for k in range(len(ft)) if ft[k] > t]
    if not below or not above:  # outside the clip: the end frame (lowest index among equal times)
        k = min(above, key=lambda k: (ft[k], k)) if not below else min(below, key=lambda k: (-ft[k], k))
        return k, k, 0.0
    i0 = min(below, key=lambda k: (-ft[k], k))
    i1 = min(above, key=lambda k: (ft[k], k))
    return i0, i1, (t - ft[i0]) / (ft[i1] - ft[i0])


def interpolate(x: Tensor, frame_times: Sequence[float] | Tensor, t: float, dim: int = 0) -> Tensor:
    """Per-frame data ``x`` at time ``t``: linear between the frames that :func:`bracket` names.

    Args:
        x: data with one entry per frame along ``dim`` (e.g. ``(T, C, H, W)``).
        frame_times: ``(T,)`` frame times.
        t: the query time.
        dim: the frame dimension of ``x``.

    Returns:
        ``x`` without ``dim`` (e.g. ``(C, H, W)``); the frame itself when ``t`` is on one.
    """
    if x.shape[dim] != len(_times(frame_times)):
        raise ValueError(f"x: expected {len(_times(frame_times))} frames along dim {dim}, got shape {tuple(x.shape)}")
    i0, i1, w = bracket(frame_times, t)
    a = x.select(dim, i0)
    return a if w == 0.0 else torch.lerp(a, x.select(dim, i1), w)


def window(frame_times: Sequence[float] | Tensor, t: float, radius: float) -> list[int]:
    """Sorted indices of the frames within ``radius`` of ``t`` (+ :data:`TIME_TOL`), always including the
    pair :func:`bracket` names (so an in-between time with radius 0 still has its two neighbours).

    Example:
        >>> window([0.0, 1.0, 2.0, 3.0], 1.0, 1), window([0.0, 1.0, 2.0], 0.5, 0)
        ([0, 1, 2], [0, 1])
    """
    ft = _times(frame_times)
    if not radius >= 0:
        raise ValueError(f"radius: expected a number >= 0, got {radius!r}")
    i0, i1, _ = bracket(ft, t)
    return sorted({k for k in range(len(ft)) if abs(ft[k] - t) <= radius + TIME_TOL} | {i0, i1})


def windows_span(frame_times: Sequence[float] | Tensor, times: Sequence[float], radius: float) -> range:
    """The frames from the first to the last that the windows (:func:`window`) of ``times`` hold: what the
    filters of those times read, as one run of frames (a slice of a clip's frames is a view).

    Example:
        >>> windows_span([0.0, 1.0, 2.0, 3.0, 4.0, 5.0], [2.0, 3.0], 1)
        range(1, 5)
    """
    held = [k for t in times for k in window(frame_times, t, radius)]
    if not held:
        raise ValueError("times: expected at least one time")
    return range(min(held), max(held) + 1)


def index_window(count: int, k: int, radius: int) -> range:
    """The frames ``k - radius .. k + radius`` of a clip of ``count`` frames numbered ``0 .. count - 1``,
    cut to the clip: :func:`window` ``(range(count), k, radius)`` without its scan over every frame (a
    streamed clip's frame times are its indices).

    Example:
        >>> list(index_window(5, 0, 2)), list(index_window(5, 3, 1))
        ([0, 1, 2], [2, 3, 4])
    """
    if not 0 <= k < count or radius < 0:
        raise ValueError(f"index_window: expected 0 <= k < count and radius >= 0, got k={k}, count={count}, "
                         f"radius={radius}")
    return range(max(0, k - radius), min(count, k + radius + 1))


def time_weights(frame_times: Tensor, query_times: Tensor, sigma_t: float) -> Tensor:
    """Gaussian weights ``(Q, T)`` exp(-(t - q)^2 / 2 sigma_t^2), rescaled so each row's largest is 1.

    The rescaling (a common factor per query) keeps far-away queries from underflowing to all zeros.
    """
    d2 = (query_times[:, None] - frame_times[None, :]).square()
    return torch.exp(-(d2 - d2.amin(1, keepdim=True)) / (2.0 * sigma_t * sigma_t))
