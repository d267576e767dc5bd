"""Charts and the markdown summary from ``benchmarks/results/*.json``.

    .venv/bin/python benchmarks/charts.py [--quick]

reads methods.json, scaling.json, ablation.json and progressive.json (whichever exist; ``results/quick/`` with
``--quick``) and writes next to them:

* ``speed_quality_<dataset>.png``: PSNR and FLIP against ms per frame for every method, Pareto front marked;
* ``scaling.png``: time against pixels, guide channels and tree height;
* ``progressive.png``: error against iteration for the progressive methods;
* ``ablation.png``: PSNR per feature set and scene;

and ``docs/benchmarks.md`` (``results/quick/benchmarks.md`` with ``--quick``).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from torchmanifold.pipeline.denoise_files import COMMAND_FILTER  # noqa: E402

#: the ``denoise`` command's time window, as the tables name it
_WINDOW = f"+-{COMMAND_FILTER['temporal_radius']}"

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
COLOURS = {"raw": "#555555", "gaussian": "#1f77b4", "joint-bilateral": "#2ca02c", "opencv-am": "#ff7f0e",
           "oidn": "#9467bd", "ours": "#d62728"}


def load(folder: Path, name: str):
    path = folder / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


# ---------------------------------------------------------------------------------------------------- pareto
def frame_ms(ds: dict, res: dict) -> float:
    """Cost of one output frame: the method's time (fastest round) plus, for filters of our tracer's frames,
    the 1-spp render they start from, so filters and plain path tracing compare at equal time."""
    ms = res["ms_min"]
    if res["family"] != "raw":
        ms += ds.get("trace_ms_1spp", 0.0)
    return ms


def pareto(points: list) -> list:
    """Indices of the (ms, quality) points no other point beats on both (less time, higher quality)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -math.inf
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def speed_quality(ds_name: str, ds: dict, out: Path) -> dict:
    """One dataset's chart; returns {method: on the PSNR Pareto front}."""
    names = [n for n, r in ds["methods"].items() if r.get("psnr") is not None and math.isfinite(r["psnr"])]
    metrics = [("psnr", "PSNR, clamped sRGB (dB) - higher is better", 1), ("flip", "FLIP - lower is better", -1)]
    metrics = [m for m in metrics if any(m[0] in ds["methods"][n] for n in names)]
    fig, axes = plt.subplots(1, len(metrics), figsize=(6.5 * len(metrics), 4.8), squeeze=False)
    on_front = {}
    for ax, (key, label, sign) in zip(axes[0], metrics):
        timed = [n for n in names if frame_ms(ds, ds["methods"][n]) > 0 and key in ds["methods"][n]]
        untimed = [n for n in names if n not in timed and key in ds["methods"][n]]
        pts = [(frame_ms(ds, ds["methods"][n]), sign * ds["methods"][n][key]) for n in timed]
        front = pareto(pts)
        for i, n in enumerate(timed):
            r = ds["methods"][n]
            ax.scatter(pts[i][0], r[key], color=COLOURS.get(r["family"], "k"), s=46 if i in front else 22,
                       edgecolor="k" if i in front else "none", zorder=3)
            ax.annotate(n, (pts[i][0], r[key]), fontsize=7, xytext=(4, 3), textcoords="offset points")
        fx = [pts[i][0] for i in front]
        fy = [sign * pts[i][1] for i in front]
        ax.step(fx, fy, where="post", color="k", lw=1, ls="--", label="Pareto front", zorder=2)
        for n in untimed:  # frames whose render time is unknown (another renderer): a level, not a point
            ax.axhline(ds["methods"][n][key], color=COLOURS["raw"], lw=0.8, ls=":")
            ax.annotate(f"{n} (render time unknown)", (0.01, ds["methods"][n][key]), xycoords=("axes fraction", "data"),
                        fontsize=7, xytext=(0, 2), textcoords="offset points", color=COLOURS["raw"])
        ax.set_xscale("log")
        ax.set_xlabel("ms per frame" + (" (1-spp trace + filter)" if ds.get("trace_ms_1spp") else " (filter only)"))
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if key == "psnr":
            on_front = {n: (i in front) for i, n in enumerate(timed)}
    handles = [plt.Line2D([], [], marker="o", ls="", color=c, label=f) for f, c in COLOURS.items()]
    handles.append(plt.Line2D([], [], color="k", ls="--", label="Pareto front (ringed)"))
    axes[0][-1].legend(handles=handles, fontsize=7, loc="best")
    h, w = ds["size"]
    fig.suptitle(f"{ds_name}: {len(ds['frames'])} frames {w}x{h}, quality against time per frame")
    fig.tight_layout()
    fig.savefig(out / f"speed_quality_{ds_name}.png", dpi=110)
    plt.close(fig)
    return on_front


# ---------------------------------------------------------------------------------------------------- scaling
def slope(xs, ys) -> float:
    """Exponent b of ys ~ xs^b (least squares in log-log): 1 = linear."""
    x, y = np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float))
    return float(np.polyfit(x, y, 1)[0]) if len(x) >= 2 else float("nan")


def scaling_chart(sc: dict, out: Path) -> dict:
    axes_spec = [("pixels", "pixels", True), ("channels", "guide channels", False), ("height", "tree height", False)]
    axes_spec = [a for a in axes_spec if a[0] in sc]
    fig, axes = plt.subplots(1, len(axes_spec), figsize=(5 * len(axes_spec), 4), squeeze=False)
    fits = {}
    for ax, (key, label, log) in zip(axes[0], axes_spec):
        for name, rows in sc[key].items():
            xs = [r[key] for r in rows]
            ys = [r["ms_min"] for r in rows]
            family = "ours" if name.startswith("ours") else name.split("-s")[0].split("-r")[0]
            ax.plot(xs, ys, "o-", color=COLOURS.get(family, None), label=name)
            # Cost grows with the 2^H - 1 manifolds of a tree, not with H itself.
            fit_x = [2 ** x - 1 for x in xs] if key == "height" else xs
            fits[f"{key if key != 'height' else 'manifolds (2^H-1)'}: {name}"] = slope(fit_x, ys)
        if log:
            ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("ms (fastest of 3)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.suptitle("time against size: linear cost shows as a constant slope")
    fig.tight_layout()
    fig.savefig(out / "scaling.png", dpi=110)
    plt.close(fig)
    return fits


# ---------------------------------------------------------------------------------------------------- others
def progressive_chart(pr: dict, out: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for name, curve in pr["curves"].items():
        family = "ours" if name.startswith("ours") else ("gaussian" if "gauss" in name else "raw")
        axes[0].plot(curve["iteration"], curve["psnr"], "o-", ms=3, color=COLOURS.get(family), label=name)
        axes[1].plot(np.asarray(curve["seconds"]), curve["psnr"], "o-", ms=3, color=COLOURS.get(family), label=name)
    axes[0].set_xlabel("iteration (spp per frame)")
    axes[1].set_xlabel("wall time (s)")
    for ax in axes:
        ax.set_ylabel("PSNR, clamped sRGB (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(pr.get("title", "progressive rendering: error against iteration"))
    fig.tight_layout()
    fig.savefig(out / "progressive.png", dpi=110)
    plt.close(fig)


def ablation_chart(ab: dict, out: Path) -> None:
    """Horizontal bars: each feature set's PSNR minus the colour-only guide's, per scene (scenes differ in level)."""
    scenes = list(ab["scenes"])
    sets = list(dict.fromkeys(s for sc in scenes for s in ab["scenes"][sc]["sets"]))
    fig, ax = plt.subplots(figsize=(8, 0.32 * len(sets) * len(scenes) + 1.5))
    height = 0.8 / len(scenes)
    y = np.arange(len(sets))
    for j, sc in enumerate(scenes):
        rows = ab["scenes"][sc]["sets"]
        base = rows["colour"]["psnr"]
        vals = [rows[s]["psnr"] - base if s in rows else np.nan for s in sets]
        ax.barh(y + j * height, vals, height, label=f"{sc} (colour only {base:.2f} dB)")
    ax.set_yticks(y + 0.4 - height / 2, sets, fontsize=8)
    ax.invert_yaxis()
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xlabel("PSNR gain over the colour-only guide (dB)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="x")
    ax.set_title("feature ablation: which guide channels help (ours)")
    fig.tight_layout()
    fig.savefig(out / "ablation.png", dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------------- summary
def _f(x, nd=2):
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{nd}f}"


def key_numbers(ds: dict) -> list:
    """Bullets comparing the best of each family, and ours against plain path tracing at equal time."""
    m = {n: r for n, r in ds["methods"].items() if r.get("psnr") is not None and math.isfinite(r["psnr"])}

    def best(pred):
        cands = [(r["psnr"], n) for n, r in m.items() if pred(n, r)]
        return max(cands)[1] if cands else None

    ours = best(lambda n, r: r["family"].startswith("ours"))
    classic = best(lambda n, r: r["family"] in ("gaussian", "joint-bilateral", "opencv-am"))
    out = []
    if ours:
        r = m[ours]
        out.append(f"- Best of ours: `{ours}` {r['psnr']:.2f} dB in {frame_ms(ds, r):.1f} ms per frame.")
    if ours and classic:
        c = m[classic]
        out.append(f"- Best classic filter: `{classic}` {c['psnr']:.2f} dB in {frame_ms(ds, c):.1f} ms "
                   f"(ours {m[ours]['psnr'] - c['psnr']:+.2f} dB).")
    if "oidn" in m:
        out.append(f"- OIDN (neural, colour + albedo + normal): {m['oidn']['psnr']:.2f} dB in "
                   f"{frame_ms(ds, m['oidn']):.1f} ms.")
    raw = {n: r for n, r in m.items() if r["family"] == "raw"}
    timed_raw = [(frame_ms(ds, r), r["psnr"], n) for n, r in raw.items() if r.get("render_ms_known") and r["ms_min"]]
    if ours and timed_raw:
        t = frame_ms(ds, m[ours])
        under = [x for x in timed_raw if x[0] <= t]
        if under:
            ms, p, n = max(under)
            out.append(f"- Plain path tracing in the same time: `{n}` ({ms:.0f} ms) {p:.2f} dB, ours "
                       f"{m[ours]['psnr'] - p:+.2f} dB.")
        better = [x for x in sorted(timed_raw) if x[1] >= m[ours]["psnr"]]
        out.append(f"- Plain path tracing reaches ours' PSNR at `{better[0][2]}` ({better[0][0]:.0f} ms per frame)."
                   if better else f"- No plain path tracing run here ({max(timed_raw)[2]} at most) reaches ours' "
                                  "PSNR.")
    return out


VALIDATION = RESULTS / "validation"
FINDINGS = ROOT / "benchmarks" / "validation" / "findings.md"
CLASSIC = ("gaussian", "joint-bilateral", "opencv-am")


def score_earlier_runs(res: dict) -> str:
    """``validation/score.py``'s sentence on the earlier runs whose scenes ``res`` kept."""
    import sys

    sys.path.insert(0, str(ROOT / "benchmarks" / "validation"))
    from score import earlier_runs

    return earlier_runs(res)


def validation_section(rel: str) -> list:
    """Per-scene table of ``results/validation/scores.json`` (written by ``validation/score.py``) and the
    findings behind the denoiser's defaults (``validation/findings.md``)."""
    path = VALIDATION / "scores.json"
    if not path.exists():
        return []
    res = json.loads(path.read_text())
    meta = res.get("meta", {})
    lines = ["## Validation set: renders from Mitsuba 3 and Blender Cycles", "",
             f"{len(res['scenes'])} clips from two renderers this project did not write (`benchmarks/README.md`: what "
             "each covers, "
             "how to regenerate them); tuned on the `tune` scenes only, `test` scenes held out. Full tables with "
             "relMSE, FLIP, ms/frame and moving-object masks: `benchmarks/results/validation/scores.md`; regenerate "
             "with `.venv/bin/python benchmarks/validation/score.py` (it needs `pyoidn`, installed by the set-up), "
             "then this file with `benchmarks/charts.py`.", "",
             f"![validation PSNR]({rel}/validation/psnr.png)", "",
             f"Run {meta.get('date_utc', '?')}, commit `{meta.get('git_commit', '')[:10]}`, "
             f"{meta.get('cpu_count')} cores, torch threads {meta.get('torch_threads')}. PSNR (dB, clamped sRGB, mean "
             f"over all frames); ours: each frame alone; ours {_WINDOW}: the `denoise` command's default "
             f"(the frames within {_WINDOW} joined in space-time); best classic: the best of Gaussian, joint "
             "bilateral (each at its best setting per "
             "scene, an oracle choice) and OpenCV `amFilter`; ms: median per frame of ours and OIDN in the same "
             "process, from 1 spp." + score_earlier_runs(res), "",
             f"| scene | split | raw 1 spp | best classic | OIDN | ours | ours {_WINDOW} | ours - OIDN | "
             "raw 4 spp | "
             f"best classic | OIDN | ours | ours {_WINDOW} | ms ours / OIDN |", "|---" * 14 + "|"]
    cols = {spp: {k: [] for k in ("raw", "classic", "oidn", "ours", "st")} for spp in ("1", "4")}
    for name, sc in res["scenes"].items():
        cells = []
        for spp in ("1", "4"):
            s = sc.get(spp)
            if s is None:
                cells += ["-"] * (6 if spp == "1" else 5)
                continue
            best = {f: s["methods"][m] for f, m in s["best_of_family"].items()}
            row = {"raw": best["raw"]["psnr"], "classic": max(best[f]["psnr"] for f in CLASSIC if f in best),
                   "oidn": best["oidn"]["psnr"], "ours": best["ours"]["psnr"],
                   "st": best["ours-spacetime"]["psnr"] if "ours-spacetime" in best else float("nan")}
            for k, v in row.items():
                cols[spp][k].append(v)
            cells += [_f(row[k]) for k in ("raw", "classic", "oidn", "ours", "st")]
            if spp == "1":
                cells.append(f"{row['ours'] - row['oidn']:+.2f}")
        one = sc.get("1")
        ms = (f"{one['methods'][one['best_of_family']['ours']]['ms_median']:.0f} / "
              f"{one['methods'][one['best_of_family']['oidn']]['ms_median']:.0f}") if one else "-"
        lines.append(f"| {name} | {sc['split']} | " + " | ".join(cells) + f" | {ms} |")
    mean = lambda v: _f(float(np.mean(v))) if v else "-"  # noqa: E731
    m1, m4 = cols["1"], cols["4"]
    gap = f"{np.mean(m1['ours']) - np.mean(m1['oidn']):+.2f}" if m1["ours"] else "-"
    lines += [f"| **mean** | | {mean(m1['raw'])} | {mean(m1['classic'])} | {mean(m1['oidn'])} | **{mean(m1['ours'])}** | "
              f"**{mean(m1['st'])}** | {gap} | {mean(m4['raw'])} | {mean(m4['classic'])} | {mean(m4['oidn'])} | "
              f"**{mean(m4['ours'])}** | **{mean(m4['st'])}** | |", ""]
    lines += temporal_section(res, rel)
    lines += iterations_section(rel)
    lines += tradeoff_section(rel)
    lines += fewer_features_section()
    if FINDINGS.exists():
        lines += [FINDINGS.read_text().strip(), ""]
    return lines


def temporal_section(res: dict, rel: str) -> list:
    """The validation scenes' temporal PSNR (``metrics.temporal_psnr``) per family, from 1 / 4 spp."""
    keys = ("raw", "classic", "oidn", "ours", "ours-spacetime")
    rows, sums = [], {k: {"1": [], "4": []} for k in keys}
    for name, sc in res["scenes"].items():
        cells = []
        for k in keys:
            vals = []
            for spp in ("1", "4"):
                s = sc.get(spp)
                fams = CLASSIC if k == "classic" else (k,)
                got = [s["methods"][s["best_of_family"][f]].get("tpsnr") for f in fams
                       if s and f in s["best_of_family"]]
                got = [v for v in got if v is not None]
                if got:
                    sums[k][spp].append(max(got))
                vals.append(_f(max(got)) if got else "-")
            cells.append(" / ".join(vals))
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    if not any(sums[k]["1"] for k in keys):
        return []
    mean = " | ".join(" / ".join(_f(float(np.mean(sums[k][spp]))) if sums[k][spp] else "-" for spp in ("1", "4"))
                      for k in keys)
    return ["Temporal stability: the PSNR (dB) of each frame-to-frame change against the reference's "
            "(`torchmanifold.metrics.temporal_psnr`: flicker costs, an error that stays put does not), from 1 / 4 "
            "spp; best classic: the best of the classic filters on this measure.", "",
            f"![validation temporal PSNR]({rel}/validation/tpsnr.png)", "",
            f"| scene | raw | best classic | OIDN | ours | ours {_WINDOW} |", "|---" * 6 + "|", *rows,
            f"| **mean** | {mean} |", ""]


def iterations_section(rel: str) -> list:
    """The validation set through progressive iterations (``results/validation/iterations.*``, written by
    ``validation/iterations.py``)."""
    path = VALIDATION / "iterations.md"
    if not path.exists():
        return []
    return ["### Through progressive iterations", "",
            f"![PSNR against iterations per scene]({rel}/validation/iterations.png)", "",
            "`benchmarks/validation/iterations.py`: what a renderer holds after n samples per pixel, added "
            "one per iteration (the render scripts' `--iterations`: Mitsuba's mean of n independent 1-spp "
            "passes, Cycles' n samples of one sequence); ours: the `denoise` command's default on it, the "
            "count from the header; OIDN on the same frames.", "",
            path.read_text().strip(), ""]


def tradeoff_section(rel: str) -> list:
    """The ``denoise`` settings' speed against accuracy (``results/validation/tradeoff.*``, written by
    ``validation/tradeoff.py``)."""
    path = VALIDATION / "tradeoff.json"
    if not path.exists():
        return []
    meta = json.loads(path.read_text()).get("meta", {})
    return ["### Speed against accuracy of the `denoise` settings", "",
            f"![denoise settings: PSNR against ms per frame]({rel}/validation/tradeoff.png)", "",
            f"Run {meta.get('date_utc', '?')}, commit `{meta.get('git_commit', '')[:10]}`, "
            f"{meta.get('cpu_count')} cores; `benchmarks/validation/tradeoff.py` (each variant through the "
            "command's own path, one frame after another, OIDN in the same run).", "",
            (VALIDATION / "tradeoff.md").read_text().strip(), ""]


def fewer_features_section() -> list:
    """Every scene from colour alone and from geometry without albedo
    (``results/validation/fewer_features.*``, written by ``validation/fewer_features.py``)."""
    path = VALIDATION / "fewer_features.md"
    if not path.exists():
        return []
    return ["### Fewer features: colour alone, geometry without albedo", "",
            "A renderer's Combined pass without its AOVs; normals, depth and positions without albedo; albedo "
            "and normal alone (OIDN's auxiliary images): `benchmarks/validation/fewer_features.py` (OIDN takes "
            "normals only beside an albedo).", "", path.read_text().strip(), ""]


def summary(folder: Path, rel: str) -> str:
    methods, sc, ab, pr = (load(folder, n) for n in ("methods", "scaling", "ablation", "progressive"))
    meta = next((d["meta"] for d in (methods, sc, ab, pr) if d), {})
    lines = ["# Benchmarks: speed against accuracy", "",
             "Generated by `benchmarks/run_all.py` (`benchmarks/charts.py` writes this file from "
             "`benchmarks/results/*.json`). Quality: PSNR on clamped sRGB (the score of `/work/shared/data`), "
             "relMSE on linear values, FLIP (lower is better), mean over frames. Time: fastest round per frame "
             "(the machine is shared; medians are in the JSON). Classic filters and ours filter demodulated "
             "colour (colour / albedo, multiplied back) guided by log colour + depth + normal + albedo, each scaled by its "
             "sigma (`benchmarks/harness.py`); "
             "OIDN and `ours-pipeline*` (our `denoise_frames`, with its own firefly treatment) get the raw colour and "
             "features.", "",
             "Regenerate everything with `.venv/bin/python benchmarks/run_all.py` (about 3 minutes on 2 cores, 5 with `--all`; "
             "`--quick` for a smoke run, `--threads N`). Where each method breaks: [stability.md](stability.md).", ""]
    if meta:
        lines += [f"Machine: {meta.get('cpu')} ({meta.get('cpu_count')} cores, shared), {meta.get('torch_threads')} "
                  f"thread(s) for torch, OpenCV and OIDN, torch {meta['versions'].get('torch')}, "
                  f"commit `{meta.get('git_commit', '')[:10]}`{' (dirty)' if meta.get('git_dirty') else ''}, "
                  f"{meta.get('date_utc')}, load average {_f((meta.get('load_average') or [None])[0], 1)}; ours ran on the "
                  f"`{meta.get('ours_backend')}` backend.", ""]
    if methods:
        for ds_name, ds in methods["datasets"].items():
            front = speed_quality(ds_name, ds, folder)
            h, w = ds["size"]
            lines += [f"## {ds_name} ({len(ds['frames'])} frames, {w}x{h})", "",
                      f"![speed-quality {ds_name}]({rel}/speed_quality_{ds_name}.png)", ""]
            if ds.get("trace_ms_1spp"):
                lines += [f"Our tracer renders one 1-spp frame in {ds['trace_ms_1spp']:.0f} ms; filter times below "
                          "add to it, and `raw-Nspp` rows are plain path tracing at N spp (their render time).", ""]
            lines += key_numbers(ds) + [""]
            lines += ["| method | ms/frame (min) | ms/frame (median) | PSNR dB | relMSE | SSIM | FLIP | Pareto |",
                      "|---|---|---|---|---|---|---|---|"]
            rows = sorted(ds["methods"].items(), key=lambda kv: -(kv[1].get("psnr") or -1e9))
            for n, r in rows:
                bad = f" ({100 * r['nonfinite_fraction']:.1f}% NaN/Inf, scored with the input there)" \
                    if r.get("nonfinite_fraction") else ""
                lines.append(f"| {n}{bad} | {_f(r['ms_min'], 1)} | {_f(r['ms_median'], 1)} | {_f(r.get('psnr'))} | "
                             f"{_f(r.get('relmse'), 4)} | {_f(r.get('ssim'), 4)} | {_f(r.get('flip'), 4)} | "
                             f"{'yes' if front.get(n) else ''} |")
            lines.append("")
    if pr:
        progressive_chart(pr, folder)
        lines += ["## Progressive rendering", "", f"![progressive]({rel}/progressive.png)", ""]
        lines += [pr.get("note", ""), "", "| curve | " + " | ".join(f"it {i}" for i in pr["report_iterations"]) + " |",
                  "|---|" + "---|" * len(pr["report_iterations"])]
        for name, c in pr["curves"].items():
            vals = [_f(c["psnr"][c["iteration"].index(i)]) if i in c["iteration"] else "—"
                    for i in pr["report_iterations"]]
            lines.append(f"| {name} | " + " | ".join(vals) + " |")
        lines.append("")
    if sc:
        fits = scaling_chart(sc["scaling"], folder)
        lines += ["## Scaling", "", f"![scaling]({rel}/scaling.png)", "",
                  "Log-log slope of time against each axis (1.0 = linear; small images are dominated by fixed "
                  "costs, so slopes below 1 are expected at the low end):", "",
                  "| axis: method | slope |", "|---|---|"]
        lines += [f"| {k} | {_f(v)} |" for k, v in fits.items()]
        lines.append("")
    if ab:
        ablation_chart(ab, folder)
        lines += ["## Which features a scene needs (ablation)", "", f"![ablation]({rel}/ablation.png)", "",
                  ab.get("note", ""), ""]
        sets = list(dict.fromkeys(s for sc_ in ab["scenes"].values() for s in sc_["sets"]))
        lines += ["| feature set | " + " | ".join(ab["scenes"]) + " |", "|---|" + "---|" * len(ab["scenes"])]
        for s in sets:
            lines.append(f"| {s} | " + " | ".join(_f(ab["scenes"][sc_]["sets"].get(s, {}).get("psnr"))
                                                  for sc_ in ab["scenes"]) + " |")
        lines += ["", ab.get("conclusion", ""), ""]
    if folder == RESULTS:  # the quick run scores no validation set
        lines += validation_section(rel)
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="read and write results/quick/")
    args = p.parse_args(argv)
    folder = RESULTS / "quick" if args.quick else RESULTS
    if args.quick:
        (folder / "benchmarks.md").write_text(summary(folder, "."))
    else:
        doc = ROOT / "docs" / "benchmarks.md"
        doc.parent.mkdir(exist_ok=True)
        doc.write_text(summary(folder, "../benchmarks/results"))
    print(f"charts in {folder}")


if __name__ == "__main__":
    main()
