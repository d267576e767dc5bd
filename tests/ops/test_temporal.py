"""temporal_adaptive_manifold_filter / TemporalAdaptiveManifoldFilter: window and space-time modes."""
import math
import re

import pytest
import torch

from torchmanifold.ops import (
    TemporalAdaptiveManifoldFilter,
    adaptive_manifold_filter,
    temporal_adaptive_manifold_filter,
    time_weights,
)




@pytest.fixture
def clip(random_inputs):
    """A float64 window of frames: values (B, T, C, H, W), guide (B, T, D, H, W)."""
    def make(B=1, T=3, C=3, D=4, H=18, W=20, seed=0, dtype=torch.float64, device="cpu"):
        return random_inputs(B, C, D, H, W, T=T, dtype=dtype, seed=seed, edge=0.6, device=device)
    return make


@pytest.mark.parametrize("mode", ["window", "spacetime"])
def test_smoke_and_cardinality(clip, mode, device):
    v, g = clip(B=2, T=4, device=device)
    out = temporal_adaptive_manifold_filter(v, g, [0, 1, 2, 3], [0.0, 1.5, 3.0], 5.0, 0.3, mode=mode)
    assert out.shape == (2, 3, 3, 18, 20) and out.dtype == v.dtype and torch.isfinite(out).all()
    one = temporal_adaptive_manifold_filter(v, g, torch.arange(4.0), 2.0, 5.0, 0.3, mode=mode)
    assert one.shape == (2, 1, 3, 18, 20)


def test_time_weights():
    w = time_weights(torch.tensor([0.0, 1.0, 2.0, 5.0], dtype=torch.float64),
                     torch.tensor([1.0, 100.0], dtype=torch.float64), 1.0)
    torch.testing.assert_close(w[0], torch.tensor([math.exp(-0.5), 1.0, math.exp(-0.5), math.exp(-8.0)],
                                                  dtype=torch.float64))
    assert w[1, 3] == 1.0 and torch.isfinite(w).all()  # a far query does not underflow to all zeros


def test_window_matches_spatial_filter_of_the_average(clip):
    v, g = clip(T=3)
    ft, q, st = [0.0, 1.0, 2.0], 0.6, 0.8
    w = torch.tensor([math.exp(-(t - q) ** 2 / (2 * st**2)) for t in ft], dtype=torch.float64)
    w = w / w.sum()
    va = (w[None, :, None, None, None] * v).sum(1)
    ga = (w[None, :, None, None, None] * g).sum(1)
    expect = adaptive_manifold_filter(va, ga, 6.0, 0.3, 2, adjust_outliers=True)
    out = temporal_adaptive_manifold_filter(v, g, ft, [q], 6.0, 0.3, sigma_t=st, mode="window",
                                            adjust_outliers=True)
    torch.testing.assert_close(out[:, 0], expect, rtol=1e-12, atol=1e-12)


def test_window_skips_nonfinite_frames(clip):
    v, g = clip(T=3)
    vb = v.clone()
    vb[0, 1, :, 4, 4] = math.nan
    out = temporal_adaptive_manifold_filter(vb, g, [0, 1, 2], [1.0], 5.0, 0.3)
    assert torch.isfinite(out).all()
    vb[0, :, :, 4, 4] = math.nan  # no finite sample left at the pixel: still finite
    assert torch.isfinite(temporal_adaptive_manifold_filter(vb, g, [0, 1, 2], [1.0], 5.0, 0.3)).all()


@pytest.mark.parametrize("adjust", [False, True])
def test_spacetime_single_frame_is_the_spatial_filter(clip, adjust, device):
    v, g = clip(B=2, T=1, device=device)
    out = temporal_adaptive_manifold_filter(v, g, [3.0], [3.0], 5.0, 0.25, mode="spacetime", tree_height=3,
                                            adjust_outliers=adjust, backend="torch")
    expect = adaptive_manifold_filter(v[:, 0], g[:, 0], 5.0, 0.25, 3, adjust_outliers=adjust, backend="torch")
    torch.testing.assert_close(out[:, 0], expect, rtol=0, atol=0)


def test_spacetime_identical_frames_equal_the_spatial_filter(clip, device):
    """Frames that are copies of one frame, weighted in time, give back that frame's filter."""
    v, g = clip(T=1, device=device)
    out = temporal_adaptive_manifold_filter(v.expand(-1, 3, -1, -1, -1), g.expand(-1, 3, -1, -1, -1), [0, 1, 2],
                                            [0.7], 5.0, 0.25, mode="spacetime")
    expect = adaptive_manifold_filter(v[:, 0], g[:, 0], 5.0, 0.25, backend="torch")
    torch.testing.assert_close(out[:, 0], expect, rtol=1e-10, atol=1e-10)


def test_spacetime_constant_values_exact_and_finite_with_nans(clip):
    _, g = clip(T=3)
    v = torch.full((1, 3, 3, 18, 20), 0.3217)
    out = temporal_adaptive_manifold_filter(v, g.float(), [0, 1, 2], [0.5, 2.0], 5.0, 0.1, mode="spacetime",
                                            adjust_outliers=True)
    assert torch.equal(out, v[:, :2])
    gb = g.clone()
    gb[0, 1, 2, 5, 5] = math.nan
    vb = torch.rand_like(g[:, :, :3])
    vb[0, 0, 1, 7, 7] = math.inf
    out = temporal_adaptive_manifold_filter(vb, gb, [0, 1, 2], [1.0], 5.0, 0.3, mode="spacetime",
                                            adjust_outliers=True)
    assert torch.isfinite(out).all()


def _moving_square(T=5, H=40, W=48, speed=6, noise=0.1, seed=1):
    frames = []
    for t in range(T):
        img = torch.full((1, H, W), 0.2)
        x0 = 6 + speed * t
        img[:, 12:28, x0:x0 + 12] = 0.9
        frames.append(img)
    clean = torch.stack(frames)[None]  # (1, T, 1, H, W)
    gen = torch.Generator().manual_seed(seed)
    return clean, clean + noise * torch.randn(clean.shape, generator=gen)


def test_spacetime_does_not_ghost_a_moving_square():
    clean, noisy = _moving_square()
    t = 2
    target = clean[0, t]
    # where the square was or will be but is not now: the ghost region
    ghost = (clean[0].amax(0) > 0.5) & (target < 0.5)
    errs = {}
    for mode in ("window", "spacetime"):
        out = temporal_adaptive_manifold_filter(noisy, clean, list(range(5)), [float(t)], 3.0, 0.2, mode=mode)[0, 0]
        errs[mode] = ((out - target)[ghost].square().mean().sqrt().item(),
                      (out - target).square().mean().sqrt().item())
    noisy_rmse = (noisy[0, t] - target).square().mean().sqrt().item()
    assert errs["window"][0] > 0.1  # the window average keeps the square's trail
    assert errs["spacetime"][0] < 0.3 * errs["window"][0]
    assert errs["spacetime"][1] < 0.3 * noisy_rmse  # and it still denoises (5 frames, sigma_s 3)


def test_module_equals_function(clip, device):
    v, g = clip(T=3, device=device)
    for mode in ("window", "spacetime"):
        m = TemporalAdaptiveManifoldFilter(5.0, 0.3, sigma_t=0.7, mode=mode, tree_height=3, adjust_outliers=True,
                                           guide_sigmas=[0.1, 0.2, 0.3, 0.4])
        f = temporal_adaptive_manifold_filter(v, g, [0, 1, 2], [1.2], 5.0, 0.3, sigma_t=0.7, mode=mode,
                                              tree_height=3, adjust_outliers=True, guide_sigmas=[0.1, 0.2, 0.3, 0.4])
        torch.testing.assert_close(m(v, g, [0, 1, 2], [1.2]), f, rtol=0, atol=0)
        assert f"mode='{mode}'" in repr(m) and "sigma_t=0.7" in repr(m)


def test_gradcheck_both_modes(clip):
    v, g = clip(T=2, C=1, D=2, H=5, W=6)
    v.requires_grad_(True)
    for mode in ("window", "spacetime"):
        assert torch.autograd.gradcheck(
            lambda x: temporal_adaptive_manifold_filter(x, g, [0, 1], [0.4], 3.0, 0.3, mode=mode, backend="torch"),
            (v,), fast_mode=True)


BAD = [
    (dict(values=torch.rand(1, 3, 8, 8)), ValueError, "values must be (B, T, C, H, W), got shape (1, 3, 8, 8)"),
    (dict(values=[1.0]), TypeError, "values must be a torch.Tensor of shape (B, T, C, H, W), got list"),
    (dict(guide=torch.rand(1, 2, 4, 8)), ValueError, "guide must be (B, T, D, H, W)"),
    (dict(guide=torch.rand(1, 3, 4, 8, 8)), ValueError, "guide must share B, T, H, W"),
    (dict(frame_times=[0, 1, 2]), ValueError, "frame_times must be a sequence of 2 finite numbers or a 1-D tensor, "
                                              "got 3"),
    (dict(frame_times=[0, math.nan]), ValueError, "frame_times must be a sequence of 2 finite numbers"),
    (dict(query_times=[]), ValueError, "query_times must be a sequence of finite numbers or a 1-D tensor, got 0"),
    (dict(query_times="1"), TypeError, "query_times must be a sequence of finite numbers or a 1-D tensor, got str"),
    (dict(sigma_t=0.0), ValueError, "sigma_t must be a finite number > 0, got 0.0"),
    (dict(sigma_t="1"), TypeError, "sigma_t must be a finite number > 0, got str"),
    (dict(tree_height=0), ValueError, "tree_height must be an int in [1, 30], got 0"),
    (dict(guide_sigmas=[1.0, 1.0]), ValueError, "guide_sigmas must be a sequence of 4 positive finite numbers"),
    (dict(mode="both"), ValueError, "mode must be one of ('window', 'spacetime'), got 'both'"),
    (dict(guide=torch.rand(1, 2, 4, 8, 8, dtype=torch.float64)), ValueError, "guide must have the dtype of values"),
]


@pytest.mark.parametrize("change,exc,words", BAD, ids=[b[2][:28] for b in BAD])
def test_exception(change, exc, words):
    args = dict(values=torch.rand(1, 2, 3, 8, 8), guide=torch.rand(1, 2, 4, 8, 8), frame_times=[0, 1],
                query_times=[0.5], sigma_s=4.0, sigma_r=0.3)
    args.update(change)
    with pytest.raises(exc, match=re.escape(words)):
        temporal_adaptive_manifold_filter(**args)
