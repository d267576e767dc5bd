"""Scene model of the path tracer and its declarative TOML files.

A scene is a short list of objects (spheres, quads, triangle meshes), named materials, a camera
and render settings -- smallpt's economy with planes instead of huge wall spheres. Objects and the
camera move by linearly interpolated keyframes (objects translate; the camera interpolates eye,
target and field of view). Scene time is measured in frames.

File format (``torchmanifold/render/scenes/cornell_box.toml`` is a complete example)::

    [render]                       # all optional
    shutter = 0.5                  # shutter length in frames, centred on the frame time
    max_depth = 8                  # most path vertices
    rr_depth = 3                   # Russian roulette from this depth on
    background = [0, 0, 0]         # radiance of rays that leave the scene

    [camera]
    eye = [0, 1, 3.4]              # or [[camera.keyframes]] with time, eye, target (, fov)
    target = [0, 1, 0]
    fov = 40                       # vertical, degrees
    up = [0, 1, 0]

    [materials]
    white = { type = "diffuse", color = [0.75, 0.75, 0.75] }
    lamp = { type = "diffuse", color = [0, 0, 0], emission = [12, 12, 12] }
    glass = { type = "glass", color = [1, 1, 1], ior = 1.5 }        # also "mirror"

    [[objects]]
    name = "floor"                 # optional, for people; RenderResult.object_id is the list index
    type = "quad"                  # parallelogram origin + s*u + t*v; the front face is u x v
    origin = [-1, 0, -1]
    u = [0, 0, 2]
    v = [2, 0, 0]
    material = "white"

    [[objects]]
    type = "sphere"
    center = [0.5, 0.35, 0.3]
    radius = 0.35
    material = "glass"
    motion = [{ time = 0, offset = [0, 0, 0] }, { time = 11, offset = [0.5, 0, 0] }]

    [[objects]]
    type = "mesh"                  # any file trimesh loads; path relative to the scene file
    file = "bunny.obj"
    scale = 1.0                    # applied before translate
    translate = [0, 0, 0]
    material = "white"

Emissive spheres and quads are lights (sampled by next-event estimation); quads emit from their
front face only, spheres outward. Emissive meshes glow but are not sampled.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from torchmanifold import features as feature_table

#: material type -> the integer the shader reads (``MAT_<TYPE>`` in GLSL, see ``tracer.shader_defines``)
MATERIAL_TYPES = {"diffuse": 0, "mirror": 1, "glass": 2}
#: object kind -> the integer the shader reads (``PRIM_<KIND>`` in GLSL)
PRIM_KINDS = {"sphere": 0, "quad": 1, "mesh": 2}
SCENES_DIR = Path(__file__).parent / "scenes"


@dataclass
class Material:
    type: str = "diffuse"
    color: tuple[float, float, float] = (0.75, 0.75, 0.75)
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ior: float = 1.5

    @property
    def emissive(self) -> bool:
        return max(self.emission) > 0.0


@dataclass
class Keyframe:
    """Translation ``offset`` of an object at ``time`` (frames)."""

    time: float
    offset: tuple[float, float, float]


@dataclass
class Sphere:
    kind: ClassVar[str] = "sphere"
    center: tuple[float, float, float]
    radius: float
    material: str
    motion: list[Keyframe] = field(default_factory=list)
    name: str = ""


@dataclass
class Quad:
    kind: ClassVar[str] = "quad"
    origin: tuple[float, float, float]
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    material: str
    motion: list[Keyframe] = field(default_factory=list)
    name: str = ""


@dataclass
class Mesh:
    kind: ClassVar[str] = "mesh"
    vertices: np.ndarray  # (N, 3)
    faces: np.ndarray  # (M, 3) int
    material: str
    motion: list[Keyframe] = field(default_factory=list)
    name: str = ""


@dataclass
class CameraKey:
    time: float
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov: float = 40.0


@dataclass
class Camera:
    """Pinhole camera; ``keys`` are interpolated linearly in time (one key = static)."""

    keys: list[CameraKey]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)


@dataclass
class Scene:
    objects: list[Sphere | Quad | Mesh]
    materials: dict[str, Material]
    camera: Camera
    shutter: float = 0.0
    max_depth: int = 8
    rr_depth: int = 3
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source: str = "<scene>"

    @property
    def is_dynamic(self) -> bool:
        """Anything moves (an object or the camera has two or more keyframes)."""
        return len(self.camera.keys) > 1 or any(len(o.motion) > 1 for o in self.objects)

    def moving_objects(self) -> list[int]:
        """Indices (as in ``RenderResult.object_id``) of the objects that move, e.g. to mask them."""
        return [i for i, o in enumerate(self.objects) if len(o.motion) > 1]

    @property
    def has_lights(self) -> bool:
        """Some sphere or quad emits, so next-event estimation casts shadow rays."""
        return any(self.is_light(o) for o in self.objects)

    def is_light(self, obj) -> bool:
        return isinstance(obj, (Sphere, Quad)) and self.materials[obj.material].emissive

    def needed_features(self) -> list[str]:
        """The tracer's feature channels this scene carries information in (shader-slot order).

        ``T`` only when something moves, ``S*`` only when lights are sampled, ``D*`` only when
        paths go past the first hit, ``caustic`` only when a mirror or glass can bring light to a diffuse
        surface (a light or a sky, paths of three vertices); every other feature the tracer makes always.
        """
        specular = any(m.type != "diffuse" for m in self.materials.values())
        lit = self.has_lights or max(self.background) > 0
        skip = {"T": not self.is_dynamic, "D": self.max_depth <= 1, "S": not self.has_lights,
                "caustic": not (specular and lit and self.max_depth >= 3)}
        return [n for n in feature_table.tracer_names() if not skip.get(feature_table.group_of(n), False)]


# --------------------------------------------------------------------------- loading
class _Reader:
    """Typed field access that raises ``ValueError('<file>: <field>: expected ..., got ...')``."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, where: str, expected: str, got: Any) -> None:
        raise ValueError(f"{self.source}: {where}: expected {expected}, got {got!r}")

    def table(self, d: Mapping, key: str, where: str, required: bool = False) -> Mapping:
        if key not in d:
            if required:
                self.fail(f"{where}{key}", "a table", "nothing (missing)")
            return {}
        v = d[key]
        if not isinstance(v, Mapping):
            self.fail(f"{where}{key}", "a table", v)
        return v

    def number(self, d: Mapping, key: str, where: str, default=None, lo=None, hi=None, integer=False):
        if key not in d:
            if default is None:
                self.fail(f"{where}{key}", "a number", "nothing (missing)")
            return default
        v = d[key]
        ok = isinstance(v, int) if integer else isinstance(v, (int, float))
        if isinstance(v, bool) or not ok or not math.isfinite(v):
            self.fail(f"{where}{key}", "an integer" if integer else "a finite number", v)
        if lo is not None and v < lo:
            self.fail(f"{where}{key}", f"a number >= {lo}", v)
        if hi is not None and v > hi:
            self.fail(f"{where}{key}", f"a number <= {hi}", v)
        return int(v) if integer else float(v)

    def vec3(self, d: Mapping, key: str, where: str, default=None, nonneg=False):
        if key not in d:
            if default is None:
                self.fail(f"{where}{key}", "a list of 3 numbers", "nothing (missing)")
            return tuple(default)
        v = d[key]
        if (
            not isinstance(v, (list, tuple))
            or len(v) != 3
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        ):
            self.fail(f"{where}{key}", "a list of 3 finite numbers", v)
        if nonneg and min(v) < 0:
            self.fail(f"{where}{key}", "3 numbers >= 0", v)
        return tuple(float(x) for x in v)

    def string(self, d: Mapping, key: str, where: str, default=None, choices=None) -> str:
        if key not in d:
            if default is None:
                self.fail(f"{where}{key}", "a string", "nothing (missing)")
            return default
        v = d[key]
        if not isinstance(v, str) or (choices is not None and v not in choices):
            self.fail(f"{where}{key}", f"one of {sorted(choices)}" if choices else "a string", v)
        return v

    def unknown(self, d: Mapping, allowed: Sequence[str], where: str) -> None:
        extra = sorted(set(d) - set(allowed))
        if extra:
            self.fail(f"{where}{extra[0]}", f"one of the fields {sorted(allowed)}", extra[0])


def _increasing(r: _Reader, where: str, times: list[float]) -> None:
    if times != sorted(times) or len(set(times)) != len(times):
        r.fail(where, "keyframes in strictly increasing time", times)


def _motion(r: _Reader, obj: Mapping, where: str) -> list[Keyframe]:
    raw = obj.get("motion", [])
    if not isinstance(raw, list):
        r.fail(f"{where}motion", "a list of {time, offset} tables", raw)
    keys = []
    for j, k in enumerate(raw):
        w = f"{where}motion[{j}]."
        if not isinstance(k, Mapping):
            r.fail(f"{where}motion[{j}]", "a table {time, offset}", k)
        r.unknown(k, ["time", "offset"], w)
        keys.append(Keyframe(r.number(k, "time", w), r.vec3(k, "offset", w)))
    _increasing(r, f"{where}motion", [k.time for k in keys])
    return keys


def _read_render(r: _Reader, data: Mapping) -> dict:
    """The ``[render]`` table as :class:`Scene` keyword arguments."""
    ren = r.table(data, "render", "")
    r.unknown(ren, ["shutter", "max_depth", "rr_depth", "background"], "render.")
    return dict(
        shutter=r.number(ren, "shutter", "render.", default=0.0, lo=0.0),
        max_depth=r.number(ren, "max_depth", "render.", default=8, lo=1, hi=1024, integer=True),
        rr_depth=r.number(ren, "rr_depth", "render.", default=3, lo=1, integer=True),
        background=r.vec3(ren, "background", "render.", default=(0.0, 0.0, 0.0), nonneg=True),
    )


def _read_camera(r: _Reader, data: Mapping) -> Camera:
    """The ``[camera]`` table: one static key or ``[[camera.keyframes]]``, each with a usable view."""
    cam = r.table(data, "camera", "", required=True)
    r.unknown(cam, ["eye", "target", "fov", "up", "keyframes"], "camera.")
    fov = r.number(cam, "fov", "camera.", default=40.0, lo=1e-3, hi=179.0)
    up = r.vec3(cam, "up", "camera.", default=(0.0, 1.0, 0.0))
    if "keyframes" in cam:
        if "eye" in cam or "target" in cam:
            r.fail("camera", "either eye/target or keyframes, not both", sorted(cam))
        raw = cam["keyframes"]
        if not isinstance(raw, list) or not raw:
            r.fail("camera.keyframes", "a non-empty list of {time, eye, target, fov} tables", raw)
        ckeys = []
        for j, k in enumerate(raw):
            w = f"camera.keyframes[{j}]."
            if not isinstance(k, Mapping):
                r.fail(f"camera.keyframes[{j}]", "a table", k)
            r.unknown(k, ["time", "eye", "target", "fov"], w)
            ckeys.append(
                CameraKey(r.number(k, "time", w), r.vec3(k, "eye", w), r.vec3(k, "target", w),
                          r.number(k, "fov", w, default=fov, lo=1e-3, hi=179.0))
            )
        _increasing(r, "camera.keyframes", [k.time for k in ckeys])
    else:
        ckeys = [CameraKey(0.0, r.vec3(cam, "eye", "camera."), r.vec3(cam, "target", "camera."), fov)]
    for j, k in enumerate(ckeys):
        fwd = np.subtract(k.target, k.eye)
        if np.linalg.norm(fwd) < 1e-9 or np.linalg.norm(np.cross(fwd, up)) < 1e-9 * np.linalg.norm(fwd):
            r.fail(f"camera (key {j})", "target != eye and a view direction not parallel to up",
                   {"eye": k.eye, "target": k.target, "up": up})
    return Camera(ckeys, up)


def _read_materials(r: _Reader, data: Mapping) -> dict[str, Material]:
    mats_raw = r.table(data, "materials", "", required=True)
    materials: dict[str, Material] = {}
    for name, m in mats_raw.items():
        w = f"materials.{name}."
        if not isinstance(m, Mapping):
            r.fail(f"materials.{name}", "a table {type, color, emission, ior}", m)
        r.unknown(m, ["type", "color", "emission", "ior"], w)
        materials[name] = Material(
            type=r.string(m, "type", w, default="diffuse", choices=MATERIAL_TYPES),
            color=r.vec3(m, "color", w, default=(0.75, 0.75, 0.75), nonneg=True),
            emission=r.vec3(m, "emission", w, default=(0.0, 0.0, 0.0), nonneg=True),
            ior=r.number(m, "ior", w, default=1.5, lo=1.0),
        )
    return materials


_OBJECT_FIELDS = ["type", "material", "motion", "name"]


def _read_sphere(r: _Reader, o: Mapping, w: str, common: tuple, base_dir: Path) -> Sphere:
    r.unknown(o, _OBJECT_FIELDS + ["center", "radius"], w)
    return Sphere(r.vec3(o, "center", w), r.number(o, "radius", w, lo=1e-9), *common)


def _read_quad(r: _Reader, o: Mapping, w: str, common: tuple, base_dir: Path) -> Quad:
    r.unknown(o, _OBJECT_FIELDS + ["origin", "u", "v"], w)
    q = Quad(r.vec3(o, "origin", w), r.vec3(o, "u", w), r.vec3(o, "v", w), *common)
    if np.linalg.norm(np.cross(q.u, q.v)) <= 0.0:
        r.fail(f"{w}u/v", "two non-parallel edges", (q.u, q.v))
    return q


def _read_mesh(r: _Reader, o: Mapping, w: str, common: tuple, base_dir: Path) -> Mesh:
    r.unknown(o, _OBJECT_FIELDS + ["file", "scale", "translate"], w)
    path = Path(r.string(o, "file", w))
    if not path.is_absolute():
        path = base_dir / path
    scale = r.number(o, "scale", w, default=1.0, lo=1e-12)
    translate = r.vec3(o, "translate", w, default=(0.0, 0.0, 0.0))
    verts, faces = _load_mesh(r, path, f"{w}file")
    return Mesh(verts * scale + np.asarray(translate), faces, *common)


#: object ``type`` -> reader of its fields (one per entry of ``PRIM_KINDS``)
_OBJECT_READERS = {"sphere": _read_sphere, "quad": _read_quad, "mesh": _read_mesh}


def _read_objects(r: _Reader, data: Mapping, materials: Mapping[str, Material],
                  base_dir: Path) -> list[Sphere | Quad | Mesh]:
    objs_raw = data.get("objects")
    if not isinstance(objs_raw, list) or not objs_raw:
        r.fail("objects", "a non-empty array of tables [[objects]]", objs_raw)
    objects = []
    for i, o in enumerate(objs_raw):
        w = f"objects[{i}]."
        if not isinstance(o, Mapping):
            r.fail(f"objects[{i}]", "a table", o)
        kind = r.string(o, "type", w, choices=tuple(PRIM_KINDS))
        mat = r.string(o, "material", w)
        if mat not in materials:
            r.fail(f"{w}material", f"one of the materials {sorted(materials)}", mat)
        common = (mat, _motion(r, o, w), r.string(o, "name", w, default=f"{kind}{i}"))
        objects.append(_OBJECT_READERS[kind](r, o, w, common, base_dir))
    return objects


def scene_from_dict(data: Mapping, source: str = "<dict>", base_dir: str | Path | None = None) -> Scene:
    """Build a :class:`Scene` from the parsed form of a scene file (see the module docstring).

    Args:
        data: the TOML content as nested dicts/lists.
        source: name used in error messages (the file path when loading a file).
        base_dir: folder that relative mesh ``file`` paths are resolved against.

    Raises:
        ValueError: a field is missing, has the wrong type or an impossible value; the message names
            ``source``, the field (``objects[2].radius``) and what was expected.
    """
    r = _Reader(source)
    base_dir = Path(base_dir) if base_dir is not None else Path.cwd()
    if not isinstance(data, Mapping):
        r.fail("top level", "a table", data)
    r.unknown(data, ["render", "camera", "materials", "objects"], "")
    render = _read_render(r, data)
    camera = _read_camera(r, data)
    materials = _read_materials(r, data)
    objects = _read_objects(r, data, materials, base_dir)
    return Scene(objects, materials, camera, source=source, **render)


def _load_mesh(r: _Reader, path: Path, where: str) -> tuple[np.ndarray, np.ndarray]:
    if not path.is_file():
        r.fail(where, "an existing mesh file", str(path))
    import trimesh  # only scenes with meshes pay for it

    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        r.fail(where, f"a mesh file trimesh can read ({exc})", str(path))
    if len(mesh.faces) == 0:
        r.fail(where, "a mesh with at least one triangle", str(path))
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def load_scene(path: str | Path) -> Scene:
    """Load a scene from a TOML file (format in the module docstring).

    Raises:
        FileNotFoundError: no such file.
        ValueError: invalid TOML or fields; the message names the file, the field and what was expected.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML: expected a TOML scene file ({exc})") from exc
    return scene_from_dict(data, source=str(path), base_dir=path.parent)


def default_scene() -> Scene:
    """The built-in Cornell box: coloured walls, an area light, a mirror and a glass sphere, a
    diffuse sphere moving across the box and a slow camera move over frames 0..11."""
    return load_scene(SCENES_DIR / "cornell_box.toml")


# --------------------------------------------------------------------------- GPU packing
def pack_scene(scene: Scene) -> dict[str, np.ndarray]:
    """Flatten a scene into the storage-buffer layouts ``shaders/pathtracer.comp`` reads.

    Returns ``{prims, materials, keys, camkeys, lights, nodes, tris}`` numpy arrays (raw bytes
    layouts: float32 / int32, std430).
    """
    from torchmanifold.render.bvh import build_bvh

    mat_names = list(scene.materials)
    mats = np.zeros((max(len(mat_names), 1), 8), np.float32)
    for i, n in enumerate(mat_names):
        m = scene.materials[n]
        mats[i] = [*m.color, MATERIAL_TYPES[m.type], *m.emission, m.ior]

    prims = np.zeros((len(scene.objects), 20), np.float32)
    pints = prims.view(np.int32)
    keys: list[list[float]] = []
    lights: list[int] = []
    node_chunks, tri_chunks = [], []
    n_nodes = n_tris = 0
    for i, o in enumerate(scene.objects):
        row = prims[i]
        if isinstance(o, Sphere):
            row[0:4] = [*o.center, o.radius]
        elif isinstance(o, Quad):
            row[0:3], row[4:7], row[8:11] = o.origin, o.u, o.v
        else:
            tris = o.vertices[o.faces]  # (M, 3, 3)
            nodes, order = build_bvh(tris)
            nodes[:, 3] = np.where(nodes[:, 7] > 0, nodes[:, 3] + n_tris, nodes[:, 3] + n_nodes)
            packed = nodes.astype(np.float32)
            packed.view(np.int32)[:, 3] = nodes[:, 3].astype(np.int32)  # ints stored as float bits
            packed.view(np.int32)[:, 7] = nodes[:, 7].astype(np.int32)
            node_chunks.append(packed)
            t4 = np.zeros((len(order), 3, 4), np.float32)
            t4[:, :, :3] = tris[order]
            tri_chunks.append(t4.reshape(-1, 4))
            pints[i, 17] = n_nodes
            n_nodes += len(nodes)
            n_tris += len(order)
        pints[i, 12:16] = [PRIM_KINDS[o.kind], mat_names.index(o.material), len(keys), len(o.motion)]
        keys += [[k.time, *k.offset] for k in o.motion]
        if scene.is_light(o):
            pints[i, 16] = 1
            lights.append(i)

    camkeys = np.asarray([[k.time, *k.eye, *k.target, k.fov] for k in scene.camera.keys], np.float32)
    return {
        "prims": prims,
        "materials": mats,
        "keys": np.asarray(keys or [[0, 0, 0, 0]], np.float32),
        "camkeys": camkeys,
        "lights": np.asarray(lights or [0], np.int32),
        "n_lights": len(lights),
        "nodes": np.concatenate(node_chunks) if node_chunks else np.zeros((1, 8), np.float32),
        "tris": np.concatenate(tri_chunks) if tri_chunks else np.zeros((3, 4), np.float32),
        "has_mesh": bool(node_chunks),
    }
