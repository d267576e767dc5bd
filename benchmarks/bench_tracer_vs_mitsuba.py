"""Our path tracer against Mitsuba 3 (``llvm_ad_rgb``) on the built-in Cornell box, in the same run.

Both renderers get the same scene (``cornell_box.toml`` at frame 0 with the shutter closed: Mitsuba has no
keyframed shape motion), resolution, samples per pixel and path length: our ``max_depth`` counts hits, and
next-event estimation adds one more segment, so Mitsuba's ``max_depth`` (path segments) is ours + 1; both start
Russian roulette at the same vertex. Mitsuba runs in its own virtual environment as a subprocess (it is a
benchmark dependency only, ``benchmarks/requirements-mitsuba.txt``) and the two are timed in alternating
blocks of frames rendered back to back (:data:`BLOCK`), round by round, on the same shared machine; medians
are reported.

Measured:

* throughput: megapaths per second at 1 spp (one path per pixel, what a progressive viewer asks for every
  frame), our full tracer (all 14 features) and our colour-only tracer;
* error at equal time: each renderer spends about ``BUDGET_S`` seconds (spp chosen from its measured
  throughput) and is scored by relMSE against a shared reference, the mean of a long render from each (their
  disagreement is reported too: it bounds how well either can score).

Run ``python benchmarks/bench_tracer_vs_mitsuba.py [--quick]`` or through pytest; writes
``benchmarks/results/tracer_vs_mitsuba.json``. ``MITSUBA_PYTHON`` (default ``/work/venvs/mitsuba/bin/python``)
and ``DRJIT_LIBLLVM_PATH`` (Debian 12's LLVM 14/15 aborts in Dr.Jit; LLVM 19 works) choose the Mitsuba side.
"""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

MITSUBA_PYTHON = os.environ.get("MITSUBA_PYTHON", "/work/venvs/mitsuba/bin/python")
LIBLLVM = os.environ.get("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")
SIZE = 256
ROUNDS = 7
BUDGET_S = 4.0  # equal-time budget per renderer
REF_SPP = 256  # per renderer; the shared reference averages both
TRIAL_SPP = 8  # the timed trial that sets each renderer's spp for the equal-time budget
#: frames each renderer renders back to back per round, as a progressive viewer asks for them: the first
#: after the other renderer's turn pays for that one's worker threads (Dr.Jit's spin a while after a job;
#: a single frame per turn measured ours 14.6 ms and Mitsuba 19.0 ms, 0.3 s of pause before each 11.0 and
#: 24.8 ms), so the median over a block is each one's steady pace
BLOCK = 5


# ------------------------------------------------------------------------------------------ Mitsuba side
def _mitsuba_scene(desc: dict):
    import mitsuba as mi

    T = mi.ScalarTransform4f

    def bsdf(m):
        if m["type"] == "mirror":
            return {"type": "conductor", "material": "none", "specular_reflectance": {"type": "rgb", "value": m["color"]}}
        if m["type"] == "glass":
            return {"type": "dielectric", "int_ior": m["ior"], "ext_ior": 1.0,
                    "specular_reflectance": {"type": "rgb", "value": m["color"]},
                    "specular_transmittance": {"type": "rgb", "value": m["color"]}}
        # ours shades both sides of a diffuse surface
        return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": m["color"]}}}

    cam = desc["camera"]
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": desc["max_depth"] + 1, "rr_depth": desc["rr_depth"]},
        "sensor": {
            "type": "perspective", "fov": cam["fov"], "fov_axis": "y",
            "to_world": T().look_at(origin=cam["eye"], target=cam["target"], up=cam["up"]),
            "sampler": {"type": "independent", "sample_count": 1},
            "film": {"type": "hdrfilm", "width": desc["size"], "height": desc["size"], "pixel_format": "rgb",
                     "rfilter": {"type": "box"}},
        },
    }
    for i, o in enumerate(desc["objects"]):
        m = desc["materials"][o["material"]]
        if o["kind"] == "sphere":
            shape = {"type": "sphere", "center": o["center"], "radius": o["radius"]}
        else:  # Mitsuba's rectangle is [-1, 1]^2 in z = 0 facing +z: map it onto origin + [0, 1] u + [0, 1] v
            u, v, q = (np.asarray(o[k], float) for k in ("u", "v", "origin"))
            n = np.cross(u, v)
            mat = np.eye(4)
            mat[:3, 0], mat[:3, 1], mat[:3, 2], mat[:3, 3] = u / 2, v / 2, n / np.linalg.norm(n), q + (u + v) / 2
            shape = {"type": "rectangle", "to_world": T(mat.tolist())}
        shape["bsdf"] = bsdf(m)
        if max(m["emission"]) > 0:
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": m["emission"]}}
        d[f"shape{i}"] = shape
    return mi.load_dict(d)


def _worker() -> None:
    """Mitsuba process: one JSON request per stdin line, one JSON answer per stdout line."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    scene = None
    for line in sys.stdin:
        req = json.loads(line)
        if req["cmd"] == "scene":
            scene = _mitsuba_scene(req["desc"])
            ans = {"variant": mi.variant(), "mitsuba": mi.__version__, "drjit": dr.__version__,
                   "threads": dr.thread_count()}
        elif req["cmd"] == "render":
            each = []
            for k in range(req.get("repeat", 1)):  # back to back, as a progressive viewer asks
                t0 = time.perf_counter()
                img = mi.render(scene, spp=req["spp"], seed=req["seed"] + k)
                arr = np.asarray(img, dtype=np.float32)  # forces evaluation: the render is timed in full
                each.append(time.perf_counter() - t0)
            ans = {"seconds": each[-1], "each": each}
            if req.get("out"):
                np.save(req["out"], arr.transpose(2, 0, 1))
        else:
            break
        print(json.dumps(ans), flush=True)


# ------------------------------------------------------------------------------------------ our side
def _scene_description(scene, size: int) -> dict:
    """The parts of our scene Mitsuba needs, at frame 0 with the shutter closed, as plain JSON."""
    cam = scene.camera.keys[0]
    objects = []
    for o in scene.objects:
        if o.kind == "sphere":
            objects.append({"kind": "sphere", "center": list(o.center), "radius": o.radius, "material": o.material})
        elif o.kind == "quad":
            objects.append({"kind": "quad", "origin": list(o.origin), "u": list(o.u), "v": list(o.v),
                            "material": o.material})
        else:
            raise ValueError(f"scene: object kind {o.kind!r} is not translated to Mitsuba here (spheres, quads)")
    return {
        "size": size, "max_depth": scene.max_depth, "rr_depth": scene.rr_depth,
        "camera": {"eye": list(cam.eye), "target": list(cam.target), "fov": cam.fov, "up": list(scene.camera.up)},
        "materials": {k: {"type": m.type, "color": list(m.color), "emission": list(m.emission), "ior": m.ior}
                      for k, m in scene.materials.items()},
        "objects": objects,
    }


class _Mitsuba:
    def __init__(self):
        env = dict(os.environ, DRJIT_LIBLLVM_PATH=LIBLLVM)
        self.proc = subprocess.Popen([MITSUBA_PYTHON, __file__, "--worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env)

    def ask(self, **req) -> dict:
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the Mitsuba worker ({MITSUBA_PYTHON}) exited; is mitsuba installed there?")
        return json.loads(line)

    def close(self) -> None:
        self.proc.stdin.write(json.dumps({"cmd": "quit"}) + "\n")
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


def rel_mse(x: np.ndarray, ref: np.ndarray) -> float:
    """Relative MSE on linear colour, the project's score: ``mean((x - r)^2 / (r^2 + 0.01))``."""
    return float(np.mean((x.astype(np.float64) - ref) ** 2 / (ref ** 2 + 0.01)))


def main(quick: bool = False, out_dir: Path | None = None) -> dict:
    import dataclasses
    import tempfile

    from torchmanifold.render import PathTracer, create_context, default_scene

    size, rounds, budget, ref_spp = (64, 3, 0.5, 16) if quick else (SIZE, ROUNDS, BUDGET_S, REF_SPP)
    scene = dataclasses.replace(default_scene(), shutter=0.0)
    ctx = create_context()
    ours = {"full": PathTracer(scene, size, size, ctx=ctx), "colour_only": PathTracer(scene, size, size, features=[], ctx=ctx)}
    mts = _Mitsuba()
    tmp = Path(tempfile.mkdtemp())
    try:
        info = mts.ask(cmd="scene", desc=_scene_description(scene, size))
        mts.ask(cmd="render", spp=1, seed=0)  # warm-up: Dr.Jit compiles and caches its kernel
        for tr in ours.values():
            tr.render([0.0], spp=1, seed=0)  # warm-up: llvmpipe compiles the shader
        times: dict[str, list[float]] = {"mitsuba": [], **{k: [] for k in ours}}
        for r in range(rounds):  # alternate blocks, so both see the same load
            times["mitsuba"] += mts.ask(cmd="render", spp=1, seed=1 + BLOCK * r, repeat=BLOCK)["each"]
            for k, tr in ours.items():
                for j in range(BLOCK):
                    t0 = time.perf_counter()
                    tr.render([0.0], spp=1, seed=0, sample_offset=1 + BLOCK * r + j)
                    times[k].append(time.perf_counter() - t0)
        med = {k: statistics.median(v) for k, v in times.items()}
        mpaths = {k: size * size / v / 1e6 for k, v in med.items()}

        # shared reference: a long render from each, averaged
        mts.ask(cmd="render", spp=ref_spp, seed=10_000, out=str(tmp / "ref_mitsuba.npy"))
        ref_m = np.load(tmp / "ref_mitsuba.npy").astype(np.float64)
        ref_o = ours["colour_only"].render([0.0], spp=ref_spp, seed=10_000).color[0].double().numpy()
        ref = 0.5 * (ref_m + ref_o)

        # equal time: each one's spp from a timed trial at TRIAL_SPP (per-frame costs amortise over samples),
        # both scored against the shared reference
        trial = 2 if quick else TRIAL_SPP
        mts.ask(cmd="render", spp=trial, seed=19_998)  # Dr.Jit compiles a kernel per sample count: not timed
        spp_m = max(1, round(trial * budget / mts.ask(cmd="render", spp=trial, seed=19_999)["seconds"]))
        mts.ask(cmd="render", spp=spp_m, seed=19_997)  # compile, not timed
        ans = mts.ask(cmd="render", spp=spp_m, seed=20_000, out=str(tmp / "eq_mitsuba.npy"))
        equal = {"mitsuba": {"spp": spp_m, "seconds": ans["seconds"],
                             "rel_mse": rel_mse(np.load(tmp / "eq_mitsuba.npy"), ref)}}
        # a render of more samples than one dispatch takes compiles the tracer's accumulate pass: not timed
        ours["full"].render([0.0], spp=ours["full"].spp_per_dispatch + 1, seed=19_996)
        t0 = time.perf_counter()
        ours["full"].render([0.0], spp=trial, seed=19_999)
        spp_o = max(1, round(trial * budget / (time.perf_counter() - t0)))
        t0 = time.perf_counter()
        res = ours["full"].render([0.0], spp=spp_o, seed=20_000)
        equal["ours_full"] = {"spp": spp_o, "seconds": time.perf_counter() - t0,
                              "rel_mse": rel_mse(res.color[0].numpy(), ref)}
    finally:
        mts.close()
    out = {
        "what": f"built-in Cornell box at frame 0 (shutter closed), {size}x{size}, 1 spp, our max_depth "
                f"{scene.max_depth} = Mitsuba path max_depth {scene.max_depth + 1}, rr_depth {scene.rr_depth}; "
                f"timed in alternating blocks of {BLOCK} frames, medians",
        "gl_renderer": ctx.info["GL_RENDERER"],
        "llvmpipe_threads": os.environ.get("LP_NUM_THREADS", f"default (= {os.cpu_count()} cpus)"),
        "mitsuba": info,
        "rounds": rounds,
        "seconds_per_frame": times,
        "median_seconds_per_frame": med,
        "megapaths_per_s": mpaths,
        "speedup_vs_mitsuba": {k: mpaths[k] / mpaths["mitsuba"] for k in ours},
        "reference": {"spp_each": ref_spp, "rel_mse_between_the_two_references": rel_mse(ref_o, ref_m),
                      "mean_colour": {"mitsuba": ref_m.mean((1, 2)).tolist(), "ours": ref_o.mean((1, 2)).tolist()}},
        "equal_time": {"budget_s": budget, **equal},
        "load_average_1_5_15min": list(os.getloadavg()),
    }
    folder = out_dir or Path(__file__).resolve().parent / "results" / ("quick" if quick else "")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "tracer_vs_mitsuba.json").write_text(json.dumps(out, indent=2))
    return out


def test_tracer_vs_mitsuba(quick):
    out = main(quick)
    assert out["megapaths_per_s"]["mitsuba"] > 0  # timings are recorded, never asserted


if __name__ == "__main__":
    if "--worker" in sys.argv:
        _worker()
    else:
        print(json.dumps(main(quick="--quick" in sys.argv), indent=2))
