"""The C++ CPU kernel of ``torchmanifold::adaptive_manifold`` against the pure-PyTorch reference.

The reference (torchmanifold/ops/_reference.py) is a second, independent implementation of the
same fixed algorithm; the kernel must agree with it to rounding (float64) and to float32 noise.
Also: thread-count invariance, OpenMP really used, hazards, errors.
"""
import itertools
import os
import re

import pytest
import torch

import torchmanifold
from torchmanifold.ops import adaptive_manifold_torch

op = torch.ops.torchmanifold.adaptive_manifold


def _rel_err(a, b):
    return ((a - b).abs().max() / b.abs().max().clamp_min(1e-30)).item()



SHAPES = [  # (B, C, D, H, W)
    (1, 1, 1, 1, 1),
    (1, 3, 3, 23, 31),
    (2, 1, 1, 17, 9),
    (1, 7, 17, 20, 21),
    (1, 3, 64, 9, 13),
    (2, 3, 3, 1, 19),
]
SIGMAS = [(8.0, 0.3), (3.0, 0.1), (20.0, 0.6)]


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "x".join(map(str, s)))
@pytest.mark.parametrize("sigmas", SIGMAS, ids=lambda s: f"s{s[0]}r{s[1]}")
def test_matches_reference_float64(random_inputs, shape, sigmas):
    f, g = random_inputs(*shape, dtype=torch.float64, edge=1.0)
    for height, adjust in itertools.product([1, 2, 3, 4], [False, True]):
        a = op(f, g, sigmas[0], sigmas[1], height, 3, adjust)
        b = adaptive_manifold_torch(f, g, sigmas[0], sigmas[1], height, 3, adjust)
        assert a.shape == f.shape and a.dtype == torch.float64
        assert _rel_err(a, b) < 1e-10, (height, adjust)


@pytest.mark.parametrize("height", [1, 2, 3])
@pytest.mark.parametrize("D", [1, 3, 17])
def test_matches_reference_float32(random_inputs, height, D):
    f, g = random_inputs(2, 3, D, 24, 29, dtype=torch.float32, seed=D, edge=1.0)
    a = op(f, g, 10.0, 0.4, height, 3, True)
    b = adaptive_manifold_torch(f, g, 10.0, 0.4, height, 3, True)
    assert a.dtype == torch.float32
    assert _rel_err(a, b) < 1e-5


@pytest.mark.parametrize("offset", [0.0, 100.0])
def test_float32_guide_far_from_zero(offset):
    """A guide far from 0 (depth, time) keeps float32 accuracy: the split's projection is taken about
    a centre, not as the difference of two large dot products."""
    gen = torch.Generator().manual_seed(3)
    f = torch.rand(1, 3, 40, 53, generator=gen, dtype=torch.float64)
    g = torch.rand(1, 17, 40, 53, generator=gen, dtype=torch.float64)
    g[..., :20, :] += 1.0
    ref = adaptive_manifold_torch(f, g + offset, 10.0, 0.4, 3, 3, False)
    got = op(f.float(), (g + offset).float(), 10.0, 0.4, 3, 3, False)
    # float32 holds the guide itself only to offset * 6e-8
    assert _rel_err(got.double(), ref) < 2e-6 + 1e-6 * offset


def test_float32_dim_values_beside_a_bright_one():
    """High dynamic range keeps float32 accuracy at the dim pixels: values are filtered about the point of
    their range nearest 0. About the range's middle (5e3 here) every dim result was a small difference of
    large numbers, rounded to about 3e-4 (a rendered frame's light neighbour read 3641 for 2048)."""
    gen = torch.Generator().manual_seed(4)
    f = 0.2 + 0.1 * torch.rand(1, 3, 40, 53, generator=gen, dtype=torch.float64)
    f[..., 20, 26] = 1e4
    g = torch.rand(1, 3, 40, 53, generator=gen, dtype=torch.float64)
    g[..., 20, 26] = 3.0  # a light apart from the rest, as its radiance guide keeps it
    for height in (1, 3):
        ref = adaptive_manifold_torch(f, g, 10.0, 0.4, height, 3, False)
        got = op(f.float(), g.float(), 10.0, 0.4, height, 3, False).double()
        dim = f < 1.0  # the light itself, alone on its manifold, is another case (S0 under the float32 floor)
        assert float(((got - ref).abs() / ref)[dim].max()) < 1e-5  # was 1e-3 and more


@pytest.mark.parametrize("sigma_s", [3.0, 5.0, 8.0, 16.0, 32.0])  # downsampling factor 1, 2, 4, 8, 16
def test_float32_vector_paths_match_reference(random_inputs, sigma_s):
    """Wide enough rows for the kernel's vector paths (8-lane upsampling per factor, 8-block sums) and
    odd sizes for their scalar tails, against the float64 reference."""
    f, g = random_inputs(1, 3, 5, 70, 131, dtype=torch.float32, seed=int(sigma_s), edge=1.0)
    for height in (1, 2):
        a = op(f, g, sigma_s, 0.4, height, 3, True)
        b = adaptive_manifold_torch(f.double(), g.double(), sigma_s, 0.4, height, 3, True)
        assert _rel_err(a.double(), b) < 1e-5, (sigma_s, height)


@pytest.mark.parametrize("iterations", [0, 1, 10])
def test_power_iterations_match(random_inputs, iterations):
    f, g = random_inputs(1, 3, 5, 21, 22, dtype=torch.float64, seed=3, edge=1.0)
    a = op(f, g, 6.0, 0.2, 3, iterations, False)
    b = adaptive_manifold_torch(f, g, 6.0, 0.2, 3, iterations, False)
    assert _rel_err(a, b) < 1e-10


def test_split_direction_from_every_sth_band(monkeypatch):
    """From 2**18 pixels up the split's M sums every s-th band of 4 rows (step 8). Channel 0 varies
    only on the bands it samples and channel 1, twice as much, only on the others, so the direction,
    the clusters and the output all depend on which rows are summed."""
    from torchmanifold.ops import _reference

    H, W = 48, 8192
    assert _reference.gram_band_stride(H, W) == 3
    gen = torch.Generator().manual_seed(11)
    g = torch.zeros(1, 2, H, W, dtype=torch.float64)
    sampled = torch.arange(H) // 4 % 3 == 0
    g[0, 0, sampled] = torch.rand(int(sampled.sum()), W, generator=gen, dtype=torch.float64)
    g[0, 1, ~sampled] = 2 * torch.rand(int((~sampled).sum()), W, generator=gen, dtype=torch.float64)
    f = g[:, :1] - g[:, 1:]  # values that follow the guide, so the clusters show in the output
    got = op(f, g, 8.0, 0.5, 2, 3, False)
    ref = adaptive_manifold_torch(f, g, 8.0, 0.5, 2, 3, False)
    assert _rel_err(got, ref) < 1e-10
    monkeypatch.setattr(_reference, "gram_band_stride", lambda height, width: 1)
    every_row = adaptive_manifold_torch(f, g, 8.0, 0.5, 2, 3, False)
    assert (every_row - ref).abs().max() > 1e-2


def test_batch_equals_images_one_by_one(random_inputs):
    f, g = random_inputs(3, 3, 4, 19, 25, dtype=torch.float64, seed=5, edge=1.0)
    whole = op(f, g, 8.0, 0.3, 3, 3, True)
    for b in range(3):
        single = op(f[b : b + 1], g[b : b + 1], 8.0, 0.3, 3, 3, True)
        assert torch.equal(whole[b : b + 1], single)


def test_noncontiguous_inputs(random_inputs):
    f, g = random_inputs(1, 3, 4, 21, 18, dtype=torch.float64, seed=6, edge=1.0)
    ft = f.transpose(2, 3).contiguous().transpose(2, 3)  # same values, other strides
    gt = g.transpose(2, 3).contiguous().transpose(2, 3)
    assert not ft.is_contiguous()
    assert torch.equal(op(ft, gt, 8.0, 0.3, 2, 3, False), op(f, g, 8.0, 0.3, 2, 3, False))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("D,sigma_s", [(17, 12.0), (1, 4.0)])
def test_thread_count_invariance(random_inputs, threads, dtype, D, sigma_s):
    # Large enough (above the kernel's serial-work threshold) that the passes really split over threads.
    # One guide channel at sigma_s 4 (no downsampling): the children's 4 planes are fewer than twice
    # the threads, so the recursive filters split their rows (8-row vector blocks, scalar rows left
    # over) between threads too.
    f, g = random_inputs(1, 3, D, 401, 417, dtype=dtype, seed=7, edge=1.0)
    g[0, 0, 40:60, 50:70] = float("nan")  # exercise the sanitising path too
    results = []
    for n in (1, 2, 3):
        torch.set_num_threads(n)
        results.append(op(f, g, sigma_s, 0.3, 3, 3, True))
    assert torch.equal(results[0], results[1])
    assert torch.equal(results[0], results[2])


def test_built_with_openmp_and_runs_parallel(random_inputs, threads):
    info = torchmanifold.build_info()
    assert info["openmp"] is True and info["isa"] in ("avx2+fma", "sse2", "generic")
    # Two threads whatever the cores: on one core they take turns, and each still burns CPU time.
    torch.set_num_threads(2)
    f, g = random_inputs(1, 3, 17, 400, 400, dtype=torch.float32, seed=8, edge=1.0)
    op(f, g, 16.0, 0.4, 2, 3, False)  # warm the thread pool

    def cpu_ticks():
        ticks = {}
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
                ticks[tid] = int(fields[11]) + int(fields[12])  # utime + stime
            except OSError:
                pass
        return ticks

    before = cpu_ticks()
    for _ in range(3):
        op(f, g, 16.0, 0.4, 3, 3, False)
    after = cpu_ticks()
    busy = [t for t in after if after[t] - before.get(t, 0) > 0]
    assert len(busy) >= 2, "the op ran on one thread only"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hazards_give_finite_output_and_match(random_inputs, dtype):
    f, g = random_inputs(1, 3, 4, 30, 33, dtype=dtype, seed=9, edge=1.0)
    cases = {}
    fv = f.clone()
    fv[0, 1, 5, 5] = float("nan")
    fv[0, 0, 7, 9] = float("inf")
    cases["nonfinite values"] = (fv, g, 0.3)
    gv = g.clone()
    gv[0, 2, 10, 10] = float("nan")
    gv[0, 0, 3, 3] = -float("inf")
    cases["nonfinite guide"] = (f, gv, 0.3)
    cases["constant guide"] = (f, torch.full_like(g, 0.5), 0.3)
    cases["zero guide"] = (f, torch.zeros_like(g), 0.3)
    cases["tiny sigma_r"] = (f, g, 1e-4)
    cases["128-channel guide"] = (f, torch.rand(1, 128, 30, 33, dtype=dtype), 0.2)
    for name, (fi, gi, sr) in cases.items():
        for adjust in (False, True):
            a = op(fi, gi, 8.0, sr, 3, 3, adjust)
            assert torch.isfinite(a).all(), name
            b = adaptive_manifold_torch(fi, gi, 8.0, sr, 3, 3, adjust)
            tol = 1e-10 if dtype == torch.float64 else 1e-5
            assert _rel_err(a, b) < tol, name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_constant_values_exact(dtype):
    gen = torch.Generator().manual_seed(10)
    g = torch.randn(2, 6, 27, 31, generator=gen).to(dtype) * 3
    f = torch.empty(2, 3, 27, 31, dtype=dtype)
    f[:, 0], f[:, 1], f[:, 2] = 0.1, -7.25, 1e6
    for height, adjust in [(1, False), (3, True), (4, False)]:
        assert torch.equal(op(f, g, 9.0, 0.2, height, 3, adjust), f)


def test_far_from_every_manifold_returns_input(random_inputs):
    # Every pixel so far from every manifold that all weights underflow: S0 == 0 -> input.
    f, _ = random_inputs(1, 3, 1, 12, 12, dtype=torch.float64, seed=11, edge=1.0)
    g = torch.zeros(1, 1, 12, 12, dtype=torch.float64)
    g[..., ::2, :] = 1e3
    g[..., 1::2, :] = -1e3
    out = op(f, g, 4.0, 1e-3, 1, 3, False)
    assert torch.isfinite(out).all()
    assert torch.equal(out, adaptive_manifold_torch(f, g, 4.0, 1e-3, 1, 3, False))


@pytest.mark.parametrize(
    "mutate, exc, words",
    [
        (lambda a: {**a, "values": a["values"][0]}, ValueError, "values"),
        (lambda a: {**a, "guide": a["guide"][0]}, ValueError, "guide"),
        (lambda a: {**a, "guide": torch.rand(1, 2, 8, 9)}, ValueError, "guide"),
        (lambda a: {**a, "guide": torch.rand(1, 0, 8, 8)}, ValueError, "guide"),
        (lambda a: {**a, "values": a["values"].double()}, ValueError, "guide must have the dtype of values"),
        (lambda a: {**a, "values": a["values"].int(), "guide": a["guide"].int()}, TypeError, "values"),
        (lambda a: {**a, "sigma_s": 0.0}, ValueError, "sigma_s"),
        (lambda a: {**a, "sigma_s": float("nan")}, ValueError, "sigma_s"),
        (lambda a: {**a, "sigma_r": -1.0}, ValueError, "sigma_r"),
        (lambda a: {**a, "sigma_r": float("inf")}, ValueError, "sigma_r"),
        (lambda a: {**a, "tree_height": 0}, ValueError, "tree_height must be an int in [1, 30], got 0"),
        (lambda a: {**a, "tree_height": 31}, ValueError, "tree_height must be an int in [1, 30], got 31"),
        (lambda a: {**a, "power_iterations": -1}, ValueError, "power_iterations"),
    ],
)
def test_bad_input(random_inputs, mutate, exc, words):
    f, g = random_inputs(1, 3, 2, 8, 8)
    args = dict(values=f, guide=g, sigma_s=4.0, sigma_r=0.3, tree_height=2, power_iterations=3,
                adjust_outliers=False)
    args = mutate(args)
    with pytest.raises(exc, match=re.escape(words)):
        op(args["values"], args["guide"], args["sigma_s"], args["sigma_r"], args["tree_height"],
           args["power_iterations"], args["adjust_outliers"])


def test_empty_image():
    out = op(torch.rand(1, 3, 0, 5), torch.rand(1, 2, 0, 5), 4.0, 0.3, 2, 3, False)
    assert out.shape == (1, 3, 0, 5)


def test_reused_scratch_buffers_do_not_leak_between_calls(random_inputs):
    # Scratch buffers are pooled across calls with undefined contents: dirty them with a larger
    # call full of non-finite samples, then a smaller call must still match the reference.
    big_f, big_g = random_inputs(1, 7, 17, 64, 70, dtype=torch.float64, seed=12, edge=1.0)
    big_f[..., ::3, ::5] = float("nan")
    big_g[..., 1::4, ::3] = float("inf")
    op(big_f, big_g, 8.0, 0.3, 4, 3, True)
    f, g = random_inputs(1, 3, 5, 21, 26, dtype=torch.float64, seed=13, edge=1.0)
    for height in (1, 3):
        a = op(f, g, 6.0, 0.25, height, 3, True)
        b = adaptive_manifold_torch(f, g, 6.0, 0.25, height, 3, True)
        assert _rel_err(a, b) < 1e-10


def test_tree_height_limit_is_the_python_one(random_inputs):
    """The kernel accepts the tallest tree the Python checks allow (empty clusters are pruned, so a
    small image stays cheap) and rejects one level more with the same message."""
    from torchmanifold._checks import MAX_TREE_HEIGHT

    f, g = random_inputs(1, 2, 3, 6, 7, dtype=torch.float64)
    out = op(f, g, 4.0, 0.3, MAX_TREE_HEIGHT, 3, False)
    assert torch.isfinite(out).all()
    assert (out >= f.amin((2, 3), keepdim=True) - 1e-12).all() and (out <= f.amax((2, 3), keepdim=True) + 1e-12).all()
    with pytest.raises(ValueError, match=re.escape(f"tree_height must be an int in [1, {MAX_TREE_HEIGHT}]")):
        op(f, g, 4.0, 0.3, MAX_TREE_HEIGHT + 1, 3, False)
