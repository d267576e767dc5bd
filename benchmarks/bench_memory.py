"""Peak memory of ``torchmanifold denoise`` against clip length: a streamed clip holds only its window.

    .venv/bin/python benchmarks/bench_memory.py [--frames 20 1000] [--size 48]

Each clip is a ``--size`` crop of the shared Mitsuba clip's frames, repeated and brightened per frame (so
no two frames are equal), written as EXR files; each ``denoise`` run is its own process, with the CLI's
default settings (+-2 frames space-time window), and its peak resident memory is read from
``getrusage(RUSAGE_CHILDREN)`` of a fresh driver process. Writes ``results/memory.json``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "benchmarks"))

_DRIVER = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True); "
           "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")


def write_clip(folder: Path, n: int, size: int) -> list[Path]:
    import harness
    from torchmanifold.io import read_exr, write_exr

    src = [read_exr(harness.DATA / f"frame_{k:04d}.exr") for k in range(4)]
    paths = []
    for k in range(n):
        d = {c: v[96:96 + size, 96:96 + size].copy() for c, v in src[k % 4].items()}
        for c in "RGB":
            d[c] *= 1.0 + 0.001 * k
        paths.append(write_exr(folder / f"frame_{k:05d}.exr", d))
    return paths


def peak_rss_mb(inputs: list[Path], out: Path) -> tuple[float, float]:
    cli = [str(Path(sys.executable).parent / "torchmanifold"), "denoise", *map(str, inputs), "--out", str(out),
           "--quiet", "--threads", "1"]
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", _DRIVER, *cli], check=True, capture_output=True, text=True)
    return int(res.stdout.strip().splitlines()[-1]) / 1024.0, time.perf_counter() - t0


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, nargs="+", default=[20, 1000])
    p.add_argument("--size", type=int, default=48)
    a = p.parse_args(argv)
    out = {"size": a.size, "threads": 1, "runs": {}}
    for n in a.frames:
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp) / "in"
            folder.mkdir()
            mb, secs = peak_rss_mb(write_clip(folder, n, a.size), Path(tmp) / "out")
        out["runs"][str(n)] = {"peak_rss_mb": round(mb, 1), "seconds": round(secs, 1),
                               "ms_per_frame_incl_start": round(1000 * secs / n, 1)}
        print(f"{n} frames of {a.size}x{a.size}: peak RSS {mb:.0f} MB, {secs:.0f} s")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "memory.json").write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
