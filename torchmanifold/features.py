"""The guide features: one table that names each feature once, and lookups for the rest of the code.

A *feature* is a per-pixel quantity a renderer writes beside the colour (albedo, normal, depth ...),
one or three channels. Its ``group`` is the one name the whole project uses for it (the path tracer's
shader slots, our EXR files, the readers of Mitsuba's and Blender's files, the denoiser's guide
selection and range sigmas, the demo's feature sets). Its channels have a *canonical name* each:
the channel name in our EXR files (``albedo.R``, ``N.X``, ``Z``), which Mitsuba's ``aov`` integrator
shares; the tracer's short names (``Mr``) and Blender's pass names (``Denoising Albedo.R``) are
aliases of it.

The rows (:data:`FEATURES`) give, per feature: its channels under our, Mitsuba's and Blender's names,
its storage precision, its default range sigma with where that figure came from, and whether it
guides the denoiser by default.

Meanings: ``T`` the sample's time in frames; ``Z`` the distance along the camera ray to the first hit
(0 where the ray leaves the scene; Blender's ``Denoising Depth`` counts from where the ray crosses
the camera's near clip plane, ``clip_start`` 0.1 by default: checked on a Blender 5.0.1 render in
``tests/io``); ``Zplane`` the distance along the camera's view axis (Blender's
``Depth`` pass: planar depth, background written as 1e10, read as 0); ``albedo`` the first hit's
diffuse reflectance (Mitsuba: 0 on glass and mirrors, and pi times the BSDF towards the normal where a
BSDF defines no diffuse part: 22.5 on a rough aluminium conductor of alpha 0.1 seen head-on, Mitsuba
3.9.1; Blender's denoising albedo looks through near-specular surfaces, and on a light seen directly it
is the light's emitted radiance, far above 1: seen on ``bl_motion_blur`` and the ``bl_materials``
probe); ``N`` the world-space normal facing the ray; ``Ncam`` the camera-space normal (X right, Y
up, +Z forward: surfaces facing the camera have Z < 0) that Blender's denoising data gives, looking
through near-specular surfaces like its albedo; ``P`` the world-space position; ``D`` the
direction the path leaves the first hit (one random draw per sample); ``S`` the shadow-ray direction
at the first hit (one random draw per sample); ``caustic`` the share of the sample's radiance (luminance)
that reached a diffuse surface from a light or the sky through mirrors or glass, in [0, 1]: caustic light,
which only our tracer tells apart (it does not guide: per sample it is as sparse as the light it marks; the
bandwidth selection reads it, :func:`~torchmanifold.pipeline.selection._caustic_light`).

Adding a feature is one entry in :data:`FEATURES` (plus the shader code that writes it when our tracer
makes it: the shader's slots ``FEAT_<TRACER NAME>`` and ``N_FEAT`` are generated from this table, see
:func:`shader_defines`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Iterator, Mapping, Sequence

__all__ = [
    "Feature", "FEATURES", "RENDERERS", "register", "feature", "feature_of", "groups", "canonical_name",
    "group_of", "default_sigma", "guides_by_default", "is_half", "tracer_names", "tracer_channels",
    "channel_aliases", "renderer_channel", "shader_defines", "GroupSigmas",
]

#: the renderers whose file channel names the table lists (``torchmanifold`` = our tracer's EXR files)
RENDERERS = ("torchmanifold", "mitsuba", "blender")

_TUNED = ("tuned on shared/data mitsuba/cbox_glossy_tex (1-spp frames, PSNR on clamped sRGB); scaled x0.5 "
          "to x4 on the validation set's tuning part it gains at most 0.05 dB from 1 or 4 spp "
          "(benchmarks/validation/findings.md)")
_BY_HAND = "set by hand for unit directions, not measured (the group does not guide by default)"
_AS_N = "the N figure (unit normals the same way), not measured on its own"
_AS_Z = "the Z figure (depth the same way), not measured on its own"
_P_VALIDATED = ("validation set's tuning part (benchmarks/validation/findings.md): 2.5x the figure tuned on "
                "shared/data alone; 2x to 3x are within 0.02 dB, 1x is 0.2 dB worse from 1 and 4 spp")


@dataclass(frozen=True)
class Feature:
    """One row of the feature table.

    Attributes:
        group: the feature's one name (``"albedo"``, ``"N"``, ...), used by every part of the project.
        channels: canonical channel names, one per component (our EXR channel names).
        tracer: our path tracer's channel names in its shader-slot order, ``()`` if it does not make it.
        mitsuba: channel names Mitsuba's ``aov`` integrator writes for it, ``()`` if none.
        blender: Blender pass channel names without the view-layer prefix (``"Denoising Albedo.R"``),
            ``()`` if none.
        half: stored as 16-bit half floats in our EXR files (else float32).
        sigma: default range sigma (in the feature's units, or a fraction of the data's extent when
            ``sigma_of_extent``); ``None`` = no default (it cannot guide without an explicit sigma).
        sigma_source: where ``sigma`` comes from.
        sigma_of_extent: ``sigma`` is a fraction of the data's robust extent (scene units vary).
        guides: guides the filter by default.
        superseded_by: groups whose presence among the available features stops this one guiding by
            default (it would say the same thing again).
        blender_background: value Blender writes where the ray leaves the scene, read as 0 (our
            and Mitsuba's convention), or ``None``.
        zero_is_no_hit: the value 0 marks pixels whose ray left the scene (depth).
        may_be_all_zero: a frame where every channel is 0 is valid data (else readers take it for a
            pass that was never rendered and refuse it).
        unit: each sample's value is a unit vector (0 where the ray left the scene), so a pixel averaging
            samples of different directions is shorter: how a file's point samples are told from pixel
            averages (:func:`torchmanifold.io.frames.samples_per_pixel_shown`).
        other_names: base names (any case) under which other renderers write the feature's components as
            ``<base>.X/Y/Z`` or ``.R/G/B`` (any case) or ``<base>X``, a scalar as ``<base>`` or ``<base>.Z``
            (``.Y``, ``.V``, ``.R``); read where no name above is in a file (:func:`other_renderer_channels`).
        preferred_names: those of ``other_names`` read even where a file holds a name above too (pbrt-v4
            writes its geometric normal as ``N.*`` and the shading normal, smooth over a mesh's facets and
            what OIDN asks for, as ``Ns.*``).
    """

    group: str
    channels: tuple[str, ...]
    tracer: tuple[str, ...] = ()
    mitsuba: tuple[str, ...] = ()
    blender: tuple[str, ...] = ()
    half: bool = True
    sigma: float | None = None
    sigma_source: str = ""
    sigma_of_extent: bool = False
    guides: bool = False
    superseded_by: tuple[str, ...] = ()
    blender_background: float | None = None
    zero_is_no_hit: bool = False
    may_be_all_zero: bool = False
    unit: bool = False
    other_names: tuple[str, ...] = ()
    preferred_names: tuple[str, ...] = ()

    def __post_init__(self):
        n = len(self.channels)
        if n == 0:
            raise ValueError(f"Feature {self.group!r}: channels must name at least one channel")
        for kind in ("tracer", "mitsuba", "blender"):
            names = getattr(self, kind)
            if names and len(names) != n:
                raise ValueError(f"Feature {self.group!r}: {kind} must name {n} channels like channels "
                                 f"{list(self.channels)}, got {list(names)}")
        if self.guides and self.sigma is None:
            raise ValueError(f"Feature {self.group!r}: guides by default but has no default sigma")
        if self.sigma is not None and not self.sigma_source:
            raise ValueError(f"Feature {self.group!r}: sigma {self.sigma} needs a sigma_source")

    def aliases(self, renderer: str) -> tuple[str, ...]:
        """The channel names ``renderer`` (one of :data:`RENDERERS`) writes, ``()`` if none."""
        if renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {renderer!r}")
        return self.channels if renderer == "torchmanifold" else getattr(self, renderer)


def _xyz(head: str) -> tuple[str, str, str]:
    return (f"{head}.X", f"{head}.Y", f"{head}.Z")


def _rgb(head: str) -> tuple[str, str, str]:
    return (f"{head}.R", f"{head}.G", f"{head}.B")


#: The feature table. Its order is the shader's slot order and the order features are listed in.
FEATURES: tuple[Feature, ...] = (
    Feature("T", ("T",), tracer=("T",), half=False, may_be_all_zero=True),  # frame 0, no shutter
    Feature("Z", ("Z",), tracer=("Z",), mitsuba=("Z",), blender=("Denoising Depth.Z",), half=False,
            sigma=0.15, sigma_source=_TUNED, sigma_of_extent=True, guides=True, superseded_by=("P",),
            zero_is_no_hit=True, other_names=("z", "depth", "dd", "distance")),
    # other_names: pbrt-v4's gbuffer film (Albedo, Ns for the shading normal, P; its AOV film Px), the names
    # users give Mitsuba's aov integrator (its documentation's dd.y:depth and nn:sh_normal) and OIDN's examples
    # (albedo.r, normal, normals, position), Blender's Diffuse Color pass (DiffCol) where its denoising data
    # was not rendered
    Feature("albedo", _rgb("albedo"), tracer=("Mr", "Mg", "Mb"), mitsuba=_rgb("albedo"),
            blender=_rgb("Denoising Albedo"), sigma=0.1, sigma_source=_TUNED, guides=True,
            other_names=("albedo", "diffuse_albedo", "diffusealbedo", "diffcol")),
    Feature("N", _xyz("N"), tracer=("Nx", "Ny", "Nz"), mitsuba=_xyz("N"), blender=_xyz("Normal"),
            sigma=0.3, sigma_source=_TUNED, guides=True, superseded_by=("Ncam",), unit=True,
            other_names=("ns", "n", "normal", "normals", "nn", "sh_normal", "shading_normal"),
            preferred_names=("ns",)),
    Feature("D", _xyz("D"), tracer=("Dx", "Dy", "Dz"), sigma=0.6, sigma_source=_BY_HAND),
    Feature("S", _xyz("S"), tracer=("Sx", "Sy", "Sz"), sigma=0.6, sigma_source=_BY_HAND),
    Feature("caustic", ("caustic",), tracer=("C",), may_be_all_zero=True),
    Feature("P", _xyz("P"), mitsuba=_xyz("P"), blender=_xyz("Position"), half=False, sigma=0.1,
            sigma_source=_P_VALIDATED, sigma_of_extent=True, guides=True,
            other_names=("p", "position", "positions", "world_position")),
    # Blender's denoising normal goes with its denoising albedo: both look through near-specular
    # surfaces, as OIDN wants (seen on a Blender 5.0.1 render of a glass sphere before a red wall:
    # through the glass both are the wall's, at about half weight; the Normal pass is the sphere's), so it
    # is preferred to the world-space Normal pass when a file has both
    Feature("Ncam", _xyz("Ncam"), blender=_xyz("Denoising Normal"), sigma=0.3, sigma_source=_AS_N,
            guides=True, unit=True),
    Feature("Zplane", ("Zplane",), blender=("Depth.Z",), half=False, sigma=0.15, sigma_source=_AS_Z,
            sigma_of_extent=True, guides=True, superseded_by=("P", "Z"), zero_is_no_hit=True,
            blender_background=1e10),
)


def register(feat: Feature) -> None:
    """Add ``feat`` to :data:`FEATURES` (e.g. a renderer's extra AOV), checking that none of its names
    is taken. Code that looks features up through this module sees it at once."""
    global FEATURES
    if not isinstance(feat, Feature):
        raise TypeError(f"register: feat must be a Feature, got {type(feat).__name__}")
    _check_table(FEATURES + (feat,))
    FEATURES = FEATURES + (feat,)


def _check_table(table: Sequence[Feature]) -> None:
    seen: dict[str, str] = {}
    for f in table:
        names = {f.group} | set(f.channels) | set(f.tracer)
        for renderer in RENDERERS:
            names |= set(f.aliases(renderer))
        for n in names:
            owner = seen.setdefault(n, f.group)
            # a group may share its name with its own single channel (Z) or alias its own channels
            if owner != f.group:
                raise ValueError(f"feature table: name {n!r} of group {f.group!r} is already used by group "
                                 f"{owner!r}")
    for f in table:
        unknown = [g for g in f.superseded_by if g not in {x.group for x in table}]
        if unknown:
            raise ValueError(f"feature table: {f.group!r}.superseded_by names unknown groups {unknown}")


class _Index:
    """Lookups built from one version of :data:`FEATURES` (rebuilt when it changes)."""

    def __init__(self, table: tuple[Feature, ...]):
        _check_table(table)
        self.table = table
        self.by_group = {f.group: f for f in table}
        self.canonical: dict[str, str] = {}
        self.group: dict[str, str] = {}
        for f in table:
            for k, c in enumerate(f.channels):
                for alias in {c, *(f.tracer[k:k + 1]), *(r[k] for r in (f.mitsuba, f.blender) if r)}:
                    self.canonical[alias] = c
            for c in f.channels:
                self.group[c] = f.group


_cache: _Index | None = None


def _index() -> _Index:
    global _cache
    if _cache is None or _cache.table is not FEATURES:
        _cache = _Index(FEATURES)
    return _cache


def feature(group: str) -> Feature:
    """The table row of ``group``.

    Raises:
        ValueError: unknown group (the message lists the known ones).
    """
    idx = _index()
    if group not in idx.by_group:
        raise ValueError(f"feature group must be one of {list(idx.by_group)}, got {group!r}")
    return idx.by_group[group]


def feature_of(name: str) -> Feature | None:
    """The table row a channel (any alias) belongs to, ``None`` for channels the table does not know."""
    return _index().by_group.get(group_of(name))


def groups() -> list[str]:
    """All groups, in table order."""
    return [f.group for f in FEATURES]


def canonical_name(name: str) -> str:
    """Canonical channel name of a tracer name (``Mr``), a Mitsuba or Blender channel name
    (``Denoising Albedo.R``) or a canonical name; unknown names come back unchanged."""
    return _index().canonical.get(name, name)


def group_of(name: str) -> str:
    """Group of a channel (any alias); for unknown channels the part before the first dot
    (``emission.R`` -> ``emission``), which names no group of the table."""
    c = canonical_name(name)
    return _index().group.get(c, c.split(".")[0])


def default_sigma(name: str) -> float | None:
    """Default range sigma of a channel's group (``None`` if it has none or is unknown); a fraction of
    the data's extent where ``feature(group).sigma_of_extent``."""
    f = feature_of(name)
    return None if f is None else f.sigma


def guides_by_default(name: str, available: Iterable[str] = ()) -> bool:
    """Whether channel ``name`` guides the filter when no guide is chosen, given the ``available``
    channels (a group is left out when a group that supersedes it is available)."""
    f = feature_of(name)
    if f is None or not f.guides:
        return False
    present = {group_of(n) for n in available}
    return not any(g in present for g in f.superseded_by)


def is_half(name: str) -> bool:
    """The channel is stored as half float in our EXR files (unknown channels: float32)."""
    f = feature_of(name)
    return f is not None and f.half


def tracer_names() -> list[str]:
    """Our path tracer's feature channel names in shader-slot order."""
    return [n for f in FEATURES for n in f.tracer]


def tracer_channels(group: str) -> tuple[str, ...]:
    """The tracer's channel names of ``group`` (``()`` if the tracer does not make it)."""
    return feature(group).tracer


def channel_aliases(renderer: str) -> dict[str, str]:
    """Channel name ``renderer`` writes -> canonical name, for every feature it writes
    (``renderer`` one of :data:`RENDERERS`)."""
    return {a: c for f in FEATURES for a, c in zip(f.aliases(renderer), f.channels)}


#: the component suffixes other renderers write a 3-vector's channels with (any case), and a scalar's
_COMPONENTS = (("x", "y", "z"), ("r", "g", "b"))
_SCALAR_SUFFIXES = ("", ".z", ".y", ".v", ".r")


def other_renderer_channels(channels: Iterable[str], missing: Iterable[str],
                            found: Iterable[str] = ()) -> dict[str, str]:
    """File channel -> canonical name for the groups ``missing`` (none of whose names above a file holds)
    that ``channels`` hold under one of their ``other_names``, and for the groups ``found`` (read under a
    name above) under one of their ``preferred_names``: every component as ``<base>.<c>`` or ``<base><c>``,
    base and component in any case (``Albedo.R``, ``normal.x``, ``Px``). The first of a group's names (then
    suffix forms) that a file holds wins; groups without such names are left out."""
    lower: dict[str, str] = {}
    for c in channels:
        lower.setdefault(c.lower(), c)
    out: dict[str, str] = {}
    wanted = [(g, feature(g).other_names) for g in missing] + [(g, feature(g).preferred_names) for g in found]
    for group, bases in wanted:
        f = feature(group)
        if len(f.channels) not in (1, 3):
            continue
        for base in bases:
            forms = ([[f"{base}{sep}{c}" for c in comps] for comps in _COMPONENTS for sep in (".", "")]
                     if len(f.channels) == 3 else [[f"{base}{suffix}"] for suffix in _SCALAR_SUFFIXES])
            match = next(([lower[n] for n in names] for names in forms if all(n in lower for n in names)), None)
            if match is not None:
                out.update(zip(match, f.channels))
                break
    return out


def renderer_channel(name: str, renderer: str) -> str | None:
    """The channel name ``renderer`` uses for canonical channel ``name``, ``None`` if it writes none."""
    for a, c in channel_aliases(renderer).items():
        if c == canonical_name(name):
            return a
    return None


def shader_defines() -> str:
    """GLSL ``#define`` lines of the tracer's feature slots: ``N_FEAT`` and ``FEAT_<NAME>`` (upper-case
    tracer name) = the slot index the shader accumulates that channel in."""
    names = tracer_names()
    lines = [f"#define N_FEAT {len(names)}"] + [f"#define FEAT_{n.upper()} {k}" for k, n in enumerate(names)]
    return "\n".join(lines) + "\n"


class GroupSigmas(Mapping):
    """Read-only ``{group: default sigma}`` of the groups that have one, always the current table's."""

    def __getitem__(self, group: str) -> float:
        f = _index().by_group.get(group)
        if f is None or f.sigma is None:
            raise KeyError(group)
        return f.sigma

    def __iter__(self) -> Iterator[str]:
        return iter([f.group for f in FEATURES if f.sigma is not None])

    def __len__(self) -> int:
        return sum(f.sigma is not None for f in FEATURES)

    def __repr__(self) -> str:
        return f"GroupSigmas({dict(self)})"
