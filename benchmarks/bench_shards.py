"""Frame-window shards on Ray against the one-process path: throughput, and the halo's cost per chunk size.

Run: ``.venv/bin/python -m pytest benchmarks/bench_shards.py`` (``--quick`` for a smoke run). Starts a local
Ray cluster of 2 workers (``TORCHMANIFOLD_BENCH_WORKERS``), warms every worker (torch imported, GL context
made) with a small job, then times:

- ``denoise``: :func:`~torchmanifold.pipeline.job.denoise_files` vs :func:`~torchmanifold.pipeline.shards.
  shard_denoise` at several chunk sizes (frames read = owned + halo, counted by the workers);
- ``render``: the progressive loop of :func:`~torchmanifold.pipeline.job.render_job` over the clip in one
  process (warm tracer, no reference, no files) vs :func:`~torchmanifold.pipeline.shards.shard_render`
  (which also writes every frame's EXR and PNG) at several chunk sizes (frame renders counted);
- the render halo's cost from the plan alone (no run) for a production-like 16 iterations and larger chunks.

Writes ``benchmarks/results/shards.json``. Times are recorded, never asserted; on a shared machine the
speed-up is bounded by the cores the neighbours leave (the load average is recorded with each run).
"""
from __future__ import annotations

import os
import shutil
import time

import numpy as np
import pytest

import harness
from torchmanifold.io import read_exr, write_exr
from torchmanifold.pipeline import shards
from torchmanifold.pipeline.denoise import DenoiseSettings
from torchmanifold.pipeline.job import denoise_files
from torchmanifold.pipeline.render_job import render_query_times
from torchmanifold.pipeline.progressive import ProgressiveRenderer
from torchmanifold.render import PathTracer, default_scene

WORKERS = int(os.environ.get("TORCHMANIFOLD_BENCH_WORKERS", "2"))
RESULT: dict = {}


@pytest.fixture(scope="module")
def cluster():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=WORKERS, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module", autouse=True)
def _write(quick):
    yield
    if RESULT:
        harness.write_json("shards", {"workers": WORKERS, **RESULT}, quick)


def _clip(dst, n, crop):
    dst.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(n):
        d = read_exr(harness.DATA / f"frame_{k % 10:04d}.exr")
        paths.append(write_exr(dst / f"f_{k:04d}.exr", {c: v[:crop, :crop].copy() for c, v in d.items()}))
    return paths


def _load():
    return os.getloadavg()[0]


def test_denoise_throughput(cluster, tmp_path, quick):
    n, crop, r = (6, 48, 1) if quick else (16, 128, 1)
    paths = _clip(tmp_path / "in", n, crop)
    st = DenoiseSettings(temporal_radius=r, tree_height=3)  # the denoise command's defaults
    shards.shard_denoise(paths[:2 * WORKERS], tmp_path / "warm", settings=st, chunk=1, progress=False)
    t = time.perf_counter()
    denoise_files(paths, tmp_path / "one", settings=st, progress=False)
    one = time.perf_counter() - t
    rows = []
    for chunk in ([1, 3] if quick else [1, 2, 4, 8]):
        load = _load()
        res = shards.shard_denoise(paths, tmp_path / f"c{chunk}", settings=st, chunk=chunk, progress=False)
        s = res["shards"]
        rows.append({"chunk": chunk, "chunks": s["chunks"], "seconds": s["seconds"],
                     "frames_per_second": s["frames_per_second"], "speedup": one / s["seconds"],
                     "frames_read": s["frames_read"], "read_overhead": s["frames_read"] / n,
                     "read_overhead_formula": "(C + 2r) / C per interior chunk",
                     "load_average_1min": load,
                     "workers": {w: round(v["frames_per_second"], 3) for w, v in s["workers"].items()}})
        shutil.rmtree(tmp_path / f"c{chunk}")
    RESULT["denoise"] = {"frames": n, "size": [crop, crop], "temporal_radius": r,
                         "one_process_seconds": one, "one_process_frames_per_second": n / one, "sharded": rows}


def test_render_throughput(cluster, tmp_path, quick):
    cfg = (dict(frames=4, iterations=3, width=16, height=12) if quick else
           dict(frames=12, iterations=6, width=64, height=48))
    shards.shard_render(tmp_path / "warm", frames=2 * WORKERS, iterations=1, width=8, height=8, chunk=1,
                        progress=False)
    # the one-process loop of render_job with a warm tracer: what the shards split (the tracer's context is
    # made once per worker process too, by the warm-up above)
    tracer = PathTracer(default_scene(), cfg["width"], cfg["height"])
    times = [float(k) for k in range(cfg["frames"])]
    t = time.perf_counter()
    ProgressiveRenderer(tracer, times, settings=DenoiseSettings(temporal_radius=1, mode="spacetime")).run(
        cfg["iterations"])
    one = time.perf_counter() - t
    tracer.release()
    rows = []
    for chunk in ([1, 2] if quick else [2, 3, 6]):
        load = _load()
        res = shards.shard_render(tmp_path / f"c{chunk}", chunk=chunk, progress=False, **cfg)
        s = res["shards"]
        rows.append({"chunk": chunk, "chunks": s["chunks"], "seconds": s["seconds"],
                     "frames_per_second": s["frames_per_second"], "speedup": one / s["seconds"],
                     "frames_traced": s["frames_traced"], "frames_traced_one_process": s["frames_traced_one_process"],
                     "traced_overhead": s["frames_traced"] / s["frames_traced_one_process"],
                     "load_average_1min": load,
                     "workers": {w: round(v["frames_per_second"], 3) for w, v in s["workers"].items()}})
        shutil.rmtree(tmp_path / f"c{chunk}")
    RESULT["render"] = {**cfg, "temporal_radius": 1, "one_process_seconds": one,
                        "one_process_frames_per_second": cfg["frames"] / one, "sharded": rows}


def test_render_halo_plan():
    """Frame renders per owned frame-iteration, from the plan, for a 240-frame clip at radius 1."""
    frames, rows = 240, []
    times, query = render_query_times(frames, 0)
    for iterations in (4, 16, 64):
        for chunk in (8, 24, 60, 120):
            plan = shards.plan_chunks(range(frames), chunk, lambda o: (0, 0))
            traced = sum(shards.traced_frames(times, query, shards.render_cone(times, query, c.owned, 1,
                                                                                 iterations)[0], 1) for c in plan)
            rows.append({"iterations": iterations, "chunk": chunk, "traced_overhead": traced / (frames * iterations),
                         "formula_interior": 1 + (iterations ** 2 + 3 * iterations - 2) / (iterations * chunk)})
    RESULT["render_halo_plan"] = {"frames": frames, "temporal_radius": 1, "rows": rows}
    assert all(np.isfinite(r["traced_overhead"]) for r in rows)
