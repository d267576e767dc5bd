"""PNG images, written atomically."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from torchmanifold.io.files import atomic_path

__all__ = ["write_png"]


def write_png(path: str | os.PathLike, img: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` uint8 image (e.g. :func:`~torchmanifold.io.video.to_uint8_srgb`'s) as a PNG."""
    import imageio.v3 as iio

    img = np.asarray(img)
    if img.ndim != 3 or img.shape[-1] != 3 or img.dtype != np.uint8:
        raise ValueError(f"write_png: img must be an (H, W, 3) uint8 array, got {img.shape} {img.dtype}")
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img)
    return Path(path)
