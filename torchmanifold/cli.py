"""Command line: ``torchmanifold render`` (the main job) and ``torchmanifold denoise FRAME.exr ... --out DIR``.

A thin layer over :func:`torchmanifold.pipeline.render_job.render_job` and
:func:`torchmanifold.pipeline.denoise_files.denoise_files`; errors in the input end the program with exit code 2 and a
one-line message naming the file and channel.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

from torchmanifold._checks import MAX_TREE_HEIGHT, check_int, check_tree_height
from torchmanifold._threads import set_threads

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


def _add_filter_args(p: argparse.ArgumentParser, temporal_radius: int, mode: str, tree_height: int,
                     selection_softness: float | None = None, evidence_radius: int | None = None,
                     frame_alone_bandwidths: Sequence[float] | None = None) -> None:
    from torchmanifold.pipeline.denoise import DenoiseSettings

    d = DenoiseSettings()
    g = p.add_argument_group("filter")
    g.add_argument("--sigma-s", type=float, default=d.sigma_s,
                   help="reference spatial sigma in pixels from 1 spp, the unit of --bandwidths; denoise "
                        "scales it by spp^-1/4 (%(default)s)")
    g.add_argument("--bandwidths", type=float, nargs="+", default=list(d.bandwidths), metavar="FACTOR",
                   help="spatial sigmas blended per pixel by their cross-validated error, as multiples of "
                        "--sigma-s; one value filters at that bandwidth alone (%(default)s)")
    g.add_argument("--selection-softness", type=float,
                   default=d.selection_softness if selection_softness is None else selection_softness,
                   help="how sure the evidence must be before a bandwidth is left out at a pixel, in "
                        "standard errors; 0 keeps the least-error bandwidth alone (%(default)s)")
    g.add_argument("--tree-height", type=int, default=tree_height,
                   help="manifold tree height at the base bandwidth, one level more per doubling of a "
                        "wider one (1 to %d; default %%(default)s)" % MAX_TREE_HEIGHT)
    g.add_argument("--guide", nargs="+", default=None, metavar="CHANNEL",
                   help="feature channels that guide the filter (default: albedo, normals, position or depth)")
    g.add_argument("--guide-sigma", action="append", metavar="NAME=SIGMA",
                   help="range sigma of one guide channel, e.g. --guide-sigma Z=0.3 (repeatable)")
    g.add_argument("--firefly", choices=["clamp", "log", "none"], default=d.firefly,
                   help="firefly treatment (%(default)s)")
    g.add_argument("--firefly-k", type=float, default=d.firefly_k, help="clamp at k x the pilot (%(default)s)")
    g.add_argument("--no-demodulate", action="store_true", help="filter colour, not colour / albedo")
    g.add_argument("--filter-sky", action="store_true",
                   help="filter pixels whose camera ray left the scene too (by default they keep their "
                        "samples unless their colour is noise, as in fog)")
    g.add_argument("--temporal-radius", type=int, default=temporal_radius,
                   help="neighbour frames on each side (%(default)s)")
    g.add_argument("--albedo-radius", type=int, default=d.albedo_radius,
                   help="with a time window and world positions, the frames on each side whose samples of a "
                        "pixel's albedo join it (%(default)s)")
    g.add_argument("--evidence-radius", type=int,
                   default=d.evidence_radius if evidence_radius is None else evidence_radius,
                   help="with a time window, the frames on each side whose queries lend their "
                        "cross-validated errors to a frame's bandwidth selection (%(default)s)")
    alone = "the bandwidths under 1" if frame_alone_bandwidths is None else \
        list(frame_alone_bandwidths) or "none"
    g.add_argument("--frame-alone", type=float, nargs="*", metavar="FACTOR",
                   default=None if frame_alone_bandwidths is None else list(frame_alone_bandwidths),
                   help="with a time window, bandwidths (multiples of --sigma-s) at which each frame is also "
                        f"filtered alone, blended with the window's; no value: none (default: {alone})")
    g.add_argument("--sigma-t", type=float, default=d.sigma_t, help="temporal sigma in frames (%(default)s)")
    g.add_argument("--no-align", action="store_true",
                   help="leave the time window's frames where they are instead of bringing them to each "
                        "frame's pixels where the view moves (faster, by the flow search between every two "
                        "frames; less accurate where the camera pans: docs/benchmarks.md's trade-off table)")
    g.add_argument("--mode", choices=["window", "spacetime"], default=mode,
                   help="time window: average then filter, or joint space-time (%(default)s)")


def _settings(a):
    from torchmanifold.pipeline.denoise import DenoiseSettings

    return DenoiseSettings(sigma_s=a.sigma_s, bandwidths=tuple(a.bandwidths),
                           selection_softness=a.selection_softness, tree_height=a.tree_height, guide=a.guide,
                           guide_sigmas=_guide_sigmas(a.guide_sigma), firefly=a.firefly, firefly_k=a.firefly_k,
                           demodulate=not a.no_demodulate, keep_sky=not a.filter_sky,
                           temporal_radius=a.temporal_radius, albedo_radius=a.albedo_radius,
                           evidence_radius=a.evidence_radius,
                           frame_alone_bandwidths=None if a.frame_alone is None else tuple(a.frame_alone),
                           sigma_t=a.sigma_t, mode=a.mode, align_frames=not a.no_align).check()


def _add_threads_arg(p: argparse.ArgumentParser) -> None:
    # Every core this process may run on. Two threads used to be 4-10x slower than one: OpenMP workers
    # spun after each of the pipeline's many small ops; torchmanifold/__init__.py makes them sleep.
    p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)),
                   help="cores to use: torch threads for filtering, and the path tracer's llvmpipe threads "
                        "unless LP_NUM_THREADS is set (default: every core, %(default)s here)")


def _chunk_size(v: str) -> int:
    try:
        n = int(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer number of frames >= 1, got {v!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected an integer number of frames >= 1, got {v!r}")
    return n


def _add_engine_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("cluster (docs/sharding.md)")
    g.add_argument("--engine", choices=["local", "ray"], default="local",
                   help="local: one process (%(default)s); ray: frame chunks on a Ray cluster")
    g.add_argument("--address", default=None, help="Ray cluster HOST:PORT (default: a local cluster)")
    g.add_argument("--chunk", type=_chunk_size, default=None, help="frames per Ray task (default: from the "
                   "temporal window and the number of workers)")


def _main_sharded(args) -> int:
    """``--engine ray``: the frame-chunk path (:mod:`torchmanifold.pipeline.shards`); prints its JSON."""
    from torchmanifold.pipeline import shards

    common = dict(overwrite=args.overwrite, progress=not args.quiet, chunk=args.chunk, address=args.address,
                  threads=args.threads)
    try:
        if args.command == "render":
            res = shards.shard_render(args.out, scene=args.scene, frames=args.frames, iterations=args.iterations,
                                      width=args.width, height=args.height, seed=args.seed,
                                      reference_spp=args.reference_spp, settings=_settings(args),
                                      alpha=args.alpha, inbetween=args.inbetween, scheme=args.scheme, **common)
        else:
            res = shards.shard_denoise(args.frames, args.out, settings=_settings(args), color_channels=args.color,
                                       feature_channels=args.features, layer=args.layer,
                                       output_layout=args.output_layout, samples_per_pixel=args.spp, **common)
    except (FileNotFoundError, FileExistsError, ValueError, TypeError, ImportError, ConnectionError) as exc:
        print(f"torchmanifold {args.command}: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: v for k, v in res.items() if k != "outputs"}))
    return 0


def _reuse_freed_memory() -> None:
    """Let glibc keep freed blocks for reuse instead of returning them to the system: each frame step
    allocates and frees the same few-MB tensors, and fresh pages cost page faults (the +-1 space-time
    `denoise` of the shared clip: 0.35 -> 0.31 s per frame, three interleaved runs). Process-wide, so
    only the command line sets it; without glibc it does nothing."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3
    mallopt(m_mmap_threshold, 64 << 20)  # blocks under 64 MB come from the reusable heap
    mallopt(m_trim_threshold, 256 << 20)  # up to 256 MB of free heap stays mapped
    mallopt(m_top_pad, 64 << 20)


def build_parser() -> argparse.ArgumentParser:
    from torchmanifold.pipeline.denoise_files import COMMAND_FILTER, OUTPUT_LAYOUTS
    from torchmanifold.pipeline.render_job import RENDER_DEFAULTS
    from torchmanifold.pipeline.schedule import DEFAULT_ALPHA
    from torchmanifold.pipeline.progressive import PROGRESSIVE_FILTER, SCHEMES

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
                   help="bandwidth shrink: sigma_{i+1}^2/sigma_i^2 = (i+alpha)/(i+1) (%(default)s)")
    r.add_argument("--inbetween", type=int, default=0, help="extra frames between rendered frames (%(default)s)")
    r.add_argument("--scheme", choices=SCHEMES, default="accumulate",
                   help="filter the running mean of the samples (accumulate) or average filtered 1-spp "
                        "iterations, the paper's scheme (%(default)s)")
    r.add_argument("--fps", type=float, default=8.0, help="MP4 frame rate (%(default)s)")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--overwrite", action="store_true", help="reuse a non-empty --out")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_threads_arg(r)
    _add_filter_args(r, **PROGRESSIVE_FILTER)
    _add_engine_args(r)

    d = sub.add_parser("denoise", help="denoise EXR frames rendered elsewhere",
                       description="Denoise one multi-channel EXR per frame: colour R,G,B plus feature "
                                   "channels such as albedo.R/G/B, N.X/Y/Z, Z, P.X/Y/Z (ours, Mitsuba's), or "
                                   "Blender's multilayer ViewLayer.Combined with its Denoising Albedo/Normal/Depth, "
                                   "Normal and Depth passes (single- or multi-part). Writes the filtered colour "
                                   "under the input file names in --out.")
    d.add_argument("frames", nargs="+", help="EXR frames in frame order")
    d.add_argument("--out", required=True, help="output folder")
    d.add_argument("--overwrite", action="store_true", help="reuse a non-empty --out")
    d.add_argument("--color", nargs=3, default=None, metavar="CH",
                   help="colour channels (default: R G B, or Blender's <layer>.Combined.R/G/B)")
    d.add_argument("--features", nargs="+", default=None, metavar="CH",
                   help="feature channels to read, by any name (albedo.R, Mr, Denoising Albedo.R, ...; "
                        "default: the known ones the first file has)")
    d.add_argument("--layer", default=None, help="Blender view layer to read (needed when a file has several)")
    d.add_argument("--output-layout", choices=OUTPUT_LAYOUTS, default="input",
                   help="input: colour under the channels it was read from (Blender: <layer>.Combined); "
                        "plain: R,G,B (%(default)s)")
    d.add_argument("--spp", type=int, default=None, metavar="N",
                   help="samples per pixel of the frames, where their header does not say (it sets the "
                        "bandwidth and the footprint width; default: the header's, else the count the "
                        "features show)")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_threads_arg(d)
    # denoise filters each frame once and can afford one more level: against the brute-force filter
    # H=3 gives 33-37 dB where H=2 gives 29-37 (docs/adaptive-manifolds.md, "Accuracy")
    _add_filter_args(d, temporal_radius=COMMAND_FILTER["temporal_radius"], mode="spacetime", tree_height=3)
    _add_engine_args(d)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        # options whose range argparse does not know; the rest are checked where they are used
        check_int("--threads", args.threads, min=1)
        check_tree_height(args.tree_height, name="--tree-height")
        set_threads(args.threads)
        _reuse_freed_memory()
        if args.engine == "ray":
            return _main_sharded(args)
        if args.address is not None or args.chunk is not None:
            raise ValueError("--address and --chunk need --engine ray")
        if args.command == "render":
            from torchmanifold.pipeline.render_job import render_job

            res = render_job(args.out, scene=args.scene, frames=args.frames, iterations=args.iterations,
                             width=args.width, height=args.height, seed=args.seed,
                             reference_spp=args.reference_spp, overwrite=args.overwrite,
                             settings=_settings(args), alpha=args.alpha, inbetween=args.inbetween,
                             fps=args.fps, progress=not args.quiet, scheme=args.scheme)
            if "final" in res:
                f = res["final"]
                print(f"after {args.iterations} iterations (PSNR dB): raw {f['raw']['psnr']:.2f}  "
                      f"gaussian {f['gaussian']['psnr']:.2f}  ours {f['ours']['psnr']:.2f}; plain path tracing "
                      f"needs at least ~{res['spp_plain_to_match_ours_final']:.0f} spp to match ours (MSE ~ 1/spp "
                      "extrapolated from the raw curve: a lower bound; benchmarks/bench_progressive_schemes.py "
                      "measures it)")
            print(f"wrote {args.out}")
        else:
            from torchmanifold.pipeline.denoise_files import denoise_files

            res = denoise_files(args.frames, args.out, settings=_settings(args), color_channels=args.color,
                                feature_channels=args.features, overwrite=args.overwrite,
                                progress=not args.quiet, layer=args.layer, output_layout=args.output_layout,
                                samples_per_pixel=args.spp)
            if res["nonfinite_samples"]:
                print(f"warning: {res['nonfinite_samples']} non-finite samples (colour {res['nonfinite_color']}, "
                      f"features {res['nonfinite_features']}) were kept out of the filter", file=sys.stderr)
            for note in res["notes"]:
                print(f"note: {note}", file=sys.stderr)
            print(json.dumps({k: v for k, v in res.items() if k != "outputs"}))
    except (FileNotFoundError, FileExistsError, ValueError, TypeError) as exc:
        print(f"torchmanifold {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
