"""Score every denoiser on every scene of the validation set, per scene, from 1 spp and from 4 spp.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/validation/score.py [--data-root /work/valdata] [--scenes a b]

Scenes come from ``benchmarks/validation/split.json`` (the shared Mitsuba clip included, by path). Methods are
those of ``benchmarks/baselines.py`` run through ``benchmarks/harness.py`` exactly as ``bench_methods.py`` runs
them: raw input; Gaussian blur (best of sigma 1/2/4/8 per scene); kornia joint bilateral and OpenCV ``amFilter``
guided by albedo + normal + depth (demodulated colour, the harness' preprocessing); Intel OIDN (``pyoidn``,
albedo + normal, ``hdr=True``); ours (``torchmanifold.pipeline.denoise_frames``, default settings, each frame
alone) and ours-spacetime (the ``denoise`` command's default: the frames within +-2 join in space-time).
Scores:
PSNR (clamped sRGB, mean over frames), relMSE (linear, ``mean((x-r)^2/(r^2+0.01))``), FLIP (LDR sRGB), and
ms/frame (median, this machine, this run). Where a clip has a mask of moving objects, PSNR inside and outside it;
where it has a second reference, the PSNR of one reference against the other (a ceiling for every method).

Writes ``benchmarks/results/validation/scores.json``, ``scores.md``, ``psnr.png`` and ``tpsnr.png``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import baselines  # noqa: E402
import harness  # noqa: E402

ROOT = HERE.parents[1]
OUT = ROOT / "benchmarks" / "results" / "validation"
SIGMA_S, SIGMA_R = 4.0, 1.0  # bench_methods.py's settings: the harness guide is pre-scaled per feature group
GUIDE = ("depth", "normal", "albedo")
FAMILIES = ("raw", "gaussian", "joint-bilateral", "opencv-am", "oidn", "ours", "ours-spacetime")


# ---------------------------------------------------------------------------------------------------- reading
def read_frame(path: Path) -> dict:
    """name -> (H, W) float32 of one frame, in tracer names (``R,G,B,Mr,Mg,Mb,Nx,Ny,Nz,Z``) and ``P.X/Y/Z``.

    Read by :func:`torchmanifold.io.frames.read_render_frame` (Mitsuba's flat layout, Blender's multilayer
    one, single- or multi-part); Blender's camera-space denoising normal stands in for ``N`` and its planar
    depth for ``Z`` where the file has no other.
    """
    from torchmanifold.io.frames import read_render_frame

    return frame_channels(read_render_frame(path))


def frame_channels(fr) -> dict:
    """:func:`read_frame` of a frame already read (a :class:`~torchmanifold.io.frames.RenderFrame`)."""
    from torchmanifold import features as feature_table

    out = {c: fr.color[k] for k, c in enumerate("RGB")}
    stand_in = {"Ncam": "N", "Zplane": "Z"}
    for group in ("albedo", "N", "Z", "P", "Ncam", "Zplane"):
        chans = [n for n in fr.features if feature_table.group_of(n) == group]
        target = stand_in.get(group, group)
        tracer = feature_table.tracer_channels(target) or tuple(chans)  # P: our tracer has none, keep its own
        if not chans or tracer[0] in out:
            continue
        for name, t in zip(chans, tracer):
            out[t] = fr.features[name]
    return {k: np.asarray(v, dtype=np.float32) for k, v in out.items()}


def _stack(frames: list, names) -> torch.Tensor:
    return torch.from_numpy(np.stack([np.stack([fr[n] for n in names]) for fr in frames]))


def frame_prefix(spp: int) -> str:
    """The file names of a clip's ``spp``-sample frames: ``frame_XXXX.exr`` from 1 spp, else
    ``frame<spp>spp_XXXX.exr``."""
    return "frame" if spp == 1 else f"frame{spp}spp"


def load_scene(path: Path, spp: int, prefix: str | None = None) -> tuple[harness.Dataset, dict]:
    """The clip at ``path`` as the harness' Dataset for its ``spp``-sample frames, and extras (mask, ref_b);
    ``prefix``: other frames' file names (``iter8`` for ``iter8_XXXX.exr``) instead of the ``spp`` ones."""
    prefix = prefix or frame_prefix(spp)
    files = sorted(path.glob(f"{prefix}_*.exr"))
    if not files:
        raise FileNotFoundError(f"{path}: no {prefix}_XXXX.exr")
    from torchmanifold.io.frames import read_render_frame

    first = read_render_frame(files[0])
    frames = [frame_channels(first)] + [read_frame(p) for p in files[1:]]
    idx = [int(p.stem.split("_")[-1]) for p in files]
    feat_names = [n for n in ("Mr", "Mg", "Mb", "Nx", "Ny", "Nz", "Z", "P.X", "P.Y", "P.Z") if n in frames[0]]
    color = _stack(frames, "RGB")
    feats = _stack(frames, feat_names)
    ref = _stack([read_frame(path / f"reference_{i:04d}.exr") for i in idx], "RGB")
    # the sample count as the denoise command reads it: the renderer's header, else what the features show
    ds = harness.Dataset(path.name, color, feats, feat_names, ref, torch.tensor(idx, dtype=torch.float32),
                         {spp: (color, None)}, samples_per_pixel=first.samples_per_pixel)
    extra = {}
    masks = [path / f"mask_{i:04d}.exr" for i in idx]
    if all(m.exists() for m in masks):
        import OpenEXR
        extra["mask"] = torch.from_numpy(np.stack([
            OpenEXR.File(str(m), separate_channels=True).channels()["moving"].pixels.astype(np.float32)
            for m in masks]))[:, None]
    ref_b = sorted(path.glob("ref_b_*.exr"))
    if ref_b:
        i = int(ref_b[0].stem.split("_")[-1])
        if i in idx:
            extra["ref_b"] = (idx.index(i), _stack([read_frame(ref_b[0])], "RGB"))
    return ds, extra


# ---------------------------------------------------------------------------------------------------- scoring
def methods() -> list:
    keep = ("gaussian", "joint-bilateral", "opencv-am", "oidn")
    out = [m for m in baselines.benchmark_methods(sigma_s=SIGMA_S, sigma_r=SIGMA_R) if m.family in keep]
    out += [m for m in baselines.benchmark_methods() if m.name in ("ours-pipeline", "ours-pipeline-spacetime")]
    missing = [f"{m.name}: {m.why}" for m in out if not m.available]
    if missing:
        raise RuntimeError("methods not installed: " + "; ".join(missing))
    return out


#: a directly seen light: reference luminance above this many frame means (emitters are far brighter
#: than anything they light; the sky of the open scenes stays under 3)
LIGHT_LEVEL = 4.0
#: the ring around lights whose energy is compared (issue 15: "a ring of 8 px")
RING_PX = 8
#: a caustic: a diffuse pixel (albedo luminance over 0.02) whose irradiance (reference / albedo) is at
#: least this many times its 8-px neighbourhood's and the frame's mean: light focused by glass or a mirror
CAUSTIC_LEVEL = 2.0
MIN_REGION_PX = 20


def _dilate(m: torch.Tensor, r: int) -> torch.Tensor:
    return torch.nn.functional.max_pool2d(m.float(), 2 * r + 1, 1, r) > 0


def energy_regions(ds: harness.Dataset, open_caustics: bool = True) -> dict:
    """Per-frame masks ``(F, 1, H, W)`` of the rings around lights and of caustics, from the reference
    (frames with fewer than ``MIN_REGION_PX`` pixels in a region have it empty). ``open_caustics``
    keeps blobs only (against a noisy reference's sparkles); a clean reference's thin caustic needs it off."""
    from torchmanifold.pipeline.image import footprint_blur, luminance

    L = luminance(ds.reference.clamp_min(0))
    mean = L.mean((1, 2, 3), keepdim=True)
    light = L > LIGHT_LEVEL * mean
    ring = _dilate(light, RING_PX) & ~_dilate(light, 1)
    out = {"light_ring": ring}
    if ds.albedo is not None:  # on irradiance (radiance / albedo), so texture is no caustic
        a = luminance(ds.albedo.clamp(0, 1))
        diffuse = (a > 0.02).float()
        E = L / a.clamp_min(0.02) * diffuse
        local = footprint_blur(E, 8.0) / footprint_blur(diffuse, 8.0).clamp_min(1e-6)
        mean_e = E.sum((1, 2, 3), keepdim=True) / diffuse.sum((1, 2, 3), keepdim=True).clamp_min(1.0)
        bright = (diffuse > 0) & ~light & (E > CAUSTIC_LEVEL * local) & (E > CAUSTIC_LEVEL * mean_e)
        out["caustic"] = _dilate(~_dilate(~bright, 1), 1) if open_caustics else bright  # opened: blobs only
    for k, m in out.items():
        out[k] = m & (m.sum((1, 2, 3), keepdim=True) >= MIN_REGION_PX)
    return out


def energy_ratios(out: torch.Tensor, ds: harness.Dataset, regions: dict) -> dict:
    """Energy of ``out`` over the reference's in each region (1 = kept), over the frames that have it."""
    from torchmanifold.pipeline.image import luminance

    res = {}
    for k, m in regions.items():
        if bool(m.any()):
            res[f"{k}_energy"] = float((luminance(out.clamp_min(0)) * m).sum() /
                                       (luminance(ds.reference.clamp_min(0)) * m).sum())
    return res


def score(out: torch.Tensor, ds: harness.Dataset, extra: dict) -> dict:
    from torchmanifold import metrics

    res = harness.scores(out, ds.reference)
    if out.shape[0] >= 2:  # flicker: the frame-to-frame changes against the reference's
        res["tpsnr"] = metrics.temporal_psnr(out, ds.reference)
    res.update(energy_ratios(out, ds, extra["regions"]))
    if "mask" in extra:
        m = extra["mask"]
        frames = [q for q in range(m.shape[0]) if float(m[q].sum()) >= 1.0]
        if frames:
            res["psnr_moving"] = float(np.mean([metrics.psnr(out[q], ds.reference[q], m[q]) for q in frames]))
            res["psnr_static"] = float(np.mean([metrics.psnr(out[q], ds.reference[q], 1 - m[q]) for q in frames]))
    return res


def run_scene(path: Path, spp: int, meths: list, strips: Path | None = None) -> dict:
    ds, extra = load_scene(path, spp)
    extra["regions"] = energy_regions(ds)
    clip, alb = harness.clip_for(ds, use=GUIDE)
    res = {"size": list(ds.color.shape[-2:]), "frames": ds.color.shape[0], "features": list(ds.names), "methods": {},
           "region_pixels": {k: int(m.sum()) for k, m in extra["regions"].items()}}
    res["methods"]["raw"] = {"family": "raw", **score(ds.color, ds, extra), "ms_median": 0.0}
    outputs = {"input": ds.color, "reference": ds.reference}
    if "ref_b" in extra:
        q, rb = extra["ref_b"]
        res["reference_agreement_psnr"] = harness.scores(rb, ds.reference[q : q + 1], with_flip=False)["psnr"]
    for m in meths:
        out, secs = harness.run_method(m, ds, clip, alb, list(range(ds.color.shape[0])), SIGMA_S, SIGMA_R)
        finite = torch.isfinite(out)
        r = {"family": m.family, "params": m.params, **harness.timing_summary(secs),
             "nonfinite_fraction": float((~finite).float().mean())}
        out = torch.where(finite, out, ds.color)
        r.update(score(out, ds, extra))
        res["methods"][m.name] = r
        if m.family in ("oidn", "ours"):  # the strips show the per-frame result
            outputs[m.family] = out
    # Per family, the member with the best PSNR on this scene (Gaussian: best sigma; bilateral: best sigma_r).
    best = {}
    for name, r in res["methods"].items():
        f = r["family"]
        if f not in best or r["psnr"] > res["methods"][best[f]]["psnr"]:
            best[f] = name
    res["best_of_family"] = best
    if strips is not None:
        res["worst_frame"] = worst_frame_strip(outputs, strips / f"{path.name}_{spp}spp.png")
    return res


def worst_frame_strip(outputs: dict, png: Path) -> int:
    """Input, ours, OIDN and reference of the frame where ours scores lowest, above their error maps
    (4x the absolute sRGB error); written to ``png``. Returns the frame index."""
    from PIL import Image

    from torchmanifold import metrics

    ref = outputs["reference"]
    q = int(np.argmin([metrics.psnr(outputs["ours"][k], ref[k]) for k in range(ref.shape[0])]))
    names = ["input", "ours", "oidn", "reference"]
    srgb = {n: metrics.linear_to_srgb(outputs[n][q].clamp(0, 1)) for n in names}
    err = {n: (4 * (srgb[n] - srgb["reference"]).abs().mean(0, keepdim=True)).expand(3, -1, -1) for n in names}
    img = torch.cat([torch.cat([srgb[n] for n in names], -1), torch.cat([err[n] for n in names], -1)], -2)
    img = (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    scale = max(1, 256 // ref.shape[-2])
    png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).resize((img.shape[1] * scale, img.shape[0] * scale), Image.NEAREST).save(png)
    return q


def _entries(split: dict) -> dict:
    """The set's scenes, then its probes: clips rendered on demand, not committed, scored only when named
    (``--scenes``) with the ``--data-root`` they were rendered into."""
    return {**split["scenes"], **split.get("probes", {})}


def resolve(entry: dict, data_root: Path | None) -> Path:
    if entry.get("shared"):
        return harness.DATA if harness.DATA.is_dir() else Path("/work/shared/data") / entry["shared"]
    p = ROOT / entry["path"]
    if data_root is not None and (data_root / p.name).is_dir():
        return data_root / p.name
    return p


# ---------------------------------------------------------------------------------------------------- reports
def family_row(scene: dict) -> dict:
    return {f: scene["methods"][scene["best_of_family"][f]] for f in FAMILIES if f in scene["best_of_family"]}


def earlier_runs(results: dict) -> str:
    """A sentence naming the runs (``--merge``) whose scenes a results dict kept, or ``""``."""
    runs = results.get("meta_previous_runs", [])
    if not runs:
        return ""
    return " Scenes not scored in this run come from earlier runs: " + ", ".join(
        f"commit {m.get('git_commit', '?')[:10]} ({m.get('date_utc', '?')})" for m in runs) + "."


def markdown(results: dict, split: dict) -> str:
    lines = ["# Validation set: per-scene scores", "",
             f"Run {results['meta']['date_utc']}, commit {results['meta']['git_commit'][:10]}, "
             f"{results['meta']['cpu_count']} cores ({results['meta']['cpu']}), load {results['meta']['load_average']}, "
             f"torch threads {results['meta']['torch_threads']}. Produced by `benchmarks/validation/score.py`."
             + earlier_runs(results), "",
             "PSNR: clamped sRGB, mean over frames (dB, higher is better). relMSE: linear. FLIP: LDR sRGB (lower is "
             "better). Gaussian and joint bilateral: the best of their settings on each scene (an oracle choice). "
             "`ours`: each frame alone; `ours-spacetime`: the `denoise` command's default, +-2 frames joined "
             "in "
             "space-time. Filters other than OIDN and ours see colour / albedo with an albedo + normal + depth guide "
             "(`benchmarks/harness.py`). `ref agree`: PSNR of a second independent reference against the reference "
             "(a ceiling on every score) where the clip has one.", ""]
    if results.get("meta_runs"):
        loads = ", ".join(f"{m['load_average'][0]:.1f}" for m in results["meta_runs"] if m.get("load_average"))
        lines += [f"Scored in {len(results['meta_runs'])} runs, partly in parallel on the shared 2-core machine "
                  f"(1-min load averages at their starts: {loads}): every method of a scene and spp ran in the same "
                  "process one after another, so ms/frame compare methods within a row, not across scenes.", ""]
    for spp in ("1", "4"):
        lines += [f"## From {spp} spp", "", "| scene | split | " + " | ".join(FAMILIES) + " | ref agree |",
                  "|---" * (len(FAMILIES) + 3) + "|"]
        means = {f: [] for f in FAMILIES}
        for name, sc in results["scenes"].items():
            s = sc.get(spp)
            if s is None:
                continue
            row = family_row(s)
            cells = []
            for f in FAMILIES:
                r = row.get(f)
                if r is None:
                    cells.append("-")
                    continue
                means[f].append(r["psnr"])
                cells.append(f"{r['psnr']:.2f} / {r['relmse']:.4f} / {r.get('flip', float('nan')):.3f}")
            agree = s.get("reference_agreement_psnr")
            lines.append(f"| {name} | {sc['split']} | " + " | ".join(cells) + f" | {agree:.2f} |" if agree else
                         f"| {name} | {sc['split']} | " + " | ".join(cells) + " | - |")
        lines.append("| **mean PSNR** | | " + " | ".join(f"**{np.mean(v):.2f}**" if v else "-" for v in means.values())
                     + " | |")
        lines += ["", "Cells: PSNR / relMSE / FLIP.", ""]
    lines += ["## ms per frame (median over frames, from 1 spp)", "", "| scene | size | " + " | ".join(FAMILIES[1:])
              + " |", "|---" * (len(FAMILIES) + 1) + "|"]
    for name, sc in results["scenes"].items():
        s = sc.get("1")
        if s is None:
            continue
        row = family_row(s)
        lines.append(f"| {name} | {s['size'][1]}x{s['size'][0]} | "
                     + " | ".join(f"{row[f]['ms_median']:.1f}" if f in row else "-" for f in FAMILIES[1:]) + " |")
    lines += ["", "## Temporal stability (PSNR of the frame-to-frame changes against the reference's, from 1 / 4 "
              "spp)", "", "Flicker costs here, an error that stays put from frame to frame does not "
              "(`torchmanifold.metrics.temporal_psnr`).", "",
              "| scene | " + " | ".join(FAMILIES) + " |", "|---" * (len(FAMILIES) + 1) + "|"]
    for name, sc in results["scenes"].items():
        rows = {spp: family_row(sc[spp]) for spp in ("1", "4") if spp in sc}
        if not rows or not all("tpsnr" in r["raw"] for r in rows.values()):
            continue
        lines.append(f"| {name} | " + " | ".join(" / ".join(
            f"{rows[spp][f]['tpsnr']:.2f}" if f in rows[spp] else "-" for spp in rows) for f in FAMILIES) + " |")
    lines += ["", "## Moving objects (PSNR inside / outside the mask of moving objects, from 1 spp)", "",
              "| scene | " + " | ".join(FAMILIES) + " |", "|---" * (len(FAMILIES) + 1) + "|"]
    for name, sc in results["scenes"].items():
        s = sc.get("1")
        if s is None or "psnr_moving" not in s["methods"]["raw"]:
            continue
        row = family_row(s)
        lines.append(f"| {name} | " + " | ".join(
            f"{row[f]['psnr_moving']:.2f} / {row[f]['psnr_static']:.2f}" if f in row else "-" for f in FAMILIES) + " |")
    lines += ["", "## Energy kept (from 1 spp; ratio of the output's luminance to the reference's, 1 = kept)", "",
              f"Light ring: pixels 2 to {RING_PX} px from a directly seen light (reference luminance over "
              f"{LIGHT_LEVEL:g} frame means). Caustic: diffuse pixels over {CAUSTIC_LEVEL:g} times both their 8-px "
              "neighbourhood and the frame mean. Scenes without such regions are left out.", "",
              "| scene | region (px) | " + " | ".join(FAMILIES) + " |", "|---" * (len(FAMILIES) + 2) + "|"]
    for name, sc in results["scenes"].items():
        s = sc.get("1")
        if s is None:
            continue
        row = family_row(s)
        for region, px in s.get("region_pixels", {}).items():
            key = f"{region}_energy"
            if px and key in s["methods"]["raw"]:
                lines.append(f"| {name} | {region} ({px}) | " + " | ".join(
                    f"{row[f][key]:.3f}" if f in row and key in row[f] else "-" for f in FAMILIES) + " |")
    lines += ["", "Worst frame of ours per scene (input, ours, OIDN, reference; 4x sRGB error below): "
              "`strips/<scene>_<spp>spp.png`.", ""]
    lines += ["", "## Best setting per scene", "", "| scene | spp | gaussian | joint bilateral |", "|---|---|---|---|"]
    for name, sc in results["scenes"].items():
        for spp in ("1", "4"):
            if spp in sc:
                b = sc[spp]["best_of_family"]
                lines.append(f"| {name} | {spp} | {b.get('gaussian')} | {b.get('joint-bilateral')} |")
    lines += ["", f"Split: tune {split['tune']}, test {split['test']}.", ""]
    return "\n".join(lines)


#: the charts score.py draws: file, the scores' key, the axis label, the title, the axis' floor (dB)
CHARTS = (("psnr.png", "psnr", "PSNR dB", "PSNR per scene (clamped sRGB, mean over frames)", 15),
          ("tpsnr.png", "tpsnr", "temporal PSNR dB",
           "temporal PSNR per scene (frame-to-frame changes against the reference's; flicker costs)", 5))


def chart(results: dict, path: Path, key: str = "psnr", label: str = "PSNR dB",
          title: str = "PSNR per scene (clamped sRGB, mean over frames)", bottom: float = 15) -> None:
    """Bars of ``key`` per scene and method family, from 1 spp above and 4 spp below, into ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"raw": "#555555", "gaussian": "#1f77b4", "joint-bilateral": "#2ca02c", "opencv-am": "#ff7f0e",
               "oidn": "#9467bd", "ours": "#d62728", "ours-spacetime": "#8c1c13"}
    scenes = list(results["scenes"])
    fig, axes = plt.subplots(2, 1, figsize=(max(8, 1.4 * len(scenes) + 2), 8), sharex=True)
    for ax, spp in zip(axes, ("1", "4")):
        w = 0.8 / len(FAMILIES)
        for k, f in enumerate(FAMILIES):
            vals = [family_row(results["scenes"][s][spp]).get(f, {}).get(key, np.nan)
                    if spp in results["scenes"][s] else np.nan for s in scenes]
            ax.bar(np.arange(len(scenes)) + (k - (len(FAMILIES) - 1) / 2) * w, vals, w, label=f, color=colours[f])
        ax.set_ylabel(f"{label} (from {spp} spp)")
        ax.set_ylim(bottom=bottom)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(ncol=len(FAMILIES), fontsize=8, loc="upper left")
    axes[1].set_xticks(np.arange(len(scenes)))
    axes[1].set_xticklabels([f"{s}\n({results['scenes'][s]['split']})" for s in scenes], fontsize=8)
    fig.suptitle(f"Validation set: {title}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", type=Path, default=HERE / "split.json")
    ap.add_argument("--data-root", type=Path, default=None,
                    help="folder with rendered clips (e.g. /work/valdata) used instead of the committed copies")
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--spp", nargs="+", type=int, default=[1, 4])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--merge", action="store_true",
                    help="keep the other scenes of an existing scores.json (score clips as they are rendered)")
    ap.add_argument("--combine", nargs="+", type=Path, default=None,
                    help="score nothing: merge the scenes of these scores.json files (runs done in parallel) into --out")
    args = ap.parse_args(argv)
    split = json.loads(args.split.read_text())
    if args.combine:
        runs = [json.loads(p.read_text()) for p in args.combine]
        scenes: dict = {}
        for r in runs:  # a scene's spp levels may come from different runs
            for k, v in r["scenes"].items():
                scenes[k] = {**scenes.get(k, {}), **v}
        order = list(_entries(split))
        results = {**runs[0], "scenes": {k: scenes[k] for k in sorted(scenes, key=order.index)},
                   "meta_runs": [r["meta"] for r in runs]}
        return _write(results, split, args.out)
    names = args.scenes or list(split["scenes"])
    meths = methods()
    results = {"meta": harness.metadata(), "sigma_s": SIGMA_S, "sigma_r": SIGMA_R, "guide": list(GUIDE),
               "scenes": {}}
    old = args.out / "scores.json"
    if args.merge and old.exists():
        prev = json.loads(old.read_text())
        # Keep every scene and spp of the earlier runs that this run does not redo.
        results["scenes"] = prev["scenes"]
        results["meta_previous_runs"] = prev.get("meta_previous_runs", []) + [prev["meta"]]
    from tqdm import tqdm

    for name in tqdm(names, desc="scenes"):
        entry = _entries(split)[name]
        path = resolve(entry, args.data_root)
        sc = {**results["scenes"].get(name, {}), "split": entry["split"], "renderer": entry["renderer"],
              "path": str(path)}
        for spp in args.spp:
            t0 = time.perf_counter()
            sc[str(spp)] = run_scene(path, spp, meths, args.out / "strips")
            tqdm.write(f"{name} {spp} spp: {time.perf_counter() - t0:.0f} s; " + ", ".join(
                f"{f} {r['psnr']:.2f}" for f, r in family_row(sc[str(spp)]).items()))
        results["scenes"][name] = sc
    order = list(_entries(split))
    results["scenes"] = {k: results["scenes"][k] for k in sorted(results["scenes"], key=order.index)}
    _write(results, split, args.out)


def _write(results: dict, split: dict, out: Path) -> None:
    write_results(out, "scores", results, markdown(results, split),
                  lambda: [chart(results, out / name, *how) for name, *how in CHARTS])


def write_results(out: Path, stem: str, results: dict, table: str, draw) -> None:
    """A validation benchmark's outputs in ``out``: ``<stem>.json`` (``results``), ``<stem>.md`` (``table``,
    also printed) and its charts (``draw()``)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(results, indent=1))
    (out / f"{stem}.md").write_text(table)
    draw()
    print(table)


if __name__ == "__main__":
    main()
