"""Per-stage time of one ``denoise_frames`` call on a 256x256 frame (default settings), at 1 and 2 threads.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/profile_framestep.py [--rounds 15] [--threads 1 2]

Both paths run in the same rounds: the fused C++ kernels (``fast``) and the pure-PyTorch stages
(``torch``, :func:`torchmanifold.pipeline._fast.reference`). Each stage function of :mod:`torchmanifold.pipeline.denoise` is wrapped with a timer (inclusive times:
a stage that calls another counts it too); thread counts are interleaved round by round and medians
reported, so a busy machine shifts both columns alike.
"""
from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

import torchmanifold  # noqa: F401  (before torch: sets OMP_WAIT_POLICY, as the CLI does)
import torch

DATA = Path("/work/shared/data/mitsuba/cbox_glossy_tex")
FEATURES = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z", "P.X", "P.Y", "P.Z"]


def load_frame():
    from torchmanifold.io import read_exr

    d = read_exr(DATA / "frame_0000.exr")
    c = torch.from_numpy(np.stack([d[k] for k in "RGB"]))[None]
    f = torch.from_numpy(np.stack([d[k] for k in FEATURES]))[None]
    return c, f


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    a = ap.parse_args(argv)
    from torchmanifold.pipeline import denoise as D
    from torchmanifold.pipeline import footprint as FP

    clock = defaultdict(float)

    def wrap(owner, name, label):
        fn = getattr(owner, name)

        def timed(*args, **kw):
            t = time.perf_counter()
            try:
                return fn(*args, **kw)
            finally:
                clock[label] += time.perf_counter() - t
        setattr(owner, name, timed)

    # each stage wrapped in the module whose code calls it
    for name in ("_sanitize", "_demodulation_albedo", "_footprint_albedo", "_guide", "_extent", "_log_radiance",
                 "_clamp_fireflies", "_pilot_noise", "_radiance_from_pilot", "_select_bandwidth"):
        wrap(D, name, name)
    wrap(FP, "_footprint_average", "_footprint_average")
    wrap(FP, "_edge_directions", "_edge_directions")
    wrap(FP, "_along_edges", "_along_edges")
    wrap(D._Filter, "apply", "op calls (_Filter.apply)")
    wrap(D._Filter, "_guard", "_guard (in normalise)")
    wrap(D._Filter, "normalise", "normalise (incl. guard)")
    wrap(D._Filter, "with_held_out", "pilot (_Filter.with_held_out)")
    from torchmanifold.pipeline import _fast

    c, f = load_frame()
    rows = defaultdict(lambda: defaultdict(list))
    cols = [(th, path) for th in a.threads for path in ("torch", "fast")]

    def run(th, path):
        torch.set_num_threads(th)
        ctx = _fast.reference() if path == "torch" else contextlib.nullcontext()
        with ctx:
            clock.clear()
            t = time.perf_counter()
            D.denoise_frames(c, f, FEATURES)
            return time.perf_counter() - t

    for col in cols:  # warm-up
        run(*col)
    for _ in range(a.rounds):
        for col in cols:
            rows["TOTAL"][col].append(run(*col))
            for k, v in clock.items():
                rows[k][col].append(v)
    print(f"{'stage (inclusive), median ms':36s}" + "".join(f"{f'{p} {t}thr':>12s}" for t, p in cols))
    for k, v in rows.items():
        print(f"{k:36s}" + "".join(f"{1e3 * statistics.median(v[col]) if v[col] else 0:12.2f}" for col in cols))
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
