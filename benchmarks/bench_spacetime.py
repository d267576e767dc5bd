"""The space-time mode: C++ kernel against the pure-PyTorch reference, 1 and 2 threads, in one run.

Run: ``.venv/bin/python benchmarks/bench_spacetime.py [--repeats 5]``; writes
``benchmarks/results/spacetime.json``. One query at the middle of a window of 3 frames (+-1 frame),
3 value channels, a 9-channel guide (albedo, normal, position as
the default guide), float32, sigma_s 5 / sigma_r 0.3 / tree height 2 (the :class:`DenoiseSettings` defaults),
at 128x96 (the render job) and 256x256. Median of ``--repeats`` calls after a warm-up, backends and thread
counts alternating call by call in one process with ``OMP_WAIT_POLICY=PASSIVE`` (see bench_threads.py), so
the ratios compare calls under the same machine load. Times are never asserted.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SIZES = [(96, 128), (256, 256)]  # (H, W)
THREADS = (1, 2)


def _child(repeats: int) -> dict:
    import torch

    from torchmanifold.ops import temporal_adaptive_manifold_filter

    rows = {}
    for H, W in SIZES:
        gen = torch.Generator().manual_seed(0)
        v = torch.rand(1, 3, 3, H, W, generator=gen)
        g = torch.rand(1, 3, 9, H, W, generator=gen) * 0.2
        g[..., :, : W // 2] += 1.0  # an edge, so the tree splits into two clusters
        calls = {}
        for backend in ("cpp", "torch"):
            calls[backend] = (lambda b: lambda: temporal_adaptive_manifold_filter(
                v, g, [0, 1, 2], [1.0], 5.0, 0.3, mode="spacetime", tree_height=2, backend=b))(backend)
            calls[backend]()  # warm-up
        # backends and thread counts alternate, so a change in the machine's load hits all alike
        times = {(b, n): [] for b in calls for n in THREADS}
        for _ in range(repeats):
            for b, call in calls.items():
                for n in THREADS:
                    torch.set_num_threads(n)
                    t0 = time.perf_counter()
                    call()
                    times[b, n].append(time.perf_counter() - t0)
        for (b, n), t in times.items():
            rows[f"{H}x{W}/{b}/{n}"] = statistics.median(t)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--out", default=str(RESULTS / "spacetime.json"))
    a = p.parse_args()
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_WAIT_POLICY="PASSIVE")
    out = subprocess.run([sys.executable, __file__, "--child", str(a.repeats)], env=env, capture_output=True,
                         text=True, timeout=3600, check=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    rows = []
    for H, W in SIZES:
        t = {(b, n): res[f"{H}x{W}/{b}/{n}"] for b in ("cpp", "torch") for n in THREADS}
        row = {"size": [H, W], **{f"{b}_{n}thr_ms": 1e3 * t[b, n] for b in ("cpp", "torch") for n in THREADS}}
        for n in THREADS:
            row[f"cpp_speedup_vs_torch_{n}thr"] = t["torch", n] / t["cpp", n]
        for b in ("cpp", "torch"):
            row[f"{b}_2thr_speedup_vs_1thr"] = t[b, 1] / t[b, 2]
        rows.append(row)
        print(json.dumps(row), flush=True)
    import torch

    data = {"machine": {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine(),
                        "torch": torch.__version__, "load_average_after": os.getloadavg()},
            "setup": "1 query at the middle of 3 frames, C=3, D=9, float32, sigma_s 5, sigma_r 0.3, height 2",
            "repeats": a.repeats, "rows": rows}
    Path(a.out).parent.mkdir(exist_ok=True)
    Path(a.out).write_text(json.dumps(data, indent=1))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        print(json.dumps(_child(int(sys.argv[2]))))
    else:
        main()
