"""The adaptive-manifold filter: public function, module and argument checks.

:func:`adaptive_manifold_filter` approximates the high-dimensional Gaussian (joint/cross bilateral)
filter of ``values`` guided by ``guide`` (Gastal & Oliveira 2012) in time linear in pixels and guide
channels. It dispatches to the C++ op ``torch.ops.torchmanifold.adaptive_manifold`` when that has a
kernel for the tensors' device and to the pure-PyTorch implementation otherwise.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor, nn

import torchmanifold._extension  # noqa: F401  (loads the op loudly)
from torchmanifold.ops import _registrations  # noqa: F401  (fake/autograd/cuda registrations)
from torchmanifold._checks import (
    MAX_TREE_HEIGHT,
    check_choice,
    check_int,
    check_numbers,
    check_positive,
    check_same_dtype_device,
    check_sigmas,
    check_tree_height,
    check_tree_heights,
    check_values_and_guide,
)
from torchmanifold._threads import call_parallel
from torchmanifold.ops._reference import adaptive_manifold_torch

__all__ = ["adaptive_manifold_filter", "AdaptiveManifoldFilter", "automatic_tree_height", "has_kernel"]

_FLOATS = (torch.float16, torch.bfloat16, torch.float32, torch.float64)
BACKENDS = ("auto", "cpp", "torch")
_DISPATCH_KEYS = {"cpu": "CPU", "cuda": "CUDA", "mps": "MPS", "xpu": "XPU"}


def _constant_when_compiled(fn):
    """Mark ``fn`` as :func:`torch.compiler.assume_constant_result` does, without its import of
    ``torch._dynamo``, which would double the time ``import torchmanifold`` takes; the compile tests
    (``fullgraph=True``) fail if the mark stops being honoured."""
    fn._dynamo_marked_constant = True
    return fn


@_constant_when_compiled
def _has_kernel_for(device_type: str) -> bool:
    key = _DISPATCH_KEYS.get(device_type)
    if key is None or not hasattr(torch.ops.torchmanifold, "adaptive_manifold"):
        return False
    return torch._C._dispatch_has_kernel_for_dispatch_key("torchmanifold::adaptive_manifold", key)


def has_kernel(device: torch.device | str = "cpu") -> bool:
    """Whether the op ``torchmanifold::adaptive_manifold`` has a kernel for ``device``'s type."""
    return _has_kernel_for(torch.device(device).type)


def automatic_tree_height(sigma_s: float, sigma_r: float) -> int:
    """The paper's automatic height H = max(2, ceil((floor(log2 sigma_s) - 1) (1 - sigma_r))), at most
    ``MAX_TREE_HEIGHT``."""
    sigma_s, sigma_r = check_positive("sigma_s", sigma_s), check_positive("sigma_r", sigma_r)
    return min(MAX_TREE_HEIGHT, max(2, math.ceil((math.floor(math.log2(sigma_s)) - 1) * (1.0 - sigma_r))))


def _check_inputs(values: Tensor, guide: Tensor) -> None:
    """values (B, C, H, W) / (C, H, W) and guide (B, D, H, W) / (D, H, W): floating, same dtype and device,
    same B, H, W, nothing empty but B and C."""
    check_values_and_guide(values, guide, dtypes=_FLOATS)
    check_same_dtype_device("guide", guide, "values", values)


def _check_settings(sigma_s, sigma_r, tree_height, power_iterations, backend) -> tuple:
    """The hyper-parameters every entry point takes, normalised; tree_height None stays None."""
    return (check_positive("sigma_s", sigma_s), check_positive("sigma_r", sigma_r),
            check_tree_height(tree_height, allow_none=True),
            check_int("power_iterations", power_iterations, min=0), check_choice("backend", backend, BACKENDS))


def _guide_scales(guide_sigmas, sigma_r: float, channels: int) -> Tensor:
    """sigma_r / guide_sigmas[c] per guide channel as a float64 (D,) tensor."""
    return sigma_r / check_sigmas("guide_sigmas", guide_sigmas, channels)


def _stored_sigmas(guide_sigmas) -> Tensor | tuple | None:
    """guide_sigmas as a module keeps them (checked, the count only when the guide comes)."""
    if guide_sigmas is None:
        return None
    checked = check_numbers("guide_sigmas", guide_sigmas, positive=True)
    return guide_sigmas.detach().clone() if isinstance(guide_sigmas, Tensor) else tuple(checked.tolist())


def _working_inputs(values: Tensor, guide: Tensor, sigma_r: float, guide_sigmas) -> tuple[Tensor, Tensor]:
    """Values and guide in the ops' dtype (float32, or float64), the guide scaled per channel by
    ``sigma_r / guide_sigmas`` (when given); the guide's channels are its third-last dimension (a frame's
    ``(B, D, H, W)`` or a window's ``(B, T, D, H, W)``)."""
    work = torch.float64 if values.dtype == torch.float64 else torch.float32
    v, g = values.to(work), guide.to(work)
    if guide_sigmas is not None:
        scales = _guide_scales(guide_sigmas, sigma_r, g.shape[-3]).to(device=g.device, dtype=work)
        g = g * scales[:, None, None]
    return v, g


def _filter_bandwidths(values: Tensor, guide: Tensor, sigmas_s: Sequence[float], sigma_r: float,
                       tree_height: int | Sequence[int], guide_sigmas: Sequence[float] | Tensor | None = None,
                       power_iterations: int = 32) -> Tensor:
    """:func:`adaptive_manifold_filter` of ``(B, C, H, W)`` values at every spatial sigma of ``sigmas_s``,
    with ``tree_height`` for all or one height per sigma: ``(K, B, C, H, W)``, each slice the bits of that
    call. With the CPU kernel and no gradient it is one op call whose images share the threads
    (``_adaptive_manifold_bandwidths``); otherwise one call each."""
    heights = check_tree_heights(tree_height, len(sigmas_s))
    if not (values.dim() == 4 and values.device.type == "cpu" and _has_kernel_for("cpu") and values.numel()
            and not (torch.is_grad_enabled() and values.requires_grad)):
        return torch.stack([adaptive_manifold_filter(values, guide, s, sigma_r, h, guide_sigmas=guide_sigmas,
                                                     power_iterations=power_iterations)
                            for s, h in zip(sigmas_s, heights)])
    _check_inputs(values, guide)
    sigma_r = check_positive("sigma_r", sigma_r)
    power_iterations = check_int("power_iterations", power_iterations, min=0)
    sigmas = [check_positive(f"sigmas_s[{k}]", s) for k, s in enumerate(sigmas_s)]
    v, g = _working_inputs(values, guide, sigma_r, guide_sigmas)
    out = call_parallel(torch.ops.torchmanifold._adaptive_manifold_bandwidths, v.contiguous(), g.contiguous(),
                        sigmas, sigma_r, heights, power_iterations, False)
    return out.to(values.dtype)


def adaptive_manifold_filter(values: Tensor, guide: Tensor, sigma_s: float, sigma_r: float,
                             tree_height: int | None = 2, *,
                             guide_sigmas: Sequence[float] | Tensor | None = None, adjust_outliers: bool = False,
                             power_iterations: int = 32, backend: str = "auto") -> Tensor:
    r"""Adaptive-manifold high-dimensional Gaussian filter of ``values`` guided by ``guide``.

    Approximates, for every pixel i,
    :math:`g_i = \sum_j e^{-|x_i-x_j|^2/2\sigma_s^2 - |\hat f_i-\hat f_j|^2/2\sigma_r^2} f_j / \sum_j (\cdot)`
    with :math:`2^H - 1` manifolds, in time linear in pixels and guide channels. Use it as a joint
    (cross) bilateral filter with many guide channels, e.g. denoising Monte Carlo renders guided by
    albedo, normal and depth. ``sigma_r`` is in the guide's units, as in OpenCV's ``amFilter``.

    Args:
        values: values to filter, ``(B, C, H, W)`` or ``(C, H, W)``; float16/bfloat16/float32/float64
            (half types accumulate in float32). Non-finite samples are ignored (never spread).
        guide: guide features, ``(B, D, H, W)`` or ``(D, H, W)``, same dtype and device as ``values``.
        sigma_s: spatial standard deviation in pixels (> 0).
        sigma_r: range standard deviation in guide units (> 0).
        tree_height: manifold tree height H, an int in [1, 30] (``torchmanifold._checks.MAX_TREE_HEIGHT``);
            ``None`` = automatic height (:func:`automatic_tree_height`, designed for RGB guides).
            The arguments after it are keyword-only: the C++ op takes them in another order.
        guide_sigmas: optional per-channel range sigmas ``(D,)``: channel c is scaled by
            ``sigma_r / guide_sigmas[c]`` (depth, normals, albedo have different units).
        adjust_outliers: pull pixels far from every manifold back towards their input
            (``g = f + alpha (g - f)``, ``alpha = exp(-min_k D_k / 2 sigma_r^2)``).
        power_iterations: power-iteration steps for each manifold split (>= 0). The fixed start vector
            (all ones) can be nearly orthogonal to the dominant direction (e.g. RGB guides whose top
            residual direction is red minus blue), so the default is generous: 10 steps can stop near
            the second eigenvector and lose several dB; the steps cost O(D^2) each, nothing per pixel.
        backend: ``"auto"`` (C++ op when it has a kernel for the device, else pure PyTorch),
            ``"cpp"`` (the op; error without a kernel) or ``"torch"`` (pure PyTorch).

    Returns:
        Filtered values, same shape, dtype and device as ``values``. Differentiable w.r.t. ``values``
        (the filter is linear in them); the guide gets no gradient.

    Raises:
        TypeError: a value of the wrong kind (non-tensor inputs, non-floating dtypes, a non-number
            sigma, a non-int height, guide_sigmas that are not numbers).
        ValueError: a value out of range (wrong ranks, mismatched sizes/devices/dtypes, non-positive or
            non-finite sigmas, tree_height outside [1, 30], guide_sigmas of the wrong length, unknown
            backend). See :mod:`torchmanifold._checks`.

    Example:
        >>> values, guide = torch.rand(2, 3, 32, 32), torch.rand(2, 7, 32, 32)
        >>> adaptive_manifold_filter(values, guide, sigma_s=8.0, sigma_r=0.3).shape
        torch.Size([2, 3, 32, 32])
    """
    _check_inputs(values, guide)
    sigma_s, sigma_r, tree_height, power_iterations, backend = _check_settings(
        sigma_s, sigma_r, tree_height, power_iterations, backend)
    if tree_height is None:
        tree_height = automatic_tree_height(sigma_s, sigma_r)
    adjust_outliers = bool(adjust_outliers)
    unbatched = values.dim() == 3
    if unbatched:
        values, guide = values.unsqueeze(0), guide.unsqueeze(0)

    out_dtype = values.dtype
    v, g = _working_inputs(values, guide, sigma_r, guide_sigmas)
    if values.numel() == 0:
        out = v.clone()
    elif backend == "torch" or (backend == "auto" and not _has_kernel_for(v.device.type)):
        out = adaptive_manifold_torch(v, g, sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers)
    else:
        if backend == "cpp" and not _has_kernel_for(v.device.type):
            raise ValueError(f"backend='cpp' needs a kernel of torchmanifold::adaptive_manifold for "
                             f"{v.device.type} tensors; none is registered (use backend='torch' or 'auto')")
        op = torch.ops.torchmanifold.adaptive_manifold
        out = call_parallel(op, v.contiguous(), g.detach().contiguous(), sigma_s, sigma_r, tree_height,
                            power_iterations, adjust_outliers)
    out = out.to(out_dtype)
    return out[0] if unbatched else out


class _FilterSettings(nn.Module):
    """The hyper-parameters both filter modules store, checked once at construction."""

    def __init__(self, sigma_s, sigma_r, tree_height, guide_sigmas, adjust_outliers, power_iterations,
                 backend) -> None:
        super().__init__()
        self.sigma_s, self.sigma_r, self.tree_height, self.power_iterations, self.backend = _check_settings(
            sigma_s, sigma_r, tree_height, power_iterations, backend)
        self.guide_sigmas = _stored_sigmas(guide_sigmas)
        self.adjust_outliers = bool(adjust_outliers)

    def _settings(self) -> dict:
        return dict(tree_height=self.tree_height, guide_sigmas=self.guide_sigmas,
                    adjust_outliers=self.adjust_outliers, power_iterations=self.power_iterations,
                    backend=self.backend)

    #: the attributes extra_repr shows, in order
    _REPR = ("sigma_s", "sigma_r", "tree_height", "guide_sigmas", "adjust_outliers", "power_iterations", "backend")

    def extra_repr(self) -> str:
        def show(v):
            return tuple(float(x) for x in v) if isinstance(v, (Tensor, tuple)) else v

        return ", ".join(f"{k}={show(getattr(self, k))!r}" for k in self._REPR)


class AdaptiveManifoldFilter(_FilterSettings):
    r"""Module form of :func:`adaptive_manifold_filter`; stores the hyper-parameters.

    Args: as :func:`adaptive_manifold_filter` (without ``values`` and ``guide``).

    Shape:
        - values: ``(B, C, H, W)`` or ``(C, H, W)``
        - guide: ``(B, D, H, W)`` or ``(D, H, W)``
        - output: like values

    Example:
        >>> am = AdaptiveManifoldFilter(sigma_s=8.0, sigma_r=0.3)
        >>> am(torch.rand(1, 3, 16, 16), torch.rand(1, 4, 16, 16)).shape
        torch.Size([1, 3, 16, 16])
    """

    def __init__(self, sigma_s: float, sigma_r: float, tree_height: int | None = 2, *,
                 guide_sigmas: Sequence[float] | Tensor | None = None, adjust_outliers: bool = False,
                 power_iterations: int = 32, backend: str = "auto") -> None:
        super().__init__(sigma_s, sigma_r, tree_height, guide_sigmas, adjust_outliers, power_iterations, backend)

    def forward(self, values: Tensor, guide: Tensor) -> Tensor:
        return adaptive_manifold_filter(values, guide, self.sigma_s, self.sigma_r, **self._settings())
