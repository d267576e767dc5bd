"""The `denoise` frame step's time against pixels and against window length (issue 16: "time linear in
pixels and in window length").

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_linearity.py [--rounds 5] [--threads 1]

A frame step as the command runs it (``denoise_files``): each frame prepared once
(:func:`~torchmanifold.pipeline.denoise.prepare_frames`: sanitise, guide, pilot, clamp) and each query's
window filtered (:func:`~torchmanifold.pipeline.denoise.denoise_prepared`, +-r frames in space-time). Frames
are the shared Mitsuba clip's (256x256), cropped to 64 and 128 and tiled 2x2 to 512; the window sizes are
+-0 to +-3 frames at 256x256. Every configuration runs once per round, rounds interleave, medians are
reported, so a busy machine shifts every row alike. Writes ``results/linearity.json`` and
``results/linearity.png``; times are never asserted.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "benchmarks"))

SIZES = (64, 128, 256, 512)  # pixels per side, window +-1
RADII = (0, 1, 2, 3)  # window radius at 256x256


def _frames(size: int, n: int):
    """``n`` frames of the shared clip at ``size`` x ``size``: colour (n, 3, s, s), features, their names."""
    import torch

    import harness
    from torchmanifold.io import read_exr

    names = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z", "P.X", "P.Y", "P.Z"]
    cs, fs = [], []
    for k in range(n):
        d = read_exr(harness.DATA / f"frame_{k:04d}.exr")
        c = np.stack([d[ch] for ch in "RGB"]).astype(np.float32)
        f = np.stack([d[ch] for ch in names]).astype(np.float32)
        if size <= c.shape[-1]:
            o = (c.shape[-1] - size) // 2
            c, f = c[:, o:o + size, o:o + size], f[:, o:o + size, o:o + size]
        else:
            reps = -(-size // c.shape[-1])
            c = np.tile(c, (1, reps, reps))[:, :size, :size]
            f = np.tile(f, (1, reps, reps))[:, :size, :size]
        cs.append(c)
        fs.append(f)
    return torch.from_numpy(np.stack(cs)), torch.from_numpy(np.stack(fs)), names


def _step(color, features, names, radius: int) -> tuple[float, float]:
    """Seconds to prepare one frame and to filter the middle query of a +-``radius`` window."""
    from torchmanifold.pipeline.denoise import DenoiseSettings, FrameState, denoise_prepared, prepare_frames

    settings = DenoiseSettings(temporal_radius=radius, mode="spacetime")
    n = color.shape[0]
    t0 = time.perf_counter()
    states = [prepare_frames(color[k:k + 1], features[k:k + 1], names, None, settings, samples_per_pixel=1)
              for k in range(n)]
    prepare = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    denoise_prepared(FrameState.cat(states), settings, list(range(n)), [n // 2])
    return prepare, time.perf_counter() - t0


def _slope(x, y) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)

    import torchmanifold  # noqa: F401  (sets OMP_WAIT_POLICY before torch starts its threads)
    import torch

    torch.set_num_threads(a.threads)
    # (size, radius): the sizes at +-1, then the other windows at 256x256
    keys = [(s, 1) for s in SIZES] + [(256, r) for r in RADII if r != 1]
    data = {(s, r): _frames(s, 2 * r + 1) for s, r in keys}
    for key in data:  # warm-up: first calls build the ops' workspaces
        _step(*data[key], key[1])
    times = {key: [] for key in data}
    for _ in range(a.rounds):
        for key in data:
            times[key].append(_step(*data[key], key[1]))
    med = {k: (statistics.median(p for p, _ in v), statistics.median(f for _, f in v))
           for k, v in times.items()}
    rows = [{"size": s, "radius": r, "frames": 2 * r + 1, "pixels": s * s,
             "prepare_ms": 1e3 * med[(s, r)][0], "filter_ms": 1e3 * med[(s, r)][1],
             "step_ms": 1e3 * sum(med[(s, r)])} for s, r in data]
    by_size = [r for r in rows if r["radius"] == 1]
    by_window = sorted([r for r in rows if r["size"] == 256], key=lambda r: r["frames"])
    fit = np.polyfit([r["frames"] for r in by_window], [r["filter_ms"] for r in by_window], 1)
    pred = np.polyval(fit, [r["frames"] for r in by_window])
    resid = max(abs(p - r["filter_ms"]) / r["filter_ms"] for p, r in zip(pred, by_window))
    out = {
        "machine": {"cpu": platform.processor() or platform.machine(), "threads": a.threads,
                    "load": list(os.getloadavg())},
        "rounds": a.rounds,
        "rows": rows,
        # time ~ pixels^slope: 1 is linear; the fixed per-call cost pulls small frames' slope below 1
        "pixel_slope_step": _slope([r["pixels"] for r in by_size[1:]], [r["step_ms"] for r in by_size[1:]]),
        "pixel_slope_step_all": _slope([r["pixels"] for r in by_size], [r["step_ms"] for r in by_size]),
        # the window's filter against its frames: a straight line's slope, intercept and largest misfit
        "window_fit_ms_per_frame": float(fit[0]), "window_fit_intercept_ms": float(fit[1]),
        "window_fit_largest_misfit": float(resid),
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "linearity.json").write_text(json.dumps(out, indent=1))
    _chart(out, RESULTS / "linearity.png")
    for r in rows:
        print(f"{r['size']:4d}^2 +-{r['radius']}: prepare {r['prepare_ms']:7.1f} ms  "
              f"filter {r['filter_ms']:7.1f} ms  step {r['step_ms']:7.1f} ms  "
              f"({r['step_ms'] * 1e3 / r['pixels']:.2f} us/pixel)")
    print(f"pixels^{out['pixel_slope_step']:.3f} from 128^2 up ({out['pixel_slope_step_all']:.3f} from "
          f"64^2); window filter {fit[0]:.1f} ms per frame + {fit[1]:.1f} ms, largest misfit {resid:.1%}")
    return out


def _chart(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = out["rows"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    px = [r for r in rows if r["radius"] == 1]
    a.loglog([r["pixels"] for r in px], [r["step_ms"] for r in px], "o-", label="frame step (+-1)")
    ref = px[2]
    xs = np.array([r["pixels"] for r in px], float)
    a.loglog(xs, ref["step_ms"] * xs / ref["pixels"], "k--", lw=0.8, label="linear through 256^2")
    a.set_xlabel("pixels")
    a.set_ylabel("ms per frame")
    a.legend()
    a.set_title(f"time ~ pixels^{out['pixel_slope_step']:.2f} (128^2 up)")
    win = sorted([r for r in rows if r["size"] == 256], key=lambda r: r["frames"])
    b.plot([r["frames"] for r in win], [r["filter_ms"] for r in win], "o-", label="window filter")
    b.plot([r["frames"] for r in win], [r["prepare_ms"] for r in win], "s-", label="prepare (per frame)")
    b.set_xlabel("frames in the window (256x256)")
    b.set_ylabel("ms")
    b.legend()
    b.set_title(f"{out['window_fit_ms_per_frame']:.1f} ms per window frame")
    threads, rounds = out["machine"]["threads"], out["rounds"]
    fig.suptitle(f"denoise frame step, {threads} thread(s), medians of {rounds} rounds")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
