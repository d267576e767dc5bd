"""Fixtures of the filter tests: procedural natural-looking images, a Mitsuba crop, thread-count restore."""
import numpy as np
import pytest
import torch

from _ops_inputs import make_natural, psnr


@pytest.fixture(scope="session")
def natural():
    return make_natural


@pytest.fixture(scope="session")
def psnr_fn():
    return psnr


@pytest.fixture(scope="session")
def mitsuba_crop(mitsuba_dir):
    """A 64x64 crop of 1-spp frame 0: values (1, 3, 64, 64) clipped to [0, 1] and a 7-channel guide
    (albedo, shading normal / 2, distance / 4), float64."""
    from torchmanifold.io.exr import read_exr

    d = read_exr(mitsuba_dir / "frame_0000.exr")
    sl = (slice(150, 214), slice(100, 164))
    rgb = np.stack([d[c][sl] for c in "RGB"])
    feats = [np.clip(d[f"albedo.{c}"][sl], 0, 1) for c in "RGB"]
    feats += [d[f"N.{c}"][sl] * 0.5 for c in "XYZ"] + [d["Z"][sl] * 0.25]
    values = torch.from_numpy(np.clip(rgb, 0, 1)).double()[None]
    guide = torch.from_numpy(np.stack(feats)).double()[None]
    return values, guide


@pytest.fixture
def threads():
    """Restores torch's thread count after a test that sets it."""
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)
