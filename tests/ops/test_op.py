"""The op torchmanifold::adaptive_manifold as a PyTorch citizen: opcheck, fake tensors,
torch.compile(fullgraph=True) == eager, autograd through the op (gradcheck, gradgradcheck)."""
import pytest
import torch

from torchmanifold.ops import adaptive_manifold_filter, adaptive_manifold_torch, has_kernel

op = torch.ops.torchmanifold.adaptive_manifold.default
OP_NAME = "torchmanifold::adaptive_manifold"


@pytest.fixture
def op_inputs(random_inputs):
    """Small float64 inputs (values optionally requiring grad)."""
    def make(B=1, C=2, D=3, H=9, W=11, dtype=torch.float64, seed=0, grad=False):
        v, g = random_inputs(B, C, D, H, W, dtype=dtype, seed=seed, edge=0.5)
        return v.requires_grad_(grad), g
    return make




def test_registrations():
    assert has_kernel("cpu")  # the C++ kernel
    assert torch._C._dispatch_has_kernel_for_dispatch_key(OP_NAME, "CUDA")  # pure-PyTorch until a CUDA one
    assert torch._C._dispatch_has_kernel_for_dispatch_key(OP_NAME, "Autograd")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("args", [(4.0, 0.3, 1, 3, False), (6.0, 0.2, 3, 5, True)])
def test_opcheck(op_inputs, dtype, args):
    v, g = op_inputs(dtype=dtype, grad=True)
    torch.library.opcheck(op, (v, g, *args))


def test_opcheck_backward_op(op_inputs):
    v, g = op_inputs()
    grad = torch.rand_like(v)
    # the other opcheck utils run the real kernel under a dispatch mode, which cannot see through the
    # torch.func.vjp inside it; its fake kernel is exercised by the forward op's test_aot_dispatch_dynamic
    torch.library.opcheck(torch.ops.torchmanifold._adaptive_manifold_backward.default,
                          (grad, v, g, 4.0, 0.3, 2, 5, True), test_utils=("test_autograd_registration",))
    from torch._subclasses.fake_tensor import FakeTensorMode

    with FakeTensorMode():
        fake = torch.ops.torchmanifold._adaptive_manifold_backward(torch.empty(2, 3, 5, 6), torch.empty(2, 3, 5, 6),
                                                                   torch.empty(2, 4, 5, 6), 4.0, 0.3, 2, 5, True)
    assert fake.shape == (2, 3, 5, 6)


def test_fake_tensor_shapes():
    from torch._subclasses.fake_tensor import FakeTensorMode

    with FakeTensorMode():
        v = torch.empty(2, 3, 17, 19)
        g = torch.empty(2, 5, 17, 19)
        out = op(v, g, 4.0, 0.3, 2, 5, False)
    assert out.shape == (2, 3, 17, 19) and out.dtype == torch.float32


def test_compile_fullgraph_equals_eager(op_inputs):
    torch._dynamo.reset()
    v, g = op_inputs(B=2, C=3, D=4, H=16, W=18, dtype=torch.float32)

    def f(values, guide):
        return adaptive_manifold_filter(values, guide, 6.0, 0.25, 2, guide_sigmas=[0.5, 1.0, 1.5, 2.0],
                                        adjust_outliers=True) * 2.0 + 1.0

    compiled = torch.compile(f, fullgraph=True, backend="aot_eager")
    torch.testing.assert_close(compiled(v, g), f(v, g), rtol=0, atol=0)


def test_compile_fullgraph_backward_equals_eager(op_inputs):
    torch._dynamo.reset()
    v, g = op_inputs(H=10, W=12, grad=True)

    def f(values, guide):
        return (adaptive_manifold_filter(values, guide, 4.0, 0.3, 2) ** 2).sum()

    (ge,) = torch.autograd.grad(f(v, g), v)
    (gc,) = torch.autograd.grad(torch.compile(f, fullgraph=True, backend="aot_eager")(v, g), v)
    torch.testing.assert_close(gc, ge)


@pytest.mark.parametrize("adjust", [False, True])
def test_gradcheck_through_op(op_inputs, adjust):
    v, g = op_inputs(C=1, D=2, H=5, W=6, grad=True)
    fn = lambda x: op(x, g, 3.0, 0.3, 2, 8, adjust)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (v,))
    assert torch.autograd.gradgradcheck(fn, (v,))


def test_op_gradient_matches_pure_torch_autograd(op_inputs):
    v, g = op_inputs(B=2, C=3, D=4, H=12, W=13, grad=True)
    w = torch.rand_like(v)
    (a,) = torch.autograd.grad((op(v, g, 5.0, 0.25, 3, 8, True) * w).sum(), v)
    (b,) = torch.autograd.grad((adaptive_manifold_torch(v, g, 5.0, 0.25, 3, 8, True) * w).sum(), v)
    torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_adjoint_identity(op_inputs):
    """<L x, y> == <x, L^T y> with the forward from the C++ kernel and the registered backward."""
    v, g = op_inputs(B=1, C=2, D=3, H=14, W=15, grad=True)
    y = torch.rand_like(v)
    out = op(v, g, 5.0, 0.3, 2, 8, False)
    (lt_y,) = torch.autograd.grad((out * y).sum(), v)
    x = torch.rand_like(v)
    lhs = (op(x, g, 5.0, 0.3, 2, 8, False) * y).sum()
    rhs = (x * lt_y).sum()
    torch.testing.assert_close(lhs, rhs, rtol=1e-10, atol=1e-12)
