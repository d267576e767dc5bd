"""Inputs of the filter tests: procedural natural-looking images and PSNR (random inputs and the sample
data's path are fixtures of tests/conftest.py).

A uniquely named module (not conftest) so test files import it unambiguously whatever else pytest collects."""
import math

import torch


def make_natural(H, W, seed=0, noise=0.05, dtype=torch.float64):
    """(1, 3, H, W) in about [0, 1]: smooth gradients, two hard-edged shapes, texture, Gaussian noise."""
    gen = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.linspace(0, 1, H, dtype=torch.float64),
                          torch.linspace(0, 1, W, dtype=torch.float64), indexing="ij")
    phase = float(torch.rand((), generator=gen, dtype=torch.float64)) * 6.0
    img = torch.stack([0.3 + 0.4 * x, 0.2 + 0.5 * y, 0.5 + 0.2 * torch.sin(6 * x + 3 * y + phase)])
    disc = ((x - 0.6) ** 2 + (y - 0.4) ** 2 < 0.06).to(torch.float64)
    rect = ((x > 0.1) & (x < 0.4) & (y > 0.55) & (y < 0.9)).to(torch.float64)
    img = img * (1 - disc) + disc * torch.tensor([0.9, 0.2, 0.1], dtype=torch.float64)[:, None, None]
    img = img * (1 - rect) + rect * torch.tensor([0.1, 0.3, 0.8], dtype=torch.float64)[:, None, None]
    img = (img + 0.08 * torch.sin(40 * x) * torch.sin(37 * y)).clamp(0, 1)
    img = img + noise * torch.randn(img.shape, generator=gen, dtype=torch.float64)
    return img[None].to(dtype)


def psnr(a, b, peak=1.0):
    mse = (a.double() - b.double()).square().mean().item()
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)
