"""The validation set through progressive iterations: ours and Intel OIDN on what a renderer holds after 1 to
16 samples per pixel, added one per iteration.

    # the iterations (not committed: the set is at its 60 MB budget), then the scores
    cd benchmarks/validation    # Mitsuba with DRJIT_LIBLLVM_PATH as benchmarks/README.md says
    /work/venvs/mitsuba/bin/python render_mitsuba.py <clips> --out data --iterations 16
    /work/venvs/bpy/bin/python render_blender.py <clips> --out data --iterations 16
    PYTHONPATH=$PWD .venv/bin/python benchmarks/validation/iterations.py [--threads 2] [--scenes a b]

After n iterations the frame is ``frame_XXXX.exr`` for n = 1, else ``iter<n>_XXXX.exr`` (header ``spp`` n)
for n = 2, 4, 8, 16: from Mitsuba the mean of n independent 1-spp passes (its independent sampler), from
Cycles n samples of the 1-spp frame's own sequence (as its progressive render accumulates them; 1-spp renders
with other seeds all sample the pixel at one position). Each is denoised as a user would: the ``denoise``
command's own path and default (the header's count sets the bandwidths and the footprint), and OIDN on the
same frames in the same run. Scenes without the iterations (the shared clip, which this project did
not render) are left out and named.

Writes ``benchmarks/results/validation/iterations.json``, ``iterations.md`` and ``iterations.png`` (PSNR
against iterations per scene).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))
import torchmanifold  # noqa: E402,F401  (before torch, as the command imports it)
import torch  # noqa: E402

import harness  # noqa: E402
import score  # noqa: E402
import tradeoff  # noqa: E402

OUT = score.OUT
#: iterations scored: the 1-spp frames and the running means the render scripts write
ITERATIONS = (1, 2, 4, 8, 16)


def prefix(n: int) -> str:
    return "frame" if n == 1 else f"iter{n}"


def clip_files(path: Path, n: int) -> list[Path]:
    return sorted(path.glob(f"{prefix(n)}_*.exr"))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", type=Path, default=HERE / "split.json")
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    split = json.loads(args.split.read_text())
    names = args.scenes or list(split["scenes"])
    from tqdm import tqdm

    results = {"meta": harness.metadata(), "threads": args.threads, "iterations": list(ITERATIONS),
               "scenes": {}, "left_out": {}}
    settings = tradeoff.settings_of({})
    for name in tqdm(names, desc="scenes"):
        path = score.resolve(split["scenes"][name], None)
        missing = [n for n in ITERATIONS if not clip_files(path, n)]
        if missing:
            results["left_out"][name] = f"no iter<n>_XXXX.exr for n in {missing} (see --iterations)"
            continue
        sc = {"split": split["scenes"][name]["split"]}
        for n in ITERATIONS:
            files = clip_files(path, n)
            oidn, ds, secs_oidn = tradeoff.run_oidn(path, n, prefix(n))
            ref = ds.reference
            outs, secs = tradeoff.run_variant(files, settings)
            sc[str(n)] = {"raw": tradeoff.psnr(ds.color, ref), "oidn": tradeoff.psnr(oidn, ref),
                          "ours": tradeoff.psnr(outs, ref), "ms_ours": 1e3 * statistics.median(secs),
                          "ms_oidn": 1e3 * statistics.median(secs_oidn)}
            tqdm.write(f"{name} after {n}: " + ", ".join(f"{k} {v:.2f}" for k, v in sc[str(n)].items()))
        results["scenes"][name] = sc
    score.write_results(args.out, "iterations", results, markdown(results),
                        lambda: chart(results, args.out / "iterations.png"))
    return results


def markdown(results: dict) -> str:
    its = [str(n) for n in results["iterations"]]
    meta = results["meta"]
    lines = [f"Validation set through progressive iterations (n samples per pixel added one per iteration), "
             f"run {meta.get('date_utc', '')}, commit `{meta.get('git_commit', '')[:10]}`, "
             f"torch threads {results['threads']}. "
             "PSNR (dB, clamped sRGB, mean over frames) of raw / OIDN / ours (the `denoise` default) after n "
             "iterations.", "",
             "| scene | split | " + " | ".join(f"after {n}" for n in its) + " | ours - OIDN after 8 |",
             "|---|---|" + "---|" * (len(its) + 1)]
    sums = {n: {k: [] for k in ("raw", "oidn", "ours")} for n in its}
    for name, sc in results["scenes"].items():
        cells = []
        for n in its:
            r = sc[n]
            cells.append(f"{r['raw']:.2f} / {r['oidn']:.2f} / {r['ours']:.2f}")
            for k in sums[n]:
                sums[n][k].append(r[k])
        gap = sc["8"]["ours"] - sc["8"]["oidn"]
        lines.append(f"| {name} | {sc['split']} | " + " | ".join(cells) + f" | {gap:+.2f} |")
    if results["scenes"]:
        mean = {n: {k: float(np.mean(v)) for k, v in sums[n].items()} for n in its}
        lines.append("| **mean** | | " + " | ".join(
            f"{m['raw']:.2f} / {m['oidn']:.2f} / **{m['ours']:.2f}**" for m in mean.values())
            + f" | {mean['8']['ours'] - mean['8']['oidn']:+.2f} |")
    for name, why in results["left_out"].items():
        lines.append(f"\nLeft out: `{name}`: {why}.")
    return "\n".join(lines) + "\n"


def chart(results: dict, path: Path) -> None:
    """PSNR against iterations (log scale), one panel per scene: raw, OIDN and ours."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(results["scenes"])
    if not scenes:
        return
    its = results["iterations"]
    cols = min(4, len(scenes))
    rows = -(-len(scenes) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for ax, name in zip(axes.flat, scenes):
        sc = results["scenes"][name]
        for key, colour in (("raw", "#555555"), ("oidn", "#9467bd"), ("ours", "#d62728")):
            ax.plot(its, [sc[str(n)][key] for n in its], "o-", color=colour, label=key, ms=3)
        ax.set_xscale("log", base=2)
        ax.set_xticks(its, [str(n) for n in its])
        ax.set_title(f"{name} ({sc['split']})", fontsize=9)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(scenes):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    fig.supxlabel("iterations (samples per pixel, one added per iteration)")
    fig.supylabel("PSNR dB")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
