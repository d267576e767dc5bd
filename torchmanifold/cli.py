"""Command line: ``torchmanifold render`` (the main job) and ``torchmanifold denoise FRAME.exr ... --out DIR``.

A thin layer over :func:`torchmanifold.pipeline.job.render_job` and
:func:`torchmanifold.pipeline.job.denoise_files`; errors in the input end the program with exit code 2 and a
one-line message naming the file and channel.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import torch

__all__ = ["main", "build_parser"]


def _guide_sigmas(items):
    out = {}
    for it in items or []:
        name, sep, val = it.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"--guide-sigma expects NAME=SIGMA, got {it!r}")
        try:
            out[name] = float(val)
        except ValueError:
            raise argparse.ArgumentTypeError(f"--guide-sigma {it!r}: {val!r} is not a number") from None
    return out


def _add_filter_args(p: argparse.ArgumentParser, temporal_radius: int, mode: str) -> None:
    from torchmanifold.pipeline.denoise import DenoiseSettings

    d = DenoiseSettings()
    g = p.add_argument_group("filter")
    g.add_argument("--sigma-s", type=float, default=d.sigma_s, help="spatial sigma in pixels (%(default)s)")
    g.add_argument("--tree-height", type=int, default=None, help="manifold tree height (default: %s)" % d.tree_height)
    g.add_argument("--guide", nargs="+", default=None, metavar="CHANNEL",
                   help="feature channels that guide the filter (default: albedo, normals, position or depth)")
    g.add_argument("--guide-sigma", action="append", metavar="NAME=SIGMA",
                   help="range sigma of one guide channel, e.g. --guide-sigma Z=0.3 (repeatable)")
    g.add_argument("--firefly", choices=["clamp", "log", "none"], default=d.firefly,
                   help="firefly treatment (%(default)s)")
    g.add_argument("--firefly-k", type=float, default=d.firefly_k, help="clamp at k x the pilot (%(default)s)")
    g.add_argument("--no-demodulate", action="store_true", help="filter colour, not colour / albedo")
    g.add_argument("--temporal-radius", type=int, default=temporal_radius,
                   help="neighbour frames on each side (%(default)s)")
    g.add_argument("--sigma-t", type=float, default=d.sigma_t, help="temporal sigma in frames (%(default)s)")
    g.add_argument("--mode", choices=["window", "spacetime"], default=mode,
                   help="time window: average then filter, or joint space-time (%(default)s)")


def _settings(a, default_height: int):
    from torchmanifold.pipeline.denoise import DenoiseSettings

    return DenoiseSettings(sigma_s=a.sigma_s, tree_height=a.tree_height or default_height, guide=a.guide,
                           guide_sigmas=_guide_sigmas(a.guide_sigma), firefly=a.firefly, firefly_k=a.firefly_k,
                           demodulate=not a.no_demodulate, temporal_radius=a.temporal_radius,
                           sigma_t=a.sigma_t, mode=a.mode).check()


def _add_threads_arg(p: argparse.ArgumentParser) -> None:
    # Every core this process may run on. Two threads used to be 4-10x slower than one: OpenMP workers
    # spun after each of the pipeline's many small ops; torchmanifold/__init__.py makes them sleep.
    p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)),
                   help="torch threads for filtering (default: every core, %(default)s here)")


def build_parser() -> argparse.ArgumentParser:
    from torchmanifold.pipeline.job import RENDER_DEFAULTS
    from torchmanifold.pipeline.schedule import DEFAULT_ALPHA

    p = argparse.ArgumentParser(prog="torchmanifold", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="path-trace a clip progressively, filter it, measure it, write video",
                       description="Render a clip at 1 sample per pixel per iteration, filter every frame "
                                   "with its neighbours in time, and write frames, MP4s, metrics.json and a "
                                   "chart of error vs iteration / wall time (raw, Gaussian, ours).")
    r.add_argument("--scene", default=None, help="scene file (.toml); default: the built-in Cornell box")
    r.add_argument("--frames", type=int, default=RENDER_DEFAULTS["frames"], help="frames (%(default)s)")
    r.add_argument("--iterations", type=int, default=RENDER_DEFAULTS["iterations"],
                   help="progressive iterations = spp per frame (%(default)s)")
    r.add_argument("--width", type=int, default=RENDER_DEFAULTS["width"], help="(%(default)s)")
    r.add_argument("--height", type=int, default=RENDER_DEFAULTS["height"], help="(%(default)s)")
    r.add_argument("--seed", type=int, default=RENDER_DEFAULTS["seed"], help="(%(default)s)")
    r.add_argument("--reference-spp", type=int, default=RENDER_DEFAULTS["reference_spp"],
                   help="spp of the converged reference the errors are measured against; 0 = none (%(default)s)")
    r.add_argument("--alpha", type=float, default=DEFAULT_ALPHA,
                   help="bandwidth shrink: sigma_{i+1}^2/sigma_i^2 = (i+a)/(i+1) (%(default)s)")
    r.add_argument("--inbetween", type=int, default=0, help="extra frames between rendered frames (%(default)s)")
    r.add_argument("--fps", type=float, default=8.0, help="MP4 frame rate (%(default)s)")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--overwrite", action="store_true", help="reuse a non-empty --out")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_threads_arg(r)
    _add_filter_args(r, temporal_radius=1, mode="spacetime")

    d = sub.add_parser("denoise", help="denoise EXR frames rendered elsewhere",
                       description="Denoise one multi-channel EXR per frame (colour R,G,B plus feature "
                                   "channels such as albedo.R/G/B, N.X/Y/Z, Z, P.X/Y/Z); writes the filtered "
                                   "R,G,B under the input file names in --out.")
    d.add_argument("frames", nargs="+", help="EXR frames in frame order")
    d.add_argument("--out", required=True, help="output folder")
    d.add_argument("--overwrite", action="store_true", help="reuse a non-empty --out")
    d.add_argument("--color", nargs=3, default=["R", "G", "B"], metavar="CH", help="colour channels (R G B)")
    d.add_argument("--features", nargs="+", default=None, metavar="CH",
                   help="feature channels to read (default: the known ones each file has)")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_threads_arg(d)
    _add_filter_args(d, temporal_radius=1, mode="spacetime")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.threads < 1:
        print(f"torchmanifold {args.command}: error: --threads must be >= 1, got {args.threads}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    try:
        if args.command == "render":
            from torchmanifold.pipeline.job import render_job

            res = render_job(args.out, scene=args.scene, frames=args.frames, iterations=args.iterations,
                             width=args.width, height=args.height, seed=args.seed,
                             reference_spp=args.reference_spp, overwrite=args.overwrite,
                             settings=_settings(args, 2), alpha=args.alpha, inbetween=args.inbetween,
                             fps=args.fps, progress=not args.quiet)
            if "final" in res:
                f = res["final"]
                print(f"after {args.iterations} iterations (PSNR dB): raw {f['raw']['psnr']:.2f}  "
                      f"gaussian {f['gaussian']['psnr']:.2f}  ours {f['ours']['psnr']:.2f}; plain path tracing "
                      f"needs ~{res['spp_plain_to_match_ours_final']:.0f} spp to match ours")
            print(f"wrote {args.out}")
        else:
            from torchmanifold.pipeline.job import denoise_files

            res = denoise_files(args.frames, args.out, settings=_settings(args, 3), color_channels=args.color,
                                feature_channels=args.features, overwrite=args.overwrite,
                                progress=not args.quiet)
            if res["nonfinite_samples"]:
                print(f"warning: {res['nonfinite_samples']} non-finite samples (colour {res['nonfinite_color']}, "
                      f"features {res['nonfinite_features']}) were kept out of the filter", file=sys.stderr)
            print(json.dumps({k: v for k, v in res.items() if k != "outputs"}))
    except (FileNotFoundError, FileExistsError, ValueError, TypeError) as exc:
        print(f"torchmanifold {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
