"""torchmanifold._checks: the rules (TypeError for the wrong kind, ValueError for out of range) and that every
entry point of the filter gives the same error, with the same words, for the same bad setting."""
import math
import re

import pytest
import torch

from torchmanifold import _checks as C
from torchmanifold.ops import (
    AdaptiveManifoldFilter,
    TemporalAdaptiveManifoldFilter,
    adaptive_manifold_filter,
    temporal_adaptive_manifold_filter,
)
from torchmanifold.pipeline.schedule import BandwidthSchedule


@pytest.mark.parametrize("call,exc,words", [
    (lambda: C.check_positive("s", "1"), TypeError, "s must be a finite number > 0, got str"),
    (lambda: C.check_positive("s", True), TypeError, "got bool"),
    (lambda: C.check_positive("s", torch.ones(2)), TypeError, "got a tensor of shape (2,)"),
    (lambda: C.check_positive("s", 0), ValueError, "s must be a finite number > 0, got 0"),
    (lambda: C.check_positive("s", math.inf), ValueError, "got inf"),
    (lambda: C.check_nonnegative("s", -1e-9), ValueError, "s must be a finite number >= 0"),
    (lambda: C.check_number("a", 1.5, low=0, high=1, low_open=True), ValueError, "a must be a finite number in (0, 1]"),
    (lambda: C.check_int("n", 2.0, min=1), TypeError, "n must be an int >= 1, got float"),
    (lambda: C.check_int("n", 7, min=1, max=5), ValueError, "n must be an int in [1, 5], got 7"),
    (lambda: C.check_tree_height(None), TypeError, "tree_height must be an int in [1, 30], got NoneType"),
    (lambda: C.check_choice("mode", 3, ("a", "b")), TypeError, "mode must be one of ('a', 'b'), got int"),
    (lambda: C.check_choice("mode", "c", ("a", "b")), ValueError, "mode must be one of ('a', 'b'), got 'c'"),
    (lambda: C.check_sigmas("gs", [1.0, -1.0], 2), ValueError, "gs must be a sequence of 2 positive finite"),
    (lambda: C.check_sigmas("gs", torch.tensor([1.0, math.nan]), 2), ValueError, "got [1.0, nan]"),
    (lambda: C.check_numbers("t", {1: 2}), TypeError, "t must be a sequence of finite numbers or a 1-D tensor, got dict"),
    (lambda: C.check_tensor("x", [1], dims=4, layout="(B, C, H, W)"), TypeError,
     "x must be a torch.Tensor of shape (B, C, H, W), got list"),
    (lambda: C.check_tensor("x", torch.zeros(2, 3), dims=(3, 4)), ValueError, "x must be 3-D or 4-D, got shape (2, 3)"),
    (lambda: C.check_tensor("x", torch.zeros(1, 1, 1, dtype=torch.int64), dims=3, dtypes=(torch.float32,)), TypeError,
     "x must have dtype float32, got torch.int64"),
], ids=lambda x: x if isinstance(x, str) else "")
def test_rules(call, exc, words):
    with pytest.raises(exc, match=re.escape(words)):
        call()


def test_values_come_back_normalised():
    assert C.check_positive("s", 3) == 3.0 and isinstance(C.check_positive("s", 3), float)
    assert C.check_positive("s", torch.tensor(2.5)) == 2.5
    assert C.check_tree_height(None, allow_none=True) is None
    assert C.check_tree_height(C.MAX_TREE_HEIGHT) == C.MAX_TREE_HEIGHT
    assert C.check_numbers("t", 2.0, allow_scalar=True).tolist() == [2.0]
    t = C.check_sigmas("gs", (1, 2.5), 2)
    assert t.dtype == torch.float64 and t.tolist() == [1.0, 2.5]


def _entry_points(random_inputs):
    """Every public way to run the filter, each taking the settings as keywords."""
    v, g = random_inputs(1, 2, 3, 8, 9)
    vt, gt = random_inputs(1, 2, 3, 8, 9, T=2)
    return {
        "function": lambda **kw: adaptive_manifold_filter(v, g, **{"sigma_s": 4.0, "sigma_r": 0.3, **kw}),
        "module": lambda **kw: AdaptiveManifoldFilter(**{"sigma_s": 4.0, "sigma_r": 0.3, **kw})(v, g),
        "temporal": lambda **kw: temporal_adaptive_manifold_filter(vt, gt, [0, 1], [0.5],
                                                                   **{"sigma_s": 4.0, "sigma_r": 0.3, **kw}),
        "temporal module": lambda **kw: TemporalAdaptiveManifoldFilter(**{"sigma_s": 4.0, "sigma_r": 0.3, **kw})(
            vt, gt, [0, 1], [0.5]),
    }


SAME_ERROR = [
    ({"sigma_s": "4"}, TypeError, "sigma_s must be a finite number > 0, got str"),
    ({"sigma_r": -0.3}, ValueError, "sigma_r must be a finite number > 0, got -0.3"),
    ({"tree_height": 0}, ValueError, "tree_height must be an int in [1, 30], got 0"),
    ({"tree_height": 2.5}, TypeError, "tree_height must be an int in [1, 30], got float"),
    ({"power_iterations": -2}, ValueError, "power_iterations must be an int >= 0, got -2"),
    ({"guide_sigmas": [1.0, 0.0, 1.0]}, ValueError, "guide_sigmas must be a sequence of"),
    ({"guide_sigmas": ["1", 1.0, 1.0]}, TypeError, "guide_sigmas must be a sequence of"),
    ({"backend": "gpu"}, ValueError, "backend must be one of ('auto', 'cpp', 'torch'), got 'gpu'"),
]


@pytest.mark.parametrize("bad,exc,words", SAME_ERROR, ids=[str(b[0]) for b in SAME_ERROR])
def test_every_entry_point_gives_the_same_error(random_inputs, bad, exc, words):
    for name, run in _entry_points(random_inputs).items():
        with pytest.raises(exc, match=re.escape(words)):
            run(**bad)


def test_the_op_and_the_schedule_follow_the_same_rules(random_inputs):
    v, g = random_inputs(1, 2, 3, 8, 9)
    op = torch.ops.torchmanifold.adaptive_manifold
    with pytest.raises(ValueError, match=re.escape("sigma_r must be a finite number > 0, got -0.3")):
        op(v, g, 4.0, -0.3, 2, 3, False)
    with pytest.raises(ValueError, match=re.escape("tree_height must be an int in [1, 30], got 0")):
        op(v, g, 4.0, 0.3, 0, 3, False)
    with pytest.raises(TypeError, match=re.escape("sigma_s must be a finite number > 0, got str")):
        BandwidthSchedule("8")
    with pytest.raises(ValueError, match=re.escape("alpha must be a finite number in (0, 1], got 1.5")):
        BandwidthSchedule(8.0, alpha=1.5)
