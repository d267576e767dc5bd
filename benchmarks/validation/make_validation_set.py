"""Regenerate the whole validation set with one command: every Mitsuba 3 and Blender Cycles clip, then (optionally)
the compact copy committed under ``benchmarks/validation/data``.

    python benchmarks/validation/make_validation_set.py                       # render all clips into /work/valdata
    python benchmarks/validation/make_validation_set.py --only mi_glass_mirror bl_env_thin
    python benchmarks/validation/make_validation_set.py --copy-to benchmarks/validation/data   # after rendering

Each renderer runs in its own virtual environment (see ``benchmarks/requirements-validation.txt``): Mitsuba's
(``--mitsuba-python``, with ``DRJIT_LIBLLVM_PATH`` set for the LLVM variant where libLLVM 19 is installed) and
bpy's (``--blender-python``, Python 3.11). Both get ``nice -n 10``: the machines here are shared. Seeds are fixed
(``_common.seed``), so a rerun gives the same images up to the renderers' own thread scheduling.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from tqdm import tqdm

HERE = Path(__file__).resolve().parent
MITSUBA_CLIPS = ("mi_ceiling_light", "mi_glass_mirror", "mi_env_thin", "mi_indirect_dof", "mi_dark_glossy",
                 "mi_still_textures")
BLENDER_CLIPS = ("bl_glass_caustic", "bl_moving_metal", "bl_env_thin", "bl_indirect_dof", "bl_motion_blur")
LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"  # what Debian 12's libllvm19 package installs


def render(clip: str, args) -> float:
    """Render one clip in its renderer's venv; returns wall seconds."""
    mitsuba = clip in MITSUBA_CLIPS
    script = HERE / ("render_mitsuba.py" if mitsuba else "render_blender.py")
    python = args.mitsuba_python if mitsuba else args.blender_python
    env = dict(os.environ)
    if mitsuba and "DRJIT_LIBLLVM_PATH" not in env and Path(LLVM).exists():
        env["DRJIT_LIBLLVM_PATH"] = LLVM
    cmd = ["nice", "-n", "10", str(python), str(script), clip, "--out", str(args.out), "--frames", str(args.frames)]
    if args.ref_spp:
        cmd += ["--ref-spp", str(args.ref_spp)]
    t0 = time.perf_counter()
    log = args.out / f"{clip}.log"
    with open(log, "w") as f:
        rc = subprocess.run(cmd, env=env, stdout=f, stderr=subprocess.STDOUT).returncode
    if rc:
        raise RuntimeError(f"{clip}: {script.name} exited with {rc}; see {log}")
    return time.perf_counter() - t0


def copy_clip(src: Path, dst: Path) -> int:
    """Copy one rendered clip (EXRs are already ZIP-compressed with half features) into the repository; bytes."""
    dst.mkdir(parents=True, exist_ok=True)
    total = 0
    for p in sorted(src.iterdir()):
        if p.suffix in (".exr", ".json"):
            shutil.copy2(p, dst / p.name)
            total += p.stat().st_size
    return total


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="+", default=None, help="clips to render (default: all)")
    ap.add_argument("--out", type=Path, default=Path("/work/valdata"), help="render root (outside git)")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--ref-spp", type=int, default=None, help="override every clip's reference spp")
    ap.add_argument("--mitsuba-python", default="/work/venvs/mitsuba/bin/python")
    ap.add_argument("--blender-python", default="/work/venvs/bpy/bin/python")
    ap.add_argument("--copy-to", type=Path, default=None,
                    help="after rendering, copy the clips here (e.g. benchmarks/validation/data)")
    ap.add_argument("--max-mb", type=float, default=60.0, help="refuse a copy larger than this")
    ap.add_argument("--skip-render", action="store_true", help="only copy what is already rendered")
    args = ap.parse_args(argv)
    clips = args.only or list(MITSUBA_CLIPS + BLENDER_CLIPS)
    unknown = [c for c in clips if c not in MITSUBA_CLIPS + BLENDER_CLIPS]
    if unknown:
        ap.error(f"unknown clips {unknown}; known: {list(MITSUBA_CLIPS + BLENDER_CLIPS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.skip_render:
        for clip in tqdm(clips, desc="clips", unit="clip"):
            secs = render(clip, args)
            tqdm.write(f"{clip}: {secs:.0f} s -> {args.out / clip}")
    if args.copy_to is not None:
        sizes = {c: sum(p.stat().st_size for p in (args.out / c).iterdir() if p.suffix in (".exr", ".json"))
                 for c in clips}
        mb = sum(sizes.values()) / 1e6  # decimal megabytes, as the issue counts them
        if mb > args.max_mb:
            sys.exit(f"the clips take {mb:.1f} MB, over --max-mb {args.max_mb}: not copied")
        for c in clips:
            copy_clip(args.out / c, args.copy_to / c)
        print(f"copied {len(clips)} clips, {mb:.1f} MB, to {args.copy_to}")


if __name__ == "__main__":
    main()
