"""Fewer features: every validation scene denoised from its colour alone (a renderer's Combined pass without
AOVs), from its colour and geometry without the albedo, and from its colour, albedo and normal (OIDN's own
auxiliary images, no depth or positions).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/validation/fewer_features.py [--data-root DIR] [--scenes a b]

Per scene, from 1 and 4 spp, over all frames (PSNR on clamped sRGB, mean over frames, this run): the raw
input; a Gaussian blur (the best of sigma 1/2/4/8 per scene, as ``score.py``'s); Intel OIDN (``pyoidn``,
``hdr=True``) from colour alone and from colour, albedo and normal; ours, the ``denoise`` command's default
(``DenoiseSettings(**COMMAND_FILTER)``) given no feature channel (``ours, colour``), the scene's normals,
depth and positions (``ours, no albedo``) and its albedo and normal (``ours, albedo + normal``).
:func:`torchmanifold.pipeline.denoise.adapt_to_features` adds two narrower bandwidth candidates where no
albedo guides, and filters each frame alone for colour alone, guided by the pilot's log radiance and
chromaticity. Writes ``benchmarks/results/validation/fewer_features.json`` and ``fewer_features.md``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))
import baselines  # noqa: E402
import score  # noqa: E402

OUT = HERE.parents[1] / "benchmarks" / "results" / "validation"
BLURS = (1.0, 2.0, 4.0, 8.0)


def scene_scores(path: Path, spp: int) -> dict:
    from torchmanifold import metrics
    from torchmanifold.features import canonical_name, group_of
    from torchmanifold.pipeline import DenoiseSettings, denoise_frames
    from torchmanifold.pipeline.denoise_files import COMMAND_FILTER
    from torchmanifold.pipeline.progressive import gaussian_baseline

    ds, _ = score.load_scene(path, spp)
    x, ref = ds.color, ds.reference
    psnr = lambda out: float(np.mean([metrics.psnr(o, r) for o, r in zip(out, ref)]))  # noqa: E731
    groups = [group_of(canonical_name(n)) for n in ds.names]
    geometry = [k for k, g in enumerate(groups) if g != "albedo"]
    albedo = [k for k, g in enumerate(groups) if g == "albedo"]
    normal = [k for k, g in enumerate(groups) if g == "N"]
    res = {"raw": psnr(x), "gaussian": max(psnr(gaussian_baseline(x, s)) for s in BLURS)}

    def oidn(alb: list, nrm: list) -> float:
        out = []
        for t in range(len(x)):
            a = baselines._to_hwc(ds.features[t, alb].clamp(0, 1)) if alb else None
            n = baselines._to_hwc(ds.features[t, nrm].clamp(-1, 1)) if nrm else None
            out.append(baselines._from_hwc(baselines._oidn_run(baselines._to_hwc(x[t]), a, n), x[t]))
        return psnr(torch.stack(out))

    res["oidn"] = oidn([], [])
    res["oidn, albedo + normal"] = oidn(albedo, normal)
    for name, feats in (("ours, colour", []), ("ours, no albedo", geometry),
                        ("ours, albedo + normal", albedo + normal)):
        t0 = time.perf_counter()
        out = denoise_frames(x, ds.features[:, feats], [ds.names[k] for k in feats],
                             settings=DenoiseSettings(**COMMAND_FILTER),
                             frame_times=[float(t) for t in ds.times], samples_per_pixel=ds.samples_per_pixel)
        res[name] = psnr(out)
        res[f"{name} ms/frame"] = (time.perf_counter() - t0) * 1e3 / len(x)
    return {**res, "frames": len(x)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", type=Path, default=HERE / "split.json")
    ap.add_argument("--data-root", type=Path, default=None)
    ap.add_argument("--scenes", nargs="*", default=None)
    args = ap.parse_args(argv)
    split = json.loads(args.split.read_text())
    names = args.scenes or split["tune"] + split["test"]
    res = {}
    for name in names:
        path = score.resolve(split["scenes"][name], args.data_root)
        res[name] = {"split": "tune" if name in split["tune"] else "test",
                     **{f"{spp}spp": scene_scores(path, spp) for spp in (1, 4)}}
        print(name, {k: {m: round(v, 2) for m, v in s.items()} for k, s in res[name].items() if k != "split"})
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "fewer_features.json").write_text(json.dumps(res, indent=1) + "\n")
    methods = ("raw", "gaussian", "oidn", "ours, colour", "ours, no albedo", "oidn, albedo + normal",
               "ours, albedo + normal")
    lines = ["PSNR (dB, clamped sRGB, mean over all frames), from 1 spp / 4 spp; `oidn`: from colour alone",
             "",
             "| scene | split | " + " | ".join(methods) + " | ours, colour - best classic |",
             "|---|---|" + "---|" * (len(methods) + 1)]
    for name, r in res.items():
        cells = [f"{r['1spp'][m]:.2f} / {r['4spp'][m]:.2f}" for m in methods]
        margin = [r[k]["ours, colour"] - max(r[k]["raw"], r[k]["gaussian"]) for k in ("1spp", "4spp")]
        lines.append(f"| {name} | {r['split']} | " + " | ".join(cells) +
                     f" | {margin[0]:+.2f} / {margin[1]:+.2f} |")
    mean = lambda spp, m: np.mean([r[spp][m] for r in res.values()])  # noqa: E731
    means = [f"{mean('1spp', m):.2f} / {mean('4spp', m):.2f}" for m in methods]
    lines.append("| mean | | " + " | ".join(means) + " | |")
    (OUT / "fewer_features.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
