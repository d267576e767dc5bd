"""Rendered frames as torch tensors, and their multi-channel EXR files.

EXR channel names follow the conventions other tools read (Mitsuba's ``aov`` integrator, OIDN
examples) so files from this tracer and from other renderers go through the same code. Feature
channels are named by the feature table (:mod:`torchmanifold.features`: ``albedo.R``, ``N.X``, ``Z``,
``D.X`` ... in half or float32 as it says); the rest:

=========  ==========================  =======
data       EXR channel                 storage
=========  ==========================  =======
colour     ``R G B``                   float32
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

from torchmanifold import features as F
from torchmanifold.io.exr import write_exr
from torchmanifold.io.frames import read_render_frame


@dataclass
class RenderResult:
    """A batch of T rendered frames of size H x W.

    Attributes:
        color: ``(T, 3, H, W)`` float32 linear radiance, mean over the samples.
        features: ``(T, D, H, W)`` float32 per-pixel mean of the per-sample features.
        feature_names: the D tracer channel names (from :func:`torchmanifold.features.tracer_names`).
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
        chans[F.canonical_name(name)] = feats[k]
    emi = res.emission[index].numpy()
    for c, n in enumerate("RGB"):
        chans[f"emission.{n}"] = emi[c]
    mot = res.motion[index].numpy()
    chans["motion.X"], chans["motion.Y"] = mot[0], mot[1]
    chans["objectId"] = res.object_id[index].numpy().astype(np.float32)
    return write_exr(path, chans, half=[c for c in chans if F.is_half(c)])


def read_frame_exr(path: str | os.PathLike) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """Read colour and the tracer's features back from an EXR written by :func:`write_frame_exr` (or
    any file :func:`~torchmanifold.io.frames.read_render_frame` reads, e.g. Mitsuba's).

    Returns:
        ``(color (3, H, W), features (D, H, W), feature_names)``: the features our tracer makes that
        the file has, under their tracer names, in shader-slot order.
    """
    frame = read_render_frame(path)
    canon = {t: F.canonical_name(t) for t in F.tracer_names()}
    names = [t for t, c in canon.items() if c in frame.features]
    h, w = frame.color.shape[1:]
    feats = np.stack([frame.features[canon[t]] for t in names]) if names else np.zeros((0, h, w), np.float32)
    return torch.from_numpy(frame.color), torch.from_numpy(feats), names
