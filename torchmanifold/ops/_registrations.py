"""Python-side registrations for ``torchmanifold::adaptive_manifold`` and
``torchmanifold::spacetime_adaptive_manifold`` (run once, only if the ops loaded; the space-time op's
are the same three, its reference is ``torchmanifold.ops.temporal.spacetime_torch``).

- ``register_fake``: shapes/dtypes only, so ``torch.compile(fullgraph=True)`` and ``opcheck`` trace it.
- ``register_autograd``: gradient w.r.t. ``values``. The filter is linear in values for a fixed guide,
  so the exact adjoint is the vector-Jacobian product of the pure-PyTorch implementation with the
  guide detached. It runs as its own private op ``torchmanifold::_adaptive_manifold_backward`` (with a
  fake and its own autograd, the forward op: the adjoint of the adjoint), so it traces under compile.
- the pure-PyTorch implementation as the op's kernel for CUDA until a CUDA kernel exists.
  No CPU kernel is registered here: that is the C++ kernel's job.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchmanifold._checks import (
    check_int,
    check_positive,
    check_same_dtype_device,
    check_tensor,
    check_tree_height,
    check_tree_heights,
)
from torchmanifold.ops._reference import adaptive_manifold_torch

OP_NAME = "torchmanifold::adaptive_manifold"
BACKWARD_NAME = "torchmanifold::_adaptive_manifold_backward"
_OP_FLOATS = (torch.float32, torch.float64)  # the op's dtypes; the Python function converts half types


def _check_op_args(values: Tensor, guide: Tensor, sigma_s: float, sigma_r: float, tree_height: int,
                   power_iterations: int) -> None:
    """The C++ kernel's argument checks, for the kernels and fakes registered here (same errors).

    Sizes are compared with ``torch._check_value`` (a ValueError like the rest) so that symbolic sizes
    under ``torch.compile`` become assertions, not guards.
    """
    check_tensor("values", values, dims=4, layout="(B, C, H, W)", dtypes=_OP_FLOATS)
    check_tensor("guide", guide, dims=4, layout="(B, D, H, W)")
    check_same_dtype_device("guide", guide, "values", values)
    torch._check_value(values.shape[0] == guide.shape[0] and values.shape[2:] == guide.shape[2:],
                       lambda: f"guide must share B, H, W with values {tuple(values.shape)}, got {tuple(guide.shape)}")
    torch._check_value(guide.shape[1] >= 1, lambda: f"guide must have D >= 1 channels, got {tuple(guide.shape)}")
    check_positive("sigma_s", sigma_s)
    check_positive("sigma_r", sigma_r)
    check_tree_height(tree_height)
    check_int("power_iterations", power_iterations, min=0)


def _vjp(grad: Tensor, values: Tensor, guide: Tensor, sigma_s: float, sigma_r: float, tree_height: int,
         power_iterations: int, adjust_outliers: bool) -> Tensor:
    # Linear in values for a fixed guide; the point only decides which samples are finite (splat).
    # torch.func.vjp: plain autograd is switched off inside an op's kernel (below the Autograd key)
    guide = guide.detach()
    _, vjp_fn = torch.func.vjp(
        lambda x: adaptive_manifold_torch(x, guide, sigma_s, sigma_r, tree_height, power_iterations,
                                          adjust_outliers), values.detach())
    return vjp_fn(grad.contiguous())[0]


def _register() -> None:
    if not hasattr(torch.ops.torchmanifold, "adaptive_manifold"):  # pragma: no cover - broken build
        return

    @torch.library.register_fake(OP_NAME)
    def _fake(values, guide, sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers):
        _check_op_args(values, guide, sigma_s, sigma_r, tree_height, power_iterations)
        return torch.empty_like(values, memory_format=torch.contiguous_format)

    @torch.library.register_fake("torchmanifold::_adaptive_manifold_bandwidths")
    def _bandwidths_fake(values, guide, sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers):
        torch._check(len(sigma_s) > 0,
                     lambda: "_adaptive_manifold_bandwidths: sigma_s must hold at least one sigma")
        for s, h in zip(sigma_s, check_tree_heights(tree_height, len(sigma_s))):
            _check_op_args(values, guide, s, sigma_r, h, power_iterations)
        return values.new_empty((len(sigma_s), *values.shape))

    @torch.library.custom_op(BACKWARD_NAME, mutates_args=())
    def _adaptive_manifold_backward(grad: Tensor, values: Tensor, guide: Tensor, sigma_s: float,
                                    sigma_r: float, tree_height: int, power_iterations: int,
                                    adjust_outliers: bool) -> Tensor:
        """Adjoint of the filter w.r.t. values at ``values``: grad (B, C, H, W) -> (B, C, H, W)."""
        return _vjp(grad, values, guide, sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers)

    @_adaptive_manifold_backward.register_fake
    def _backward_fake(grad, values, guide, sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers):
        _check_op_args(grad, guide, sigma_s, sigma_r, tree_height, power_iterations)
        return torch.empty_like(grad, memory_format=torch.contiguous_format)

    def _setup_context(ctx, inputs, output):
        values, guide, *params = inputs
        ctx.save_for_backward(values, guide)
        ctx.params = params

    def _backward(ctx, grad):
        values, guide = ctx.saved_tensors
        grad_values = torch.ops.torchmanifold._adaptive_manifold_backward(grad, values, guide, *ctx.params)
        return grad_values, None, None, None, None, None, None

    torch.library.register_autograd(OP_NAME, _backward, setup_context=_setup_context)

    # adjoint of the adjoint: the VJP is linear in grad and its own VJP is the forward filter
    def _setup_backward_context(ctx, inputs, output):
        _, values, guide, *params = inputs
        ctx.save_for_backward(guide)
        ctx.params = params

    def _backward_backward(ctx, gg):
        (guide,) = ctx.saved_tensors
        gv = torch.ops.torchmanifold.adaptive_manifold(gg.contiguous(), guide, *ctx.params)
        return gv, None, None, None, None, None, None, None

    _adaptive_manifold_backward.register_autograd(_backward_backward, setup_context=_setup_backward_context)

    @torch.library.register_kernel(OP_NAME, "cuda")
    def _cuda(values, guide, sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers):
        _check_op_args(values, guide, sigma_s, sigma_r, tree_height, power_iterations)
        return adaptive_manifold_torch(values, guide, sigma_s, sigma_r, tree_height, power_iterations,
                                       adjust_outliers)


_register()


SPACETIME_NAME = "torchmanifold::spacetime_adaptive_manifold"
SPACETIME_BACKWARD_NAME = "torchmanifold::_spacetime_adaptive_manifold_backward"


def _check_spacetime_shapes(values: Tensor, guide: Tensor, weights: Tensor, query_guide: Tensor) -> None:
    torch._check(values.dim() == 5, lambda: f"values must be (B, T, C, H, W), got {tuple(values.shape)}")
    torch._check(guide.dim() == 5, lambda: f"guide must be (B, T, D, H, W), got {tuple(guide.shape)}")
    torch._check(weights.dim() == 2, lambda: f"weights must be (Q, T), got {tuple(weights.shape)}")
    torch._check(query_guide.dim() == 5, lambda: f"query_guide must be (B, Q, D, H, W), got {tuple(query_guide.shape)}")
    B, T, _, H, W = values.shape
    torch._check(guide.shape[:2] == (B, T) and guide.shape[3:] == (H, W),
                 lambda: f"values {tuple(values.shape)} and guide {tuple(guide.shape)} differ in B, T, H or W")
    torch._check(weights.shape[1] == T, lambda: f"weights {tuple(weights.shape)} must have T={T} columns")
    torch._check(query_guide.shape == (B, weights.shape[0], guide.shape[2], H, W),
                 lambda: f"query_guide {tuple(query_guide.shape)} must be (B, Q, D, H, W)")
    torch._check(values.dtype == guide.dtype == weights.dtype == query_guide.dtype,
                 lambda: "values, guide, weights and query_guide must share a dtype")


def _spacetime_vjp(grad: Tensor, values: Tensor, guide: Tensor, weights: Tensor, query_guide: Tensor,
                   sigma_s: float, sigma_r: float, tree_height: int, power_iterations: int,
                   adjust_outliers: bool) -> Tensor:
    # linear in values for fixed guides and weights, as the spatial op; the reference is imported
    # here because torchmanifold.ops.temporal imports this module's importer
    from torchmanifold.ops.temporal import spacetime_torch

    guide, weights, query_guide = guide.detach(), weights.detach(), query_guide.detach()
    _, vjp_fn = torch.func.vjp(
        lambda x: spacetime_torch(x, guide, weights, query_guide, sigma_s, sigma_r, tree_height,
                                  power_iterations, adjust_outliers), values.detach())
    return vjp_fn(grad.contiguous())[0]


def _register_spacetime() -> None:
    if not hasattr(torch.ops.torchmanifold, "spacetime_adaptive_manifold"):  # pragma: no cover - broken build
        return

    @torch.library.register_fake(SPACETIME_NAME)
    def _fake(values, guide, weights, query_guide, sigma_s, sigma_r, tree_height, power_iterations,
              adjust_outliers):
        _check_spacetime_shapes(values, guide, weights, query_guide)
        B, _, C, H, W = values.shape
        return values.new_empty((B, weights.shape[0], C, H, W))

    @torch.library.register_fake("torchmanifold::_spacetime_adaptive_manifold_bandwidths")
    def _bandwidths_fake(values, guide, weights, query_guide, sigma_s, sigma_r, tree_height, power_iterations,
                         adjust_outliers):
        torch._check(len(sigma_s) > 0,
                     lambda: "_spacetime_adaptive_manifold_bandwidths: sigma_s must hold at least one sigma")
        check_tree_heights(tree_height, len(sigma_s))
        _check_spacetime_shapes(values, guide, weights, query_guide)
        B, _, C, H, W = values.shape
        return values.new_empty((len(sigma_s), B, weights.shape[0], C, H, W))

    @torch.library.custom_op(SPACETIME_BACKWARD_NAME, mutates_args=())
    def _spacetime_backward(grad: Tensor, values: Tensor, guide: Tensor, weights: Tensor, query_guide: Tensor,
                            sigma_s: float, sigma_r: float, tree_height: int, power_iterations: int,
                            adjust_outliers: bool) -> Tensor:
        """Adjoint w.r.t. values at ``values``: grad (B, Q, C, H, W) -> (B, T, C, H, W)."""
        return _spacetime_vjp(grad, values, guide, weights, query_guide, sigma_s, sigma_r, tree_height,
                              power_iterations, adjust_outliers)

    @_spacetime_backward.register_fake
    def _backward_fake(grad, values, guide, weights, query_guide, sigma_s, sigma_r, tree_height,
                       power_iterations, adjust_outliers):
        _check_spacetime_shapes(values, guide, weights, query_guide)
        return torch.empty_like(values, memory_format=torch.contiguous_format)

    def _setup_context(ctx, inputs, output):
        values, guide, weights, query_guide, *params = inputs
        ctx.save_for_backward(values, guide, weights, query_guide)
        ctx.params = params

    def _backward(ctx, grad):
        values, guide, weights, query_guide = ctx.saved_tensors
        grad_values = torch.ops.torchmanifold._spacetime_adaptive_manifold_backward(
            grad, values, guide, weights, query_guide, *ctx.params)
        return grad_values, None, None, None, None, None, None, None, None

    torch.library.register_autograd(SPACETIME_NAME, _backward, setup_context=_setup_context)

    # the adjoint of the adjoint is the forward op (the VJP is linear in grad)
    def _setup_backward_context(ctx, inputs, output):
        _, _, guide, weights, query_guide, *params = inputs
        ctx.save_for_backward(guide, weights, query_guide)
        ctx.params = params

    def _backward_backward(ctx, gg):
        guide, weights, query_guide = ctx.saved_tensors
        gv = torch.ops.torchmanifold.spacetime_adaptive_manifold(gg.contiguous(), guide, weights, query_guide,
                                                                 *ctx.params)
        return gv, None, None, None, None, None, None, None, None, None

    _spacetime_backward.register_autograd(_backward_backward, setup_context=_setup_backward_context)

    @torch.library.register_kernel(SPACETIME_NAME, "cuda")
    def _cuda(values, guide, weights, query_guide, sigma_s, sigma_r, tree_height, power_iterations,
              adjust_outliers):
        from torchmanifold.ops.temporal import spacetime_torch

        return spacetime_torch(values, guide, weights, query_guide, sigma_s, sigma_r, tree_height,
                               power_iterations, adjust_outliers)


_register_spacetime()
