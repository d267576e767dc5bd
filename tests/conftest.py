"""Fixtures every test directory shares: devices, random filter inputs and where the sample data lies.

- ``device``: ``"cpu"``, and ``"cuda"`` when a GPU is there; a test that takes it runs once per device.
- ``random_inputs``: the one generator of random values and guides for filter tests.
- ``data_dir``: the sample data (``shared/data``, see ``data_dir``'s docstring for where it is looked for).
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


def random_inputs(B: int, C: int, D: int, H: int, W: int, *, T: int | None = None, dtype=torch.float32,
                  seed: int = 0, edge: float = 0.7, device="cpu"):
    """Values ``(B, C, H, W)`` uniform in [0, 1) and a guide ``(B, D, H, W)`` uniform in [0, 1) with ``edge``
    added to its top half rows (a step, so the manifold tree really splits into clusters).

    ``T``: frames, giving ``(B, T, C, H, W)`` / ``(B, T, D, H, W)``. Drawn in float64 from a generator seeded
    with ``seed`` on the CPU, then cast and moved, so every dtype and device sees the same numbers.
    """
    gen = torch.Generator().manual_seed(seed)
    lead = (B,) if T is None else (B, T)
    v = torch.rand(*lead, C, H, W, generator=gen, dtype=torch.float64)
    g = torch.rand(*lead, D, H, W, generator=gen, dtype=torch.float64)
    g[..., : H // 2, :] += edge
    return v.to(device, dtype), g.to(device, dtype)


@pytest.fixture(scope="session", name="random_inputs")
def random_inputs_fixture():
    """:func:`random_inputs` (a fixture so that test files in any directory share the one generator)."""
    return random_inputs


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The sample data folder (``mitsuba/``, ...): ``$TORCHMANIFOLD_DATA`` if set (the benchmarks read the
    same variable), else ``shared/data`` inside the checkout, else beside it. Missing data fails the
    test that needs it, naming where it looked."""
    env = os.environ.get("TORCHMANIFOLD_DATA")
    candidates = [Path(env)] if env else [REPO / "shared" / "data", REPO.parent / "shared" / "data"]
    for path in candidates:
        if (path / "mitsuba").is_dir():
            return path
    pytest.fail(f"sample data not found at {', '.join(map(str, candidates))}; set TORCHMANIFOLD_DATA")


@pytest.fixture(scope="session")
def mitsuba_dir(data_dir) -> Path:
    """The Mitsuba 3 sample clip (1-spp frames with features, 1024-spp references)."""
    return data_dir / "mitsuba" / "cbox_glossy_tex"
