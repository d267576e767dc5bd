"""Demo speed: iterations per second and ms per stage, against the demo before the display moved to the GPU.

Run: ``.venv/bin/python -m pytest benchmarks/bench_demo.py`` (``--quick`` for a smoke run). Every variant is
``python -m demo --headless --size 128x128 --clip 3 --frames N --stats FILE`` in its own process, in the same
run, one after another (round-robin when ``TORCHMANIFOLD_BENCH_ROUNDS`` > 1), so their ratios are comparable on a
noisy shared machine even when the absolute numbers are not. Results: ``benchmarks/results/demo.json``.

Variants:

* ``before``: the demo at :data:`BEFORE` (tracer in the window's context, trace then filter then display, CPU
  packing of the panels, PIL overlay; its time window +-1 frame). It prints median ms per stage only; its ms per
  iteration is their sum (its stages run one after the other).
* ``window r1, in turn``: this demo with the same filter (+-1 frame window) and the tracer not running ahead.
* ``window r1, ahead``: the same with the tracer one iteration ahead (the overlap alone).
* ``per frame, in turn`` / ``per frame, ahead``: this demo's filter default (each frame filtered alone), the
  tracer in turn / ahead (the default).
* ``per frame, ahead, fitting zoom``: the same at the default zoom (the largest with the window at most 1280
  pixels wide: 2 at 128x128); every other variant draws the panels at zoom 3, the demo before's default, so
  their display times compare at equal window size.

This demo's ``display_ms`` includes the window clear; the demo before cleared outside its display time.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tarfile
import io
from pathlib import Path

from harness import RESULTS, ROOT, metadata

#: The commit whose demo is the "before" (the demo just moved onto the progressive engine).
BEFORE = "059659d"

VARIANTS = {
    "before": ["--time-window", "1"],
    "window r1, in turn": ["--time-window", "1", "--no-overlap"],
    "window r1, ahead": ["--time-window", "1"],
    "per frame, in turn": ["--no-overlap"],
    "per frame, ahead": [],
    "per frame, ahead, fitting zoom": ["--scale", "0"],
}


def _before_tree(tmp: Path) -> Path:
    """``demo/`` as of :data:`BEFORE`, extracted under ``tmp`` (it imports torchmanifold from this tree)."""
    data = subprocess.run(["git", "archive", BEFORE, "demo"], cwd=ROOT, capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(tmp, filter="data")
    return tmp


def _run(name: str, common: list[str], tmp: Path, before: Path) -> dict:
    stats = tmp / f"{len(list(tmp.glob('*.json')))}.json"
    front = str(before) if name == "before" else str(ROOT)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([front, str(ROOT)]))
    argv = common + VARIANTS[name]
    if name == "before":
        argv = [a for a in _old_size_argv(argv)]
    else:
        argv += ["--stats", str(stats)]
    proc = subprocess.run([sys.executable, "-m", "demo", *argv], cwd=tmp, env=env, capture_output=True, text=True,
                          timeout=1800)
    if proc.returncode != 0:
        raise RuntimeError(f"{name}: demo failed:\n{proc.stderr[-3000:]}")
    if name != "before":
        return json.loads(stats.read_text())
    m = re.search(r"median ms per frame: trace ([\d.]+)\s+filter ([\d.]+)\s+display ([\d.]+)", proc.stdout)
    if m is None:
        raise RuntimeError(f"before: no stage times in its output:\n{proc.stdout[-2000:]}")
    trace, filt, display = (float(g) for g in m.groups())
    total = trace + filt + display
    return {"iterations_per_second": 1e3 / total, "ms_per_iteration": total, "trace_ms": trace, "trace_wait_ms": trace,
            "filter_ms": filt, "display_ms": display, "load_average": os.getloadavg()[0]}


def _old_size_argv(argv: list[str]) -> list[str]:
    """The old demo has no ``--size``: ``--width`` / ``--height`` instead."""
    i = argv.index("--size")
    w, h = argv[i + 1].split("x")
    return argv[:i] + ["--width", w, "--height", h] + argv[i + 2:]


def test_demo_speed(quick, tmp_path):
    size, frames = ("48x48", 4) if quick else ("128x128", 12)
    rounds = int(os.environ.get("TORCHMANIFOLD_BENCH_ROUNDS", "1"))
    common = ["--headless", "--size", size, "--scale", "3", "--clip", "3", "--frames", str(frames),
              "--reference-spp", "8",
              "--threads", os.environ.get("TORCHMANIFOLD_BENCH_THREADS", "1")]
    before = _before_tree(tmp_path / "before")
    runs: dict[str, list[dict]] = {name: [] for name in VARIANTS}
    for _ in range(rounds):
        for name in VARIANTS:
            runs[name].append(_run(name, common, tmp_path, before))
    best = {name: min(rs, key=lambda r: r["ms_per_iteration"]) for name, rs in runs.items()}
    ref = best["before"]
    ratios = {name: {"speedup": ref["ms_per_iteration"] / r["ms_per_iteration"],
                     "display_speedup": ref["display_ms"] / r["display_ms"]} for name, r in best.items()}
    for name, r in best.items():
        print(f"{name:>20}: {r['iterations_per_second']:5.2f} it/s  trace {r['trace_ms']:6.1f} (waited "
              f"{r['trace_wait_ms']:6.1f})  filter {r['filter_ms']:6.1f}  display {r['display_ms']:6.1f} ms  "
              f"x{ratios[name]['speedup']:.2f} vs before (display x{ratios[name]['display_speedup']:.1f})  "
              f"load {r['load_average']:.1f}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / ("demo_quick.json" if quick else "demo.json")).write_text(json.dumps(
        {"size": size, "clip": 3, "frames": frames, "rounds": rounds, "before_commit": BEFORE, "best": best,
         "ratios": ratios, "runs": runs, "metadata": metadata(quick)}, indent=1, default=float))
