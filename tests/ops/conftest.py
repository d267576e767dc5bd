"""Shared inputs for the filter tests: procedural natural-looking images and a Mitsuba crop."""
import math
from pathlib import Path

import numpy as np
import pytest
import torch

# shared/ lies beside the repository (CI's clean clone and a developer's checkout alike).
DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "mitsuba" / "cbox_glossy_tex"
if not DATA.is_dir():
    DATA = Path("/work/shared/data/mitsuba/cbox_glossy_tex")


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


@pytest.fixture(scope="session")
def natural():
    return make_natural


@pytest.fixture(scope="session")
def psnr_fn():
    return psnr


@pytest.fixture(scope="session")
def mitsuba_crop():
    """A 64x64 crop of 1-spp frame 0: values (1, 3, 64, 64) clipped to [0, 1] and a 7-channel guide
    (albedo, shading normal / 2, distance / 4), float64."""
    from torchmanifold.io.exr import read_exr

    d = read_exr(DATA / "frame_0000.exr")
    sl = (slice(150, 214), slice(100, 164))
    rgb = np.stack([d[c][sl] for c in "RGB"])
    feats = [np.clip(d[f"albedo.{c}"][sl], 0, 1) for c in "RGB"]
    feats += [d[f"N.{c}"][sl] * 0.5 for c in "XYZ"] + [d["Z"][sl] * 0.25]
    values = torch.from_numpy(np.clip(rgb, 0, 1)).double()[None]
    guide = torch.from_numpy(np.stack(feats)).double()[None]
    return values, guide
