"""What both renderer scripts share: seeds, EXR writing, value-noise textures, manifests, the READY list.

Runs inside the renderers' own virtual environments (numpy + OpenEXR only, no torch, no torchmanifold).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import OpenEXR

FRAMES = 8
WIDTH = HEIGHT = 128

# Passes of one clip, each with its own block of seeds (see ``seed``).
PASSES = {"noisy1": 1, "noisy4": 2, "reference": 3, "ref_b": 4, "mask": 5, "iteration": 6}

#: the iterations ``--iterations`` writes as ``iter{n}_XXXX.exr``: what the renderer holds after n samples per
#: pixel added one per iteration (iteration 1 is ``frame_``)
ITERATION_LEVELS = (2, 4, 8, 16)


def seed(clip_id: int, pass_name: str, frame: int, chunk: int = 0) -> int:
    """A new seed per clip, pass, frame and reference chunk; fits an int32 (Blender's ``cycles.seed``)."""
    if not (0 <= chunk < 100 and 0 <= frame < 100):
        raise ValueError(f"seed: frame {frame} and chunk {chunk} must be in [0, 100)")
    return clip_id * 100_000 + PASSES[pass_name] * 10_000 + frame * 100 + chunk


def write_exr(path: Path, channels: dict, half: tuple = (), header: dict | None = None) -> None:
    """Write one-part scanline EXR, ZIP-compressed; channel names in ``half`` are stored as float16.

    Args:
        channels: name -> (H, W) array.
        half: names stored as half floats (features); the rest float32.
    """
    out = {}
    for name, a in channels.items():
        a = np.ascontiguousarray(a, dtype=np.float16 if name in half else np.float32)
        out[name] = a
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})}
    path = Path(path)
    tmp = path.with_name(path.stem + ".tmp.exr")
    with OpenEXR.File(hdr, out) as f:
        f.write(str(tmp))
    tmp.replace(path)


def read_rgb(path: Path, prefix: str = "") -> np.ndarray:
    """(H, W, 3) float64 of channels ``<prefix>R/G/B`` from any part of an EXR (Blender writes one part a pass)."""
    f = OpenEXR.File(str(path), separate_channels=True)
    for part in f.parts:
        ch = part.channels
        if all(prefix + c in ch for c in "RGB"):
            return np.stack([ch[prefix + c].pixels for c in "RGB"], -1).astype(np.float64)
    raise KeyError(f"{path}: no channels {prefix}R/G/B in any part")


def read_channel(path: Path, name: str) -> np.ndarray:
    """(H, W) float64 of one channel from whichever part of an EXR holds it."""
    for part in OpenEXR.File(str(path), separate_channels=True).parts:
        if name in part.channels:
            return part.channels[name].pixels.astype(np.float64)
    raise KeyError(f"{path}: no channel {name!r} in any part")


def read_all(path: Path) -> dict:
    """name -> (H, W) float64 of every channel of every part of an EXR."""
    out = {}
    for part in OpenEXR.File(str(path), separate_channels=True).parts:
        for name, ch in part.channels.items():
            out[name] = ch.pixels.astype(np.float64)
    return out


def clip_frames(clip_dir: Path) -> int:
    """The frame count a rendered clip was made with (its manifest's): the scenes move over the whole clip, so
    a frame is the same scene only within the same count."""
    manifest = Path(clip_dir) / "manifest.json"
    if not manifest.exists():
        raise FileNotFoundError(f"{manifest}: render the clip first (without --iterations)")
    return int(json.loads(manifest.read_text())["frames"])


def value_noise(h: int, w: int, octaves: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w) fractal value noise in [0, 1]: a procedural texture made here, no downloaded asset."""
    acc = np.zeros((h, w))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = 4 * 2**o
        grid = rng.random((n + 1, n + 1))
        y = np.linspace(0, n, h, endpoint=False)
        x = np.linspace(0, n, w, endpoint=False)
        y0, x0 = y.astype(int), x.astype(int)
        fy, fx = (y - y0)[:, None], (x - x0)[None, :]
        fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)  # smoothstep between lattice values
        a = grid[y0][:, x0] * (1 - fx) + grid[y0][:, x0 + 1] * fx
        b = grid[y0 + 1][:, x0] * (1 - fx) + grid[y0 + 1][:, x0 + 1] * fx
        acc += amp * (a * (1 - fy) + b * fy)
        total += amp
        amp *= 0.5
    return acc / total


def host() -> dict:
    return {"machine": platform.machine(), "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "nice": os.nice(0)}


def ref_b_entry(ref_b_frame: int | None) -> dict | None:
    """The manifest's ``ref_b`` entry: the frame with a second, independent reference (None: no such frame)."""
    if ref_b_frame is None:
        return None
    return {"frame": ref_b_frame, "file": f"ref_b_{ref_b_frame:04d}.exr",
            "note": "second reference of one frame with independent seeds: its PSNR against reference_ caps what any "
                    "method can score"}


def ref_b_files(ref_b_frame: int | None) -> dict:
    """The manifest's ``files`` entry for the second reference (empty without one)."""
    return {} if ref_b_frame is None else {"ref_b_XXXX.exr": "a second independent reference of that frame"}


def write_manifest(out_dir: Path, manifest: dict) -> None:
    (Path(out_dir) / "manifest.json").write_text(json.dumps(manifest, indent=1))


def mark_ready(out_dir: Path) -> None:
    """Append the finished clip's folder to ``<root>/READY`` (one line per clip)."""
    out_dir = Path(out_dir)
    with open(out_dir.parent / "READY", "a") as f:
        f.write(f"{out_dir.name}\t{out_dir}\t{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}\n")


class Timer:
    """Wall and CPU seconds (all threads of this process) per named pass, recorded in the manifest: on a shared
    machine the wall time says more about the other users than about the renderer."""

    def __init__(self):
        self.secs: dict = {}
        self.cpu: dict = {}
        self._cpu0 = time.process_time()

    def add(self, name: str, t0: float) -> None:
        self.secs[name] = round(self.secs.get(name, 0.0) + time.perf_counter() - t0, 2)
        now = time.process_time()
        self.cpu[name] = round(self.cpu.get(name, 0.0) + now - self._cpu0, 2)
        self._cpu0 = now


def _size(v: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in v.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 256x256, got {v!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"expected a size of at least 8x8, got {v!r}")
    return w, h


def clip_main(description: str, clips, render_clip, argv=None, render_iterations=None) -> None:
    """A renderer script's command line: render the named clips (default all of ``clips``) with
    ``render_clip(name, out_root, frames, ref_spp, renderer_defaults=..., size=..., position=...) -> clip
    folder`` and list each finished one in READY; with ``--iterations N``, only ``render_iterations(name,
    out_root, frames, N) -> clip folder`` on clips already rendered."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("clips", nargs="*", default=list(clips), help=f"clips to render (default all: {list(clips)})")
    ap.add_argument("--out", type=Path, default=Path("/work/valdata"))
    ap.add_argument("--frames", type=int, default=FRAMES)
    ap.add_argument("--ref-spp", type=int, default=None, help="reference spp (default per clip, see CLIPS)")
    ap.add_argument("--no-ready", action="store_true", help="do not append to <out>/READY")
    ap.add_argument("--renderer-defaults", action="store_true",
                    help="the renderer's own pixel filter and clamping (Mitsuba: gaussian; Cycles: Blackman-Harris "
                         "1.5 px, indirect clamp 10), as a new user's renders have them, instead of the set's box "
                         "filter without clamping (a probe of the denoiser, not part of the set)")
    ap.add_argument("--size", type=_size, default=None, metavar="WxH",
                    help="render at WxH instead of the clip's own size (a probe at another resolution, e.g. "
                         "the 256x256 of the clips the denoiser is scored on outside this set)")
    ap.add_argument("--position", action="store_true",
                    help="Blender: also write the Position pass (world positions, which the denoiser reads "
                         "for the window albedo and for defocus; off in the set, which is at its 60 MB "
                         "budget). Mitsuba's clips always carry them")
    ap.add_argument("--iterations", type=int, default=0, metavar="N",
                    help="render only the progressive loop of clips already rendered in --out: what "
                         "the renderer holds after n samples per pixel, added one per iteration from "
                         f"frame_XXXX.exr, as iter<n>_XXXX.exr for n in {ITERATION_LEVELS} up to N (Mitsuba: "
                         "the mean of n independent 1-spp passes; Cycles: n samples of the frame's own "
                         "sequence); no reference, nothing else rewritten")
    args = ap.parse_args(argv)
    for name in args.clips:
        if name not in clips:
            ap.error(f"unknown clip {name!r}; known: {list(clips)}")
    for name in args.clips:
        if args.iterations:
            print(f"{name}: {render_iterations(name, args.out, args.frames, args.iterations)}")
            continue
        out = render_clip(name, args.out, args.frames, args.ref_spp, renderer_defaults=args.renderer_defaults,
                          size=args.size, position=args.position)
        if not args.no_ready:
            mark_ready(out)
        print(f"{name}: {out}")
