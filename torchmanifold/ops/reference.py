"""Brute-force high-dimensional Gaussian filter: the test oracle for the adaptive-manifold filter.

    g_i = sum_j exp(-|x_i - x_j|^2 / 2 sigma_s^2 - |f^_i - f^_j|^2 / 2 sigma_r^2) f_j / sum_j (same)

computed exactly in float64 over the whole image (or a square window of ``radius`` pixels), in
chunks of query pixels so 128 x 128 images take about a second. O(N^2): for small images only.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchmanifold._checks import check_int, check_positive, check_values_and_guide

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
    check_values_and_guide(values, guide)
    sigma_s, sigma_r = check_positive("sigma_s", sigma_s), check_positive("sigma_r", sigma_r)
    if radius is not None:
        radius = check_int("radius", radius, min=0)
    chunk = check_int("chunk", chunk, min=1)
    unbatched = values.dim() == 3
    if unbatched:
        values, guide = values.unsqueeze(0), guide.unsqueeze(0)
    f = values.detach().to(torch.float64)
    g = guide.detach().to(torch.float64)
    B, C, H, W = f.shape
    N = H * W
    dev = f.device
    # separable spatial log-weights per axis, broadcast into (chunk, H, W) rows below
    ay = torch.arange(H, dtype=torch.float64, device=dev)
    ax = torch.arange(W, dtype=torch.float64, device=dev)
    ly = -(ay[:, None] - ay[None, :]).square() / (2 * sigma_s**2)  # (H, H)
    lx = -(ax[:, None] - ax[None, :]).square() / (2 * sigma_s**2)  # (W, W)
    if radius is not None:
        ly = ly.masked_fill((ay[:, None] - ay[None, :]).abs() > radius, -torch.inf)
        lx = lx.masked_fill((ax[:, None] - ax[None, :]).abs() > radius, -torch.inf)
    iy = torch.arange(N, device=dev) // W
    ix = torch.arange(N, device=dev) % W
    inv = 1.0 / (2 * sigma_r**2)
    out = torch.empty((B, C, N), dtype=torch.float64, device=dev)
    for b in range(B):
        fb = torch.cat([f[b].reshape(C, N).T, torch.ones(N, 1, dtype=torch.float64, device=dev)], 1)
        gb = g[b].reshape(-1, N).T  # (N, D)
        sq = gb.square().sum(1)
        for s in range(0, N, chunk):
            e = min(N, s + chunk)
            # -|g_i - g_j|^2 / 2 sigma_r^2 via |a|^2 + |b|^2 - 2ab (float64; clamped at 0), in place
            logw = torch.addmm(sq[None, :], gb[s:e], gb.T, beta=1.0, alpha=-2.0)
            logw.add_(sq[s:e, None]).clamp_(min=0.0).mul_(-inv)
            logw.view(e - s, H, W).add_(ly[iy[s:e]][:, :, None]).add_(lx[ix[s:e]][:, None, :])
            acc = logw.exp_() @ fb  # (chunk, C + 1): numerators and the denominator
            out[b, :, s:e] = (acc[:, :C] / acc[:, C:]).T
    out = out.reshape(B, C, H, W)
    return out[0] if unbatched else out
