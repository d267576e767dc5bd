"""Multi-channel EXR files with named channels (``R``, ``albedo.R``, ``N.X``, ``Z`` ...).

Thin wrappers over the OpenEXR Python bindings that other renderers' AOV files and our own
frames go through. Reads see every part of a multi-part file (Blender 5 writes one part per pass).
Writes are atomic (temporary name, then rename) so a failed run never leaves a half-written frame
behind.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
import OpenEXR

from torchmanifold.io.files import atomic_path


def exr_samples_per_pixel(path: str | os.PathLike) -> int | None:
    """Samples per pixel the file's header records (see :func:`header_samples_per_pixel`); ``None`` when
    no part says, or the file cannot be read (:func:`read_exr` reports unreadable files)."""
    try:
        with OpenEXR.File(str(path), header_only=True) as exr:  # headers are views: copy them inside
            headers = [dict(p.header.items()) for p in exr.parts]
    except Exception:  # only a hint
        return None
    return header_samples_per_pixel(headers)


def header_samples_per_pixel(headers: Iterable[Mapping]) -> int | None:
    """Samples per pixel that EXR part headers record: ``spp`` (as the shared Mitsuba clips carry it) or
    Blender Cycles' ``cycles.<view layer>.samples``; ``None`` when no part says, or says something else
    than a positive integer."""
    for h in headers:
        for key, value in h.items():
            if key == "spp" or (key.startswith("cycles.") and key.endswith(".samples")):
                try:
                    n = int(value.decode() if isinstance(value, bytes) else value)
                except (TypeError, ValueError):
                    continue
                if n > 0:
                    return n
    return None


def read_exr(path: str | os.PathLike, channels: Iterable[str] | None = None,
             headers: list | None = None) -> dict[str, np.ndarray]:
    """Read the channels of a scanline or tiled, single- or multi-part EXR file as float32 ``(H, W)`` arrays.

    Channels of all parts are merged. Parts normally carry full channel names (Blender 5:
    part ``ViewLayer.Depth`` holds ``ViewLayer.Depth.Z``); a short name that two parts share is
    prefixed with its part's name (``<part>.<channel>``).

    Args:
        path: the file.
        channels: names to read; all channels when ``None``.
        headers: a list that, when given, receives each part's header as a dict (one open of the file
            for its pixels and its attributes).

    Returns:
        ``{name: (H, W) float32 array}`` in the file's channel order.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable EXR, or a requested channel is missing (the message
            names the file, the channel and the channels the file has), or two parts hold the same
            channel name.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            parts = [(p.name(), {n: np.asarray(c.pixels) for n, c in p.channels.items()}) for p in exr.parts]
            origins = {tuple(int(v) for v in p.header["dataWindow"][0]) for p in exr.parts}
            if headers is not None:  # headers are views: copy them inside
                headers += [dict(p.header.items()) for p in exr.parts]
    except Exception as exc:  # OpenEXR raises plain Exceptions for corrupt files
        raise ValueError(f"{path}: not a readable EXR file ({exc})") from exc
    if len(origins) > 1:  # arrays start at their data window: parts that start elsewhere would not line up
        raise ValueError(f"{path}: the parts' data windows start at different pixels {sorted(origins)}; "
                         f"expected parts that line up")
    found = _merge_parts(path, parts)
    if channels is None:
        return {name: arr.astype(np.float32, copy=False) for name, arr in found.items()}
    out = {}
    for name in channels:
        if name not in found:
            raise ValueError(f"{path}: channel {name!r} not found; the file has {sorted(found)}")
        out[name] = found[name].astype(np.float32, copy=False)
    return out


def _merge_parts(path: Path, parts: list[tuple[str | None, dict[str, np.ndarray]]]) -> dict[str, np.ndarray]:
    count: dict[str, int] = {}
    for _, chans in parts:
        for n in chans:
            count[n] = count.get(n, 0) + 1
    found: dict[str, np.ndarray] = {}
    for part, chans in parts:
        for n, arr in chans.items():
            key = f"{part}.{n}" if count[n] > 1 and part else n
            if key in found:
                raise ValueError(f"{path}: channel {key!r} is stored in two parts of the file")
            found[key] = arr
    return found


def write_exr(
    path: str | os.PathLike,
    channels: Mapping[str, np.ndarray],
    half: Iterable[str] = (),
    attributes: Mapping[str, str] | None = None,
) -> Path:
    """Write ``(H, W)`` arrays as named channels of one EXR file, atomically.

    Args:
        path: destination; written under a temporary name first, then renamed.
        channels: ``{name: (H, W) array}``; all must share one shape.
        half: names stored as 16-bit half floats (features need no more); the rest as float32.
        attributes: extra string attributes of the header (e.g. Blender's ``BlenderMultiChannel``).

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
    header = {**(attributes or {}), "compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(header, data) as exr:
        exr.write(str(tmp))
    return path
