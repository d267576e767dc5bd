"""The one rule for frames around a time, against brute force written here from the rule's words."""
from __future__ import annotations

import itertools
import random

import pytest
import torch

from torchmanifold.timewindow import (TIME_TOL, bracket, frame_at, index_window, interpolate, time_weights,
                                      window, windows_span)


def brute_bracket(ft: list[float], t: float) -> tuple[int, int, float]:
    """By enumeration: on a frame -> that frame; else the closest frame on each side (lowest index among
    equal times); outside the clip -> the end frame with weight 0."""
    on = [k for k in range(len(ft)) if abs(ft[k] - t) <= TIME_TOL]
    if on:
        return on[0], on[0], 0.0
    best0 = best1 = None
    for k in range(len(ft)):  # first index kept on ties: strict comparisons
        if ft[k] < t and (best0 is None or ft[k] > ft[best0]):
            best0 = k
        if ft[k] > t and (best1 is None or ft[k] < ft[best1]):
            best1 = k
    if best0 is None or best1 is None:
        end = best1 if best0 is None else best0
        return end, end, 0.0
    return best0, best1, (t - ft[best0]) / (ft[best1] - ft[best0])


def brute_value(ft: list[float], t: float, values: list[float]) -> float:
    """Piecewise-linear interpolation through (time, value) points sorted by time, flat outside."""
    pts = sorted(set((ft[k], k) for k in range(len(ft))))
    first = {}
    for time, k in pts:  # equal times: the lowest index speaks for the time
        first.setdefault(time, values[k])
    xs = sorted(first)
    if t <= xs[0] + TIME_TOL:
        return first[xs[0]]
    if t >= xs[-1] - TIME_TOL:
        return first[xs[-1]]
    for a, b in zip(xs, xs[1:]):
        if abs(t - a) <= TIME_TOL:
            return first[a]
        if a < t < b:
            return first[a] + (first[b] - first[a]) * (t - a) / (b - a)
    raise AssertionError("unreachable")


CLIPS = [
    [0.0, 1.0, 2.0, 3.0],
    [2.0, 0.0, 3.0, 1.0],           # any order
    [0.0, 1.0, 1.0, 2.0],           # duplicate times
    [5.0],                           # one frame
    [0.0, 0.25, 0.5, 2.0, 2.0, 7.5],
]
TIMES = [-3.0, -1e-12, 0.0, 1e-12, 0.25, 0.5, 0.75, 1.0, 1.0 + 1e-10, 1.5, 1.999999, 2.0, 2.4, 3.0, 3.5, 7.5, 9.0]


@pytest.mark.parametrize("ft, t", list(itertools.product(CLIPS, TIMES)))
def test_bracket_matches_brute_force(ft, t):
    i0, i1, w = bracket(ft, t)
    b0, b1, bw = brute_bracket(ft, t)
    assert (i0, i1) == (b0, b1)
    assert w == pytest.approx(bw, abs=1e-12)
    if i0 != i1:
        assert ft[i0] < t < ft[i1] and 0.0 < w < 1.0


def test_ties_ends_and_on_frame():
    ft = [0.0, 1.0, 1.0, 2.0]
    assert bracket(ft, 1.0) == (1, 1, 0.0)                 # on a duplicate time: the lowest index
    assert bracket(ft, 1.0 + TIME_TOL / 2) == (1, 1, 0.0)  # rounding error is the same time
    assert bracket(ft, 0.5) == (0, 1, 0.5)
    assert bracket(ft, 1.5) == (1, 3, 0.5)                 # the later duplicate is never picked
    assert bracket(ft, -4.0) == (0, 0, 0.0) and bracket(ft, 9.0) == (3, 3, 0.0)
    assert bracket([3.0, 3.0], 5.0) == (0, 0, 0.0)
    assert frame_at(ft, 1.0) == 1 and frame_at(ft, 1.5) is None and frame_at(ft, 1.0 + 1e-6) is None


@pytest.mark.parametrize("ft", CLIPS)
def test_interpolate_is_the_piecewise_linear_curve(ft):
    gen = torch.Generator().manual_seed(len(ft))
    vals = torch.rand(len(ft), 2, 3, generator=gen, dtype=torch.float64)
    for t in TIMES + [random.Random(1).uniform(-1, 8) for _ in range(20)]:
        got = interpolate(vals, ft, t)
        for c, h in itertools.product(range(2), range(3)):
            want = brute_value(ft, t, vals[:, c, h].tolist())
            assert float(got[c, h]) == pytest.approx(want, abs=1e-12), (ft, t)
    # another frame dimension gives the same numbers
    torch.testing.assert_close(interpolate(vals.movedim(0, 1), ft, 0.3, dim=1), interpolate(vals, ft, 0.3))
    with pytest.raises(ValueError, match="x: expected"):
        interpolate(vals[:1], [0.0, 1.0], 0.5)


@pytest.mark.parametrize("ft, t, radius", list(itertools.product(CLIPS, TIMES, [0, 1, 2.5])))
def test_window_matches_brute_force(ft, t, radius):
    inside = {k for k in range(len(ft)) if abs(ft[k] - t) <= radius + TIME_TOL}
    b0, b1, _ = brute_bracket(ft, t)
    assert window(ft, t, radius) == sorted(inside | {b0, b1})


def test_window_examples_and_errors():
    assert window([0.0, 1.0, 2.0, 3.0], 1.0, 1) == [0, 1, 2]
    assert window([0.0, 1.0, 2.0, 3.0], 1.0 - 1e-12, 1) == [0, 1, 2]  # distance 1 + rounding: still inside
    assert window([0.0, 1.0, 2.0, 3.0], 1.5, 0) == [1, 2]
    assert window([0.0, 1.0, 2.0, 3.0], 2.0, 0) == [2]
    assert window([0.0, 1.0, 2.0, 3.0], -2.0, 1) == [0]  # only the clamped end frame
    with pytest.raises(ValueError, match="radius"):
        window([0.0], 0.0, -1)
    with pytest.raises(ValueError, match="frame_times"):
        bracket([], 0.0)


@pytest.mark.parametrize("count", [1, 2, 5, 9])
def test_index_window_is_the_window_of_a_clip_numbered_by_frame(count):
    for k, radius in itertools.product(range(count), [0, 1, 2, 7]):
        assert list(index_window(count, k, radius)) == window(range(count), k, radius), (k, radius)
    for bad in ((count, count, 1), (count, -1, 1), (count, 0, -1)):
        with pytest.raises(ValueError, match="index_window"):
            index_window(*bad)


def test_windows_span_runs_from_the_first_to_the_last_frame_any_window_holds():
    ft = [0.0, 0.5, 1.0, 2.0, 3.0, 4.0]
    for times, radius in itertools.product([[1.0], [0.0, 4.0], [2.5], [1.0, 3.0]], [0, 0.5, 1]):
        held = {k for t in times for k in window(ft, t, radius)}
        assert windows_span(ft, times, radius) == range(min(held), max(held) + 1), (times, radius)
    assert windows_span(ft, [0.0, 4.0], 0) == range(0, 6)  # the frames between two windows come along
    with pytest.raises(ValueError, match="times"):
        windows_span(ft, [], 1)


def test_time_weights_are_gaussian_up_to_a_row_factor():
    ft = torch.tensor([0.0, 1.0, 2.0, 5.0], dtype=torch.float64)
    qt = torch.tensor([0.0, 1.5, 40.0], dtype=torch.float64)
    w = time_weights(ft, qt, 0.7)
    for i, q in enumerate(qt.tolist()):
        g = [pow(2.718281828459045, -((t - q) ** 2) / (2 * 0.49)) for t in ft.tolist()]
        if max(g) > 0:
            torch.testing.assert_close(w[i], torch.tensor(g, dtype=torch.float64) / max(g))
        assert float(w[i].max()) == 1.0  # far queries keep a weight (no underflow to all zeros)
