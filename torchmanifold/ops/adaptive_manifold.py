"""The adaptive-manifold filter: public function, module and argument checks.

:func:`adaptive_manifold_filter` approximates the high-dimensional Gaussian (joint/cross bilateral)
filter of ``values`` guided by ``guide`` (Gastal & Oliveira 2012) in time linear in pixels and guide
channels. It dispatches to the C++ op ``torch.ops.torchmanifold.adaptive_manifold`` when that has a
kernel for the tensors' device and to the pure-PyTorch implementation otherwise.
"""
from __future__ import annotations

import math
import numbers
from typing import Sequence

import torch
from torch import Tensor, nn

import torchmanifold._extension  # noqa: F401  (loads the op loudly)
from torchmanifold.ops import _registrations  # noqa: F401  (fake/autograd/cuda registrations)
from torchmanifold.ops._reference import adaptive_manifold_torch

__all__ = ["adaptive_manifold_filter", "AdaptiveManifoldFilter", "automatic_tree_height", "has_kernel"]

_FLOATS = (torch.float16, torch.bfloat16, torch.float32, torch.float64)
_BACKENDS = ("auto", "cpp", "torch")
_DISPATCH_KEYS = {"cpu": "CPU", "cuda": "CUDA", "mps": "MPS", "xpu": "XPU"}


@torch.compiler.assume_constant_result
def _has_kernel_for(device_type: str) -> bool:
    key = _DISPATCH_KEYS.get(device_type)
    if key is None or not hasattr(torch.ops.torchmanifold, "adaptive_manifold"):
        return False
    return torch._C._dispatch_has_kernel_for_dispatch_key("torchmanifold::adaptive_manifold", key)


def has_kernel(device: torch.device | str = "cpu") -> bool:
    """Whether the op ``torchmanifold::adaptive_manifold`` has a kernel for ``device``'s type."""
    return _has_kernel_for(torch.device(device).type)


def automatic_tree_height(sigma_s: float, sigma_r: float) -> int:
    """The paper's automatic height H = max(2, ceil((floor(log2 sigma_s) - 1) (1 - sigma_r)))."""
    return max(2, math.ceil((math.floor(math.log2(sigma_s)) - 1) * (1.0 - sigma_r)))


def _check_sigma(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, Tensor)):
        raise TypeError(f"{name} must be a positive finite number, got {type(value).__name__}")
    if isinstance(value, Tensor):
        if value.numel() != 1:
            raise TypeError(f"{name} must be a number or a one-element tensor, got shape {tuple(value.shape)}")
        value = value.item()
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value}")
    return value


def _check_dtype_device(values: Tensor, guide: Tensor) -> None:
    if values.dtype not in _FLOATS:
        raise TypeError(f"values must be float16, bfloat16, float32 or float64, got {values.dtype}")
    if guide.dtype != values.dtype:
        raise ValueError(f"guide must have the dtype of values ({values.dtype}), got {guide.dtype}")
    if guide.device != values.device:
        raise ValueError(f"guide must be on the device of values ({values.device}), got {guide.device}")


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an int >= {minimum}, got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value}")
    return int(value)


def _guide_scales(guide_sigmas, sigma_r: float, channels: int) -> Tensor:
    """sigma_r / sigma_c per guide channel as a float64 (D,) tensor."""
    if isinstance(guide_sigmas, Tensor):
        if guide_sigmas.dim() != 1:
            raise ValueError(f"guide_sigmas must be a (D,) tensor, got shape {tuple(guide_sigmas.shape)}")
        if guide_sigmas.numel() != channels:
            raise ValueError(f"guide_sigmas must have one sigma per guide channel (D={channels}), "
                             f"got {guide_sigmas.numel()}")
        sig = guide_sigmas.detach().to(torch.float64)
        if not torch.compiler.is_compiling():  # a data-dependent check: eager only
            if not bool(torch.isfinite(sig).all()) or not bool((sig > 0).all()):
                raise ValueError(f"guide_sigmas must be positive and finite, got {sig.tolist()}")
        return sigma_r / sig
    if not isinstance(guide_sigmas, Sequence) or isinstance(guide_sigmas, str):
        raise TypeError(f"guide_sigmas must be None, a sequence of numbers or a (D,) tensor, "
                        f"got {type(guide_sigmas).__name__}")
    if not all(isinstance(s, numbers.Real) and not isinstance(s, bool) for s in guide_sigmas):
        raise TypeError("guide_sigmas must be a sequence of numbers or a (D,) tensor")
    sig = [float(s) for s in guide_sigmas]
    if len(sig) != channels:
        raise ValueError(f"guide_sigmas must have one sigma per guide channel (D={channels}), got {len(sig)}")
    if not all(math.isfinite(s) and s > 0 for s in sig):
        raise ValueError(f"guide_sigmas must be positive and finite, got {sig}")
    return torch.tensor([sigma_r / s for s in sig], dtype=torch.float64)


def adaptive_manifold_filter(values: Tensor, guide: Tensor, sigma_s: float, sigma_r: float,
                             tree_height: int | None = 2, guide_sigmas: Sequence[float] | Tensor | None = None,
                             adjust_outliers: bool = False, power_iterations: int = 32,
                             backend: str = "auto") -> Tensor:
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
        tree_height: manifold tree height H >= 1; ``None`` = automatic height
            (:func:`automatic_tree_height`, designed for RGB guides).
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
        TypeError: wrong argument types (non-tensor inputs, non-floating dtypes, non-int height).
        ValueError: wrong ranks, mismatched sizes/devices/dtypes, non-positive or non-finite sigmas,
            tree_height < 1, guide_sigmas of the wrong length, unknown backend.

    Example:
        >>> values, guide = torch.rand(2, 3, 32, 32), torch.rand(2, 7, 32, 32)
        >>> adaptive_manifold_filter(values, guide, sigma_s=8.0, sigma_r=0.3).shape
        torch.Size([2, 3, 32, 32])
    """
    if not isinstance(values, Tensor):
        raise TypeError(f"values must be a torch.Tensor, got {type(values).__name__}")
    if not isinstance(guide, Tensor):
        raise TypeError(f"guide must be a torch.Tensor, got {type(guide).__name__}")
    if values.dim() not in (3, 4):
        raise ValueError(f"values must be (B, C, H, W) or (C, H, W), got shape {tuple(values.shape)}")
    if guide.dim() != values.dim():
        raise ValueError(f"guide must have the same rank as values ({values.dim()}: "
                         f"{'(B, D, H, W)' if values.dim() == 4 else '(D, H, W)'}), got shape {tuple(guide.shape)}")
    unbatched = values.dim() == 3
    if unbatched:
        values, guide = values.unsqueeze(0), guide.unsqueeze(0)
    if values.shape[0] != guide.shape[0] or values.shape[2:] != guide.shape[2:]:
        raise ValueError(f"values {tuple(values.shape)} and guide {tuple(guide.shape)} must share "
                         "batch size and H, W")
    if values.shape[2] < 1 or values.shape[3] < 1 or guide.shape[1] < 1:
        raise ValueError(f"H, W and the guide channels D must be >= 1, got values {tuple(values.shape)}, "
                         f"guide {tuple(guide.shape)}")
    _check_dtype_device(values, guide)
    sigma_s = _check_sigma("sigma_s", sigma_s)
    sigma_r = _check_sigma("sigma_r", sigma_r)
    if tree_height is None:
        tree_height = automatic_tree_height(sigma_s, sigma_r)
    tree_height = _check_int("tree_height", tree_height, 1)
    power_iterations = _check_int("power_iterations", power_iterations, 0)
    if backend not in _BACKENDS:
        raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
    adjust_outliers = bool(adjust_outliers)

    out_dtype = values.dtype
    work = torch.float64 if out_dtype == torch.float64 else torch.float32
    v, g = values.to(work), guide.to(work)
    if guide_sigmas is not None:
        scales = _guide_scales(guide_sigmas, sigma_r, g.shape[1]).to(device=g.device, dtype=work)
        g = g * scales[:, None, None]

    if values.numel() == 0:
        out = v.clone()
    elif backend == "torch" or (backend == "auto" and not _has_kernel_for(v.device.type)):
        out = adaptive_manifold_torch(v, g, sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers)
    else:
        if backend == "cpp" and not _has_kernel_for(v.device.type):
            raise ValueError(f"backend='cpp' needs a kernel of torchmanifold::adaptive_manifold for "
                             f"{v.device.type} tensors; none is registered (use backend='torch' or 'auto')")
        out = torch.ops.torchmanifold.adaptive_manifold(v.contiguous(), g.detach().contiguous(), sigma_s,
                                                        sigma_r, tree_height, power_iterations, adjust_outliers)
    out = out.to(out_dtype)
    return out[0] if unbatched else out


class AdaptiveManifoldFilter(nn.Module):
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

    def __init__(self, sigma_s: float, sigma_r: float, tree_height: int | None = 2,
                 guide_sigmas: Sequence[float] | Tensor | None = None, adjust_outliers: bool = False,
                 power_iterations: int = 32, backend: str = "auto") -> None:
        super().__init__()
        self.sigma_s = _check_sigma("sigma_s", sigma_s)
        self.sigma_r = _check_sigma("sigma_r", sigma_r)
        self.tree_height = None if tree_height is None else _check_int("tree_height", tree_height, 1)
        self.guide_sigmas = (guide_sigmas.detach().clone() if isinstance(guide_sigmas, Tensor)
                             else None if guide_sigmas is None else tuple(float(s) for s in guide_sigmas))
        if self.guide_sigmas is not None:
            _guide_scales(self.guide_sigmas, self.sigma_r, len(self.guide_sigmas))
        self.adjust_outliers = bool(adjust_outliers)
        self.power_iterations = _check_int("power_iterations", power_iterations, 0)
        if backend not in _BACKENDS:
            raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
        self.backend = backend

    def forward(self, values: Tensor, guide: Tensor) -> Tensor:
        return adaptive_manifold_filter(values, guide, self.sigma_s, self.sigma_r, self.tree_height,
                                        self.guide_sigmas, self.adjust_outliers, self.power_iterations,
                                        self.backend)

    def extra_repr(self) -> str:
        sig = None if self.guide_sigmas is None else tuple(float(s) for s in self.guide_sigmas)
        return (f"sigma_s={self.sigma_s}, sigma_r={self.sigma_r}, tree_height={self.tree_height}, "
                f"guide_sigmas={sig}, adjust_outliers={self.adjust_outliers}, "
                f"power_iterations={self.power_iterations}, backend={self.backend!r}")
