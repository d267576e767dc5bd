"""Image helpers the frame step's stages share: luminance, per-frame means and totals whose bits do not follow
the thread count, the small Gaussian of a pixel's footprint, a pixel's four neighbours, and the offset that
keeps relative measures finite in the dark."""
from __future__ import annotations

import math

import torch
from torch import Tensor

#: the log-radiance guide's offset as a fraction of the frame's mean luminance (validation set: 0.1
#: separates shadows and lights as well as 0 does in bright scenes, without resolving noise in dark ones);
#: the bandwidth selection's relative errors take the same offset
_LOG_RADIANCE_OFFSET = 0.1


def luminance(x: Tensor) -> Tensor:
    """Rec. 709 luminance of ``(..., 3, H, W)`` -> ``(..., 1, H, W)``."""
    return 0.2126 * x[..., 0:1, :, :] + 0.7152 * x[..., 1:2, :, :] + 0.0722 * x[..., 2:3, :, :]


def _frame_mean(lum: Tensor, mask: Tensor) -> Tensor:
    """Mean of ``lum`` ``(T, 1, H, W)`` over each frame's valid samples: ``(T, 1, 1, 1)``. Every level
    the denoiser sets (log offsets, firefly floor, tone-mapping knee) is relative to it, so the result
    scales with the exposure."""
    return _channel_means(lum, mask).to(lum.dtype)


def _channel_means(x: Tensor, mask: Tensor) -> Tensor:
    """Mean of each channel of ``(T, C, H, W)`` over each frame's valid samples (weights ``mask``
    ``(T, 1, H, W)``), in float64: ``(T, C, 1, 1)``."""
    return _frame_total(x * mask, per_channel=True) / _frame_total(mask).clamp_min(1.0)


def _frame_total(x: Tensor, per_channel: bool = False) -> Tensor:
    """Sum of each frame of ``(T, C, H, W)`` in float64: ``(T, 1, 1, 1)``, or ``(T, C, 1, 1)`` per channel."""
    # row by row: a one-pass sum over a whole frame splits across threads, and its last bits (hence a
    # Kuwahara choice or a clamp decision downstream) would follow the thread count
    rows = x.double().sum(-1, keepdim=True).sum(-2, keepdim=True)
    return rows if per_channel else rows.sum(-3, keepdim=True)


def _gaussian_taps(sigma: float, dtype: torch.dtype, device=None) -> Tensor:
    """The normalised 1-D taps of :func:`footprint_blur`'s Gaussian (radius three sigmas, at least 1)."""
    r = max(1, int(math.ceil(3 * sigma)))
    k = torch.arange(-r, r + 1, dtype=dtype, device=device)
    k = torch.exp(-(k * k) / (2 * sigma * sigma))
    return k / k.sum()


def footprint_blur(x: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of ``(N, C, H, W)`` with a small ``sigma`` (pixels): a 1-sample image's estimate of
    the pixel-footprint average. ``sigma <= 0`` returns ``x``."""
    if sigma <= 0:
        return x
    k = _gaussian_taps(sigma, x.dtype, x.device)
    r = (k.numel() - 1) // 2
    c = x.shape[1]
    xp = torch.nn.functional.pad(x, (r, r, r, r), mode="replicate")
    xp = torch.nn.functional.conv2d(xp, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return torch.nn.functional.conv2d(xp, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def _four_neighbours(x: Tensor) -> Tensor:
    """The sum of each pixel's four adjacent pixels of ``(T, C, H, W)`` (none beyond the border)."""
    p = torch.nn.functional.pad(x, (1, 1, 1, 1))
    return p[..., :-2, 1:-1] + p[..., 2:, 1:-1] + p[..., 1:-1, :-2] + p[..., 1:-1, 2:]


def _eight_neighbours_max(x: Tensor) -> Tensor:
    """The largest of each pixel's eight surrounding pixels of ``(T, C, H, W)`` (0 beyond the border)."""
    H, W = x.shape[-2:]
    p = torch.nn.functional.pad(x, (1, 1, 1, 1))
    return torch.stack([p[..., 1 + dy:1 + dy + H, 1 + dx:1 + dx + W]
                        for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]).amax(0)
