"""Helpers of the demo tests: small sizes so the real tracer and filter run in seconds."""
from __future__ import annotations

import numpy as np

SMALL = ["--width", "48", "--height", "32", "--scale", "2", "--clip", "2", "--reference-spp", "32", "--paused"]


def srgb_u8(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Second implementation of the panel shader's tone map: clamped sRGB, in 0..255 floats."""
    c = np.clip(linear * exposure, 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return s * 255.0


def upscale(img: np.ndarray, scale: int) -> np.ndarray:
    return img.repeat(scale, axis=0).repeat(scale, axis=1)


def crop(frame: np.ndarray, rect) -> np.ndarray:
    x, y, w, h = rect
    return frame[y:y + h, x:x + w].astype(np.float64)
