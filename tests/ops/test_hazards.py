"""The hazards of docs/adaptive-manifolds.md: finite output, no NaN spreading, constants exact."""
import math

import pytest
import torch

from torchmanifold.ops import adaptive_manifold_filter, adaptive_manifold_torch
from torchmanifold.ops._reference import downsample, downsample_factor, recursive_lowpass, upsample

BACKENDS = ["auto", "torch"]




def _in_range(out, v, tol=1e-5):
    """The filter is a convex combination of samples (or the input): stays in each channel's range."""
    lo = v.amin((-2, -1), keepdim=True)
    hi = v.amax((-2, -1), keepdim=True)
    return bool(((out >= lo - tol) & (out <= hi + tol)).all())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("adjust", [False, True])
def test_nonfinite_samples_are_ignored(random_inputs, backend, adjust, device):
    v, g = random_inputs(2, 3, 4, 30, 34, device=device)
    vb, gb = v.clone(), g.clone()
    vb[0, 1, 10, 10] = math.nan
    vb[1, :, 3, 30] = math.inf
    gb[0, 2, 20, 5] = math.nan
    gb[1, :, 25, 12] = -math.inf
    out = adaptive_manifold_filter(vb, gb, 8.0, 0.3, 3, adjust_outliers=adjust, backend=backend)
    assert torch.isfinite(out).all()
    # a NaN and an Inf in the same place give the same result: the sample is dropped, not used
    vc, gc = vb.clone(), gb.clone()
    vc[0, 1, 10, 10] = -math.inf
    gc[0, 2, 20, 5] = math.inf
    torch.testing.assert_close(adaptive_manifold_filter(vc, gc, 8.0, 0.3, 3, adjust_outliers=adjust,
                                                        backend=backend), out, rtol=0, atol=0)
    # and the result does not depend on a dropped sample's other (finite) channels
    vd = vb.clone()
    vd[0, :, 10, 10] = torch.tensor([5.0, math.nan, -7.0])
    torch.testing.assert_close(adaptive_manifold_filter(vd, gb, 8.0, 0.3, 3, adjust_outliers=adjust,
                                                        backend=backend)[:, :, :8], out[:, :, :8], rtol=0, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_nan_pixel_is_filled_from_neighbours(backend):
    v = torch.full((1, 1, 16, 16), 0.5)
    v[..., 8, 8] = math.nan
    g = torch.zeros(1, 2, 16, 16)
    out = adaptive_manifold_filter(v, g, 4.0, 0.2, backend=backend)
    assert torch.equal(out[..., 8, 8], torch.tensor([[0.5]]))


@pytest.mark.parametrize("backend", BACKENDS)
def test_all_nonfinite_image(backend):
    v = torch.full((1, 3, 9, 9), math.nan)
    g = torch.full((1, 2, 9, 9), math.inf)
    out = adaptive_manifold_filter(v, g, 4.0, 0.2, 2, adjust_outliers=True, backend=backend)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_constant_guide_is_a_spatial_filter(random_inputs, backend):
    """Flat guide: one manifold (children have no theta mass), so the filter is the normalised spatial
    low-pass up(h(down(f))) -- computed here from the building blocks."""
    v, _ = random_inputs(1, 3, 1, 40, 36, dtype=torch.float64)
    g = torch.full((1, 5, 40, 36), 0.7, dtype=torch.float64)
    out = adaptive_manifold_filter(v, g, 12.0, 0.3, 3, adjust_outliers=True, backend=backend)
    df = downsample_factor(12.0, 0.3)
    expect = upsample(recursive_lowpass(downsample(v, df), 12.0 / df), df, (40, 36))
    torch.testing.assert_close(out, expect, rtol=1e-9, atol=1e-9)
    # a huge sigma_r makes any guide flat
    gr = torch.rand(1, 5, 40, 36, dtype=torch.float64)
    torch.testing.assert_close(adaptive_manifold_filter(v, gr, 12.0, 1e8, 3, backend=backend), expect,
                               rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_centre_pixel_and_zero_guide(random_inputs, backend):
    v, g = random_inputs(1, 3, 3, 31, 31)
    g[..., 15, 15] = 0.0
    out = adaptive_manifold_filter(v, g, 8.0, 0.2, 3, backend=backend)
    assert torch.isfinite(out).all() and _in_range(out, v)
    out = adaptive_manifold_filter(v, torch.zeros_like(g), 8.0, 0.2, 3, backend=backend)
    assert torch.isfinite(out).all() and _in_range(out, v)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("sigma_r", [1e-30, 0.01, 1e6])
def test_extreme_sigma_r(random_inputs, backend, sigma_r, device):
    v, g = random_inputs(1, 3, 3, 25, 27, device=device)
    for adjust in (False, True):
        out = adaptive_manifold_filter(v, g, 6.0, sigma_r, 3, adjust_outliers=adjust, backend=backend)
        assert torch.isfinite(out).all() and _in_range(out, v)


@pytest.mark.parametrize("backend", BACKENDS)
def test_far_from_every_manifold_returns_input(random_inputs, backend, device):
    """S0 underflows to 0 everywhere: the output is the input, exactly."""
    v, g = random_inputs(1, 3, 6, 20, 22, device=device)
    out = adaptive_manifold_filter(v, g, 6.0, 1e-30, 2, backend=backend)
    assert torch.equal(out, v)


@pytest.mark.parametrize("backend", BACKENDS)
def test_128_channel_random_guide(backend):
    gen = torch.Generator().manual_seed(3)
    v = torch.rand(1, 3, 24, 24, generator=gen)
    g = torch.randn(1, 128, 24, 24, generator=gen)
    for sr in (0.2, 3.0):
        out = adaptive_manifold_filter(v, g, 8.0, sr, 3, adjust_outliers=True, backend=backend)
        assert torch.isfinite(out).all() and _in_range(out, v)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("hw", [(1, 1), (1, 7), (5, 1), (3, 3), (17, 31)])
def test_tiny_and_odd_sizes(random_inputs, backend, hw, device):
    v, g = random_inputs(2, 2, 3, *hw, device=device)
    out = adaptive_manifold_filter(v, g, 16.0, 0.5, 3, adjust_outliers=True, backend=backend)
    assert out.shape == v.shape and torch.isfinite(out).all() and _in_range(out, v)
    if hw == (1, 1):
        assert torch.equal(out, v)  # a single pixel is its own average


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_types_accumulate_in_float32(random_inputs, backend, dtype):
    v, g = random_inputs(1, 3, 4, 28, 30)
    ref = adaptive_manifold_filter(v.to(dtype).float(), g.to(dtype).float(), 8.0, 0.05, 2, adjust_outliers=True,
                                   backend=backend)
    out = adaptive_manifold_filter(v.to(dtype), g.to(dtype), 8.0, 0.05, 2, adjust_outliers=True, backend=backend)
    assert out.dtype == dtype and torch.isfinite(out).all()
    # only the final rounding differs (sigma_r = 0.05: D / sigma_r^2 well past fp16's exp underflow)
    torch.testing.assert_close(out.float(), ref.to(dtype).float(), rtol=0, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_constant_values_exact(backend, dtype):
    gen = torch.Generator().manual_seed(5)
    guides = [torch.rand(2, 4, 19, 23, generator=gen), torch.randn(2, 64, 19, 23, generator=gen) * 10,
              torch.zeros(2, 1, 19, 23)]
    bad = torch.rand(2, 4, 19, 23, generator=gen)
    bad[0, 1, 3, 3] = math.nan
    guides.append(bad)
    cases = [(0.1234567, 0, 0.3, False), (-3.7e4, 1, 0.01, True), (1e-20, 2, 5.0, True), (0.0, 3, 0.3, True),
             (0.1234567, 3, 0.01, False), (-3.7e4, 0, 5.0, True)]
    for value, gi, sr, adjust in cases:
        v = torch.full((2, 3, 19, 23), value).to(dtype)
        out = adaptive_manifold_filter(v, guides[gi].to(dtype), 7.0, sr, 3, adjust_outliers=adjust, backend=backend)
        assert torch.equal(out, v), (value, gi, sr, adjust)


def test_constant_per_image_and_channel():
    v = torch.tensor([0.25, -1.5, 3.0])[None, :, None, None].expand(2, 3, 15, 16).clone()
    v[1] *= 7.0
    g = torch.rand(2, 6, 15, 16)
    assert torch.equal(adaptive_manifold_torch(v, g, 5.0, 0.2, 4, 10, True), v)


@pytest.mark.parametrize("backend", ["cpp", "torch"])
@pytest.mark.parametrize("sigma_r", [0.3, 0.1])
def test_underflowing_weights_stay_in_the_samples_range(mitsuba_dir, backend, sigma_r):
    # A real 1-spp frame filtered as irradiance with a sharp guide: many pixels lie so far from every
    # manifold that S and S0 are subnormal. Their ratio must not leave the range of the samples
    # (before the S0 floor, float32 gave -18 from samples in [0, 79]).
    from torchmanifold.io import read_exr

    d = read_exr(mitsuba_dir / "frame_0006.exr")
    stack = lambda names: torch.stack([torch.from_numpy(d[n]) for n in names])[None]  # noqa: E731
    albedo = stack(["albedo.R", "albedo.G", "albedo.B"])
    values = stack(["R", "G", "B"]) / albedo.clamp_min(1e-3)
    guide = torch.cat([albedo / 0.1, stack(["N.X", "N.Y", "N.Z"]) / 0.3, stack(["P.X", "P.Y", "P.Z"]) / 0.05], 1)
    for dtype in (torch.float32, torch.float64):
        out = adaptive_manifold_filter(values.to(dtype), guide.to(dtype), 5.0, sigma_r, backend=backend)
        lo, hi = values.amin((2, 3), keepdim=True), values.amax((2, 3), keepdim=True)
        slack = 1e-5 * (hi - lo)
        assert torch.isfinite(out).all()
        assert (out.double() >= lo - slack).all() and (out.double() <= hi + slack).all(), dtype
