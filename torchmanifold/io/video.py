"""Video files of a clip: MP4 (H.264 through imageio-ffmpeg), written atomically."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from torchmanifold.io.files import atomic_path

__all__ = ["to_uint8_srgb", "write_mp4"]


def to_uint8_srgb(frames: torch.Tensor) -> np.ndarray:
    """``(T, 3, H, W)`` or ``(3, H, W)`` linear radiance -> ``(T, H, W, 3)`` / ``(H, W, 3)`` uint8 sRGB."""
    from torchmanifold.metrics import linear_to_srgb

    if not isinstance(frames, torch.Tensor) or frames.dim() not in (3, 4) or frames.shape[-3] != 3:
        raise ValueError(f"frames must be a (T, 3, H, W) or (3, H, W) tensor, got "
                         f"{tuple(frames.shape) if isinstance(frames, torch.Tensor) else type(frames).__name__}")
    x = torch.nan_to_num(frames.float(), nan=0.0, posinf=1.0, neginf=0.0)
    x = (linear_to_srgb(x) * 255.0 + 0.5).clamp(0, 255).to(torch.uint8)
    return x.movedim(-3, -1).numpy()


def write_mp4(path: str | os.PathLike, frames, fps: float = 12.0, quality: int = 8) -> Path:
    """Write frames as an H.264 MP4 (yuv420p, odd sizes padded by one pixel).

    Args:
        path: destination; written as ``<name>.tmp.mp4`` then renamed.
        frames: ``(T, H, W, 3)`` uint8 array, or a ``(T, 3, H, W)`` linear tensor (converted to sRGB).
        fps: frames per second.
        quality: imageio-ffmpeg quality 0..10.
    """
    import imageio_ffmpeg

    if isinstance(frames, torch.Tensor):
        frames = to_uint8_srgb(frames)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or frames.shape[0] == 0:
        raise ValueError(f"frames must be a non-empty (T, H, W, 3) uint8 array, got {frames.shape} {frames.dtype}")
    if not (fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    h, w = frames.shape[1:3]
    ph, pw = h + h % 2, w + w % 2
    if (ph, pw) != (h, w):
        frames = np.pad(frames, ((0, 0), (0, ph - h), (0, pw - w), (0, 0)), mode="edge")
    with atomic_path(path) as tmp:
        writer = imageio_ffmpeg.write_frames(str(tmp), (pw, ph), fps=fps, quality=quality, pix_fmt_out="yuv420p",
                                             macro_block_size=1)
        writer.send(None)
        for f in frames:
            writer.send(np.ascontiguousarray(f))
        writer.close()
    return Path(path)
