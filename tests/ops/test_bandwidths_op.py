"""torchmanifold::_adaptive_manifold_bandwidths: the filter at K spatial sigmas in one call (the denoiser's
bandwidth candidates; one tree height for all or one per sigma), against the op called once per sigma, for
any thread count."""
import pytest
import torch

from torchmanifold._threads import torch_threads
from torchmanifold.ops import adaptive_manifold_filter
from torchmanifold.ops.adaptive_manifold import _filter_bandwidths

op = torch.ops.torchmanifold._adaptive_manifold_bandwidths.default
single = torch.ops.torchmanifold.adaptive_manifold.default


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("B, sigmas, heights", [(2, (2.0, 8.0, 3.0), (3,)), (1, (4.0,), (3,)),
                                                (1, (16.0, 2.0), (3,)), (2, (2.0, 8.0, 16.0), (1, 4, 5))])
def test_each_slice_is_the_single_op(random_inputs, threads, B, sigmas, heights):
    # (1, (4,)) runs on one thread's loop, (2, ...) has more images than threads: side by side
    v, g = random_inputs(B, 5, 4, 40, 52, seed=3)
    with torch_threads(threads):
        out = op(v, g, list(sigmas), 0.4, list(heights), 8, False)
    assert out.shape == (len(sigmas), *v.shape)
    for k, s in enumerate(sigmas):
        h = heights[k if len(heights) > 1 else 0]
        assert torch.equal(out[k], single(v, g, s, 0.4, h, 8, False)), (k, s, h)


def test_filter_bandwidths_matches_the_public_filter(random_inputs):
    v, g = random_inputs(1, 3, 4, 33, 30, seed=5)
    sig = torch.tensor([0.5, 0.2, 0.3, 0.9], dtype=torch.float64)
    out = _filter_bandwidths(v, g, [2.0, 6.0], 1.0, 2, sig)
    for k, s in enumerate((2.0, 6.0)):
        assert torch.equal(out[k], adaptive_manifold_filter(v, g, s, 1.0, 2, guide_sigmas=sig))
    out = _filter_bandwidths(v, g, [2.0, 6.0], 1.0, [2, 4], sig)
    for k, (s, h) in enumerate(((2.0, 2), (6.0, 4))):
        assert torch.equal(out[k], adaptive_manifold_filter(v, g, s, 1.0, h, guide_sigmas=sig))


def test_filter_bandwidths_keeps_gradients(random_inputs):
    v, g = random_inputs(1, 2, 3, 16, 16, dtype=torch.float64, seed=1)
    v.requires_grad_(True)
    out = _filter_bandwidths(v, g, [2.0, 4.0], 0.3, 2)
    (grad,) = torch.autograd.grad(out.square().sum(), v)
    want = sum(adaptive_manifold_filter(v, g, s, 0.3, 2).square().sum() for s in (2.0, 4.0))
    (grad_want,) = torch.autograd.grad(want, v)
    torch.testing.assert_close(grad, grad_want)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck(random_inputs, dtype):
    v, g = random_inputs(2, 2, 3, 9, 11, dtype=dtype)
    torch.library.opcheck(op, (v, g, [2.0, 5.0], 0.3, [2, 3], 5, False))


@pytest.mark.parametrize("sigmas, heights, match", [
    ([], [2], "at least one sigma"), ([2.0, -1.0], [2], "sigma_s"), ([2.0, 4.0], [2, 3, 4], "one per sigma"),
    ([2.0, 4.0], [2, 0], "tree_height")])
def test_bad_sigmas_and_heights_are_named(random_inputs, sigmas, heights, match):
    v, g = random_inputs(1, 2, 3, 8, 8)
    with pytest.raises(ValueError, match=match):
        op(v, g, sigmas, 0.3, heights, 5, False)
    if len(heights) > 1:  # the wrapper names them too
        with pytest.raises(ValueError, match=match):
            _filter_bandwidths(v, g, sigmas, 0.3, heights)


spacetime = torch.ops.torchmanifold.spacetime_adaptive_manifold.default
spacetime_k = torch.ops.torchmanifold._spacetime_adaptive_manifold_bandwidths.default


def _window(random_inputs, B=2, T=3, Q=2, seed=4):
    v, g = random_inputs(B, 3, 4, 24, 28, T=T, seed=seed)
    w = torch.tensor([[0.5, 1.0, 0.5], [0.0, 0.6, 1.0]])[:Q, :T]
    gq = torch.stack([g[:, 1], 0.5 * (g[:, 1] + g[:, 2])], 1)[:, :Q]
    return v, g, w, gq


@pytest.mark.parametrize("threads", [1, 2])
def test_spacetime_slices_are_the_single_op(random_inputs, threads):
    v, g, w, gq = _window(random_inputs)
    with torch_threads(threads):
        out = spacetime_k(v, g, w, gq, [6.0, 2.0], 0.5, [4, 2], 8, False)
    assert out.shape == (2, *v.shape[:1], w.shape[0], *v.shape[2:])
    for k, (s, h) in enumerate(((6.0, 4), (2.0, 2))):
        for b in range(v.shape[0]):  # each window alone: the batched op runs its images side by side
            want = spacetime(v[b:b + 1], g[b:b + 1], w, gq[b:b + 1], s, 0.5, h, 8, False)
            assert torch.equal(out[k, b:b + 1], want), (k, b)


@pytest.mark.parametrize("threads", [1, 2])
def test_batched_op_images_are_the_single_images(random_inputs, threads):
    v, g = random_inputs(3, 2, 3, 30, 20, seed=8)
    with torch_threads(threads):
        out = single(v, g, 4.0, 0.3, 2, 8, False)
    for b in range(3):
        assert torch.equal(out[b:b + 1], single(v[b:b + 1], g[b:b + 1], 4.0, 0.3, 2, 8, False))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_spacetime_opcheck(random_inputs, dtype):
    v, g, w, gq = (t.to(dtype) for t in _window(random_inputs, B=1, Q=1))
    torch.library.opcheck(spacetime_k, (v, g, w, gq, [2.0, 5.0], 0.3, [2], 5, False))


def test_spacetime_bad_sigmas_are_named(random_inputs):
    v, g, w, gq = _window(random_inputs, B=1, Q=1)
    with pytest.raises(ValueError, match="at least one sigma"):
        spacetime_k(v, g, w, gq, [], 0.3, [2], 5, False)
    with pytest.raises(ValueError, match="sigma_s"):
        spacetime_k(v, g, w, gq, [0.0], 0.3, [2], 5, False)
    with pytest.raises(ValueError, match="^_spacetime_adaptive_manifold_bandwidths: tree_height"):
        spacetime_k(v, g, w, gq, [2.0, 3.0], 0.3, [2, 2, 2], 5, False)


def test_fake_kernels_check_the_heights(random_inputs):
    """Traced (fake tensors), the ops take one height or one per sigma as the kernels do."""
    from torch._subclasses.fake_tensor import FakeTensorMode

    v, g = random_inputs(1, 2, 3, 8, 8)
    sv, sg, w, gq = _window(random_inputs, B=1, Q=1)
    with FakeTensorMode() as mode:
        v, g, sv, sg, w, gq = (mode.from_tensor(t) for t in (v, g, sv, sg, w, gq))
        assert op(v, g, [2.0, 4.0], 0.3, [2], 5, False).shape == (2, *v.shape)
        assert spacetime_k(sv, sg, w, gq, [2.0, 4.0], 0.3, [2, 3], 5, False).shape[0] == 2
        for bad, match in (([2, 3, 4], "one per sigma"), ([2, 0], r"tree_height\[1\]")):
            with pytest.raises(ValueError, match=match):
                op(v, g, [2.0, 4.0], 0.3, bad, 5, False)
            with pytest.raises(ValueError, match=match):
                spacetime_k(sv, sg, w, gq, [2.0, 4.0], 0.3, bad, 5, False)
