"""Run every benchmark and the stability suite, then redraw the charts and the summaries. One command:

    .venv/bin/python benchmarks/run_all.py            # full run (about 3 minutes on 2 shared cores, 5 with --all)
    .venv/bin/python benchmarks/run_all.py --quick    # smoke run: tiny sizes, results/quick/, seconds

Steps: the stability suite (``tests/stability``, rewrites ``docs/stability.md``), ``bench_methods.py`` (speed
against accuracy, scaling, progressive curves), ``bench_ablation.py`` (feature sets), with ``--all`` also the other
``bench_*.py`` files (filter, tracer, pipeline: their owners' JSON), then ``charts.py`` (PNGs + ``docs/benchmarks.md``).
Each step is its own pytest process with ``TORCHMANIFOLD_BENCH_THREADS`` threads (default 1, see conftest.py).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
MINE = ["bench_methods.py", "bench_ablation.py"]


def steps(args) -> list:
    py = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    quick = ["--quick"] if args.quick else []
    out = [("stability suite", py + ["tests/stability"])]
    files = MINE + (sorted(p.name for p in BENCH.glob("bench_*.py") if p.name not in MINE) if args.all else [])
    for name in files:
        extra = []
        if not args.quick:
            extra = ["--benchmark-json", str(BENCH / "results" / f"pytest-benchmark-{Path(name).stem}.json")]
        out.append((name, py + [str(BENCH / name)] + quick + extra))
    out.append(("charts", [sys.executable, str(BENCH / "charts.py")] + quick))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="Run all benchmarks and regenerate the charts.")
    p.add_argument("--quick", action="store_true", help="smoke run at tiny sizes (writes results/quick/)")
    p.add_argument("--threads", type=int, default=int(os.environ.get("TORCHMANIFOLD_BENCH_THREADS", "1")),
                   help="threads for torch/OpenCV (default 1: stable timings on a shared machine)")
    p.add_argument("--all", action="store_true", help="also run the other bench_*.py files in benchmarks/")
    args = p.parse_args(argv)
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    # TORCHMANIFOLD_WRITE_DOCS: the stability suite rewrites docs/stability.md only when asked (here)
    env = {**os.environ, "TORCHMANIFOLD_BENCH_THREADS": str(args.threads),
           "TORCHMANIFOLD_WRITE_DOCS": "0" if args.quick else "1"}
    failed = []
    bar = tqdm(steps(args), desc="benchmarks", unit="step")
    for label, cmd in bar:
        bar.set_postfix_str(label)
        t0 = time.perf_counter()
        rc = subprocess.run(cmd, cwd=ROOT, env=env).returncode
        tqdm.write(f"[{label}] exit {rc} in {time.perf_counter() - t0:.0f} s")
        if rc != 0:
            failed.append(label)
    if failed:
        print("failed steps: " + ", ".join(failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
