"""Path tracer throughput: megapaths per second at 256x256 and 512x512, 1 sample per pixel.

On this machine that is Mesa's llvmpipe (compute shaders run on the CPU, synchronously, so wall clock is
the right timer); on a GPU machine the same file measures the GPU. Each size is measured for the built-in
Cornell box (full paths: NEE, glass, Russian roulette, all 14 features) and, as the baseline from the same
run, for primary rays only (``max_depth = 1``, no features) -- the ratio says what the light transport
costs on top of casting camera rays through the same scene. ``mesh_scene`` is ``torus_box.toml`` (a
768-triangle glass mesh through the BVH, a sphere light, motion blur).

``pytest benchmarks/bench_tracer.py`` writes ``benchmarks/results/tracer.json`` (``--quick``: 64x64, a
smoke run, written to ``results/quick/``).
"""
from __future__ import annotations

import dataclasses
import json
import os
import statistics

import pytest

import harness
from torchmanifold.render import PathTracer, create_context, default_scene, load_scene
from torchmanifold.render.scene import SCENES_DIR

SIZES = (256, 512)
FRAMES = 2  # frames per render call (one dispatch per call covers all of them)
_RESULTS: dict = {}


def _variants():
    full = default_scene()
    primary = dataclasses.replace(full, max_depth=1)
    mesh = load_scene(SCENES_DIR / "torus_box.toml")
    return {"full": (full, None), "primary_rays": (primary, []), "mesh_scene": (mesh, None)}


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("variant", ["primary_rays", "full", "mesh_scene"])
def test_tracer_megapaths(benchmark, quick, size, variant):
    if quick:
        size = 64
    scene, feats = _variants()[variant]
    ctx = create_context()
    tracer = PathTracer(scene, size, size, features=feats, ctx=ctx)
    times = [float(i) for i in range(FRAMES)]
    tracer.render(times, spp=1, seed=123)  # warm-up: llvmpipe compiles the shader on first dispatch
    state = {"i": 0}

    def run():
        state["i"] += 1
        return tracer.render(times, spp=1, seed=0, sample_offset=state["i"])

    benchmark.group = f"tracer {size}x{size}"
    benchmark.pedantic(run, rounds=2 if quick else 5, iterations=1, warmup_rounds=0)
    assert ctx.error == "GL_NO_ERROR"
    paths = size * size * FRAMES
    st = benchmark.stats.stats
    _RESULTS.setdefault(str(size), {})[variant] = {
        "median_s": st.median,
        "iqr_s": st.iqr,
        "rounds": st.rounds,
        "paths_per_call": paths,
        "megapaths_per_s": paths / st.median / 1e6,
        "features": tracer.feature_names,
        "max_depth": scene.max_depth,
    }
    benchmark.extra_info["megapaths_per_s"] = paths / st.median / 1e6


def test_write_results(quick):
    """Runs last in this file: ratios vs the primary-ray baseline and the JSON."""
    if not _RESULTS:
        return  # nothing measured (e.g. -k selected only this test)
    ctx = create_context()
    for size, r in _RESULTS.items():
        if "full" in r and "primary_rays" in r:
            r["full_vs_primary_time_ratio"] = r["full"]["median_s"] / r["primary_rays"]["median_s"]
    out = {
        "what": "megapaths/s at 1 spp: built-in Cornell box (full paths), primary rays only, torus_box (mesh)",
        "gl_renderer": ctx.info["GL_RENDERER"],
        "gl_version": ctx.info["GL_VERSION"],
        "llvmpipe_threads": os.environ.get("LP_NUM_THREADS", f"default (= {os.cpu_count()} cpus)"),
        "frames_per_call": FRAMES,
        "load_average_1_5_15min": list(os.getloadavg()),  # the CPU is shared: llvmpipe gets what is left
        "sizes": _RESULTS,
        "summary": {
            size: {k: round(v["megapaths_per_s"], 4) for k, v in r.items() if isinstance(v, dict)}
            for size, r in _RESULTS.items()
        },
        "median_megapaths_per_s": statistics.median(
            r["full"]["megapaths_per_s"] for r in _RESULTS.values() if "full" in r
        ) if any("full" in r for r in _RESULTS.values()) else None,
        "meta": harness.metadata(quick),
    }
    folder = harness.RESULTS / "quick" if quick else harness.RESULTS
    folder.mkdir(parents=True, exist_ok=True)
    name = "tracer.json"
    if "GL_RENDERER" in ctx.info and "llvmpipe" not in ctx.info["GL_RENDERER"].lower():
        name = "tracer_gpu.json"  # a GPU run keeps the llvmpipe numbers
    (folder / name).write_text(json.dumps(out, indent=2))
