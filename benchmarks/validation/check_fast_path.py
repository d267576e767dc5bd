"""The denoiser's fused C++ stages against its PyTorch stages on the validation clips: per scene and spp, the
largest difference of ``denoise_frames`` outputs and both PSNRs against the reference.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/validation/check_fast_path.py [--frames 2] [--scenes a b]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))
import torchmanifold  # noqa: E402,F401
import torch  # noqa: E402

import score  # noqa: E402


def main(argv=None) -> dict:
    from torchmanifold import metrics
    from torchmanifold.pipeline import _fast, denoise_frames

    split = json.loads((HERE / "split.json").read_text())
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--scenes", nargs="*", default=list(split["scenes"]))
    a = ap.parse_args(argv)
    rows = {}
    for name in a.scenes:
        s = split["scenes"][name]  # shared scenes resolve like harness.DATA (<data>/mitsuba/cbox_glossy_tex)
        path = (Path(score.harness.DATA).parents[1] / s["shared"]) if "shared" in s else score.ROOT / s["path"]
        for spp in (1, 4):
            ds, _ = score.load_scene(path, spp)
            for q in range(min(a.frames, ds.color.shape[0])):
                c, f = ds.color[q:q + 1], ds.features[q:q + 1]
                out = denoise_frames(c, f, ds.names)
                with _fast.reference():
                    ref = denoise_frames(c, f, ds.names)
                d = (out - ref).abs()
                rows[f"{name} {spp}spp frame {q}"] = r = {
                    "max_abs": float(d.max()), "max_rel": float((d / ref.abs().clamp_min(1e-3)).max()),
                    "mean_abs": float(d.mean()),
                    "psnr_fast": metrics.psnr(out, ds.reference[q:q + 1]),
                    "psnr_pytorch": metrics.psnr(ref, ds.reference[q:q + 1])}
                print(f"{name:18s} {spp}spp f{q}: max|d| {r['max_abs']:.2e} max rel {r['max_rel']:.2e} "
                      f"mean|d| {r['mean_abs']:.2e} PSNR {r['psnr_fast']:.4f} vs {r['psnr_pytorch']:.4f}", flush=True)
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
