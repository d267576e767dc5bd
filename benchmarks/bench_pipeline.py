"""Pipeline benchmarks: the ``denoise`` score on the Mitsuba clip and the built-in scene's progressive curves.

Run: ``.venv/bin/python -m pytest benchmarks/bench_pipeline.py`` (``--quick`` for a smoke run).
Results go to ``benchmarks/results/pipeline_*.json`` (and a chart); times are ratios against a kornia
Gaussian blur measured in the same run, never asserted.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from torchmanifold import metrics as M
from torchmanifold.io import read_exr
from torchmanifold.pipeline import DenoiseSettings, denoise_frames
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
    """`denoise` defaults (tree height 3, +-1 frame space-time) on the 1-spp frames; per-frame variant beside."""
    frames = [0, 1, 2] if quick else list(range(12))
    c, f = _load("frame", frames)
    ref, _ = _load("reference", frames)
    c4, _ = _load("frame4spp", frames)
    variants = {
        "per_frame_h3": DenoiseSettings(tree_height=3),
        "spacetime_r1_h3 (CLI default)": DenoiseSettings(tree_height=3, temporal_radius=1, mode="spacetime"),
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
