"""Pipeline benchmarks: the ``denoise`` score on the Mitsuba clip and the built-in scene's progressive curves.

Run: ``.venv/bin/python -m pytest benchmarks/bench_pipeline.py`` (``--quick`` for a smoke run); the frame
step against OIDN alone: ``PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_pipeline.py [rounds]``.
Results go to ``benchmarks/results/pipeline_*.json`` (and a chart); times are ratios against a kornia
Gaussian blur measured in the same run, never asserted.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

import torchmanifold  # noqa: F401  (before torch: OMP_WAIT_POLICY, as the CLI sets it)
import torch

from torchmanifold import metrics as M
from torchmanifold.io import read_exr
from torchmanifold.pipeline import DenoiseSettings, denoise_frames
from torchmanifold.pipeline.denoise_files import COMMAND_FILTER
from torchmanifold.pipeline.job import spp_to_match, write_chart
from torchmanifold.pipeline.progressive import ProgressiveRenderer, gaussian_baseline

DATA = Path("/work/shared/data/mitsuba/cbox_glossy_tex")
if not DATA.is_dir():
    DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "mitsuba" / "cbox_glossy_tex"
RESULTS = Path(__file__).resolve().parent / "results"
FEATURES = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z", "P.X", "P.Y", "P.Z"]


def _load(kind, frames):
    cols, feats = [], []
    for i in frames:
        d = read_exr(DATA / f"{kind}_{i:04d}.exr")
        cols.append(np.stack([d[c] for c in "RGB"]))
        if kind == "frame":
            feats.append(np.stack([d[c] for c in FEATURES]))
    return torch.from_numpy(np.stack(cols)), (torch.from_numpy(np.stack(feats)) if feats else None)


def _save(name: str, data: dict) -> None:
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / name).write_text(json.dumps(data, indent=1, default=float))


def test_denoise_mitsuba(benchmark, quick):
    """`denoise` defaults (``COMMAND_FILTER``: +-2 frames in space-time) on the 1-spp frames; per-frame
    variant beside."""
    frames = [0, 1, 2] if quick else list(range(12))
    c, f = _load("frame", frames)
    ref, _ = _load("reference", frames)
    c4, _ = _load("frame4spp", frames)
    variants = {
        "per_frame_h3": DenoiseSettings(tree_height=3),
        "spacetime (CLI default)": DenoiseSettings(**COMMAND_FILTER),
    }
    if quick:
        variants = {"per_frame_h2": DenoiseSettings(tree_height=2)}
    rows = {}
    t0 = time.perf_counter()
    gauss = {s: gaussian_baseline(c, s) for s in (1.0, 1.5, 2.0, 3.0)}
    gauss_s = (time.perf_counter() - t0) / 4 / len(frames)
    best_g = max(gauss, key=lambda s: M.psnr(gauss[s], ref))
    rows["raw_1spp"] = {"psnr": M.psnr(c, ref), "relmse": M.relmse(c, ref)}
    rows["raw_4spp"] = {"psnr": M.psnr(c4, ref), "relmse": M.relmse(c4, ref)}
    rows[f"gaussian_sigma{best_g}"] = {"psnr": M.psnr(gauss[best_g], ref), "relmse": M.relmse(gauss[best_g], ref),
                                       "seconds_per_frame": gauss_s}
    last = None
    for name, s in variants.items():
        t = time.perf_counter()
        out, st = denoise_frames(c, f, FEATURES, settings=s, return_stats=True)
        sec = (time.perf_counter() - t) / len(frames)
        rows[name] = {"psnr": M.psnr(out, ref), "relmse": M.relmse(out, ref), "ssim": M.ssim(out, ref),
                      "seconds_per_frame": sec, "time_vs_gaussian": sec / max(gauss_s, 1e-9),
                      "firefly_energy_removed": st["firefly_energy_removed"]}
        last = s
    benchmark.pedantic(lambda: denoise_frames(c[:1], f[:1], FEATURES, settings=last), rounds=1, iterations=1)
    data = {"frames": frames, "threads": torch.get_num_threads(), "results": rows,
            "classic_best_psnr": 28.52, "oidn_psnr": 32.37}
    _save("pipeline_denoise_quick.json" if quick else "pipeline_denoise.json", data)
    print(json.dumps(data, indent=1, default=float))


def test_progressive_builtin(benchmark, quick):
    """Curves of raw / Gaussian / ours on the built-in scene, and the spp plain path tracing needs to match
    our 10-iteration result."""
    from torchmanifold.render import PathTracer, default_scene

    W, H, times = (32, 32, [0.0, 1.0]) if quick else (64, 64, [0.0, 1.0])
    iters, ref_spp = (4, 32) if quick else (64, 1024)
    tr = PathTracer(default_scene(), W, H)
    ref = tr.render(times=times, spp=ref_spp, seed=999).color
    pr = ProgressiveRenderer(tr, times, settings=DenoiseSettings(temporal_radius=1, mode="window"))
    rows, raw_mse, clock = [], [], {"raw": 0.0, "gaussian": 0.0, "ours": 0.0}
    for i in range(1, iters + 1):
        s = pr.step()
        clock["raw"] += s.render_seconds
        clock["gaussian"] += s.render_seconds
        clock["ours"] += s.seconds
        row = {"iteration": i, "sigma_s": s.sigma_s}
        for m, img in (("raw", s.raw), ("gaussian", s.gaussian), ("ours", s.ours)):
            row[m] = {"psnr": M.psnr(img, ref), "relmse": M.relmse(img, ref), "seconds": clock[m],
                      "mse_srgb": float(((M.linear_to_srgb(img) - M.linear_to_srgb(ref)) ** 2).mean())}
            if i in (1, 10, iters):
                row[m]["flip"] = M.flip(img, ref)
        raw_mse.append(row["raw"]["mse_srgb"])
        rows.append(row)
    k = min(10, iters) - 1
    data = {"size": [W, H], "times": times, "reference_spp": ref_spp, "alpha": pr.schedule.alpha,
            "threads": torch.get_num_threads(), "per_iteration": rows,
            "spp_plain_to_match_ours_at_10": spp_to_match(raw_mse, rows[k]["ours"]["mse_srgb"]),
            "ours_below_raw_every_iteration": all(r["ours"]["mse_srgb"] < r["raw"]["mse_srgb"] for r in rows)}
    benchmark.pedantic(lambda: tr.render(times=times, spp=1, seed=5), rounds=1, iterations=1)
    RESULTS.mkdir(exist_ok=True)
    write_chart(RESULTS / ("pipeline_progressive_quick.png" if quick else "pipeline_progressive.png"), rows,
                f"built-in scene {W}x{H}, {len(times)} frames")
    _save("pipeline_progressive_quick.json" if quick else "pipeline_progressive.json", data)
    print(json.dumps({k: v for k, v in data.items() if k != "per_iteration"}, indent=1, default=float))


def frame_step_vs_oidn(threads=(1, 2), rounds: int = 9, frame: int = 0) -> dict:
    """ms per 256x256 frame of ``denoise_frames`` (default settings) with the fused C++ stages and with the
    pure-PyTorch stages (``_fast.reference()``), and of Intel OIDN (RT filter, hdr, albedo + normal, its
    own device with the same thread count: ``baselines._oidn_run``), on one frame of the shared clip.

    Every round runs every method at every thread count (interleaved), so a busy machine slows them alike;
    medians over rounds and their ratios are reported."""
    import statistics

    from baselines import _oidn_run, _to_hwc
    from torchmanifold.pipeline import _fast

    c, f = _load("frame", [frame])
    alb = _to_hwc(f[0, 0:3].clamp(0, 1))
    nrm = _to_hwc(f[0, 3:6].clamp(-1, 1))
    col = _to_hwc(c[0])

    def ours():
        denoise_frames(c, f, FEATURES)

    def ours_torch():
        with _fast.reference():
            denoise_frames(c, f, FEATURES)

    methods = {"ours": ours, "ours_pytorch_stages": ours_torch, "oidn": lambda: _oidn_run(col, alb, nrm)}
    old = torch.get_num_threads()
    times = {(m, t): [] for m in methods for t in threads}
    try:
        for t in threads:  # warm-up: OIDN builds its device and filter, ours its scratch pools
            torch.set_num_threads(t)
            for fn in methods.values():
                fn()
        for _ in range(rounds):
            for t in threads:
                torch.set_num_threads(t)
                for m, fn in methods.items():
                    t0 = time.perf_counter()
                    fn()
                    times[(m, t)].append(time.perf_counter() - t0)
    finally:
        torch.set_num_threads(old)
    ms = {t: {m: 1e3 * statistics.median(times[(m, t)]) for m in methods} for t in threads}
    out = {"size": list(c.shape[-2:]), "rounds": rounds, "ms_per_frame": ms,
           "ours_vs_oidn": {t: ms[t]["ours"] / ms[t]["oidn"] for t in threads},
           "pytorch_stages_vs_ours": {t: ms[t]["ours_pytorch_stages"] / ms[t]["ours"] for t in threads}}
    if len(threads) > 1:
        t1, t2 = threads[0], threads[1]
        out[f"ours_{t1}thr_vs_{t2}thr"] = ms[t1]["ours"] / ms[t2]["ours"]
    return out


def test_frame_step_vs_oidn(benchmark, quick):
    """The frame step's speed: ours (fused C++ stages and the PyTorch ones) against OIDN, 1 and 2 threads."""
    data = frame_step_vs_oidn(rounds=2 if quick else 15)
    benchmark.pedantic(lambda: None, rounds=1, iterations=1)
    _save("pipeline_frame_step_quick.json" if quick else "pipeline_frame_step.json", data)
    print(json.dumps(data, indent=1, default=float))


if __name__ == "__main__":  # PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_pipeline.py [rounds]
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    r = frame_step_vs_oidn(rounds=int(sys.argv[1]) if len(sys.argv) > 1 else 15)
    _save("pipeline_frame_step.json", r)
    print(json.dumps(r, indent=1, default=float))
