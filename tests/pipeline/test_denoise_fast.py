"""The denoiser's fused C++ frame-step kernels (torchmanifold/pipeline/_fast.py) against the PyTorch
stages they replace (the reference, run under ``_fast.reference()``): stage by stage on random, rendered
and hazard inputs, the whole frame step, thread-count invariance, and the ops' argument errors."""
import math

import pytest
import torch

from _pipeline_data import FEATURES, load_clip
from torchmanifold.pipeline import DenoiseSettings, denoise_frames
from torchmanifold.pipeline import _fast
from torchmanifold.pipeline import denoise as D
from torchmanifold.pipeline import selection as SEL
from torchmanifold.pipeline import filter as FL
from torchmanifold.pipeline import footprint as FP

pytestmark = pytest.mark.skipif(not _fast.enabled(torch.zeros(1)), reason="fused kernels not built")


def _both(fn, *args, **kw):
    out = fn(*args, **kw)
    with _fast.reference():
        ref = fn(*args, **kw)
    return out, ref


def _same(a, b):
    torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)


@pytest.fixture(scope="module")
def frame(mitsuba_dir):
    """One rendered 1-spp frame (128x128 crop) with its features, and the stage inputs derived from it."""
    c, f = load_clip(mitsuba_dir, "frame", [0], crop=(slice(64, 192), slice(64, 192)))
    cc, ff, mask, _, _ = D._sanitize(c, f, None)
    alb, flat = D._demodulation_albedo(ff, FEATURES, DenoiseSettings())
    return {"c": c, "f": f, "e": cc / alb, "mask": mask, "flat": flat}


def _hazards(seed=0):
    """(name, e, mask) inputs that break naive kernels: non-finite and masked samples, flat and black
    frames, fireflies, images smaller than any window."""
    g = torch.Generator().manual_seed(seed)
    e = torch.rand(2, 3, 20, 23, generator=g) * 2
    m = (torch.rand(2, 1, 20, 23, generator=g) > 0.3).float()
    fire = e.clone()
    fire[:, :, 5, 7] = 1e6
    one = torch.zeros_like(m)
    one[:, :, 3, 4] = 1.0
    return [("random", e, m), ("all_masked", e, torch.zeros_like(m)), ("one_valid", e, one),
            ("constant", torch.full_like(e, 0.7), m), ("black", torch.zeros_like(e), m), ("fireflies", fire, m),
            ("tiny", e[:1, :, :2, :3].contiguous(), m[:1, :, :2, :3].contiguous()),
            ("pixel", e[:1, :, :1, :1].contiguous(), torch.ones(1, 1, 1, 1))]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_normalise_guard_equals_reference_bitwise(frame, dtype):
    cases = _hazards() + [("rendered", frame["e"], frame["mask"])]
    for name, e, m in cases:
        e, m = e.to(dtype), m.to(dtype)
        g = torch.Generator().manual_seed(1)
        num = torch.rand(e.shape, generator=g, dtype=dtype) * e
        den = torch.rand(m.shape, generator=g, dtype=dtype) * m
        # around the least support (denoise._min_support): float32's 1.2e-5 and float64's 1e-8
        den.view(-1)[1:5] = torch.tensor([2e-5, 1e-6, 1e-9, 0.0], dtype=dtype)[:den.numel() - 1]
        num[..., 0, 0] = math.nan  # a NaN result stays NaN through the guard
        for sigma_s in (0.5, 2.0, 8.0, 40.0):  # radius 1 to wider than the image
            filt = D._Filter(torch.zeros(e.shape[0], 1, *e.shape[2:], dtype=dtype), torch.ones(e.shape[0], 1),
                             DenoiseSettings(), list(range(e.shape[0])), list(range(e.shape[0])), sigma_s)
            out, ref = _both(filt.normalise, num, den, e, m)
            _same(out, ref)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_window_normalise_guard_equals_reference_bitwise(dtype):
    """A query mixing a window of frames (space-time): the fallback and bounds come from the window."""
    for name, e, m in _hazards():
        if e.shape[0] < 2:
            continue
        e, m = e.to(dtype), m.to(dtype)
        g = torch.Generator().manual_seed(2)
        num = torch.rand(1, *e.shape[1:], generator=g, dtype=dtype)
        den = torch.rand(1, 1, *e.shape[2:], generator=g, dtype=dtype) * m[:1]
        den.view(-1)[1:5] = torch.tensor([2e-5, 1e-6, 1e-9, 0.0], dtype=dtype)[:den.numel() - 1]
        num[..., 0, 0] = math.nan
        st = DenoiseSettings(temporal_radius=1, mode="spacetime")
        for q, sigma_s in ((0.0, 0.5), (1.0, 8.0), (0.5, 40.0)):  # a frame, and between frames
            filt = D._Filter(torch.zeros(e.shape[0], 1, *e.shape[2:], dtype=dtype), torch.ones(e.shape[0], 1), st,
                             [0.0, 1.0], [q], sigma_s)
            out, ref = _both(filt.normalise, num, den, e, m)
            _same(out, ref)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_window_bounds_equals_reference_bitwise(dtype):
    """The window's largest valid value and largest minus valid value at each query, in one C++ pass: the
    same bits as the PyTorch maxima, with masked and unmasked NaN and infinities, no valid sample in a
    window, windows of one to three frames and queries between frames."""
    g = torch.Generator().manual_seed(4)
    T, H, W = 4, 6, 7
    e = torch.randn(T, 3, H, W, generator=g, dtype=dtype)
    m = (torch.rand(T, 1, H, W, generator=g) > 0.3).to(dtype)
    e[0, 0, 0, :3] = torch.tensor([math.nan, math.inf, -math.inf], dtype=dtype)
    m[1, 0, 0, 1] = math.nan
    m[:, 0, 2, 2] = 0.0  # no valid sample anywhere
    e[2, 1, 3, 3] = math.nan
    for radius in (0, 1, 2):
        st = DenoiseSettings(temporal_radius=radius, mode="spacetime")
        for qt in ([0.0, 1.0, 2.0, 3.0], [0.5, 2.25]):
            filt = D._Filter(torch.zeros(T, 1, H, W, dtype=dtype), torch.ones(T, 1), st,
                             [0.0, 1.0, 2.0, 3.0], qt, 2.0)
            (hi, nlo), (ref_hi, ref_nlo) = _both(filt.window_bounds, e, m)
            _same(hi, ref_hi)
            _same(nlo, ref_nlo)


def test_kuwahara_log_radiance_equals_reference_bitwise(frame):
    for name, e, m in _hazards() + [("rendered", frame["e"], frame["mask"])]:
        for dtype in (torch.float32, torch.float64):
            out, ref = _both(D._log_radiance, e.to(dtype), m.to(dtype))
            _same(out, ref)


def test_kuwahara_chromaticity_equals_reference_bitwise(frame):
    """The colour-alone guide's chromaticity from the samples: each channel its own Kuwahara windows."""
    for name, e, m in _hazards() + [("rendered", frame["e"], frame["mask"])]:
        for dtype in (torch.float32, torch.float64):
            out, ref = _both(lambda x, w: D._kuwahara3(D._chromaticity(x, w)), e.to(dtype), m.to(dtype))
            _same(out, ref)
            chroma = D._chromaticity(e.to(dtype), m.to(dtype))
            one = torch.cat([D._kuwahara3(c) for c in chroma.split(1, 1)], 1)
            _same(out, one)


def test_footprint_average_equals_reference(frame):
    for name, e, m in _hazards() + [("rendered", frame["e"], frame["mask"])]:
        for sigma in (0.5, 1.2):
            out, ref = _both(FP._footprint_average, e * m, sigma)
            torch.testing.assert_close(out, ref, rtol=2e-5, atol=1e-7, equal_nan=True, msg=name)
    out, ref = _both(FP._footprint_average, frame["e"].double(), 0.5)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=0)


def test_along_edges_equals_reference(frame):
    """The structure tensor's directions and the average along them, fused, against the PyTorch stage:
    float rounding apart (sin, cos, atan2, exp and the bilinear taps' order)."""
    for name, e, m in _hazards() + [("rendered", frame["e"], frame["mask"])]:
        x = e * m
        d, d_ref = _both(FP._edge_directions, x)
        torch.testing.assert_close(d[:, 0], d_ref[:, 0], rtol=1e-4, atol=1e-6, msg=name)
        # a direction is defined up to sign, and only where the tensor is not isotropic
        sure = d_ref[:, 0] > 1e-3
        dot = (d[:, 1] * d_ref[:, 1] + d[:, 2] * d_ref[:, 2]).abs()
        assert bool((dot[sure] > 1 - 1e-4).all()), name
        g = torch.Generator().manual_seed(1)
        widths = [torch.rand(x.shape[0], 1, *x.shape[2:], generator=g) * s for s in (2.0, 0.5)]
        images = [x, 3 * x.flip(-1) + 0.1]  # two images along the same directions, each its own width
        for a, b in zip(*_both(FP._along_edges, images, widths, d_ref)):
            torch.testing.assert_close(a, b, rtol=2e-5, atol=1e-6, equal_nan=True, msg=name)
    d = FP._edge_directions(frame["e"])
    d[:, 1:, 5, 7] = math.nan  # a direction that is NaN sends its taps to a pixel inside the image
    out = FP._along_edges([frame["e"]], [torch.full_like(d[:, :1], 2.0)], d)[0]
    assert bool(torch.isfinite(out).all())
    x = frame["e"].double()
    for tensor_sigma in (FP._EDGE_TENSOR_SIGMA, 2.7):  # the outputs' and a pilot's (_pilot_along_edges)
        d = FP._edge_directions(x, tensor_sigma)
        with _fast.reference():
            torch.testing.assert_close(d, FP._edge_directions(x, tensor_sigma), rtol=1e-9, atol=1e-10)
    out, ref = _both(FP._along_edges, [x], [torch.full_like(x[:, :1], 1.3)], d)
    torch.testing.assert_close(out[0], ref[0], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("with_level", [False, True])
def test_bandwidth_selection_blend_equals_reference(frame, with_level):
    """_select_bandwidth with its cross-validated errors, pooling and softmax blend in C++."""
    st = DenoiseSettings()
    e, m = frame["e"], frame["mask"].clone()
    m[..., :20, :20] = 0.0  # a block the caller fills (flat pixels): no weight, its output not used
    guide, sig, _ = D._guide(frame["f"], FEATURES, e, m, st)
    level = e.clamp_min(0) if with_level else None
    out, ref = _both(D._select_bandwidth, e, m, guide, sig, st, [0.0], [0.0], st.sigma_s, 1.0, level)
    # float32 weights exp(-z^2 / 2) of pooled errors summed in another order: a blend may move by a few
    # 1e-5 (2 of this frame's 49152 values by 1.2e-5 once the guide's positions were centred)
    torch.testing.assert_close(out * m, ref * m, rtol=3e-5, atol=1e-6 * float(ref.abs().mean()))


def _evidence_case(frame):
    """One query's candidates on the rendered frame and two neighbours' residual planes (its own, scaled by
    random factors of 0.5-1.5 per pixel), with per-pixel weights that run from 0 to 1."""
    st = DenoiseSettings()
    e, m = frame["e"], frame["mask"]
    guide, sig, _ = D._guide(frame["f"], FEATURES, e, m, st)
    c = SEL._bandwidth_candidates(e, m, guide, sig, st, [0.0], [0.0], st.sigma_s, 1.0, None)
    g = torch.Generator().manual_seed(3)
    planes = c.residuals()
    others = torch.stack([planes * (0.5 + torch.rand(planes.shape, generator=g)) for _ in range(2)])
    weights = torch.rand(2, 1, 1, *e.shape[2:], generator=g)
    return c, others, weights


def test_residual_planes_equal_reference(frame):
    """A query's residual planes for its neighbours (_cv_residuals) as the PyTorch residuals, NaN predictions
    (no support) resolved alike."""
    c = _evidence_case(frame)[0]
    preds = [p.clone() for p in c.preds]
    preds[0][..., 5:9, 5:9] = math.nan
    out, ref = _both(SEL._residual_planes, preds, c.e, c.weight, c.mask)
    assert out.shape == (len(preds) + 1, 1, 1, *c.e.shape[2:])
    torch.testing.assert_close(out, ref, rtol=1e-6, atol=0)


def test_blend_with_neighbours_evidence_equals_reference(frame):
    """The blend that pools the neighbours' residuals in C++ as in PyTorch; weights of 0 lend nothing (the
    bytes of no evidence), and evidence does move the blend."""
    c, others, weights = _evidence_case(frame)
    out, ref = _both(c.blend, 1.0, others, weights)
    torch.testing.assert_close(out, ref, rtol=3e-5, atol=1e-6 * float(ref.abs().mean()))
    _same(c.blend(1.0, others, torch.zeros_like(weights)), c.blend(1.0))
    assert float((out - c.blend(1.0)).abs().max()) > 1e-3 * float(ref.abs().mean())


def test_cv_halves_and_split_equal_the_pytorch_stack_bitwise(frame):
    e, m = frame["e"], frame["mask"].clone()
    m[..., :20, :20] = 0.0
    half = FL._halves(e.shape, e.device).to(e.dtype)
    _same(_fast.cv_halves(e, m), torch.cat([p for h in (half, 1 - half) for p in (e * (m * h), m * h)], 1))
    T, H, W = e.shape[0], *e.shape[2:]
    y = torch.rand(T, 8, H, W, generator=torch.Generator().manual_seed(3)) * (torch.rand(T, 8, H, W) > 0.1)
    y[:, 3, 0, :4] = y[:, 7, 0, 4:8] = torch.tensor([2e-5, 1e-6, 1e-9, 0.0])  # around float32's least support
    pred, num, den = _fast.cv_split(y)
    with _fast.reference():
        ref = FL._split_halves(y)
    for a, b in zip((pred, num, den), ref):
        _same(a, b)
    y = y.view(T, 2, 4, H, W)
    n, d = y[:, :, :3], y[:, :, 3:]
    on, od = torch.where(half > 0, n[:, 1], n[:, 0]), torch.where(half > 0, d[:, 1], d[:, 0])
    ok = od > FL._min_support(torch.float32)
    _same(pred, torch.where(ok, on / torch.where(ok, od, 1.0), float("nan")))  # NaN: no support
    assert bool(pred[:, :, 0, :4].isnan().any()) and not bool(pred.isnan().all())
    _same(num, n.sum(1))
    _same(den, d.sum(1))


def test_sanitize_equals_reference_bitwise(frame):
    c, f = frame["c"].clone(), frame["f"].clone()
    c[0, 0, 3, 4], c[0, 1, 5, 5], c[0, 2, 7, 1], f[0, 4, 9, 9], f[0, 0, 3, 4] = \
        math.nan, math.inf, -math.inf, math.nan, math.inf
    for args in ((c, f, None), (c.double(), f.double(), 0.1 * c.double()), (c, f[:, :0], None)):
        out, ref = _both(D._sanitize, *args)
        for a, b in zip(out[:4], ref[:4]):
            if a is not None:
                _same(a, b)
        assert out[4] == ref[4] and out[4]["nonfinite_color"] == 3


def test_footprint_albedo_equals_reference(frame):
    alb, flat = D._demodulation_albedo(frame["f"], FEATURES, DenoiseSettings())
    flat = flat.clone()
    flat[..., :9, :9] = True  # a flat block at the border: its neighbours average without it
    for a, fl in ((alb, flat), (alb, torch.ones_like(flat)), (alb[..., :3, :2], flat[..., :3, :2])):
        for sigma in (0.5, 1.5):
            out, ref = _both(FP._footprint_albedo, a, fl, sigma)
            torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-7)


def test_normalised_blur_equals_reference(frame):
    """Sparse weights (flat pixels' own average), none at all, non-finite values under weight 0, one
    channel and float64, against the PyTorch stage and a brute-force normalised Gaussian."""
    e, g = frame["e"], torch.Generator().manual_seed(9)
    w = (torch.rand(e.shape[0], 1, *e.shape[2:], generator=g) > 0.97).to(e.dtype)
    bad = e.clone()
    bad[:, :, 5, 5] = math.nan
    bad[:, :, 6, 6] = math.inf
    w_bad = w.clone()
    w_bad[:, :, 5:7, 5:7] = 0.0
    for x, wt, sigma in ((e, w, 2.0), (e, w * 0, 1.0), (bad, w_bad, 4.0), (e[:, :1], w + 0.5, 0.7),
                         (e.double(), w.double(), 2.0)):
        out, ref = _both(FP._normalised_blur, x, wt, sigma)
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6, equal_nan=True)
        assert bool(torch.isfinite(out[wt.expand_as(out) > 0]).all())
    x, wt, sigma = e[:1, :, :12, :10].double(), w[:1, :, :12, :10].double() + 0.1, 1.5
    H, W = x.shape[-2:]
    k = SEL._gaussian_taps(sigma, torch.float64)
    r = (k.numel() - 1) // 2
    brute = torch.zeros_like(x)
    for i in range(H):
        for j in range(W):  # replicate borders: an outside tap reads the nearest edge pixel
            ys, xs = (torch.arange(-r, r + 1) + i).clamp(0, H - 1), (torch.arange(-r, r + 1) + j).clamp(0, W - 1)
            kk = k[:, None] * k[None, :]
            wv = wt[0, 0][ys][:, xs] * kk
            brute[0, :, i, j] = (x[0][:, ys][:, :, xs] * wv).sum((1, 2)) / wv.sum()
    torch.testing.assert_close(FP._normalised_blur(x, wt, sigma), brute)


def test_quantiles_equal_torch_bitwise():
    g = torch.Generator().manual_seed(2)
    for v in (torch.randn(3, 2, generator=g), torch.randn(3, 1001, generator=g), torch.zeros(2, 50),
              torch.randint(0, 4, (3, 999), generator=g).float()):  # many ties
        q = [0.0, 0.01, 0.5, 0.99, 1.0]
        _same(_fast.quantiles(v, q), torch.quantile(v.double(), torch.tensor(q, dtype=torch.float64), dim=1))
    v = torch.randn(2, 30, generator=g)
    v[1, 4] = math.nan
    _same(_fast.quantiles(v, [0.5]), torch.quantile(v.double(), torch.tensor([0.5], dtype=torch.float64), dim=1))


@pytest.mark.parametrize("name", ["rendered", "hazards"])
def test_frame_step_equals_reference(frame, name):
    """The whole denoise_frames call; on the rendered frame and one with NaN/inf samples, black and flat
    (not demodulated) regions, fireflies."""
    c, f = frame["c"], frame["f"]
    if name == "hazards":
        c, f = c.clone(), f.clone()
        c[0, :, 10:20, 10:20] = 0.0
        c[0, 0, 30, 30], c[0, 1, 31, 40], c[0, 2, 50, 50] = math.nan, math.inf, -math.inf
        c[0, :, 60, 60] = 500.0
        f[0, 3, 70, 70] = math.nan
        f[0, :3, 80:100, 80:100] = 0.0  # albedo 0: flat pixels, filtered among themselves
    out, ref = _both(denoise_frames, c, f, FEATURES)
    if name == "rendered":
        torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-4 * float(ref.abs().mean()))
        return
    # beside the flat block, a discrete choice downstream of the flat pixels' blur (whose order of sums
    # differs: a few ulp) can turn those ulp into a step at a pixel: at most a pixel in 10000 beyond 1e-3,
    # none beyond 3%
    scale = ref.abs() + float(ref.abs().mean())
    far = (out - ref).abs() > 1e-3 * scale
    assert int(far.any(1).sum()) <= max(1, ref[0, 0].numel() // 10000), int(far.any(1).sum())
    assert float(((out - ref).abs() / scale).max()) < 0.03


def test_same_pixel_equals_reference_bitwise(mitsuba_dir):
    """_same_pixel in C++, step by step in the PyTorch stage's float operations: the same decisions, bit for
    bit, on rendered world positions (a panning clip's frames), on a still plane's jittered samples and on
    degenerate ones (NaN, all equal, one line)."""
    from test_denoise import _plane_positions

    _, f = load_clip(mitsuba_dir, "frame", [0, 1, 2], crop=(slice(64, 192), slice(64, 192)))
    P = f[:, FEATURES.index("P.X"):FEATURES.index("P.Z") + 1]
    plane = _plane_positions(24, 30).float()
    still = _plane_positions(24, 30, seed=1).float()
    panned = _plane_positions(24, 30, (0.0, 0.6), seed=2).float()
    holes = torch.where(still > 1.0, still, math.nan)
    cases = [(P[1], [P[0], P[2]]), (plane, [still, panned]), (plane.double(), [still.double()]),
             (torch.zeros(3, 8, 9), [torch.zeros(3, 8, 9)]), (plane, [holes]),
             (torch.ones(3, 1, 5) * torch.arange(5.0), [plane[:, :1, :5]])]
    for p, others in cases:
        out, ref = _both(FP._same_pixel, p, others)
        assert len(out) == len(ref) == len(others)
        for a, b in zip(out, ref):
            assert a.dtype == b.dtype == torch.bool and torch.equal(a, b)
    assert bool(_both(FP._same_pixel, plane, [still])[0][0].any())  # a still view is found at all


def test_box_mean_equals_reference_bitwise():
    """_box_mean in C++ sums in the PyTorch stage's order: the same bits for every box, on images down to one
    pixel wide, stacked planes of any leading shape, both dtypes, with NaN and infinite values."""
    g = torch.Generator().manual_seed(11)
    for shape in [(2, 3, 17, 23), (3, 1, 5), (4, 9, 1), (1, 1), (2, 2, 2, 6, 7)]:
        for dtype in (torch.float32, torch.float64):
            scale = 10.0 ** torch.randint(-3, 4, shape, generator=g)
            x = torch.randn(shape, generator=g, dtype=dtype) * scale
            x.view(-1)[:: 7] = math.nan
            x.view(-1)[3:: 11] = math.inf
            for r in (0, 1, 2, 3):
                out, ref = _both(FP._box_mean, x, r)
                assert out.shape == x.shape and out.dtype == dtype
                _same(out, ref)


def test_footprint_samples_equals_reference_bitwise(mitsuba_dir):
    """_footprint_samples in C++, step by step in the PyTorch stage's float operations: the same sums and
    counts, bit for bit, on rendered world positions (a panning clip's frames), on jittered planes panned by
    a fraction of a pixel and by several, and on degenerate ones (NaN, all equal, one line, one pixel,
    positions whose squares overflow float32); searched at every pixel and at some: 0 elsewhere."""
    from test_denoise import _plane_positions

    _, f = load_clip(mitsuba_dir, "frame", [0, 1, 2], crop=(slice(64, 192), slice(64, 192)))
    P = f[:, FEATURES.index("P.X"):FEATURES.index("P.Z") + 1]
    alb = f[:, :3]
    plane = _plane_positions(24, 30).float()
    panned = torch.stack([_plane_positions(24, 30, (0.4, 0.6), seed=1),
                          _plane_positions(24, 30, (-2.3, 3.5), seed=2)])
    holes = torch.where(plane > 1.0, plane, math.nan)
    g = torch.Generator().manual_seed(3)
    cases = [(P[1], P[[0, 2]], alb[[0, 2]]), (plane, panned.float(), None), (plane.double(), panned, None),
             (torch.zeros(3, 8, 9), torch.zeros(1, 3, 8, 9), None), (holes, panned[:1].float(), None),
             (torch.ones(3, 1, 5) * torch.arange(5.0), plane[None, :, :1, :5], None),
             (plane[:, :1, :1], panned[:, :, :1, :1].float(), None),
             (plane * 1e25, panned.float() * 1e25, None)]  # float32 squares overflow
    for p, others, albedo in cases:
        if albedo is None:
            albedo = torch.rand(others.shape, generator=g, dtype=others.dtype)
        valid = (torch.rand(others[:, 0].shape, generator=g) > 0.2).to(p.dtype)
        (sums, counts), (ref_sums, ref_counts) = _both(FP._footprint_samples, p, others, albedo, valid)
        assert sums.shape == others.shape and counts.shape == (others.shape[0], 1, *others.shape[2:])
        _same(sums, ref_sums)
        _same(counts, ref_counts)
        search = torch.rand(valid.shape, generator=g) > 0.5
        (some_sums, some_counts), (ref_sums, ref_counts) = _both(FP._footprint_samples, p, others, albedo,
                                                                 valid, search)
        _same(some_sums, ref_sums)
        _same(some_counts, ref_counts)
        _same(some_sums, torch.where(search[:, None], sums, 0.0))
        _same(some_counts, torch.where(search[:, None], counts, 0.0))
    assert float(_both(FP._footprint_samples, plane, panned.float(), panned.float(),
                       torch.ones(2, 24, 30))[0][1].mean()) > 0.5  # the moved views' samples are found


def test_kernels_thread_count_invariant(frame):
    e, m = frame["e"], frame["mask"]
    calls = [
        lambda: _fast.normalise_guard(e, m + 0.5, e, m, 8),
        lambda: _fast.footprint_average(e, torch.tensor([[[[0.3]]]]), 0.5, 0.3),
        lambda: _fast.kuwahara3(e),
        lambda: _fast.cv_blend([e, 2 * e, 3 * e], [e, e + 1, e + 2], 1.5 * e, m + 1, m, 4.0, 0.5, 2.0),
        lambda: _fast.cv_blend([e, 2 * e, 3 * e], [e, e + 1, e + 2], 1.5 * e, m + 1, m, 4.0, 0.5, 2.0,
                               _fast.cv_residuals([e, 3 * e, 2 * e], e, m + 1, m)[None], m[None, :, 0]),
        lambda: _fast.cv_residuals([e, 2 * e, 3 * e], 1.5 * e, m + 1, m),
        lambda: _fast.quantiles(e.reshape(3, -1), [0.01, 0.99]),
        lambda: _fast.cv_halves(e, m),
        lambda: _fast.cv_split(torch.cat([e, m, 2 * e, m], 1)),
        lambda: _fast.normalised_blur(e, m, 0.5),
        lambda: _fast.sanitize(e.clone().index_fill_(3, torch.tensor([5]), math.nan), e)[:3],
        lambda: _fast.same_pixel(e[0], e[:1] + 0.01 * m[:1], 1.0, 0.25, 2),
        lambda: _fast.footprint_samples(e[0], e[:1] + 0.01 * m[:1], e[:1], m[:1, 0], m[:1, 0] > 0, 2),
        lambda: _fast.edge_directions(e, torch.tensor([[[[0.3]]]]), 1.0, 3.0),
        lambda: _fast.along_edges(torch.stack([e, 2 * e]), torch.tensor([0.3, 0.5]),
                                  torch.stack([m + 0.5, m]),
                                  _fast.edge_directions(e, torch.tensor([[[[0.3]]]]), 1.0, 3.0), 0.3),
    ]
    old = torch.get_num_threads()
    try:
        for call in calls:
            torch.set_num_threads(1)
            a = call()
            a = [t.clone() for t in (a if isinstance(a, tuple) else [a])]  # cv_halves reuses its workspace
            torch.set_num_threads(3)
            b = call()
            for x, y in zip(a, b if isinstance(b, tuple) else [b]):
                _same(x, y)
    finally:
        torch.set_num_threads(old)


def test_dispatch_only_for_cpu_float():
    x = torch.zeros(1, 3, 4, 4)
    assert _fast.enabled(x) and _fast.enabled(x.double())
    assert not _fast.enabled(x.half()) and not _fast.enabled(x, x.double())
    assert not _fast.enabled(x.clone().requires_grad_())  # the kernels have no backward
    with _fast.reference():
        assert not _fast.enabled(x)
    assert _fast.enabled(x)


def test_op_argument_errors():
    x = torch.zeros(1, 3, 4, 4)
    with pytest.raises(ValueError, match="den and mask must be"):
        torch.ops.torchmanifold._normalise_guard(x, x, x, x[:, :1], 2)
    with pytest.raises(ValueError, match="fallback, hi and nlo must match num"):
        torch.ops.torchmanifold._normalise_guard_bounds(x, x[:, :1], x, x[:, :2], x, 2)
    with pytest.raises(ValueError, match="x must be .T, 3, H, W."):
        torch.ops.torchmanifold._footprint_average(x[:, :2], torch.ones(1), 0.5, 0.3)
    with pytest.raises(ValueError, match="k must be .T,."):
        torch.ops.torchmanifold._footprint_average(x, torch.ones(2), 0.5, 0.3)
    with pytest.raises(ValueError, match="preds and fulls must be"):
        torch.ops.torchmanifold._cv_blend(x[None], x, x, x[:, :1], x[:, :1], 4.0, 0.5, 2.0)
    with pytest.raises(ValueError, match=r"others must be \(J, K \+ 1, T, H, W\)"):
        torch.ops.torchmanifold._cv_blend(x[None], x[None], x, x[:, :1], x[:, :1], 4.0, 0.5, 2.0, x[None],
                                          x[None, :, 0])
    with pytest.raises(ValueError, match="others and other_weights come together"):
        torch.ops.torchmanifold._cv_blend(x[None], x[None], x, x[:, :1], x[:, :1], 4.0, 0.5, 2.0, x[None])
    with pytest.raises(ValueError, match="q must lie in"):
        torch.ops.torchmanifold._quantiles(x.view(3, -1), [1.5])
    with pytest.raises(ValueError, match="float32 or float64"):
        torch.ops.torchmanifold._kuwahara3(x.half())
    with pytest.raises(ValueError, match="tensor_sigma must be > 0"):
        torch.ops.torchmanifold._edge_directions(x, torch.ones(1), 0.0, 3.0)
    with pytest.raises(ValueError, match="sigma must be .M, T, 1, H, W."):
        torch.ops.torchmanifold._along_edges(x[None], torch.ones(1, 1), x[None], x, 0.3)
    with pytest.raises(ValueError, match="directions must be .T, 3, H, W."):
        torch.ops.torchmanifold._along_edges(x[None], torch.ones(1, 1), x[None, :, :1], x[:, :2], 0.3)
    p, o = torch.zeros(3, 4, 4), torch.zeros(2, 3, 4, 4)
    every = torch.ones(2, 4, 4, dtype=torch.bool)
    with pytest.raises(ValueError, match="others must be .K, 3, H, W."):
        torch.ops.torchmanifold._footprint_samples(p, o[:, :, :3], o, torch.ones(2, 4, 4), every, 2)
    with pytest.raises(ValueError, match="albedo must be shaped like others"):
        torch.ops.torchmanifold._footprint_samples(p, o, o[:1], torch.ones(2, 4, 4), every, 2)
    with pytest.raises(ValueError, match="valid must be .K, H, W."):
        torch.ops.torchmanifold._footprint_samples(p, o, o, torch.ones(2, 1, 4, 4), every, 2)
    with pytest.raises(ValueError, match="search must be bool .K, H, W."):
        torch.ops.torchmanifold._footprint_samples(p, o, o, torch.ones(2, 4, 4), every.float(), 2)


def _op_samples():
    g = torch.Generator().manual_seed(5)
    T, H, W = 2, 9, 11
    e = torch.rand(T, 3, H, W, generator=g)
    m = (torch.rand(T, 1, H, W, generator=g) > 0.2).float()
    y = torch.rand(T, 8, H, W, generator=g) + 0.01  # every den supported: opcheck compares without NaN
    preds, fulls = torch.rand(3, T, 3, H, W, generator=g), torch.rand(3, T, 3, H, W, generator=g)
    return [("_normalise_guard", (e, m, e, m, 2)), ("_normalise_guard_bounds", (e, m, e, e, -e, 2)),
            ("_footprint_average", (e, torch.ones(T), 0.5, 0.3)),
            ("_kuwahara3", (e,)), ("_cv_blend", (preds, fulls, e, m, m, 4.0, 1.0, 2.0)),
            ("_cv_blend", (preds, fulls, e, m, m, 4.0, 1.0, 2.0, torch.rand(2, 4, T, H, W, generator=g),
                           torch.rand(2, T, H, W, generator=g))),
            ("_cv_residuals", (preds, e, m, m)),
            ("_quantiles", (e.view(T * 3, -1), [0.01, 0.99])), ("_cv_halves", (e, m)),
            ("_cv_halves_out", (e, m, torch.empty(T, 8, H, W))), ("_cv_split", (y,)),
            ("_sanitize", (e, torch.rand(T, 4, H, W, generator=g))), ("_normalised_blur", (e, m, 0.5)),
            ("_box_mean", (e, 2)), ("_window_bounds", (e, m, [0, 0, 1], [2, 1, 1])),
            ("_same_pixel", (e[0], e + 0.01, 1.0, 0.25, 2)),
            ("_footprint_samples", (e[0], e + 0.01, e, m[:, 0], m[:, 0] > 0, 2)),
            ("_edge_directions", (e, torch.ones(T), 1.0, 3.0)),
            ("_along_edges", (e[None], torch.ones(1, T), m[None] + 0.5, torch.rand(T, 3, H, W, generator=g),
                              0.3))]


@pytest.mark.parametrize("name,args", _op_samples(), ids=[f"{n}{len(a)}" for n, a in _op_samples()])
def test_opcheck(name, args):
    """Each private op's schema, fake kernel (shapes and dtypes under fake tensors) and dispatch agree
    with its CPU kernel."""
    torch.library.opcheck(getattr(torch.ops.torchmanifold, name).default, args)
