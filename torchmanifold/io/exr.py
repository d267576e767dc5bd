"""Multi-channel EXR files with named channels (``R``, ``albedo.R``, ``N.X``, ``Z`` ...).

Thin wrappers over the OpenEXR Python bindings that other renderers' AOV files and our own
frames go through. Writes are atomic (temporary name, then rename) so a failed run never
leaves a half-written frame behind.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
import OpenEXR


def read_exr(path: str | os.PathLike, channels: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """Read the channels of a scanline or tiled EXR file as float32 ``(H, W)`` arrays.

    Args:
        path: the file.
        channels: names to read; all channels when ``None``.

    Returns:
        ``{name: (H, W) float32 array}`` in the file's channel order.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable EXR, or a requested channel is missing (the message
            names the file, the channel and the channels the file has).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            stored = exr.channels()
            found = {name: np.asarray(ch.pixels) for name, ch in stored.items()}
    except Exception as exc:  # OpenEXR raises plain Exceptions for corrupt files
        raise ValueError(f"{path}: not a readable EXR file ({exc})") from exc
    if channels is None:
        return {name: arr.astype(np.float32, copy=False) for name, arr in found.items()}
    out = {}
    for name in channels:
        if name not in found:
            raise ValueError(f"{path}: channel {name!r} not found; the file has {sorted(found)}")
        out[name] = found[name].astype(np.float32, copy=False)
    return out


def write_exr(
    path: str | os.PathLike,
    channels: Mapping[str, np.ndarray],
    half: Iterable[str] = (),
) -> Path:
    """Write ``(H, W)`` arrays as named channels of one EXR file, atomically.

    Args:
        path: destination; written under a temporary name first, then renamed.
        channels: ``{name: (H, W) array}``; all must share one shape.
        half: names stored as 16-bit half floats (features need no more); the rest as float32.

    Returns:
        The path written.
    """
    path = Path(path)
    half = set(half)
    shapes = {np.shape(a) for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"write_exr: channels must all be (H, W) arrays of one shape, got {sorted(shapes)}")
    data = {
        name: np.ascontiguousarray(arr, dtype=np.float16 if name in half else np.float32)
        for name, arr in channels.items()
    }
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    tmp = path.with_name(path.name + ".tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with OpenEXR.File(header, data) as exr:
            exr.write(str(tmp))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
