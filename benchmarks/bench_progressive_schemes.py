"""The progressive loop's two schemes against each other on the built-in scene, same run, same samples.

``accumulate`` filters the running mean of each frame's samples at the shrinking bandwidth; ``average``
is the paper's literal scheme (the running average of independently filtered 1-spp iterations). Each runs
the render job with ``--seeds`` loop seeds (the schemes share each seed's samples), each job scored against
its own 512-spp reference; the equal-error spp of plain path tracing says what the mean PSNR is worth
(issue 15's targets: >= 100 spp after 10 iterations, light rings within 5% of the reference's energy,
caustics within 10%, never worse than raw inside the moving objects' mask; the regions are the validation
scorer's, ``validation/score.py``): plain path tracing is rendered at 16 to 256 spp (its own seed) and
scored against the first seed's reference, and the equal-error spp is read off that measured curve (log-log
interpolation), not extrapolated: on this scene clamped-sRGB error falls more slowly than 1/spp (about 2 dB
per doubling between 32 and 128 spp, not 3), so extrapolating from 10 spp undercounts by about 3x. The
caustic under the glass ball is a few dozen pixels lit by a few samples each at 10 spp: one seed's energy
ratio swings by more than the 10% the issue allows (0.69-1.14 for ours, 0.67-1.32 for raw over 32), so
the figures are means over seeds with their standard errors and ranges. Writes
``results/progressive_schemes.json`` and ``.png``.

    .venv/bin/python benchmarks/bench_progressive_schemes.py [--size 96 --frames 4 --iterations 10 --seeds 32]
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


#: plain path tracing renders the equal-error spp is read from
PLAIN_SPP = (16, 32, 64, 128, 256)


def equal_error_spp(plain: dict, psnr: float):
    """The spp at which plain path tracing's measured PSNR curve reaches ``psnr`` (log-log interpolation
    between the bracketing renders); ``"<16"`` or ``">256"`` outside the measured range."""
    pts = sorted(plain.items())
    if psnr <= pts[0][1]:
        return f"<{pts[0][0]}"
    for (n0, p0), (n1, p1) in zip(pts, pts[1:]):
        if p0 < psnr <= p1:
            return round(n0 * (n1 / n0) ** ((psnr - p0) / (p1 - p0)))
    return f">{pts[-1][0]}"


def final_energy(job_dir: Path, reference=None) -> dict:
    """Energy kept in the light rings and caustics by the job's final ``ours`` and ``raw`` frames, over the
    reference's (1 = kept), with the validation scorer's regions found on the job's reference. ``reference``
    ``(F, 3, H, W)``: measure against this one instead, rendered from other samples: a region picked where
    one reference happens to be bright holds less energy in any unbiased estimate than in that reference,
    and a caustic of a few dozen pixels is where a reference is noisiest."""
    import sys

    import torch

    sys.path.insert(0, str(Path(__file__).resolve().parent / "validation"))
    import harness
    import score

    from torchmanifold.io import read_exr

    frames = [read_exr(p) for p in sorted((job_dir / "frames").glob("frame_*.exr"))]
    stack = lambda pre: torch.stack([torch.from_numpy(np.stack([d[pre + c] for c in "RGB"])) for d in frames])
    albedo = torch.stack([torch.from_numpy(np.stack([d[f"albedo.{c}"] for c in "RGB"])) for d in frames])
    ds = harness.Dataset("built-in", stack("raw."), albedo, ("Mr", "Mg", "Mb"), stack("reference."),
                         list(range(len(frames))), {})
    # the caustic here is a sliver under the glass ball, thinner than the scorer's opening: not opened
    regions = score.energy_regions(ds, open_caustics=False)
    if reference is not None:
        ds.reference = reference.to(ds.reference.dtype)
    out = {name: score.energy_ratios(img, ds, regions) for name, img in (("ours", stack("")),
                                                                          ("raw", ds.color))}
    out["region_pixels"] = {k: int(m.sum()) for k, m in regions.items()}
    return out


#: a loop seed's distance from the next: the job's reference takes its seed + 7919
#: (``render_job.REFERENCE_SEED_OFFSET``), so no loop, reference or plain render shares a seed
SEED_STEP = 1000


def summary(values: list) -> dict:
    """Mean, its standard error over the seeds, range and count."""
    se = float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else float("nan")
    return {"mean": float(np.mean(values)), "se": se, "min": float(min(values)), "max": float(max(values)),
            "n": len(values)}


def spread(s: dict) -> str:
    return f"{s['mean']:.3f} +-{s['se']:.3f} [{s['min']:.2f}-{s['max']:.2f}]"


def main(argv=None) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from torchmanifold.pipeline.progressive import SCHEMES
    from torchmanifold.pipeline.render_job import render_job

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=96)
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--reference-spp", type=int, default=512)
    p.add_argument("--seeds", type=int, default=32,
                   help="loop seeds per scheme: one run's caustic swings by more than the issue's 10%%")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    out = {"size": a.size, "frames": a.frames, "iterations": a.iterations, "reference_spp": a.reference_spp,
           "seeds": a.seeds, "threads": a.threads, "schemes": {}}
    from torchmanifold import metrics
    from torchmanifold.pipeline.render_job import RENDER_DEFAULTS, render_query_times, render_reference
    from torchmanifold.render import PathTracer, default_scene

    seed0 = RENDER_DEFAULTS["seed"]
    tracer = PathTracer(default_scene(), a.size, a.size)
    _, query = render_query_times(a.frames, 0)
    ref, _ = render_reference(tracer, query, a.reference_spp, seed0)
    # the energies are measured against a second reference, cleaner and of samples no other render uses
    ref_energy, _ = render_reference(tracer, query, 4 * a.reference_spp, seed0 + 1)
    plain = {}
    for n in PLAIN_SPP:  # a seed the job's iterations and reference do not use
        img = tracer.render(times=query, spp=n, seed=seed0 + 31, sample_offset=0).color
        plain[n] = float(metrics.psnr(img, ref.to(img.dtype)))
    out["plain_psnr"] = plain
    for scheme in SCHEMES:
        runs = []
        for k in range(a.seeds):
            seed = seed0 + SEED_STEP * k
            with tempfile.TemporaryDirectory() as tmp:
                res = render_job(tmp, frames=a.frames, iterations=a.iterations, width=a.size, height=a.size,
                                 reference_spp=a.reference_spp, seed=seed, scheme=scheme, progress=True)
                energy = final_energy(Path(tmp), ref_energy)
            runs.append({
                "seed": seed,
                "psnr_ours": [r["ours"]["psnr"] for r in res["per_iteration"]],
                "psnr_raw": [r["raw"]["psnr"] for r in res["per_iteration"]],
                "ours_seconds": [r["ours"]["seconds"] for r in res["per_iteration"]],
                "spp_plain_to_match_final_extrapolated": res["spp_plain_to_match_ours_final"],
                "final": res["final"],
                "final_energy": energy,
            })
        final = [r["final"]["ours"]["psnr"] for r in runs]
        # a seed whose reference leaves a region under the scorer's size has no ratio for it
        regions = sorted({k for r in runs for k in r["final_energy"]["ours"]})
        energies = {f"{who}_{k}": [r["final_energy"][who][k] for r in runs if k in r["final_energy"][who]]
                    for who in ("ours", "raw") for k in regions}
        moving = {who: [r["final"][who]["psnr_moving"] for r in runs] for who in ("ours", "raw")}
        out["schemes"][scheme] = {
            "runs": runs,
            "psnr_ours_final": summary(final),
            # each run against its own job's reference, all of them of the same spp: the curve is the mean's
            "spp_plain_to_match_final": equal_error_spp(plain, float(np.mean(final))),
            "psnr_moving": {who: summary(v) for who, v in moving.items()},
            "final_energy": {k: summary(v) for k, v in energies.items()},
        }
        r = out["schemes"][scheme]
        e = r["final_energy"]
        kept = ", ".join(f"{k.removesuffix('_energy')} {spread(e['ours_' + k])} ({spread(e['raw_' + k])})"
                         for k in regions)
        print(f"{scheme}, {a.seeds} seeds, mean +-standard error [range]: after {a.iterations} iterations "
              f"ours {spread(r['psnr_ours_final'])} dB, which plain path tracing matches at "
              f"{r['spp_plain_to_match_final']} spp; energy kept by ours (raw): {kept or 'no region'}; "
              f"inside the moving mask ours {spread(r['psnr_moving']['ours'])} dB, "
              f"raw {spread(r['psnr_moving']['raw'])}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "progressive_schemes.json").write_text(json.dumps(out, indent=1))
    fig, ax = plt.subplots(figsize=(6, 4))
    it = np.arange(1, a.iterations + 1)
    for scheme, r in out["schemes"].items():
        curves = np.array([run["psnr_ours"] for run in r["runs"]])
        line, = ax.plot(it, curves.mean(0), marker="o", label=f"ours, {scheme}")
        ax.fill_between(it, curves.min(0), curves.max(0), color=line.get_color(), alpha=0.2, lw=0)
    raw = np.array([run["psnr_raw"] for run in out["schemes"][SCHEMES[0]]["runs"]]).mean(0)
    ax.plot(it, raw, "k--", label="plain path tracing")
    for n, v in plain.items():
        ax.axhline(v, color="grey", lw=0.6, ls=":")
        ax.text(a.iterations, v, f" {n} spp", va="center", fontsize=7, color="grey")
    ax.set_xlabel("iteration (= spp per frame)")
    ax.set_ylabel("PSNR (dB, clamped sRGB)")
    ax.set_title(f"built-in scene {a.size}x{a.size}, {len(query)} frames, {a.seeds} seeds (mean, range)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "progressive_schemes.png", dpi=110)
    return out


if __name__ == "__main__":
    main()
