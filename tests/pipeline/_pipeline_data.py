"""The Mitsuba sample clip and the validation set's clips for the pipeline tests (a uniquely named module,
not conftest, so test files import it unambiguously whatever else pytest collects)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

FEATURES = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z", "P.X", "P.Y", "P.Z"]


def load_clip(data: Path, kind: str, frames, crop=None):
    """(T,3,H,W) colour (and (T,D,H,W) features for 1-spp frames) of the sample clip in ``data`` (the
    ``mitsuba_dir`` fixture)."""
    from torchmanifold.io import read_exr

    cols, feats = [], []
    for i in frames:
        d = read_exr(data / f"{kind}_{i:04d}.exr")
        sl = (slice(None), slice(None)) if crop is None else crop
        cols.append(np.stack([d[c][sl] for c in "RGB"]))
        if kind == "frame":
            feats.append(np.stack([d[c][sl] for c in FEATURES]))
    col = torch.from_numpy(np.stack(cols))
    return (col, torch.from_numpy(np.stack(feats))) if feats else col


def validation_clip(name: str, frames, prefix: str = "frame"):
    """Frames, features and references of a clip of the committed validation set (benchmarks/validation);
    ``prefix`` ``"frame4spp"``: its 4-spp frames."""
    from torchmanifold.io.frames import read_render_frame

    root = Path(__file__).resolve().parents[2] / "benchmarks" / "validation" / "data" / name
    fr = [read_render_frame(root / f"{prefix}_{k:04d}.exr") for k in frames]
    names = fr[0].feature_names
    c = torch.from_numpy(np.stack([f.color for f in fr]))
    f = torch.from_numpy(np.stack([f.stack(names) for f in fr]))
    refs = [read_render_frame(root / f"reference_{k:04d}.exr").color for k in frames]
    ref = torch.from_numpy(np.stack(refs))
    return c, f, names, ref
