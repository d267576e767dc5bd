"""The demo's display against an earlier commit's, frame by frame in one running demo.

Run: ``.venv/bin/python benchmarks/bench_demo_display.py [--base COMMIT] [--frames 160] [--runs 3]``; writes
``benchmarks/results/demo_display.json``.

Between processes the display's time swings by a third on the shared VM (llvmpipe's draws start with cold
caches after the filter, and the tracer process shares the cores), more than the changes it is meant to judge.
So one headless demo (128x128, 3 frames, the default zoom, the tracer ahead) draws its frames alternately with
this tree's ``DemoApp.draw`` and with ``--base``'s (its ``demo/`` extracted and imported under another name),
every frame after a new iteration as in ``bench_demo.py``; each frame's display is timed as the demo times it
(the draw and a finish). Medians per run; the ratio is the point.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import re
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

#: The last commit before the display's cached backdrop.
BASE = "b32903e"


def _base_package(commit: str, into: Path) -> None:
    """``demo/`` at ``commit`` as the package ``demo_base`` under ``into`` (its own imports renamed)."""
    data = subprocess.run(["git", "archive", commit, "demo"], cwd=ROOT, capture_output=True,
                          check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(into, filter="data")
    (into / "demo").rename(into / "demo_base")
    for path in (into / "demo_base").glob("*.py"):
        path.write_text(re.sub(r"\bfrom demo(\.| import)", r"from demo_base\1", path.read_text()))


def run_one(base_dir: str, frames: int) -> dict:
    """One demo run (in this process), its frames drawn alternately by this tree and by the base."""
    sys.path[:0] = [str(ROOT), base_dir]
    import torch._dynamo  # noqa: F401  (before any GL context, see the README's machine notes)

    from demo import app as current
    from demo_base import app as base

    draws = {"base": base.DemoApp.draw, "current": current.DemoApp.draw}
    times: dict[str, list[float]] = {name: [] for name in draws}
    if hasattr(base.DemoApp, "canvas"):  # the base's draw builds its overlay through it (gone here)
        current.DemoApp.canvas = base.DemoApp.canvas

    def on_render(self, time_s, frame_time):
        prog = self.progression
        with current.torch_threads(prog.threads):
            prog.step()
            self._advance_playback()
            name = ("base", "current")[self.frames_drawn % 2]
            self._uploaded = None  # each draw uploads as it would after its own iteration
            t0 = time.perf_counter()
            draws[name](self)
            self.ctx.finish()
            if self.frames_drawn >= 4:  # warm-up
                times[name].append((time.perf_counter() - t0) * 1e3)
        self.frames_drawn += 1

    current.DemoApp.on_render = on_render
    current.run(["--headless", "--size", "128x128", "--clip", "3", "--scale", "0", "--frames", str(frames),
                 "--reference-spp", "8"])
    return {name: statistics.median(ts) for name, ts in times.items()} | {"frames": len(times["base"])}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--base", default=BASE)
    p.add_argument("--frames", type=int, default=160)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--_one", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a._one:  # a child: one run, its medians on stdout
        print(json.dumps(run_one(a._one, a.frames)))
        return {}
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        _base_package(a.base, Path(tmp))
        for _ in range(a.runs):  # each run its own process: a fresh GL context and tracer
            proc = subprocess.run([sys.executable, __file__, "--frames", str(a.frames), "--_one", tmp],
                                  capture_output=True, text=True, check=True, timeout=1800,
                                  env=dict(os.environ, PYTHONPATH=str(ROOT)))
            runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
            r = runs[-1]
            print(f"display: base {r['base']:.2f} ms, current {r['current']:.2f} ms "
                  f"(x{r['base'] / r['current']:.2f}, {r['frames']} frames each)")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from harness import metadata

    out = {"base_commit": a.base, "size": "128x128", "clip": 3, "runs": runs,
           "ratio_median": statistics.median(r["base"] / r["current"] for r in runs), "metadata": metadata()}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "demo_display.json").write_text(json.dumps(out, indent=1) + "\n")
    return out


if __name__ == "__main__":
    main()
