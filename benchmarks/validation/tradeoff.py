"""Speed against accuracy of the ``denoise`` command's settings, on every scene of the validation set.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/validation/tradeoff.py [--threads 2] [--scenes a b]

Each variant runs the command's own path (:class:`~torchmanifold.pipeline.denoise_files.ClipWindow` and
:func:`~torchmanifold.pipeline.denoise_files.denoise_window`: files read as the window needs them, each frame
prepared once) over every frame of every scene, from 1 and from 4 spp; Intel OIDN runs on the same frames in
the same run, as ``score.py`` runs it. Variants and OIDN take turns scene by scene, so a busy machine slows
them alike. ms/frame: the median over the scene's frames of the wall time per output frame (reading included,
writing not), this machine and thread count; PSNR: clamped sRGB, the mean over frames.

Writes ``benchmarks/results/validation/tradeoff.json``, ``tradeoff.md`` and ``tradeoff.png`` (mean PSNR
against ms/frame per variant, from 1 and 4 spp, OIDN beside them).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))
import torchmanifold  # noqa: E402,F401  (before torch, as the command imports it)
import torch  # noqa: E402

import harness  # noqa: E402
import score  # noqa: E402

OUT = score.OUT
#: the command's default (``torchmanifold denoise``: +-2 frames space-time, tree height 3 at ``sigma_s`` and
#: one level more per doubling of a wider candidate), variants of it that change one thing, and the two
#: cheapest changes that lose least together
VARIANTS = {
    "default": {},
    "bandwidths 0.5 to 8": {"bandwidths": (0.5, 1.0, 2.0, 4.0, 8.0)},
    "tree height 2": {"tree_height": 2},
    "one tree height (3)": {"levels_per_doubling": 0},
    "bandwidths 1, 2, 4": {"bandwidths": (1.0, 2.0, 4.0)},
    "bandwidths 0.5, 1, 2": {"bandwidths": (0.5, 1.0, 2.0)},
    "bandwidths 1, 2": {"bandwidths": (1.0, 2.0)},
    "one bandwidth (1)": {"bandwidths": (1.0,)},
    "albedo window +-1": {"albedo_radius": 1},
    "each frame alone": {"temporal_radius": 0, "albedo_radius": 0},
    "window unaligned": {"align_frames": False},
    "tree height 2, bandwidths 0.5, 1, 2": {"tree_height": 2, "bandwidths": (0.5, 1.0, 2.0)},
}


def settings_of(variant: dict):
    from torchmanifold.pipeline.denoise import DenoiseSettings

    from torchmanifold.pipeline.denoise_files import COMMAND_FILTER

    return DenoiseSettings(**{**COMMAND_FILTER, "mode": "spacetime", "tree_height": 3, **variant}).check()


def clip_files(path: Path, spp: int) -> list[Path]:
    files = sorted(path.glob(f"{score.frame_prefix(spp)}_*.exr"))
    if not files:
        raise FileNotFoundError(f"{path}: no {spp}-spp frames")
    return files


def run_variant(files: list[Path], settings) -> tuple[list[np.ndarray], list[float]]:
    """Every frame of the clip through the command's path: outputs ``(3, H, W)`` and seconds per frame."""
    from torchmanifold.io.frames import read_render_frame
    from torchmanifold.pipeline.denoise_files import ClipWindow, denoise_window

    first = read_render_frame(files[0], None, None, None)
    outs, secs = [], []
    with ClipWindow(files, first, None) as clip:
        for t in range(len(files)):
            t0 = time.perf_counter()
            y, _, _ = denoise_window(clip, t, settings)
            secs.append(time.perf_counter() - t0)
            outs.append(y)
    return outs, secs


def run_oidn(path: Path, spp: int,
             prefix: str | None = None) -> tuple[torch.Tensor, harness.Dataset, list[float]]:
    """OIDN on the clip's ``spp``-sample frames (``prefix``: as :func:`score.load_scene` takes it): its
    outputs, the clip as read (frames and references) and the seconds per frame."""
    ds, _ = score.load_scene(path, spp, prefix)
    oidn = next(m for m in score.methods() if m.family == "oidn")
    clip, alb = harness.clip_for(ds, use=score.GUIDE)
    out, secs = harness.run_method(oidn, ds, clip, alb, list(range(ds.color.shape[0])), score.SIGMA_S,
                                   score.SIGMA_R)
    return out, ds, secs


def psnr(outs, ref: torch.Tensor) -> float:
    from torchmanifold import metrics

    out = torch.as_tensor(np.stack(outs)) if not torch.is_tensor(outs) else outs
    return float(metrics.psnr(out.float(), ref.float()))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", type=Path, default=HERE / "split.json")
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--spp", nargs="+", type=int, default=[1, 4])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    split = json.loads(args.split.read_text())
    names = args.scenes or list(split["scenes"])
    from tqdm import tqdm

    results = {"meta": harness.metadata(), "threads": args.threads,
               "variants": {v: VARIANTS[v] for v in args.variants}, "scenes": {}}
    for name in tqdm(names, desc="scenes"):
        path = score.resolve(split["scenes"][name], None)
        sc = {"split": split["scenes"][name]["split"]}
        for spp in args.spp:
            files = clip_files(path, spp)
            row = {}
            out, ds, secs = run_oidn(path, spp)
            ref = ds.reference
            row["oidn"] = {"psnr": psnr(out, ref), "ms": 1e3 * statistics.median(secs)}
            for v in args.variants:
                outs, secs = run_variant(files, settings_of(VARIANTS[v]))
                row[v] = {"psnr": psnr(outs, ref), "ms": 1e3 * statistics.median(secs)}
            sc[str(spp)] = row
            tqdm.write(f"{name} {spp} spp: " + ", ".join(f"{k} {r['psnr']:.2f} dB {r['ms']:.0f} ms"
                                                         for k, r in row.items()))
        results["scenes"][name] = sc
    score.write_results(args.out, "tradeoff", results, markdown(results),
                        lambda: chart(results, args.out / "tradeoff.png"))
    return results


def summary(results: dict, spp: str) -> dict:
    """Per method: mean PSNR and mean ms/frame over the scenes, and the worst scene's PSNR change against
    the default (``None`` for OIDN)."""
    scenes = [s[spp] for s in results["scenes"].values() if spp in s]
    out = {}
    for m in scenes[0]:
        psnrs = [s[m]["psnr"] for s in scenes]
        worst = min((s[m]["psnr"] - s["default"]["psnr"], n) for n, s in zip(results["scenes"], scenes)) \
            if m != "oidn" and "default" in scenes[0] else None
        out[m] = {"psnr": statistics.mean(psnrs), "ms": statistics.mean(s[m]["ms"] for s in scenes),
                  "time_ratio": statistics.median(s[m]["ms"] / s["default"]["ms"] for s in scenes)
                  if "default" in scenes[0] else None, "worst": worst}
    return out


def markdown(results: dict) -> str:
    spps = [k for k in ("1", "4") if any(k in s for s in results["scenes"].values())]
    lines = [f"Validation set, {len(results['scenes'])} scenes, torch threads {results['threads']}; "
             "PSNR (dB) the mean over scenes; ms/frame the mean of the scenes' medians (the scenes differ in "
             "size); time: the median over scenes of the ratio to the default's time on the scene; worst "
             "scene: the largest loss against the default on one scene.", "",
             "| method | " + " | ".join(f"{s} spp PSNR | ms/frame | time | worst scene" for s in spps) + " |",
             "|---" * (1 + 4 * len(spps)) + "|"]
    sums = {s: summary(results, s) for s in spps}
    for m in sums[spps[0]]:
        cells = []
        for s in spps:
            r = sums[s][m]
            w = "" if r["worst"] is None else f"{r['worst'][0]:+.2f} ({r['worst'][1]})"
            cells += [f"{r['psnr']:.2f}", f"{r['ms']:.0f}", f"{r['time_ratio']:.2f}x", w]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def chart(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spps = [k for k in ("1", "4") if any(k in s for s in results["scenes"].values())]
    fig, axes = plt.subplots(1, len(spps), figsize=(6 * len(spps), 4.5), squeeze=False)
    for ax, s in zip(axes[0], spps):
        for m, r in summary(results, s).items():
            ax.scatter(r["ms"], r["psnr"], color="#9467bd" if m == "oidn" else
                       "#d62728" if m == "default" else "#1f77b4", zorder=3)
            ax.annotate(m, (r["ms"], r["psnr"]), textcoords="offset points", xytext=(4, 3), fontsize=7)
        ax.set_xlabel(f"ms per frame (mean over scenes, {results['threads']} threads)")
        ax.set_ylabel("PSNR dB (mean over scenes)")
        ax.set_title(f"from {s} spp")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main(sys.argv[1:])
