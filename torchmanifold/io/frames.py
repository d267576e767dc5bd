"""One rendered frame from an EXR file, whatever renderer wrote it: colour plus named features.

Two layouts are recognised from the channel names:

- ``"flat"``: colour ``R, G, B`` and feature channels under their own names: our tracer's files
  (``albedo.R``, ``N.X``, ``Z``, ``D.X`` ..., ``emission.R/G/B``) and Mitsuba 3's ``aov`` integrator
  (``albedo.R/G/B``, ``N.X/Y/Z``, ``Z``, ``P.X/Y/Z``), which share names.
- ``"blender"``: Blender's multilayer EXR, ``<view layer>.<pass>.<channel>``: colour from
  ``ViewLayer.Combined.R/G/B`` (``A`` kept for the output), features from the passes
  ``Denoising Albedo``, ``Denoising Normal`` (camera space), ``Denoising Depth``, ``Normal`` (world
  space), ``Depth`` (planar; its background value 1e10 is read as 0) and ``Position``; its
  ``Emission`` pass (``Emit`` before) is the emission at the first hit, like our ``emission.R/G/B``.
  Blender 5 writes one part per pass, older versions one part with every channel; both read the same.

Where a file lacks the names above, albedo, normals, positions and depth are also read under the names other
renderers give them (pbrt-v4's ``Albedo.R``, ``Ns.X``, ``Px``; ``normal.x``, ``depth``, Mitsuba's documented
``dd.y`` and ``nn.X``; Blender's ``Diffuse Color`` pass ``DiffCol`` without the denoising data; ``other_names``
in :mod:`torchmanifold.features`), and a note says what was read as what.

Features come back under their canonical names (:mod:`torchmanifold.features`). Bad input raises a
``ValueError`` naming the file, the layer and the channel; nothing is guessed silently: what the
reader changed (background depth read as 0, no feature passes at all) is listed in ``notes``.
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from torchmanifold import features as F
from torchmanifold.io.exr import header_samples_per_pixel, read_exr, write_exr

__all__ = ["RenderFrame", "read_render_frame", "write_color", "samples_per_pixel_shown", "mixed_count",
           "LAYOUTS"]

LAYOUTS = ("flat", "blender")
_COMBINED = "Combined"
_EMISSION = ("emission.R", "emission.G", "emission.B")
#: Blender's pass of radiance emitted at the first hit (part of Combined): its 5.0 name, then the older one
_BLENDER_EMISSION = ("Emission", "Emit")
#: header attribute that marks a Blender multilayer file (the value Blender 5.0 writes)
BLENDER_HEADER = {"BlenderMultiChannel": "Blender V2.55.1 and newer"}
#: a unit feature's vector (a normal) averages samples that point different ways where its length lies
#: in this band: under one sample's 1 (two normals 16 degrees apart average to 0.99; half floats keep a
#: unit vector within 1e-3 of 1) and over a miss's 0. Frame 5 of every validation clip (Mitsuba and
#: Cycles, benchmarks/validation): from 1 spp no pixel that hits is in the band, from 4 spp 1.3-25% are
_AVERAGED_LENGTH = (0.01, 0.99)
#: pixels that hit needed before their normals' lengths are evidence: at the least share of shortened
#: normals in a 4-spp frame of the validation set (1.2% of the hit pixels, cbox_glossy_tex) 512 hold 6
_MIN_HITS = 512
#: Where the normals show averaged samples, the count shows in the mixes themselves: a pixel across an edge
#: whose n samples fall k on one surface and n - k on the other holds features k / n of the way from one
#: surface's to the other's. Along each image axis and diagonal, a line of five pixels whose two outer pairs
#: each agree (one surface each, within :data:`_MIX_PURE` of the pairs' difference, which exceeds
#: :data:`_MIX_STEP`) and whose centre lies on the segment between the inner pair (off it by less than
#: :data:`_MIX_OFF` of its length, :data:`_MIX_INSIDE` or more from either end) gives the fraction t of a mix;
#: albedo, unit vectors and depth (in units of the line's farthest: a per-line scale keeps the mix linear)
#: make the vector. The count is the least n from 2 to :data:`_MOST_COUNT` at which the mean of cos(2 pi n t)
#: over at least :data:`_MIN_MIXES` such lines reaches :data:`_COUNT_PEAK` (1 where every t is a multiple of
#: 1/n). Frame 3 of every validation clip (Mitsuba's mean of n 1-spp passes, Cycles' n samples of one
#: sequence), 2 / 4 / 8 / 16 spp, the clips at 256x256 and the probes: every count found was the file's, the
#: rest none (thin rods and sky, fine textures: too few lines, or t not on the grid); Cycles' Blackman-Harris
#: pixel filter keeps the grid (its samples are placed by the filter, weighted alike), Mitsuba's gaussian does
#: not (its samples are weighted: none found). With the outer pairs' test left out, mixed pixels at the line's
#: ends put t at other fractions (1/3, 2/3) and 8 spp through a lens read as 24. A divisor of the count found
#: whose mean reaches :data:`_DIVISOR_PEAK` of the count's is taken instead: 2 spp over fine textures
#: (`mi_still_textures`, 64x64, a third of its t off the grid) peaked at 0.4996 for 2 and 0.56 for 4
_MIX_PURE, _MIX_OFF, _MIX_STEP, _MIX_INSIDE = 0.02, 0.02, 0.2, 0.03
_COUNT_PEAK, _MIN_MIXES, _MOST_COUNT, _DIVISOR_PEAK = 0.5, 64, 64, 0.8
#: rows read at a time, and the mixes after which the reading stops: a 1920x1080 frame is read until its
#: edges give as many as the validation set's busiest 256x256 frame holds in all (5254)
_MIX_BAND, _ENOUGH_MIXES = 64, 4096


@dataclass
class RenderFrame:
    """One frame read by :func:`read_render_frame`.

    Attributes:
        path: the file.
        color: ``(3, H, W)`` float32 linear radiance.
        features: ``{canonical name: (H, W) float32}`` in feature-table order (channels the table does
            not know, when asked for by name, come last under their file names).
        layout: ``"flat"`` or ``"blender"`` (see the module docstring).
        layer: Blender view layer the frame came from (``None`` for flat files).
        sources: file channel each colour / feature channel was read from (``{"R": "ViewLayer.Combined.R",
            "albedo.R": "ViewLayer.Denoising Albedo.R", ...}``).
        alpha: ``(H, W)`` float32 Blender ``Combined.A``, or ``None``.
        emission: ``(3, H, W)`` float32 radiance emitted at the first hit (our tracer's
            ``emission.R/G/B``, Blender's ``Emission`` pass), or ``None``.
        notes: what the reader changed or found missing, one sentence each.
        header_samples_per_pixel: the sample count the header records (see
            :func:`~torchmanifold.io.exr.header_samples_per_pixel`), or ``None``.
    """

    path: Path
    color: np.ndarray
    features: dict[str, np.ndarray]
    layout: str
    layer: str | None = None
    sources: dict[str, str] = field(default_factory=dict)
    alpha: np.ndarray | None = None
    emission: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    header_samples_per_pixel: int | None = None

    @functools.cached_property
    def samples_per_pixel(self) -> int | None:
        """The sample count the header records; where it records none, the count the features show
        (:func:`samples_per_pixel_shown`, said in ``notes``), else ``None``. Worked out when first asked for:
        a clip's count is its first frame's, and the later frames need not show theirs."""
        if self.header_samples_per_pixel is not None:
            return self.header_samples_per_pixel
        count, how = _count_shown(self.features)
        if how is not None:
            self.notes.append(how)
        return count

    @property
    def feature_names(self) -> list[str]:
        return list(self.features)

    @property
    def size(self) -> tuple[int, int]:
        """``(H, W)``."""
        return tuple(self.color.shape[1:])

    def stack(self, names: Sequence[str] | None = None) -> np.ndarray:
        """Features ``names`` (default: all) as one ``(D, H, W)`` float32 array."""
        names = self.feature_names if names is None else list(names)
        if not names:
            return np.zeros((0, *self.size), np.float32)
        return np.stack([self.features[n] for n in names])


def _where(path: Path, layer: str | None) -> str:
    return f"{path}: layer {layer!r}" if layer is not None else str(path)


def _blender_layers(chans: Sequence[str]) -> dict[str, dict[str, list[str]]]:
    """``{view layer: {pass: [channel suffixes]}}`` of the channels named ``<layer>.<pass>.<c>`` with a
    pass Blender writes (``Combined`` or one the feature table lists)."""
    passes = {_COMBINED, *_BLENDER_EMISSION} | {a.rsplit(".", 1)[0] for f in F.FEATURES for a in f.blender}
    layers: dict[str, dict[str, list[str]]] = {}
    for name in chans:
        bits = name.rsplit(".", 2)
        if len(bits) == 3 and bits[1] in passes:
            layers.setdefault(bits[0], {}).setdefault(bits[1], []).append(bits[2])
    return layers


def _pick_layer(path: Path, layers: dict, layer: str | None) -> str:
    if layer is not None:
        if layer not in layers:
            raise ValueError(f"{path}: layer {layer!r} not found; the file has view layers {sorted(layers)}")
        return layer
    if len(layers) > 1:
        raise ValueError(f"{path}: the file has several view layers {sorted(layers)}; choose one (--layer)")
    return next(iter(layers))


def _check_pass(path: Path, layer: str, name: str, have: list[str], expected: Sequence[str],
                optional: Sequence[str] = ()) -> None:
    extra = sorted(set(have) - set(expected) - set(optional))
    missing = [c for c in expected if c not in have]
    if missing or extra:
        raise ValueError(
            f"{_where(path, layer)}: pass {name!r} has channels {sorted(have)}, expected {list(expected)}"
            + (f" (+ optional {list(optional)})" if optional else "")
            + (f"; missing {layer}.{name}.{missing[0]}" if missing
               else f"; unexpected {layer}.{name}.{extra[0]}"))


def _read_blender(path: Path, chans: dict, layers: dict, layer: str | None, frame: RenderFrame,
                  color_channels: Sequence[str] | None) -> None:
    layer = _pick_layer(path, layers, layer)
    passes = layers[layer]
    frame.layout, frame.layer = "blender", layer
    if color_channels is not None:
        _color_from(path, chans, color_channels, frame)
    elif _COMBINED not in passes:
        raise ValueError(f"{_where(path, layer)}: no {_COMBINED} pass ({layer}.{_COMBINED}.R/G/B); the layer "
                         f"has passes {sorted(passes)} (name the colour channels with --color)")
    else:
        _check_pass(path, layer, _COMBINED, passes[_COMBINED], "RGB", optional="A")
        frame.sources.update({c: f"{layer}.{_COMBINED}.{c}" for c in "RGB"})
        if "A" in passes[_COMBINED]:
            frame.sources["A"] = f"{layer}.{_COMBINED}.A"
    for name in [n for n in _BLENDER_EMISSION if n in passes][:1]:
        _check_pass(path, layer, name, passes[name], "RGB", optional="A")
        frame.sources.update({e: f"{layer}.{name}.{c}" for e, c in zip(_EMISSION, "RGB")})
    for f in F.FEATURES:
        if not f.blender:
            continue
        name = f.blender[0].rsplit(".", 1)[0]
        if name not in passes:
            continue
        _check_pass(path, layer, name, passes[name], [a.rsplit(".", 1)[1] for a in f.blender])
        for alias, canon in zip(f.blender, f.channels):
            frame.sources[canon] = f"{layer}.{alias}"
    _read_other_names(chans, frame, f"{layer}.")


def _color_from(path: Path, chans: dict, color_channels: Sequence[str], frame: RenderFrame) -> None:
    if len(color_channels) != 3:
        raise ValueError(f"color_channels must name 3 channels, got {list(color_channels)}")
    missing = [c for c in color_channels if c not in chans]
    if missing:
        raise ValueError(f"{path}: colour channel(s) {missing} not found; the file has {sorted(chans)}")
    frame.sources.update(dict(zip("RGB", color_channels)))


def _read_flat(path: Path, chans: dict, color_channels: Sequence[str], frame: RenderFrame) -> None:
    frame.layout = "flat"
    _color_from(path, chans, color_channels, frame)
    names = {**F.channel_aliases("mitsuba"), **F.channel_aliases("torchmanifold")}
    for f in F.FEATURES:
        found = [a for a in chans if names.get(a) in f.channels]
        if not found:
            continue
        got = {names[a]: a for a in found}
        absent = [c for c in f.channels if c not in got]
        if absent:
            raise ValueError(f"{path}: feature {f.group!r} has channels {sorted(found)} but not "
                             f"{absent[0]!r}; "
                             f"expected all of {list(f.channels)}")
        frame.sources.update({c: got[c] for c in f.channels})
    _read_other_names(chans, frame)


def _read_other_names(chans: dict, frame: RenderFrame, prefix: str = "") -> None:
    """Add to ``frame.sources`` the features its file holds under names other renderers use, among the
    channels starting with ``prefix`` (a Blender layer's ``<layer>.``) that nothing reads yet: for the groups
    not found under ours (pbrt-v4's ``Albedo.R``, a user's ``normal.x``, Blender's ``DiffCol``), and those
    preferred to ours (pbrt-v4's shading normal ``Ns`` beside its geometric ``N``); a note says what was read
    as what."""
    found = {F.group_of(c) for c in frame.sources} & {f.group for f in F.FEATURES}
    used = set(frame.sources.values())
    free = {c[len(prefix):]: c for c in chans if c.startswith(prefix) and c not in used}
    guessed = F.other_renderer_channels(free, [f.group for f in F.FEATURES if f.group not in found], found)
    for group in dict.fromkeys(F.group_of(c) for c in guessed.values()):
        read = {c: free[a] for a, c in guessed.items() if F.group_of(c) == group}
        instead = [frame.sources[c] for c in read if c in frame.sources]
        frame.sources.update(read)
        frame.notes.append(f"read {', '.join(read.values())} as {', '.join(read)} (names other renderers "
                           f"use for {group!r}" + (f"; in place of {', '.join(instead)})" if instead else ")"))


def _choose_features(path: Path, frame: RenderFrame, chans: dict, wanted: Sequence[str] | None) -> list[str]:
    """Canonical feature names to load: all the file has, or ``wanted`` (any alias; unknown names are
    read as the file channel of that name)."""
    known = [c for f in F.FEATURES for c in f.channels if c in frame.sources]
    if wanted is None:
        return known
    out = []
    for w in wanted:
        short = w[len(frame.layer) + 1:] if frame.layer and w.startswith(frame.layer + ".") else w
        c = F.canonical_name(short)
        if c in out:
            continue  # named twice (e.g. by two aliases)
        if c in frame.sources:
            out.append(c)
        elif w in chans:
            frame.sources[w] = w
            out.append(w)
        else:
            raise ValueError(f"{_where(path, frame.layer)}: feature channel {w!r} not found; the file has "
                             f"features {known} (channels {sorted(chans)})")
    return out


def _check_feature_values(path: Path, frame: RenderFrame) -> None:
    for g in dict.fromkeys(F.group_of(n) for n in frame.features):
        names = [n for n in frame.features if F.group_of(n) == g]
        vals = [frame.features[n] for n in names]
        src = ", ".join(frame.sources[n] for n in names)
        if not any(np.isfinite(v).any() for v in vals):
            raise ValueError(f"{_where(path, frame.layer)}: channel(s) {src}: no finite value (all NaN/inf)")
        row = F.feature_of(names[0])
        ok_zero = row is None or row.may_be_all_zero  # a channel the table does not know: 0 may be its value
        if not ok_zero and not any(np.nan_to_num(v).any() for v in vals):
            raise ValueError(f"{_where(path, frame.layer)}: channel(s) {src}: every value is 0 (a pass that "
                             f"was not rendered?); leave it out with --features / feature_channels")


def read_render_frame(path: str | os.PathLike, color_channels: Sequence[str] | None = None,
                      feature_channels: Sequence[str] | None = None, layer: str | None = None) -> RenderFrame:
    """Read colour and features of one frame from an EXR file of any layout (see the module docstring).

    Args:
        path: the EXR file (single- or multi-part).
        color_channels: the three file channels holding colour; ``None`` = ``R, G, B`` or Blender's
            ``<layer>.Combined.R/G/B``.
        feature_channels: features to load, by canonical, tracer, Mitsuba or Blender name (with or
            without the view-layer prefix), or any file channel name; ``None`` = every feature of
            the feature table the file has.
        layer: Blender view layer to read (needed only when the file has several).

    Returns:
        A :class:`RenderFrame`: ``color (3, H, W)``, ``features {canonical name: (H, W)}`` (float32).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not an EXR; no colour (a Blender file without a ``Combined`` pass); a pass with
            missing or extra channels; a feature or colour channel of another size than the colour;
            a feature with no finite value or (except time ``T``) all zeros. The message names the
            file, the layer and the channel.

    Example:
        >>> fr = read_render_frame("frame_0001.exr")  # Mitsuba's, ours or Blender's
        >>> fr.color.shape, fr.feature_names
        ((3, 256, 256), ['Z', 'albedo.R', 'albedo.G', 'albedo.B', 'N.X', 'N.Y', 'N.Z', 'P.X', 'P.Y', 'P.Z'])
    """
    path = Path(path)
    headers: list = []
    chans = read_exr(path, headers=headers)
    frame = RenderFrame(path, np.zeros((3, 0, 0), np.float32), {}, "flat",
                        header_samples_per_pixel=header_samples_per_pixel(headers))
    layers = _blender_layers(list(chans))
    if layers:
        _read_blender(path, chans, layers, layer, frame, color_channels)
    else:
        _read_flat(path, chans, color_channels or ("R", "G", "B"), frame)
    names = _choose_features(path, frame, chans, feature_channels)

    color_src = [frame.sources[c] for c in "RGB"]
    size = chans[color_src[0]].shape
    extra = names + [c for c in ("A", *_EMISSION) if c in frame.sources]
    for src in color_src + [frame.sources[n] for n in extra]:
        if chans[src].shape != size:
            raise ValueError(f"{_where(path, frame.layer)}: channel {src!r} is {chans[src].shape[1]}x"
                             f"{chans[src].shape[0]} pixels, the colour {color_src[0]!r} {size[1]}x{size[0]}")
    frame.color = np.stack([chans[s] for s in color_src]).astype(np.float32, copy=False)
    if "A" in frame.sources:
        frame.alpha = chans[frame.sources["A"]]
    frame.features = {n: chans[frame.sources[n]] for n in names}
    for n in names:
        bg = getattr(F.feature_of(n), "blender_background", None)
        if frame.layout == "blender" and bg is not None:
            far = frame.features[n] >= 0.5 * bg  # Blender writes exactly bg; half of it is still "no hit"
            if far.any():
                frame.features[n] = np.where(far, 0.0, frame.features[n]).astype(np.float32)
                frame.notes.append(f"{frame.sources[n]}: background value {bg:g} read as 0 (as in ours and "
                                   f"Mitsuba's files)")
    if frame.layout == "flat" and all(c in chans for c in _EMISSION):
        frame.sources.update({c: c for c in _EMISSION})
    if all(c in frame.sources for c in _EMISSION):
        frame.emission = np.stack([chans[frame.sources[c]] for c in _EMISSION])
    if not frame.features:
        frame.notes.append("no feature channels: the colour is all there is to go by")
    unread = sorted(set(chans) - set(frame.sources.values())) if feature_channels is None else []
    if unread:  # an AOV under a name the table does not know guides nothing: say so, not silently
        frame.notes.append(f"channels not read, names the feature table does not know (name them as "
                           f"torchmanifold.features does, or register them there): {', '.join(unread)}")
    _check_feature_values(path, frame)
    return frame


def samples_per_pixel_shown(features: dict[str, np.ndarray]) -> int | None:
    """The sample count per pixel that a frame's features show (``features`` by canonical channel name),
    where at least :data:`_MIN_HITS` pixels hit: 1 where no unit vector (the normals,
    :attr:`~torchmanifold.features.Feature.unit`) is shortened by averaging samples that point different
    ways; where one is, the count its edges' mixes show (:func:`mixed_count`), else 2, the least there can
    be; ``None`` without that evidence. A frame that is one flat surface shows 1 at any sample count:
    nothing in it points another way."""
    return _count_shown(features)[0]


def _count_shown(features: dict[str, np.ndarray]) -> tuple[int | None, str | None]:
    """:func:`samples_per_pixel_shown` and the note that says how (``None`` with no count)."""
    lo, hi = _AVERAGED_LENGTH
    shown = None, None
    for feat in F.FEATURES:
        if not feat.unit or not all(c in features for c in feat.channels):
            continue
        length = np.sqrt(sum(np.square(features[c], dtype=np.float32) for c in feat.channels))
        if int((length > lo).sum()) < _MIN_HITS:
            continue
        if bool(((length > lo) & (length < hi)).any()):
            n = mixed_count(features)
            if n is not None:
                return n, (f"the header records no sample count; the features mixed across its edges take "
                           f"fractions k/{n}: {n} samples per pixel")
            return 2, ("the header records no sample count; normals shortened by averaging show several "
                       "samples per pixel, its edges' mixes no count: taken as 2, the least there can be")
        shown = 1, ("the header records no sample count; every normal has one sample's unit length, so each "
                    "pixel holds 1 sample")
    return shown


def _mix_fractions(features: dict[str, np.ndarray]) -> np.ndarray:
    """The fractions t of the edge pixels that lie between two surfaces (see :data:`_MIX_PURE`), 1-D: read in
    bands of :data:`_MIX_BAND` rows from the top until :data:`_ENOUGH_MIXES` are found (a large frame's time
    and memory stay bounded)."""
    unit = [c for f in F.FEATURES if f.unit and all(c in features for c in f.channels) for c in f.channels]
    chans = [c for c in F.feature("albedo").channels if c in features] + unit
    (depth,) = F.feature("Z").channels
    if depth in features:
        chans.append(depth)
    if not chans:
        return np.zeros(0, np.float32)
    h, w = features[chans[0]].shape
    found, count = [], 0
    for y0 in range(0, h, _MIX_BAND):
        # the band's rows and 2 more on each side (the image's edge rows repeated past it)
        rows = min(_MIX_BAND, h - y0)
        take = np.clip(np.arange(y0 - 2, y0 + rows + 2), 0, h - 1)
        band = np.stack([features[c][take] for c in chans], -1).astype(np.float32)
        band = np.pad(np.where(np.isfinite(band), band, 0.0), ((0, 0), (2, 2), (0, 0)), mode="edge")
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            line = [band[2 + k * dy:2 + k * dy + rows, 2 + k * dx:2 + k * dx + w] for k in (-2, -1, 0, 1, 2)]
            if depth in features:
                far = np.max([x[..., -1] for x in line], 0)
                scale = np.where(far > 0, far, 1.0)[..., None]
                line = [np.concatenate([x[..., :-1], x[..., -1:] / scale], -1) for x in line]
            outer_a, a, centre, b, outer_b = line
            d = b - a
            step = np.square(d).sum(-1)
            t = ((centre - a) * d).sum(-1) / np.where(step > 0, step, 1.0)
            off = np.square(centre - a - t[..., None] * d).sum(-1)
            ok = ((step > _MIX_STEP ** 2) & (off < _MIX_OFF ** 2 * step) & (t > _MIX_INSIDE)
                  & (t < 1 - _MIX_INSIDE) & (np.square(outer_a - a).sum(-1) < _MIX_PURE ** 2 * step)
                  & (np.square(outer_b - b).sum(-1) < _MIX_PURE ** 2 * step))
            found.append(t[ok])
            count += len(found[-1])
        if count >= _ENOUGH_MIXES:
            break
    return np.concatenate(found)


def mixed_count(features: dict[str, np.ndarray]) -> int | None:
    """The samples per pixel that the mixes across a frame's edges show (:data:`_MIX_PURE`): the least n
    whose fractions k / n they take; ``None`` where too few pixels mix two surfaces cleanly, or their
    fractions keep to no such grid (samples weighted unevenly by a pixel filter)."""
    t = _mix_fractions(features).astype(np.float64)
    if len(t) < _MIN_MIXES:
        return None
    peak = {n: float(np.cos(2 * np.pi * n * t).mean()) for n in range(2, _MOST_COUNT + 1)}
    n = next((n for n, p in peak.items() if p >= _COUNT_PEAK), None)
    if n is None:
        return None
    # a count's divisors peak near 0 (n / 2 at P(k even) - P(k odd)); one peaking nearly as high is the count
    return next(d for d in range(2, n + 1) if n % d == 0 and peak[d] >= _DIVISOR_PEAK * peak[n])


def write_color(path: str | os.PathLike, color: np.ndarray, like: RenderFrame | None = None,
                layout: str = "input") -> Path:
    """Write ``(3, H, W)`` colour as an EXR, in the layout of the frame it came from.

    Args:
        path: destination (written atomically).
        color: ``(3, H, W)`` float32.
        like: the frame read by :func:`read_render_frame` (for its layout); ``None`` = plain ``R, G, B``.
        layout: ``"input"``: the channels colour was read from (Blender: ``<layer>.Combined.R/G/B``
            with the input's ``A``, marked as a Blender multilayer file); ``"plain"``: ``R, G, B``.

    Returns:
        The path written.
    """
    if layout not in ("input", "plain"):
        raise ValueError(f"layout must be 'input' or 'plain', got {layout!r}")
    color = np.asarray(color, np.float32)
    if color.ndim != 3 or color.shape[0] != 3:
        raise ValueError(f"color must be (3, H, W), got {color.shape}")
    if like is None or layout == "plain":
        return write_exr(path, dict(zip("RGB", color)))
    chans = {like.sources[c]: color[k] for k, c in enumerate("RGB")}
    if like.alpha is not None:
        chans[like.sources["A"]] = like.alpha
    return write_exr(path, chans, attributes=BLENDER_HEADER if like.layout == "blender" else None)
