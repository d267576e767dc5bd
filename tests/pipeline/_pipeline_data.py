"""The Mitsuba sample clip for the pipeline tests (a uniquely named module, not conftest, so test files
import it unambiguously whatever else pytest collects)."""
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
