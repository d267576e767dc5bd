"""The compute-shader path tracer: scene buffers on the GPU, one dispatch per sample chunk, one readback.

``PathTracer`` is made once and reused every progressive iteration: scene buffers are uploaded in
``__init__`` and output buffers are kept (and grown) between calls.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from pathlib import Path
from typing import Sequence

import moderngl
import numpy as np
import torch
from tqdm.auto import tqdm

from torchmanifold import features as feature_table
from torchmanifold.render.context import create_context, make_current
from torchmanifold.render.frames import RenderResult
from torchmanifold.render.scene import MATERIAL_TYPES, PRIM_KINDS, Scene, pack_scene

SHADER_PATH = Path(__file__).parent / "shaders" / "pathtracer.comp"
GROUP = 8  # local_size_x/y declared in the shader
MAX_BAKED_OBJECTS = 256  # scenes up to this size become shader constants
# baked scenes up to this size test every object in straight-line code; measured on the 2-core VM, 64 spheres:
# 33 s to compile (26 s as a loop), frames 4x faster than the loop
MAX_UNROLLED_OBJECTS = 64
# object ids and motion of recent frame times kept on the GPU: the progressive engine renders one frame per
# call, in turn, and the sample-free pass costs about a tenth of a 1-spp frame on llvmpipe
AUX_CACHE_BYTES = 64 << 20

#: storage-buffer binding points (``BIND_<NAME>`` in the shader): scene inputs, then outputs
BINDINGS = {
    "prims": 0, "materials": 1, "keys": 2, "camkeys": 3, "lights": 4, "times": 5,
    "color": 6, "emission": 7, "features": 8, "aux": 9, "nodes": 10, "tris": 11,
}
_SCENE_BUFFERS = ("prims", "materials", "keys", "camkeys", "lights")  # pack_scene's arrays, always bound
_MESH_BUFFERS = ("nodes", "tris")  # bound only for scenes with meshes
_OUTPUT_BUFFERS = ("color", "emission", "features", "aux")


def shader_defines() -> str:
    """The ``#define`` lines that name, in GLSL, what Python defines: feature slots (``N_FEAT``,
    ``FEAT_<NAME>``, from :mod:`torchmanifold.features`), ``MAT_<TYPE>``, ``PRIM_<KIND>`` and
    ``BIND_<BUFFER>``."""
    lines = [f"#define MAT_{k.upper()} {v}" for k, v in MATERIAL_TYPES.items()]
    lines += [f"#define PRIM_{k.upper()} {v}" for k, v in PRIM_KINDS.items()]
    lines += [f"#define BIND_{k.upper()} {v}" for k, v in BINDINGS.items()]
    return feature_table.shader_defines() + "\n".join(lines) + "\n"


def _glsl_floats(a) -> str:
    return ", ".join(f"{float(x):.9g}" for x in a)  # 9 significant digits round-trip float32


def _scene_constants(packed: dict) -> str:
    """The scene as GLSL constant arrays, named like the storage buffers they replace."""
    prims, ints = packed["prims"], packed["prims"].view(np.int32)
    rows = [
        f"Prim(vec4({_glsl_floats(p[0:4])}), vec4({_glsl_floats(p[4:8])}), vec4({_glsl_floats(p[8:12])}), "
        f"ivec4({', '.join(str(int(x)) for x in i[12:16])}), ivec4({', '.join(str(int(x)) for x in i[16:20])}))"
        for p, i in zip(prims, ints)
    ]
    mats = [f"Material(vec4({_glsl_floats(m[0:4])}), vec4({_glsl_floats(m[4:8])}))" for m in packed["materials"]]
    keys = [f"vec4({_glsl_floats(k)})" for k in packed["keys"]]
    cams = [f"vec4({_glsl_floats(c[0:4])}), vec4({_glsl_floats(c[4:8])})" for c in packed["camkeys"]]
    lights = [str(int(x)) for x in packed["lights"]]

    def arr(typ: str, name: str, items: list[str], n: int) -> str:
        return f"const {typ} {name}[{n}] = {typ}[{n}](\n    " + ",\n    ".join(items) + ");\n"

    return (
        f"#define N_PRIMS {len(rows)}\n#define N_LIGHTS {packed['n_lights']}\n#define N_CAMKEYS {len(cams)}\n"
        + ("#define FOR_EACH_PRIM(X) " + " ".join(f"X({i})" for i in range(len(rows))) + "\n"
           if len(rows) <= MAX_UNROLLED_OBJECTS else "")
        + ("#define FOR_EACH_LIGHT(X) " + " ".join(f"X({i})" for i in range(packed["n_lights"])) + "\n"
           if 0 < packed["n_lights"] <= MAX_UNROLLED_OBJECTS else "")
        + ("#define FOR_EACH_CAMSEG(X) " + " ".join(f"X({i})" for i in range(len(cams) - 1)) + "\n"
           if len(cams) <= MAX_UNROLLED_OBJECTS else "")
        + arr("Prim", "prims", rows, len(rows))
        + arr("Material", "mats", mats, len(mats))
        + arr("vec4", "keys", keys, len(keys))
        + arr("vec4", "camkeys", cams, 2 * len(cams))
        + arr("int", "lights", lights, len(lights))
    )


def _feature_slots(feature_names: Sequence[str]) -> list[int]:
    """Output channel of every tracer feature in table order, -1 where not output."""
    slots = [-1] * len(feature_table.tracer_names())
    for j, name in enumerate(feature_names):
        slots[feature_table.tracer_names().index(name)] = j
    return slots


#: the programs one tracer compiles from the shader (``PASS_<KIND>`` in GLSL): llvmpipe runs both sides of
#: every branch, so each pass is its own program instead of a branch on a uniform
PASSES = {"store": 0, "accumulate": 1, "aux": 2}


def _shader_source(packed: dict, has_mesh: bool, baked: bool, feature_names: Sequence[str],
                   kind: str = "store") -> str:
    """The shader of one of the :data:`PASSES`: ``store`` writes the sums of the first chunk of samples,
    ``accumulate`` adds later chunks to them, ``aux`` writes the sample-free object ids and motion."""
    src = SHADER_PATH.read_text()
    slots = ", ".join(str(s) for s in _feature_slots(feature_names))
    passes = "".join(f"#define PASS_{k.upper()} {v}\n" for k, v in PASSES.items())
    defines = (f"#version 430\n#define HAS_MESH {int(has_mesh)}\n#define CONST_SCENE {int(baked)}\n"
               f"{passes}#define PASS {PASSES[kind]}\n#define OUTPUT_SLOTS {slots}\n" + shader_defines())
    src = src.replace("#version 430\n", defines, 1)
    return src.replace("SCENE_CONSTANTS", _scene_constants(packed) if baked else "", 1)


def _check_features(features) -> list[str]:
    names = feature_table.tracer_names()
    if isinstance(features, str) or not all(isinstance(f, str) for f in features):
        raise TypeError(f"features must be a sequence of names from {names}, got {features!r}")
    features = list(features)
    bad = [f for f in features if f not in names]
    if bad or len(set(features)) != len(features):
        raise ValueError(f"features must be distinct names from {names}, got {features}")
    return features


def _check_int(name: str, value, lo: int, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if value < lo or (hi is not None and value > hi):
        raise ValueError(f"{name} must be in [{lo}, {hi if hi is not None else 'inf'}), got {value}")
    return int(value)


class PathTracer:
    """Render frames of a scene with a GLSL compute path tracer.

    Args:
        scene: the :class:`~torchmanifold.render.scene.Scene` to render.
        width, height: image size in pixels.
        features: feature channel names to output (any order, from
            :func:`torchmanifold.features.tracer_names`); ``None`` = ``scene.needed_features()``.
        ctx: a moderngl context with GL >= 4.3 (e.g. a window's); ``None`` = :func:`create_context`.
        spp_per_dispatch: most samples one dispatch takes (bounds the length of one GPU job).
        bake_scene: paste the scene into the shader as constants (faster; a new tracer per scene
            anyway) instead of reading storage buffers; ``None`` = when it has at most
            ``MAX_BAKED_OBJECTS`` objects. Both give the same images up to float rounding (the
            compiler folds the baked scene's constant maths).
        max_buffer_bytes: cap on one output storage buffer (default: the driver's
            ``GL_MAX_SHADER_STORAGE_BLOCK_SIZE``); longer batches of frames are rendered in parts.

    Example:
        >>> tracer = PathTracer(default_scene(), 64, 64)
        >>> res = tracer.render([0.0, 1.0], spp=1, seed=0)
        >>> res.color.shape, res.features.shape
        (torch.Size([2, 3, 64, 64]), torch.Size([2, 14, 64, 64]))
    """

    def __init__(
        self,
        scene: Scene,
        width: int = 128,
        height: int = 128,
        features: Sequence[str] | None = None,
        ctx: moderngl.Context | None = None,
        spp_per_dispatch: int = 64,
        bake_scene: bool | None = None,
        max_buffer_bytes: int | None = None,
    ):
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a torchmanifold.render.Scene, got {type(scene).__name__}")
        self.width = _check_int("width", width, 1, 1 << 14)
        self.height = _check_int("height", height, 1, 1 << 14)
        self.spp_per_dispatch = _check_int("spp_per_dispatch", spp_per_dispatch, 1)
        self.scene = scene
        self.feature_names = _check_features(scene.needed_features() if features is None else features)
        if ctx is not None and not isinstance(ctx, moderngl.Context):
            raise TypeError(f"ctx must be a moderngl.Context or None, got {type(ctx).__name__}")
        self.ctx = ctx if ctx is not None else create_context()
        if self.ctx.version_code < 430:
            raise ValueError(f"ctx must support OpenGL 4.3 compute shaders, got version {self.ctx.version_code}")
        self.frames_per_batch = self._frames_per_batch(max_buffer_bytes)

        make_current(self.ctx)
        self._upload_scene(bake_scene)
        self._times_buf: moderngl.Buffer | None = None
        self._batches: list[dict[str, moderngl.Buffer]] = []
        self._batch_frames: list[int] = []  # frames each batch holds
        self._aux_times: list[bytes | None] = []  # the frame times each batch's aux buffer was made for
        self._aux_cache: OrderedDict[bytes, moderngl.Buffer] = OrderedDict()  # float32 time -> (3, H, W), LRU
        self._last: dict | None = None
        self._set_scene_uniforms()

    def _frames_per_batch(self, max_buffer_bytes: int | None) -> int:
        """Frames one set of output buffers holds: one storage block may not exceed the driver's limit
        (128 MiB on llvmpipe; 12 frames of 14 features at 512x512 would not fit)."""
        limit = int(self.ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE") or (1 << 27))
        if max_buffer_bytes is not None:
            limit = min(limit, _check_int("max_buffer_bytes", max_buffer_bytes, 1))
        frame_bytes = 4 * self.width * self.height * max(3, len(self.feature_names))
        if frame_bytes > limit:
            raise ValueError(
                f"width x height: one frame needs {frame_bytes} bytes per output buffer, over this GL driver's "
                f"storage-block limit of {limit}; render a smaller image or fewer features")
        return min(limit // frame_bytes, 65535)  # 65535: the least dispatch-size limit

    def _upload_scene(self, bake_scene: bool | None) -> None:
        """Compile the shader for this scene and upload its storage buffers."""
        packed = pack_scene(self.scene)
        self.has_mesh = packed["has_mesh"]
        self.n_lights = packed["n_lights"]
        # small scenes are pasted into the shader as constants (the built-in box: about 13x faster on llvmpipe)
        if bake_scene is None:
            bake_scene = max(len(self.scene.objects), len(packed["keys"])) <= MAX_BAKED_OBJECTS
        self.baked = bool(bake_scene)
        self._source = lambda kind: _shader_source(packed, self.has_mesh, self.baked, self.feature_names, kind)
        self._programs: dict[str, moderngl.ComputeShader] = {}
        self._uniforms: dict[str, object] = {}
        self.program = self._program("store")  # compiled now, so shader errors show here; the others on first use
        names = _SCENE_BUFFERS + (_MESH_BUFFERS if self.has_mesh else ())
        self._scene_bufs = {BINDINGS[n]: self.ctx.buffer(packed[n].tobytes()) for n in names}

    def _set_scene_uniforms(self) -> None:
        """Uniforms fixed for this tracer: image size, scene sizes, feature slots, render settings."""
        scene = self.scene
        self._set("u_size", (self.width, self.height))
        self._set("u_n_prims", len(scene.objects))
        self._set("u_n_lights", self.n_lights)
        self._set("u_n_camkeys", len(scene.camera.keys))
        self._set("u_n_feat", len(self.feature_names))
        self._set("u_max_depth", scene.max_depth)
        self._set("u_rr_depth", scene.rr_depth)
        self._set("u_shutter", float(scene.shutter))
        self._set("u_background", tuple(float(x) for x in scene.background))
        self._set("u_up", tuple(float(x) for x in scene.camera.up))

    def _program(self, kind: str) -> moderngl.ComputeShader:
        """The compiled program of pass ``kind`` (see :data:`PASSES`), compiled on first use."""
        prog = self._programs.get(kind)
        if prog is None:
            prog = self._programs[kind] = self.ctx.compute_shader(self._source(kind))
            for name, value in self._uniforms.items():
                if name in prog:
                    prog[name].value = value
        return prog

    def _set(self, name: str, value) -> None:
        """Set a uniform in every program (and in those compiled later)."""
        self._uniforms[name] = value
        for prog in self._programs.values():
            if name in prog:  # the GLSL compiler drops unused uniforms
                prog[name].value = value

    @property
    def buffers(self) -> list[tuple[int, int, dict[str, moderngl.Buffer]]]:
        """The output storage buffers of the last :meth:`dispatch`, for consumers that keep frames on the GPU.

        A list of ``(first_frame, n_frames, {name: buffer})`` batches (one unless the frames exceed
        the driver's storage-block size). In each: ``color`` / ``emission`` float32 ``(n, 3, H, W)``
        sums over the samples (divide by the spp), ``features`` float32 ``(n, D, H, W)`` sums,
        ``aux`` float32 ``(n, 3, H, W)`` = object id, motion x, motion y.
        """
        if self._last is None:
            return []
        total, out, first = len(self._last["times"]), [], 0
        for bufs in self._batches:
            if first >= total:
                break
            k = min(self.frames_per_batch, total - first)
            out.append((first, k, dict(bufs)))
            first += k
        return out

    def _ensure_outputs(self, n_frames: int) -> None:
        plane = self.width * self.height * 4
        d = max(len(self.feature_names), 1)
        for b in range(math.ceil(n_frames / self.frames_per_batch)):
            need = min(self.frames_per_batch, n_frames - b * self.frames_per_batch)
            if b < len(self._batches) and self._batch_frames[b] >= need:
                continue
            if b < len(self._batches):
                for buf in self._batches[b].values():
                    buf.release()
            bufs = {
                "color": self.ctx.buffer(reserve=3 * plane * need),
                "emission": self.ctx.buffer(reserve=3 * plane * need),
                "features": self.ctx.buffer(reserve=d * plane * need),
                "aux": self.ctx.buffer(reserve=3 * plane * need),
            }
            if b < len(self._batches):
                self._batches[b], self._batch_frames[b], self._aux_times[b] = bufs, need, None
            else:
                self._batches.append(bufs)
                self._batch_frames.append(need)
                self._aux_times.append(None)

    def _fill_aux(self, b: int, times32: np.ndarray, tiles: list[tuple[int, int]], tw: int, th: int) -> None:
        """Object ids and motion of batch ``b``'s frames (float32 ``times32``): copied from the per-time cache when
        it holds every frame, else made by the aux pass, whose frames then enter the cache."""
        aux_buf, size = self._batches[b]["aux"], 3 * 4 * self.width * self.height
        keys = [t.tobytes() for t in times32]
        if all(k in self._aux_cache for k in keys):
            for f, k in enumerate(keys):
                self.ctx.copy_buffer(aux_buf, self._aux_cache[k], size, write_offset=f * size)
                self._aux_cache.move_to_end(k)
            return
        aux = self._program("aux")
        for x0, y0 in tiles:
            self._set("u_tile_origin", (x0, y0))
            self._set("u_tile_size", (tw, th))
            aux.run(math.ceil(tw / GROUP), math.ceil(th / GROUP), len(keys))
        self.ctx.memory_barrier()  # the copies read what the pass wrote
        for f, k in enumerate(keys):
            buf = self._aux_cache.pop(k, None) or self.ctx.buffer(reserve=size)
            self.ctx.copy_buffer(buf, aux_buf, size, read_offset=f * size)
            self._aux_cache[k] = buf
        while self._aux_cache and len(self._aux_cache) * size > AUX_CACHE_BYTES:
            self._aux_cache.popitem(last=False)[1].release()

    def dispatch(
        self,
        times: Sequence[float] | torch.Tensor,
        spp: int = 1,
        seed: int = 0,
        sample_offset: int = 0,
        tile: int | tuple[int, int] | None = None,
        progress: bool = False,
    ) -> None:
        """Render into the output :attr:`buffers` without reading them back (see :meth:`render`)."""
        if self.program is None:
            raise RuntimeError("dispatch: this PathTracer was released")
        times_np = self._check_times(times)
        spp = _check_int("spp", spp, 1)
        seed = _check_int("seed", seed, 0, 2**32 - 1)
        sample_offset = _check_int("sample_offset", sample_offset, 0, 2**32 - 1 - spp)
        if tile is None:
            tw, th = self.width, self.height
        else:
            tw, th = (tile, tile) if isinstance(tile, int) else tuple(tile)
            tw, th = _check_int("tile width", tw, 1), _check_int("tile height", th, 1)
        make_current(self.ctx)
        self._dispatch(times_np, spp, seed, sample_offset, tw, th, progress)

    def _dispatch(self, times_np, spp, seed, sample_offset, tw, th, progress) -> None:
        n = len(times_np)
        self._ensure_outputs(n)
        tbytes = times_np.astype(np.float32).tobytes()
        if self._times_buf is None or self._times_buf.size < len(tbytes):
            if self._times_buf is not None:
                self._times_buf.release()
            self._times_buf = self.ctx.buffer(reserve=max(len(tbytes), 16))
        self._times_buf.write(tbytes)

        for binding, buf in self._scene_bufs.items():
            buf.bind_to_storage_buffer(binding)
        self._times_buf.bind_to_storage_buffer(BINDINGS["times"])
        self._set("u_seed", seed)
        tiles = [(x0, y0) for y0 in range(0, self.height, th) for x0 in range(0, self.width, tw)]
        batches = [(f0, min(self.frames_per_batch, n - f0)) for f0 in range(0, n, self.frames_per_batch)]
        bar = tqdm(total=math.ceil(spp / self.spp_per_dispatch) * len(tiles) * len(batches), disable=not progress,
                   desc=f"path tracing {n}x{self.width}x{self.height} @ {spp} spp", unit="dispatch")
        for b, (f0, nb) in enumerate(batches):
            for key in _OUTPUT_BUFFERS:
                self._batches[b][key].bind_to_storage_buffer(BINDINGS[key])
            self._set("u_frame_base", f0)
            batch_times = times_np[f0:f0 + nb].astype(np.float32)
            if self._aux_times[b] != batch_times.tobytes():
                self._fill_aux(b, batch_times, tiles, tw, th)
                self._aux_times[b] = batch_times.tobytes()
            done = 0
            while done < spp:
                chunk = min(self.spp_per_dispatch, spp - done)
                self._set("u_spp", chunk)
                self._set("u_sample_start", sample_offset + done)
                program = self._program("accumulate" if done > 0 else "store")
                for x0, y0 in tiles:
                    self._set("u_tile_origin", (x0, y0))
                    self._set("u_tile_size", (tw, th))
                    program.run(math.ceil(tw / GROUP), math.ceil(th / GROUP), nb)
                    if progress:
                        self.ctx.finish()  # so the bar shows finished work, not queued work
                        bar.update()
                done += chunk
        bar.close()
        self.ctx.memory_barrier()
        self._last = {"times": times_np, "spp": spp, "seed": seed, "sample_offset": sample_offset}

    def read(self) -> RenderResult:
        """Read the last :meth:`dispatch` back as a :class:`RenderResult` (one copy per buffer)."""
        if self._last is None:
            raise RuntimeError("read: nothing rendered yet; call dispatch() or render() first")
        n, h, w = len(self._last["times"]), self.height, self.width
        d = len(self.feature_names)
        spp = self._last["spp"]

        def grab(key: str, c: int, scale: bool = True) -> np.ndarray:
            arr = np.empty((n, c, h, w), np.float32)
            if c:
                for f0, nb, bufs in self.buffers:
                    part = arr[f0:f0 + nb]  # contiguous: frames are the outer axis
                    bufs[key].read_into(part, size=part.nbytes)
                if scale and spp > 1:
                    np.divide(arr, np.float32(spp), out=arr)
            return arr

        # numpy, not torch, for the small post-processing: torch's thread pool contends with llvmpipe's
        make_current(self.ctx)
        aux = grab("aux", 3, scale=False)
        return RenderResult(
            color=torch.from_numpy(grab("color", 3)),
            features=torch.from_numpy(grab("features", d)),
            feature_names=list(self.feature_names),
            object_id=torch.from_numpy(np.rint(aux[:, 0]).astype(np.int32)),
            motion=torch.from_numpy(np.ascontiguousarray(aux[:, 1:3])),
            emission=torch.from_numpy(grab("emission", 3)),
            times=torch.from_numpy(self._last["times"].copy()),
            spp=spp,
            sample_offset=self._last["sample_offset"],
            seed=self._last["seed"],
        )

    def render(
        self,
        times: Sequence[float] | torch.Tensor,
        spp: int = 1,
        seed: int = 0,
        sample_offset: int = 0,
        tile: int | tuple[int, int] | None = None,
        progress: bool = False,
    ) -> RenderResult:
        """Render frames at the given times.

        Args:
            times: T frame times in frame units (floats; in-between frames allowed).
            spp: samples per pixel; the result is their mean.
            seed: RNG seed, ``0 <= seed < 2**32``.
            sample_offset: index of the first sample drawn: samples ``sample_offset ..
                sample_offset + spp - 1`` of every pixel, so progressive iteration i with
                ``spp=1, sample_offset=i`` gets fresh independent samples.
            tile: render in tiles of this many pixels (int or (w, h)); the image is the same for
                any tiling because the RNG is keyed on (pixel, sample index, frame time, seed).
            progress: show a tqdm bar over the dispatches (for long renders, e.g. references).

        Returns:
            :class:`RenderResult` with ``color (T, 3, H, W)``, ``features (T, D, H, W)`` etc.
        """
        self.dispatch(times, spp=spp, seed=seed, sample_offset=sample_offset, tile=tile, progress=progress)
        return self.read()

    @staticmethod
    def _check_times(times) -> np.ndarray:
        if isinstance(times, torch.Tensor):
            times = times.detach().cpu().double().numpy()
        if isinstance(times, (int, float)) and not isinstance(times, bool):
            raise TypeError(f"times must be a sequence of frame times, got a single number {times!r}")
        try:
            arr = np.asarray(times, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise TypeError(f"times must be a sequence of frame times (floats), got {times!r}") from exc
        if arr.ndim != 1 or len(arr) == 0 or not np.all(np.isfinite(arr)):
            raise ValueError(f"times must be a non-empty 1-D sequence of finite floats, got {times!r}")
        return arr

    def release(self) -> None:
        """Free the GL objects (the context stays); ``with PathTracer(...) as tracer:`` calls it on exit."""
        if self.program is None:
            return
        make_current(self.ctx)
        for b in [*self._scene_bufs.values(), *(x for bufs in self._batches for x in bufs.values())]:
            b.release()
        if self._times_buf is not None:
            self._times_buf.release()
        for prog in self._programs.values():
            prog.release()
        for buf in self._aux_cache.values():
            buf.release()
        self.program, self._programs, self._aux_cache = None, {}, OrderedDict()
        self._scene_bufs, self._batches, self._batch_frames, self._aux_times = {}, [], [], []
        self._times_buf = None

    def __enter__(self) -> "PathTracer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def __repr__(self) -> str:
        return (
            f"PathTracer({self.width}x{self.height}, features={self.feature_names}, "
            f"objects={len(self.scene.objects)}, lights={self.n_lights}, max_depth={self.scene.max_depth})"
        )
