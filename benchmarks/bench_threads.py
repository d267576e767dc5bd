"""Do more torch threads help the pipeline? 1 vs 2 (or N) threads on a ``render`` iteration and on the frame
step, under several thread environments, every configuration in its own fresh process, ratios in one run.

Run: ``.venv/bin/python benchmarks/bench_threads.py [--iterations 4] [--kinds render] [--envs ...]``; writes
``benchmarks/results/threads.json``. Each thread environment runs in its own fresh process (OpenMP reads
its settings once); inside it the thread counts alternate iteration by iteration after one warm-up, so
the ratios compare runs under the same machine load. The ``cli`` environment takes its cores as the CLI's
``--threads`` does (:func:`torchmanifold._threads.set_threads`: llvmpipe's threads too, which a process
sets once), so there each thread count has processes of its own, alternating round by round
(``--rounds``). Times are medians, never asserted.

Measured:
- ``render``: :meth:`ProgressiveRenderer.step` on the render job's defaults (its frames and size,
  ``RENDER_DEFAULTS``, and the loop's own filter settings), split into the tracer's part (llvmpipe, whose
  threads torch's count does not set; ``--threads`` does) and the rest (filtering, torch);
  ``render_small``: the same at 128x96, the job's former size, where the Python around each small frame's
  ops weighs most.
- ``frame step``: :func:`denoise_frames` of 3 frames of 256x256 with the default guide (space-time +-1),
  no GL context in the process; ``frame_step_12``: the same call with 12 frames, enough queries for it to
  prepare frames and filter queries side by side on workers as the command does (seconds per frame).
- ``clip``: the ``denoise`` command's frame step over the shared clip (12 frames of 256x256), the command's
  own loop (:func:`~torchmanifold.pipeline.denoise_files.denoised_frames`: each frame prepared once and
  each window filtered, side by side on workers), files read on the clip's thread, nothing written;
  ``command``: the command itself (:func:`~torchmanifold.pipeline.denoise_files.denoise_files`, outputs
  written on a thread of their own, which a one-thread run overlaps with its filtering too). Seconds per
  frame.
- ``matmul`` / ``copy``: the machine's own ceilings in the same run, what 2 threads can give work that is
  bound by arithmetic (a 2048x2048 float32 matrix product) or by memory (a 64 MB copy).
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


def _child(kind: str, threads: list[int], iterations: int) -> dict:
    if os.environ.get("_IMPORT_FIRST"):
        import torchmanifold  # noqa: F401  (sets its OpenMP default before torch loads libgomp)
    import torch

    if os.environ.get("_SET_THREADS"):  # one count, taken as the CLI takes it, before any GL context
        from torchmanifold._threads import set_threads

        (n,) = threads
        set_threads(n)

    from torchmanifold.pipeline import DenoiseSettings, denoise_frames

    if kind in RENDER_SIZES:
        from torchmanifold.pipeline.progressive import ProgressiveRenderer
        from torchmanifold.pipeline.render_job import RENDER_DEFAULTS
        from torchmanifold.render import PathTracer, default_scene

        size = RENDER_SIZES[kind] or (RENDER_DEFAULTS["width"], RENDER_DEFAULTS["height"])
        tracer = PathTracer(default_scene(), *size)
        pr = ProgressiveRenderer(tracer, [float(t) for t in range(RENDER_DEFAULTS["frames"])])

        def once():
            st = pr.step()
            return st.seconds, st.render_seconds
    elif kind in ("clip", "command"):
        once = _clip_step(kind)
    elif kind in CEILINGS:
        x = torch.rand(2048, 2048) if kind == "matmul" else torch.rand(1 << 24)
        y = torch.empty_like(x)

        def once():
            t0 = time.perf_counter()
            torch.mm(x, x, out=y) if kind == "matmul" else y.copy_(x)
            return time.perf_counter() - t0, 0.0
    else:
        frames = FRAME_STEPS[kind]
        gen = torch.Generator().manual_seed(0)
        color = torch.rand(frames, 3, 256, 256, generator=gen)
        names = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z"]
        feats = torch.rand(frames, len(names), 256, 256, generator=gen)
        feats[:, :3, :, 128:] += 0.5  # an edge in the guide
        settings = DenoiseSettings(temporal_radius=1, mode="spacetime")

        def once():
            t0 = time.perf_counter()
            denoise_frames(color, feats, names, None, settings)
            return (time.perf_counter() - t0) / frames, 0.0

    once()  # warm-up: shader compile, first allocations
    # the thread counts alternate, so a change in the machine's load hits all of them alike
    runs = {n: [] for n in threads}
    for _ in range(iterations):
        for n in threads:
            torch.set_num_threads(n)
            runs[n].append(once())
    out = {}
    for n, r in runs.items():
        out[n] = {"seconds": statistics.median(t for t, _ in r)}
        if kind in RENDER_SIZES:
            out[n]["render_seconds"] = statistics.median(x for _, x in r)
            out[n]["filter_seconds"] = statistics.median(t - x for t, x in r)
    return out


def _clip_step(kind: str):
    """``once()`` for the ``clip`` and ``command`` kinds: seconds per frame of the shared clip."""
    import tempfile

    import torch

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from harness import DATA

    from torchmanifold._threads import InOrder
    from torchmanifold.io.frames import read_render_frame
    from torchmanifold.pipeline.denoise import DenoiseSettings
    from torchmanifold.pipeline.denoise_files import (COMMAND_FILTER, ClipWindow, denoise_files,
                                                      denoised_frames)

    paths = sorted(DATA.glob("frame_00*.exr"))
    settings = DenoiseSettings(**COMMAND_FILTER)  # the command's default
    out = Path(tempfile.mkdtemp())
    first = read_render_frame(paths[0])

    def once():
        if kind == "command":
            res = denoise_files(paths, out, settings, overwrite=True, progress=False)
            return res["seconds_per_frame"], 0.0
        t0 = time.perf_counter()
        with InOrder(torch.get_num_threads(), len(paths)) as pool, \
                ClipWindow(paths, first, None, None, pool) as clip:
            for _ in denoised_frames(clip, settings, pool):
                pass
        return (time.perf_counter() - t0) / len(paths), 0.0
    return once


#: (width, height) of the render kinds: the job's default size (None) and its former one
RENDER_SIZES = {"render": None, "render_small": (128, 96)}
#: the machine's ceilings: arithmetic-bound and memory-bound work
CEILINGS = ("matmul", "copy")
FRAME_STEPS = {"frame_step": 3, "frame_step_12": 12}  # kind: frames in the call

ENVS = {
    # libgomp's default with OMP_WAIT_POLICY unset: workers spin for a while after each parallel region
    # (what the pipeline got before torchmanifold set a policy; torch is imported first here)
    "spin (policy unset)": {},
    # workers sleep at once; what torchmanifold/__init__.py sets unless the user set a policy
    "OMP_WAIT_POLICY=PASSIVE": {"OMP_WAIT_POLICY": "PASSIVE"},
    # as the CLI runs: nothing set, torchmanifold imported before torch (its default applies), the cores
    # taken by --threads (llvmpipe's threads too): a process per thread count
    "cli (import torchmanifold first)": {"_IMPORT_FIRST": "1", "_SET_THREADS": "1"},
    # and llvmpipe with one thread instead of one per core
    "PASSIVE + LP_NUM_THREADS=1": {"OMP_WAIT_POLICY": "PASSIVE", "LP_NUM_THREADS": "1"},
}


def _run(kind: str, threads: list[int], env: dict, iterations: int, rounds: int = 1) -> dict:
    e = dict(os.environ, PYTHONPATH=str(ROOT))
    for k in ("LP_NUM_THREADS", "OMP_WAIT_POLICY", "KMP_BLOCKTIME", "GOMP_SPINCOUNT"):
        e.pop(k, None)
    e.update(env)
    if env.get("_SET_THREADS") and len(threads) > 1:  # a process per count, alternating round by round
        runs = [_run(kind, [n], env, iterations) for _ in range(rounds) for n in threads]
        return {n: {k: statistics.median(r[n][k] for r in runs if n in r) for k in runs[0][threads[0]]}
                for n in threads}
    out = subprocess.run([sys.executable, __file__, "--child", kind, ",".join(map(str, threads)), str(iterations)],
                         env=e, capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(f"{kind} env={env} failed:\n{out.stderr[-3000:]}")
    return {int(k): v for k, v in json.loads(out.stdout.strip().splitlines()[-1]).items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--iterations", type=int, default=4)
    p.add_argument("--envs", nargs="+", default=list(ENVS), choices=list(ENVS))
    kinds = [*CEILINGS, *FRAME_STEPS, "clip", "command", *RENDER_SIZES]
    p.add_argument("--kinds", nargs="+", default=kinds, choices=kinds)
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--rounds", type=int, default=2, help="rounds of processes in the cli environment")
    p.add_argument("--out", default=str(RESULTS / "threads.json"))
    a = p.parse_args()
    rows = []
    for kind in a.kinds:
        for name in a.envs:
            res = _run(kind, a.threads, ENVS[name], a.iterations, a.rounds)
            base = res[a.threads[0]]["seconds"]
            for n in a.threads:
                row = {"kind": kind, "env": name, "threads": n, **res[n], "speedup_vs_1": base / res[n]["seconds"],
                       "load_average_1min_after": os.getloadavg()[0]}
                if "filter_seconds" in res[n]:  # the part torch's threads run
                    one = res[a.threads[0]]["filter_seconds"]
                    row["filter_speedup_vs_1"] = one / res[n]["filter_seconds"]
                rows.append(row)
                print(json.dumps(row), flush=True)
    import torch

    data = {"machine": {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine(),
                        "torch": torch.__version__, "parallel": torch.__config__.parallel_info().splitlines()[:6]},
            "iterations": a.iterations, "rounds": a.rounds, "rows": rows}
    Path(a.out).parent.mkdir(exist_ok=True)
    Path(a.out).write_text(json.dumps(data, indent=1))


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--child":
        print(json.dumps(_child(sys.argv[2], [int(n) for n in sys.argv[3].split(",")], int(sys.argv[4]))))
    else:
        main()
