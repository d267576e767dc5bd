"""adaptive_manifold_filter / AdaptiveManifoldFilter: smoke, cardinality, exceptions, noncontiguous,
module == function, backends, guide scaling, automatic height, gradients of the pure-PyTorch path."""
import math
import re

import pytest
import torch

import torchmanifold
from torchmanifold.ops import (
    AdaptiveManifoldFilter,
    adaptive_manifold_filter,
    adaptive_manifold_torch,
    automatic_tree_height,
    bilateral_brute_force,
)
from torchmanifold.ops._reference import downsample, downsample_factor, upsample




def test_smoke(random_inputs, device):
    v, noise = random_inputs(1, 3, 4, 24, 20, edge=0.0, device=device)
    g = 0.05 * noise
    g[..., :12, :] += 1.0  # a step: two regions the filter must not mix
    out = torchmanifold.adaptive_manifold_filter(v, g, 6.0, 0.3)
    assert out.shape == v.shape and out.dtype == v.dtype and out.device == v.device and torch.isfinite(out).all()
    # it filters, and edge-aware: far closer to the exact joint bilateral filter it approximates than
    # the input is. Measured 0.07 of the input's distance (height 2); a 5x5 box blur, which mixes
    # the regions, gets 0.18, the input itself 1.
    exact = bilateral_brute_force(v.double().cpu(), g.double().cpu(), 6.0, 0.3)
    assert (out.double().cpu() - exact).abs().mean() < 0.12 * (v.double().cpu() - exact).abs().mean()


@pytest.mark.parametrize("shape", [(1, 1, 1, 1, 1), (2, 3, 5, 17, 9), (1, 4, 2, 1, 23), (3, 2, 64, 11, 13),
                                   (1, 3, 3, 33, 47)], ids=lambda s: "x".join(map(str, s)))
@pytest.mark.parametrize("height", [1, 2, 3])
def test_cardinality(random_inputs, shape, height, device):
    B, C, D, H, W = shape
    v, g = random_inputs(B, C, D, H, W, device=device)
    out = adaptive_manifold_filter(v, g, 5.0, 0.25, tree_height=height)
    assert out.shape == (B, C, H, W)
    assert torch.isfinite(out).all()


def test_unbatched_matches_batched(random_inputs, device):
    v, g = random_inputs(1, 3, 4, 19, 21, device=device)
    a = adaptive_manifold_filter(v[0], g[0], 6.0, 0.3)
    b = adaptive_manifold_filter(v, g, 6.0, 0.3)
    assert a.shape == v.shape[1:]
    torch.testing.assert_close(a, b[0], rtol=0, atol=0)


def test_batch_items_independent(random_inputs, device):
    v, g = random_inputs(3, 2, 3, 16, 18, device=device)
    whole = adaptive_manifold_filter(v, g, 5.0, 0.3, backend="torch")
    for b in range(3):
        one = adaptive_manifold_filter(v[b:b + 1], g[b:b + 1], 5.0, 0.3, backend="torch")
        torch.testing.assert_close(whole[b:b + 1], one, rtol=1e-6, atol=1e-6)


def test_noncontiguous(random_inputs, device):
    v, g = random_inputs(2, 3, 5, 20, 22, dtype=torch.float64, device=device)
    ref = adaptive_manifold_filter(v, g, 5.0, 0.3)
    v_nc = v.transpose(2, 3).contiguous().transpose(2, 3)
    g_nc = g.to(memory_format=torch.channels_last)
    assert not v_nc.is_contiguous() and not g_nc.is_contiguous()
    for backend in ("auto", "torch"):
        out = adaptive_manifold_filter(v_nc, g_nc, 5.0, 0.3, backend=backend)
        torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-10)


def test_module_equals_function(random_inputs, device):
    v, g = random_inputs(2, 3, 4, 16, 16, device=device)
    m = AdaptiveManifoldFilter(7.0, 0.2, tree_height=3, guide_sigmas=[0.1, 0.2, 0.3, 0.4],
                               adjust_outliers=True, power_iterations=4)
    f = adaptive_manifold_filter(v, g, 7.0, 0.2, tree_height=3, guide_sigmas=[0.1, 0.2, 0.3, 0.4],
                                 adjust_outliers=True, power_iterations=4)
    torch.testing.assert_close(m(v, g), f, rtol=0, atol=0)
    r = repr(m)
    for words in ("sigma_s=7.0", "sigma_r=0.2", "tree_height=3", "adjust_outliers=True", "power_iterations=4",
                  "guide_sigmas=(0.1, 0.2, 0.3, 0.4)", "backend='auto'"):
        assert words in r


def test_module_tensor_guide_sigmas(random_inputs):
    v, g = random_inputs(1, 2, 3, 12, 12)
    sig = torch.tensor([0.5, 1.0, 2.0])
    m = AdaptiveManifoldFilter(4.0, 0.3, guide_sigmas=sig)
    torch.testing.assert_close(m(v, g), adaptive_manifold_filter(v, g, 4.0, 0.3, guide_sigmas=[0.5, 1.0, 2.0]))


def test_guide_sigmas_scale_the_guide(random_inputs):
    v, g = random_inputs(1, 3, 3, 20, 20, dtype=torch.float64)
    sig = [0.1, 0.5, 2.0]
    scaled = g * (0.3 / torch.tensor(sig, dtype=torch.float64))[:, None, None]
    a = adaptive_manifold_filter(v, g, 6.0, 0.3, guide_sigmas=sig)
    b = adaptive_manifold_filter(v, scaled, 6.0, 0.3)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    c = adaptive_manifold_filter(v, g, 6.0, 0.3, guide_sigmas=torch.tensor(sig, dtype=torch.float64))
    torch.testing.assert_close(a, c, rtol=1e-12, atol=1e-12)
    # sigma_c == sigma_r leaves the guide as is
    torch.testing.assert_close(adaptive_manifold_filter(v, g, 6.0, 0.3, guide_sigmas=[0.3, 0.3, 0.3]),
                               adaptive_manifold_filter(v, g, 6.0, 0.3), rtol=0, atol=0)


# The paper's H = max(2, ceil((floor(log2 sigma_s) - 1) (1 - sigma_r))), worked by hand per case.
@pytest.mark.parametrize("ss,sr,expected", [
    (16, 0.4, 2),        # (4 - 1) * 0.6 = 1.8 -> 2
    (16, 0.2, 3),        # 3 * 0.8 = 2.4 -> 3
    (32, 0.1, 4),        # 4 * 0.9 = 3.6 -> 4
    (8, 0.2, 2),         # 2 * 0.8 = 1.6 -> 2
    (2, 0.9, 2),         # 0 * 0.1 = 0 -> at least 2
    (64, 0.05, 5),       # 5 * 0.95 = 4.75 -> 5
    (1, 3.0, 2),         # (0 - 1) * (-2) = 2 -> 2
    (2.0**40, 0.01, 30),  # 39 * 0.99 = 38.6 -> 39 -> capped at MAX_TREE_HEIGHT
])
def test_automatic_tree_height(ss, sr, expected):
    assert automatic_tree_height(ss, sr) == expected


def test_tree_height_none_uses_automatic_height(random_inputs):
    v, g = random_inputs(1, 3, 3, 24, 24)
    torch.testing.assert_close(adaptive_manifold_filter(v, g, 16.0, 0.2, tree_height=None),
                               adaptive_manifold_filter(v, g, 16.0, 0.2, tree_height=3), rtol=0, atol=0)


def test_backends_agree(random_inputs, device):
    v, g = random_inputs(2, 3, 6, 21, 26, dtype=torch.float64, device=device)
    for height in (1, 2, 3):
        a = adaptive_manifold_filter(v, g, 6.0, 0.25, height, adjust_outliers=True, backend="auto")
        b = adaptive_manifold_filter(v, g, 6.0, 0.25, height, adjust_outliers=True, backend="torch")
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)


def test_deterministic(random_inputs, device):
    v, g = random_inputs(1, 3, 17, 32, 32, device=device)
    for backend in ("auto", "torch"):
        a = adaptive_manifold_filter(v, g, 8.0, 0.3, 3, backend=backend)
        b = adaptive_manifold_filter(v, g, 8.0, 0.3, 3, backend=backend)
        assert torch.equal(a, b)


def test_downsample_factor_and_resampling():
    # sigma_s / df in [2, 4) low-res pixels, df a power of two, at most 256 sigma_r
    assert downsample_factor(16, 0.4) == 8 and downsample_factor(8, 0.2) == 4 and downsample_factor(4, 1) == 2
    assert downsample_factor(3, 0.4) == 1 and downsample_factor(64, 0.001) == 1
    assert downsample_factor(40, 1) == 16
    assert downsample_factor(64, 0.01) == 2  # the range's cap
    x = torch.rand(2, 3, 11, 13, dtype=torch.float64)
    d = downsample(x, 4)
    assert d.shape == (2, 3, 3, 4)
    torch.testing.assert_close(d[..., 2, 3], x[..., 8:, 12:].mean((-2, -1)))  # partial corner block
    torch.testing.assert_close(d[..., 1, 1], x[..., 4:8, 4:8].mean((-2, -1)))
    # bilinear at pixel centres, edge clamped, checked against a direct formula
    up = upsample(d, 4, (11, 13))
    yy = ((torch.arange(11) + 0.5) / 4 - 0.5).clamp(0, 2)
    xx = ((torch.arange(13) + 0.5) / 4 - 0.5).clamp(0, 3)
    y0, x0 = yy.floor().long(), xx.floor().long()
    y1, x1 = (y0 + 1).clamp(max=2), (x0 + 1).clamp(max=3)
    fy, fx = (yy - y0).double()[:, None], (xx - x0).double()[None, :]
    ref = (d[..., y0[:, None], x0] * (1 - fy) * (1 - fx) + d[..., y0[:, None], x1] * (1 - fy) * fx
           + d[..., y1[:, None], x0] * fy * (1 - fx) + d[..., y1[:, None], x1] * fy * fx)
    torch.testing.assert_close(up, ref)


def test_gradcheck_torch_backend(random_inputs, device):
    v, g = random_inputs(1, 2, 3, 6, 7, dtype=torch.float64, device=device)
    v.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: adaptive_manifold_filter(x, g, 3.0, 0.3, 2, adjust_outliers=True,
                                                                       backend="torch"), (v,))


def test_linear_in_values(random_inputs, device):
    v1, g = random_inputs(1, 3, 4, 14, 15, dtype=torch.float64, seed=1, device=device)
    v2, _ = random_inputs(1, 3, 4, 14, 15, dtype=torch.float64, seed=2, device=device)
    f = lambda x: adaptive_manifold_torch(x, g, 5.0, 0.3, 3, 10, True)  # noqa: E731
    torch.testing.assert_close(f(2.0 * v1 - 0.5 * v2), 2.0 * f(v1) - 0.5 * f(v2), rtol=1e-9, atol=1e-9)


BAD = [
    (lambda v, g: ([1.0], g, 4.0, 0.3), {}, TypeError, "values must be a torch.Tensor of shape (B, C, H, W)"),
    (lambda v, g: (v, None, 4.0, 0.3), {}, TypeError, "guide must be a torch.Tensor"),
    (lambda v, g: (v[0, 0], g, 4.0, 0.3), {}, ValueError, "values must be (B, C, H, W) or (C, H, W), got shape"),
    (lambda v, g: (v, g[0], 4.0, 0.3), {}, ValueError, "guide must be (B, D, H, W), got shape (3, 8, 9)"),
    (lambda v, g: (v, g[:, :, :5], 4.0, 0.3), {}, ValueError, "guide must share batch size and H, W"),
    (lambda v, g: (v, g[:1], 4.0, 0.3), {}, ValueError, "guide must share batch size"),
    (lambda v, g: (v, g[:, :0], 4.0, 0.3), {}, ValueError, "guide channels D >= 1"),
    (lambda v, g: (v, g.double(), 4.0, 0.3), {}, ValueError, "guide must have the dtype of values"),
    (lambda v, g: (v.int(), g.int(), 4.0, 0.3), {}, TypeError, "values must have dtype float16"),
    (lambda v, g: (v, g, 0.0, 0.3), {}, ValueError, "sigma_s must be a finite number > 0, got 0.0"),
    (lambda v, g: (v, g, -1.0, 0.3), {}, ValueError, "sigma_s must be a finite number > 0"),
    (lambda v, g: (v, g, 4.0, 0.0), {}, ValueError, "sigma_r must be a finite number > 0"),
    (lambda v, g: (v, g, 4.0, math.nan), {}, ValueError, "sigma_r must be a finite number > 0, got nan"),
    (lambda v, g: (v, g, math.inf, 0.3), {}, ValueError, "sigma_s must be a finite number > 0, got inf"),
    (lambda v, g: (v, g, "4", 0.3), {}, TypeError, "sigma_s must be a finite number > 0, got str"),
    (lambda v, g: (v, g, 4.0, True), {}, TypeError, "sigma_r must be a finite number > 0, got bool"),
    (lambda v, g: (v, g, 4.0, 0.3), {"tree_height": 0}, ValueError, "tree_height must be an int in [1, 30], got 0"),
    (lambda v, g: (v, g, 4.0, 0.3), {"tree_height": 31}, ValueError, "tree_height must be an int in [1, 30], got 31"),
    (lambda v, g: (v, g, 4.0, 0.3), {"tree_height": 2.0}, TypeError, "tree_height must be an int in [1, 30], got float"),
    (lambda v, g: (v, g, 4.0, 0.3), {"power_iterations": -1}, ValueError, "power_iterations must be an int >= 0"),
    (lambda v, g: (v, g, 4.0, 0.3), {"guide_sigmas": [1.0, 2.0]}, ValueError,
     "guide_sigmas must be a sequence of 3 positive finite numbers or a 1-D tensor, got 2"),
    (lambda v, g: (v, g, 4.0, 0.3), {"guide_sigmas": [1.0, 0.0, 1.0]}, ValueError, "3 positive finite numbers"),
    (lambda v, g: (v, g, 4.0, 0.3), {"guide_sigmas": torch.ones(3, 1)}, ValueError, "got a tensor of shape (3, 1)"),
    (lambda v, g: (v, g, 4.0, 0.3), {"guide_sigmas": "abc"}, TypeError, "guide_sigmas must be a sequence"),
    (lambda v, g: (v, g, 4.0, 0.3), {"guide_sigmas": [1.0, "2", 1.0]}, TypeError, "got str at index 1"),
    (lambda v, g: (v, g, 4.0, 0.3), {"backend": "cuda"}, ValueError, "backend must be one of ('auto', 'cpp', 'torch')"),
    (lambda v, g: (v, g, 4.0, 0.3), {"backend": 1}, TypeError, "backend must be one of"),
]


@pytest.mark.parametrize("make,kwargs,exc,words", BAD, ids=[b[3][:30] for b in BAD])
def test_exception(random_inputs, make, kwargs, exc, words):
    v, g = random_inputs(2, 3, 3, 8, 9)
    with pytest.raises(exc, match=re.escape(words)):
        adaptive_manifold_filter(*make(v, g), **kwargs)


def test_exception_module():
    with pytest.raises(ValueError, match="sigma_s"):
        AdaptiveManifoldFilter(-1.0, 0.3)
    with pytest.raises(ValueError, match="tree_height"):
        AdaptiveManifoldFilter(4.0, 0.3, tree_height=0)
    with pytest.raises(ValueError, match="backend"):
        AdaptiveManifoldFilter(4.0, 0.3, backend="gpu")
    with pytest.raises(ValueError, match="guide_sigmas must be a sequence of positive finite numbers"):
        AdaptiveManifoldFilter(4.0, 0.3, guide_sigmas=[1.0, -2.0])


def test_device_mismatch(random_inputs):
    v, g = random_inputs(1, 3, 3, 8, 8)
    with pytest.raises(ValueError, match="guide must be on the device of values"):
        adaptive_manifold_filter(v, g.to("meta"), 4.0, 0.3)
