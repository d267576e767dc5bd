"""Brute-force high-dimensional Gaussian filter: the test oracle for the adaptive-manifold filter.

    g_i = sum_j exp(-|x_i - x_j|^2 / 2 sigma_s^2 - |f^_i - f^_j|^2 / 2 sigma_r^2) f_j / sum_j (same)

computed exactly in float64 over the whole image (or a square window of ``radius`` pixels), in
chunks of query pixels so 128 x 128 images take about a second. O(N^2): for small images only.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["bilateral_brute_force"]


def bilateral_brute_force(values: Tensor, guide: Tensor, sigma_s: float, sigma_r: float,
                          radius: int | None = None, chunk: int = 1024) -> Tensor:
    """Exact joint (cross) bilateral / high-dimensional Gaussian filter.

    Args:
        values: (B, C, H, W) or (C, H, W) values f.
        guide: (B, D, H, W) or (D, H, W) guide f^ (sigma_r applies to every channel).
        sigma_s: spatial standard deviation in pixels.
        sigma_r: range standard deviation in guide units.
        radius: if given, only pixels with |dx|, |dy| <= radius contribute (a wide window);
            ``None`` uses the whole image.
        chunk: query pixels per block (memory ~ chunk * H * W * 8 bytes).

    Returns:
        float64 tensor shaped like ``values``. The centre pixel always contributes weight 1, so the
        denominator never vanishes. Non-finite inputs are not supported (the oracle is for clean data).

    Example:
        >>> v = torch.rand(1, 3, 8, 8); g = torch.rand(1, 2, 8, 8)
        >>> bilateral_brute_force(v, g, 2.0, 0.3).shape
        torch.Size([1, 3, 8, 8])
    """
    unbatched = values.dim() == 3
    if unbatched:
        values, guide = values.unsqueeze(0), guide.unsqueeze(0)
    f = values.detach().to(torch.float64)
    g = guide.detach().to(torch.float64)
    B, C, H, W = f.shape
    N = H * W
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    ys, xs = ys.reshape(-1).to(f.device), xs.reshape(-1).to(f.device)
    out = torch.empty((B, C, N), dtype=torch.float64, device=f.device)
    for b in range(B):
        fb = f[b].reshape(C, N).T  # (N, C)
        gb = g[b].reshape(-1, N).T  # (N, D)
        for s in range(0, N, chunk):
            e = min(N, s + chunk)
            dy = ys[s:e, None] - ys[None, :]
            dx = xs[s:e, None] - xs[None, :]
            logw = -(dx.square() + dy.square()) / (2 * sigma_s**2)
            logw = logw - torch.cdist(gb[s:e], gb).square() / (2 * sigma_r**2)
            if radius is not None:
                logw = logw.masked_fill((dx.abs() > radius) | (dy.abs() > radius), -torch.inf)
            wgt = torch.exp(logw)
            out[b, :, s:e] = (wgt @ fb / wgt.sum(1, keepdim=True)).T
    out = out.reshape(B, C, H, W)
    return out[0] if unbatched else out
