"""Output files and folders: every file is written under a temporary name and renamed into place, so
a failed or interrupted run never leaves a half-written file behind."""
from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_path", "staged_dir", "write_text", "prepare_out"]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Give a temporary sibling of ``path`` to write; it replaces ``path`` when the block ends without
    an error and is removed otherwise.

    The temporary name keeps the suffix (``clip.tmp.mp4``) because some writers choose the format by it.

    Example:
        >>> with atomic_path(out / "chart.png") as tmp:
        ...     fig.savefig(tmp)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextlib.contextmanager
def staged_dir(out: str | os.PathLike) -> Iterator[Path]:
    """All or nothing for a set of files: give a staging folder inside ``out``; when the block ends
    without an error every file in it is moved into ``out``, otherwise none is.

    Example:
        >>> with staged_dir(out) as stage:
        ...     for name, img in frames.items():
        ...         write_exr(stage / name, img)
    """
    out = Path(out)
    stage = out / ".partial"
    if stage.exists():
        shutil.rmtree(stage)
    stage.mkdir(parents=True)
    try:
        yield stage
        for p in sorted(stage.iterdir()):
            os.replace(p, out / p.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def prepare_out(out: str | os.PathLike, overwrite: bool) -> Path:
    """Create the output folder ``--out``; an existing non-empty one is reused only with ``overwrite``."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a directory")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"--out {out} exists and is not empty; pass --overwrite to reuse it")
    out.mkdir(parents=True, exist_ok=True)
    return out
