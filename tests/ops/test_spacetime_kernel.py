"""The C++ CPU kernel of ``torchmanifold::spacetime_adaptive_manifold`` against its pure-PyTorch reference
(torchmanifold.ops.temporal.spacetime_torch, a second implementation of the same steps): equal to
rounding in float64 and to float32 noise on random and hazard inputs, bitwise the same for any thread
count, a PyTorch citizen (opcheck, fake tensors, torch.compile(fullgraph=True), gradients in values) and
the default of ``temporal_adaptive_manifold_filter(mode="spacetime")`` on CPU."""
import math

import pytest
import torch

from torchmanifold.ops import temporal_adaptive_manifold_filter
from torchmanifold.ops.temporal import spacetime_torch
from torchmanifold.timewindow import time_weights

op = torch.ops.torchmanifold.spacetime_adaptive_manifold.default
OP_NAME = "torchmanifold::spacetime_adaptive_manifold"


def _rel_err(a, b):
    return ((a.double() - b.double()).abs().max() / b.double().abs().max().clamp_min(1e-30)).item()


def _window(B=1, T=3, C=3, D=4, H=18, W=21, Q=2, dtype=torch.float64, seed=0, shift=2):
    """A clip whose guide has an edge that moves by ``shift`` pixels a frame, time weights of Q queries
    spread over the window, and each query's guide (linear between its frames, as the public function)."""
    gen = torch.Generator().manual_seed(seed)
    v = torch.rand(B, T, C, H, W, generator=gen, dtype=torch.float64)
    g = torch.rand(B, T, D, H, W, generator=gen, dtype=torch.float64) * 0.5
    for t in range(T):
        g[:, t, :, : H // 2 + shift * t - shift, :] += 1.0
    ft = torch.arange(T, dtype=torch.float64)
    qt = torch.linspace(0.0, T - 1.0, Q, dtype=torch.float64) + 0.25 * (Q > 1)
    w = time_weights(ft, qt, 0.8)
    from torchmanifold.timewindow import interpolate

    gq = torch.stack([interpolate(g, ft, float(q), dim=1) for q in qt], 1)
    return v.to(dtype), g.to(dtype), w.to(dtype), gq.to(dtype)


CASES = [  # (B, T, C, D, H, W, Q)
    (1, 1, 1, 1, 1, 1, 1),
    (1, 3, 3, 4, 18, 21, 2),
    (2, 2, 1, 1, 17, 9, 1),
    (1, 3, 7, 17, 20, 21, 1),
    (1, 4, 2, 3, 1, 19, 3),
]
SIGMAS = [(8.0, 0.3), (3.0, 0.1), (20.0, 0.6)]


@pytest.mark.parametrize("case", CASES, ids=lambda c: "x".join(map(str, c)))
@pytest.mark.parametrize("sigmas", SIGMAS, ids=lambda s: f"s{s[0]}r{s[1]}")
def test_matches_reference_float64(case, sigmas):
    B, T, C, D, H, W, Q = case
    v, g, w, gq = _window(B, T, C, D, H, W, Q, seed=H)
    for height in (1, 2, 3):
        for adjust in (False, True):
            args = (*sigmas, height, 5, adjust)
            got = op(v, g, w, gq, *args)
            ref = spacetime_torch(v, g, w, gq, *args)
            assert got.shape == (B, Q, C, H, W) and got.dtype == torch.float64
            assert _rel_err(got, ref) < 1e-10, (height, adjust)


@pytest.mark.parametrize("height", [1, 2, 3])
@pytest.mark.parametrize("sigma_s", [3.0, 5.0, 8.0, 16.0])  # downsampling factor 1, 2, 4, 8
def test_matches_reference_float32(height, sigma_s):
    """float32 kernel (vector paths, odd widths for their tails) against the float64 reference."""
    v, g, w, gq = _window(1, 3, 3, 5, 40, 75, 2, seed=int(sigma_s))
    got = op(v.float(), g.float(), w.float(), gq.float(), sigma_s, 0.4, height, 5, True)
    ref = spacetime_torch(v, g, w, gq, sigma_s, 0.4, height, 5, True)
    assert got.dtype == torch.float32
    assert _rel_err(got, ref) < 1e-5


def _hazards(dtype):
    v, g, w, gq = _window(1, 3, 3, 4, 30, 33, 2, dtype=dtype, seed=9)
    cases = {}
    vb = v.clone()
    vb[0, 1, 1, 5, 5] = math.nan
    vb[0, 0, 0, 7, 9] = math.inf
    vb[0, :, 2, 20, 20] = math.nan  # no finite sample of one channel at a pixel
    cases["nonfinite values"] = (vb, g, w, gq, 0.3, 8.0)
    gb = g.clone()  # a frame's guide, not the query's: those samples only stop splatting
    gb[0, 0, 2, 10, 10] = math.nan
    gb[0, 2, 0, 3, 3] = -math.inf
    cases["nonfinite frame guide"] = (v, gb, w, gq, 0.3, 8.0)
    qb = gq.clone()  # the query's guide: those pixels sit on the root manifold
    qb[0, 0, 1, 12, 12] = math.nan
    cases["nonfinite query guide"] = (v, g, w, qb, 0.3, 8.0)
    flat = torch.full_like(g, 0.5)
    cases["flat guides"] = (v, flat, w, flat[:, :2].clone(), 0.3, 8.0)
    wz = w.clone()
    wz[0, 1] = 0.0  # a frame that does not count for a query
    wz[1] = 0.0  # a query no frame counts for: the output is 0 (no weighted sample)
    cases["zero time weights"] = (v, g, wz, gq, 0.3, 8.0)
    cases["tiny sigma_r"] = (v, g, w, gq, 1e-4, 8.0)
    cases["huge sigma_r"] = (v, g, w, gq, 1e4, 8.0)
    cases["tiny sigma_s"] = (v, g, w, gq, 0.3, 0.05)
    cases["huge sigma_s"] = (v, g, w, gq, 0.3, 1e4)
    cases["constant values"] = (torch.full_like(v, 0.3217), g, w, gq, 0.3, 8.0)
    return cases


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hazards_match_reference(dtype):
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    for name, (v, g, w, gq, sigma_r, sigma_s) in _hazards(dtype).items():
        for height, adjust in ((1, True), (3, False), (3, True)):
            got = op(v, g, w, gq, sigma_s, sigma_r, height, 5, adjust)
            ref = spacetime_torch(v.double(), g.double(), w.double(), gq.double(), sigma_s, sigma_r, height, 5,
                                  adjust)
            assert torch.isfinite(got).all(), name
            assert _rel_err(got, ref) < tol, (name, height, adjust, _rel_err(got, ref))
    v, g, w, gq, *_ = _hazards(dtype)["constant values"]
    assert torch.equal(op(v, g, w, gq, 8.0, 0.3, 3, 5, True), v[:, :2])  # constants come back exactly
    v, g, wz, gq, *_ = _hazards(dtype)["zero time weights"]
    assert torch.equal(op(v, g, wz, gq, 8.0, 0.3, 2, 5, True)[:, 1], torch.zeros_like(v[:, 0]))


def test_single_frame_matches_the_spatial_kernel():
    """One frame, queried at itself, is the spatial filter (both C++ kernels)."""
    v, g, _, _ = _window(2, 1, 3, 4, 23, 31, 1, seed=4)
    w = torch.ones(1, 1, dtype=torch.float64)
    got = op(v, g, w, g.clone(), 6.0, 0.25, 3, 5, True)
    spatial = torch.ops.torchmanifold.adaptive_manifold(v[:, 0], g[:, 0], 6.0, 0.25, 3, 5, True)
    assert _rel_err(got[:, 0], spatial) < 1e-10


def test_queries_and_images_are_independent():
    v, g, w, gq = _window(2, 3, 2, 3, 19, 25, 3, seed=5)
    whole = op(v, g, w, gq, 8.0, 0.3, 3, 5, True)
    for b in range(2):
        for q in range(3):
            one = op(v[b : b + 1], g[b : b + 1], w[q : q + 1], gq[b : b + 1, q : q + 1], 8.0, 0.3, 3, 5, True)
            assert torch.equal(whole[b : b + 1, q : q + 1], one)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_thread_count_invariance(threads, dtype):
    # large enough (above the serial-work threshold of parallel_work) that every pass really splits
    v, g, w, gq = _window(1, 3, 3, 8, 203, 211, 1, dtype=dtype, seed=7)
    g[0, 1, 0, 40:60, 50:70] = math.nan  # the masked route too
    results = []
    for n in (1, 2, 3):
        torch.set_num_threads(n)
        results.append(op(v, g, w, gq, 12.0, 0.3, 3, 5, True))
    assert torch.equal(results[0], results[1])
    assert torch.equal(results[0], results[2])


def test_registrations():
    assert torch._C._dispatch_has_kernel_for_dispatch_key(OP_NAME, "CPU")  # the C++ kernel
    assert torch._C._dispatch_has_kernel_for_dispatch_key(OP_NAME, "CUDA")  # the reference until a CUDA one
    assert torch._C._dispatch_has_kernel_for_dispatch_key(OP_NAME, "Autograd")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("args", [(4.0, 0.3, 1, 3, False), (6.0, 0.2, 3, 5, True)])
def test_opcheck(dtype, args):
    v, g, w, gq = _window(1, 2, 2, 3, 9, 11, 2, dtype=dtype)
    torch.library.opcheck(op, (v.requires_grad_(True), g, w, gq, *args))


def test_fake_tensor_shapes():
    from torch._subclasses.fake_tensor import FakeTensorMode

    with FakeTensorMode():
        out = op(torch.empty(2, 3, 4, 17, 19), torch.empty(2, 3, 5, 17, 19), torch.empty(6, 3),
                 torch.empty(2, 6, 5, 17, 19), 4.0, 0.3, 2, 5, False)
    assert out.shape == (2, 6, 4, 17, 19) and out.dtype == torch.float32


def test_compile_fullgraph_equals_eager():
    torch._dynamo.reset()
    v, g, w, gq = _window(1, 3, 3, 4, 16, 18, 2, dtype=torch.float32)

    def f(values, guide, weights, query_guide):
        return op(values, guide, weights, query_guide, 6.0, 0.25, 2, 5, True) * 2.0 + 1.0

    compiled = torch.compile(f, fullgraph=True, backend="aot_eager")
    torch.testing.assert_close(compiled(v, g, w, gq), f(v, g, w, gq), rtol=0, atol=0)


def test_compile_fullgraph_backward_equals_eager():
    torch._dynamo.reset()
    v, g, w, gq = _window(1, 2, 2, 3, 10, 12, 1)
    v.requires_grad_(True)

    def f(values):
        return (op(values, g, w, gq, 4.0, 0.3, 2, 5, False) ** 2).sum()

    (ge,) = torch.autograd.grad(f(v), v)
    (gc,) = torch.autograd.grad(torch.compile(f, fullgraph=True, backend="aot_eager")(v), v)
    torch.testing.assert_close(gc, ge)


@pytest.mark.parametrize("adjust", [False, True])
def test_gradcheck_through_the_public_function(adjust):
    v, g, _, _ = _window(1, 2, 1, 2, 5, 6, 1)
    v.requires_grad_(True)
    fn = lambda x: temporal_adaptive_manifold_filter(x, g, [0, 1], [0.4, 1.0], 3.0, 0.3, mode="spacetime",  # noqa: E731
                                                     adjust_outliers=adjust, backend="cpp")
    assert torch.autograd.gradcheck(fn, (v,), fast_mode=True)
    assert torch.autograd.gradgradcheck(fn, (v,), fast_mode=True)


def test_gradient_matches_the_torch_backend():
    v, g, _, _ = _window(1, 3, 2, 3, 12, 13, 1)
    v.requires_grad_(True)
    r = torch.rand(1, 2, 2, 12, 13, dtype=torch.float64)
    grads = []
    for backend in ("cpp", "torch"):
        out = temporal_adaptive_manifold_filter(v, g, [0, 1, 2], [0.5, 1.7], 5.0, 0.25, mode="spacetime",
                                                tree_height=3, adjust_outliers=True, backend=backend)
        grads.append(torch.autograd.grad((out * r).sum(), v)[0])
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=1e-12)


def test_public_function_uses_the_kernel_by_default(monkeypatch):
    """``backend="auto"`` on CPU is the C++ op (not the reference, which is made to fail here); ``"torch"``
    is the reference; both agree."""
    import torchmanifold.ops.temporal as temporal

    v, g, _, _ = _window(1, 3, 3, 4, 18, 20, 1, dtype=torch.float32)
    args = (v, g, [0, 1, 2], [0.6, 2.0], 5.0, 0.3)
    ref = temporal_adaptive_manifold_filter(*args, mode="spacetime", backend="torch")
    monkeypatch.setattr(temporal, "spacetime_torch", lambda *a: pytest.fail("the reference ran"))
    auto = temporal_adaptive_manifold_filter(*args, mode="spacetime")
    assert torch.equal(auto, temporal_adaptive_manifold_filter(*args, mode="spacetime", backend="cpp"))
    assert _rel_err(auto, ref) < 1e-5


BAD = [
    (dict(values=torch.rand(1, 3, 8, 8)), "values must be \\(B, T, C, H, W\\)"),
    (dict(guide=torch.rand(1, 2, 4, 8, 9)), "guide must match values"),
    (dict(weights=torch.rand(1, 3)), "one weight per frame"),
    (dict(weights=-torch.rand(1, 2)), "weights must be finite and >= 0"),
    (dict(query_guide=torch.rand(1, 1, 3, 8, 8)), "query_guide must be"),
    (dict(sigma_r=0.0), "sigma_r must be"),
    (dict(tree_height=0), "tree_height must be"),
]


@pytest.mark.parametrize("change,words", BAD, ids=[b[1][:24] for b in BAD])
def test_errors_name_the_argument(change, words):
    args = dict(values=torch.rand(1, 2, 3, 8, 8), guide=torch.rand(1, 2, 4, 8, 8), weights=torch.rand(1, 2),
                query_guide=torch.rand(1, 1, 4, 8, 8), sigma_s=4.0, sigma_r=0.3, tree_height=2,
                power_iterations=5, adjust_outliers=False)
    args.update(change)
    with pytest.raises(ValueError, match=words):
        op(**args)
    with pytest.raises(TypeError, match="dtype of values"):
        op(torch.rand(1, 2, 3, 8, 8), torch.rand(1, 2, 4, 8, 8, dtype=torch.float64), torch.rand(1, 2),
           torch.rand(1, 1, 4, 8, 8), 4.0, 0.3, 2, 5, False)


def test_stability_cases_match_reference():
    """Every case of the stability suite (tests/stability/cases.py: non-finite samples, constant and zero
    guides, 128 guide channels, tiny sizes, half precision, moving objects...) through the public function
    as the suite calls it: the C++ kernel equals the reference."""
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    for p in (root / "benchmarks", root / "tests" / "stability"):
        if str(p) not in sys.path:
            sys.path.insert(0, str(p))
    from cases import CASES

    for case in CASES:
        pr = case.build()
        x, g = pr.clip.values[None], pr.clip.guide[None].to(pr.clip.values.dtype)
        t = pr.clip.times.to(torch.float32)
        for adjust in (False, True):
            out = {b: temporal_adaptive_manifold_filter(x, g, t, t[pr.query : pr.query + 1], pr.sigma_s, pr.sigma_r,
                                                        mode="spacetime", adjust_outliers=adjust, backend=b)
                   for b in ("cpp", "torch")}
            assert torch.isfinite(out["cpp"]).all(), case.name
            # float32 noise relative to the samples' scale (c + S / S0 rounds at the scale of the inputs:
            # a 1e4 firefly costs 1e4 * eps absolute)
            xs = x.float()
            scale = max(xs[torch.isfinite(xs)].abs().max().item(), out["torch"].abs().max().item())
            err = (out["cpp"].double() - out["torch"].double()).abs().max().item()
            # (a float16 case's output is rounded to float16: one of its steps apart at most)
            tol = max(1e-5, torch.finfo(out["cpp"].dtype).eps)
            assert err <= tol * scale, (case.name, adjust, err, scale)
