"""Rendered frames as torch tensors, and their multi-channel EXR files.

EXR channel names follow the conventions other tools read (Mitsuba's ``aov`` integrator, Blender
passes, OIDN examples) so files from this tracer and from other renderers go through the same code:

=========  ==========================  =======
feature    EXR channel                 storage
=========  ==========================  =======
colour     ``R G B``                   float32
``T``      ``T``                       float32
``Z``      ``Z``                       float32 (distance along the camera ray, 0 = background)
``Mr..b``  ``albedo.R albedo.G albedo.B``  half
``Nx..z``  ``N.X N.Y N.Z``             half (world space, facing the camera ray)
``Dx..z``  ``D.X D.Y D.Z``             half (direction leaving the first hit)
``Sx..z``  ``S.X S.Y S.Z``             half (shadow-ray direction at the first hit)
emission   ``emission.R/G/B``          float32
motion     ``motion.X motion.Y``       float32 (pixels per frame, x right, y down)
object id  ``objectId``                float32 (integer values, -1 = background)
=========  ==========================  =======
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchmanifold.io.exr import read_exr, write_exr
from torchmanifold.render.scene import FEATURE_NAMES

EXR_CHANNELS = {
    "T": "T", "Z": "Z",
    "Mr": "albedo.R", "Mg": "albedo.G", "Mb": "albedo.B",
    "Nx": "N.X", "Ny": "N.Y", "Nz": "N.Z",
    "Dx": "D.X", "Dy": "D.Y", "Dz": "D.Z",
    "Sx": "S.X", "Sy": "S.Y", "Sz": "S.Z",
}
_HALF_FEATURES = {"Mr", "Mg", "Mb", "Nx", "Ny", "Nz", "Dx", "Dy", "Dz", "Sx", "Sy", "Sz"}


@dataclass
class RenderResult:
    """A batch of T rendered frames of size H x W.

    Attributes:
        color: ``(T, 3, H, W)`` float32 linear radiance, mean over the samples.
        features: ``(T, D, H, W)`` float32 per-pixel mean of the per-sample features.
        feature_names: the D channel names (a subset of ``FEATURE_NAMES``).
        object_id: ``(T, H, W)`` int32 object hit by the pixel-centre ray at the frame time, -1 = none.
        motion: ``(T, 2, H, W)`` float32 screen-space motion (pixels per frame, x right, y down) of
            that first hit from the frame time to one frame later.
        emission: ``(T, 3, H, W)`` float32 radiance emitted at the first hit (part of ``color``).
        times: ``(T,)`` float64 frame times.
        spp, sample_offset, seed: the samples that were drawn.
    """

    color: torch.Tensor
    features: torch.Tensor
    feature_names: list[str]
    object_id: torch.Tensor
    motion: torch.Tensor
    emission: torch.Tensor
    times: torch.Tensor
    spp: int
    sample_offset: int
    seed: int

    def feature(self, name: str) -> torch.Tensor:
        """The ``(T, H, W)`` channel ``name`` of :attr:`features`."""
        if name not in self.feature_names:
            raise ValueError(f"feature: name must be one of {self.feature_names}, got {name!r}")
        return self.features[:, self.feature_names.index(name)]

    def __len__(self) -> int:
        return self.color.shape[0]


def write_frame_exr(path: str | os.PathLike, res: RenderResult, index: int = 0) -> Path:
    """Write frame ``index`` of ``res`` as one multi-channel EXR (channel names in the module docstring).

    Returns:
        The path written.
    """
    if not isinstance(res, RenderResult):
        raise TypeError(f"write_frame_exr: res must be a RenderResult, got {type(res).__name__}")
    if not isinstance(index, int) or not -len(res) <= index < len(res):
        raise ValueError(f"write_frame_exr: index must be an int in [0, {len(res)}), got {index!r}")
    chans: dict[str, np.ndarray] = {}
    col = res.color[index].numpy()
    for c, n in enumerate("RGB"):
        chans[n] = col[c]
    feats = res.features[index].numpy()
    for k, name in enumerate(res.feature_names):
        chans[EXR_CHANNELS[name]] = feats[k]
    emi = res.emission[index].numpy()
    for c, n in enumerate("RGB"):
        chans[f"emission.{n}"] = emi[c]
    mot = res.motion[index].numpy()
    chans["motion.X"], chans["motion.Y"] = mot[0], mot[1]
    chans["objectId"] = res.object_id[index].numpy().astype(np.float32)
    half = [EXR_CHANNELS[n] for n in res.feature_names if n in _HALF_FEATURES]
    return write_exr(path, chans, half=half)


def read_frame_exr(path: str | os.PathLike) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """Read colour and features back from an EXR written by :func:`write_frame_exr` (or by another
    renderer using the same names, e.g. Mitsuba's ``albedo.R``/``N.X``/``Z``).

    Returns:
        ``(color (3, H, W), features (D, H, W), feature_names)`` with the features present in the
        file, in ``FEATURE_NAMES`` order.
    """
    chans = read_exr(path)
    missing = [c for c in "RGB" if c not in chans]
    if missing:
        raise ValueError(f"{path}: channels {missing} not found; the file has {sorted(chans)}")
    color = torch.from_numpy(np.stack([chans[c] for c in "RGB"]))
    names = [n for n in FEATURE_NAMES if EXR_CHANNELS[n] in chans]
    h, w = color.shape[1:]
    feats = torch.from_numpy(np.stack([chans[EXR_CHANNELS[n]] for n in names])) if names else torch.zeros(0, h, w)
    return color, feats, names
