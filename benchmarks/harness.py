"""What every benchmark shares: inputs (the Mitsuba clip, the built-in scene), guides, timing, scores, metadata.

* ``load_mitsuba(frames, crop)`` reads ``/work/shared/data/mitsuba/cbox_glossy_tex`` (another renderer's 1-spp
  frames with albedo / normal / depth, 4-spp frames, 1024-spp references).
* ``make_guide(features, names, use, sigmas)`` stacks the chosen feature groups, each divided by its sigma, so one
  ``sigma_r = 1`` applies to all of them (the guide convention of the filter op).
* The default guide is colour + depth + normal + albedo (``bench_ablation.py`` measures the alternatives).
* Filters see demodulated colour (colour / albedo, multiplied back after) when the clip has an albedo: the same
  preprocessing for every classic filter and ours; OIDN gets the raw colour with its albedo and normal.
* ``metadata()`` is stored in every results JSON: git commit, library versions, threads, CPU.
"""
from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from baselines import Clip, Method

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DATA = Path(os.environ.get("TORCHMANIFOLD_DATA", ROOT.parent / "shared" / "data")) / "mitsuba" / "cbox_glossy_tex"

# Feature groups: channel names in the tracer's vocabulary and the default sigma each is divided by (picked by a
# small sweep of ours on Mitsuba frames 2 and 8, 128x128 crop: normal 0.15 vs 0.3 +1.8 dB, albedo 0.2 vs 0.1 +0.7 dB).
GROUPS = {
    "colour": (("Lr", "Lg", "Lb"), 0.5),      # log(1 + noisy colour): the self-guided filter's guide
    "depth": (("Z",), 0.25),                  # relative to the frame's median depth
    "normal": (("Nx", "Ny", "Nz"), 0.15),
    "albedo": (("Mr", "Mg", "Mb"), 0.2),
    "reflected": (("Dx", "Dy", "Dz"), 0.3),
    "shadow": (("Sx", "Sy", "Sz"), 0.3),
    "time": (("T",), 1.0),
}
DEFAULT_FEATURES = ("colour", "depth", "normal", "albedo")
_MITSUBA_NAMES = {"albedo.R": "Mr", "albedo.G": "Mg", "albedo.B": "Mb", "N.X": "Nx", "N.Y": "Ny", "N.Z": "Nz",
                  "Z": "Z"}


# ---------------------------------------------------------------------------------------------------- inputs
class Dataset:
    """A clip to denoise: noisy colour, named features, the reference, and plain path tracing at more samples.

    color (T, 3, H, W), features (T, F, H, W) with ``names``, reference (T, 3, H, W); ``spp_frames`` maps
    spp -> ((T, 3, H, W) frames, render ms per frame or None where unknown), 1 spp included; ``emission``
    (T, 3, H, W) the part of ``color`` emitted at the first hit, where the renderer reports it.
    """

    def __init__(self, name, color, features, names, reference, times, spp_frames, emission=None,
                 samples_per_pixel=None):
        self.name, self.color, self.features, self.names = name, color, features, tuple(names)
        self.reference, self.times, self.spp_frames, self.emission = reference, times, spp_frames, emission
        self.samples_per_pixel = samples_per_pixel  # as the CLI reads it: the header's, else the features'

    @property
    def trace_ms(self) -> float:
        """Render time of one 1-spp frame (0 where the frames came from elsewhere)."""
        return self.spp_frames[1][1] or 0.0

    def feature(self, names) -> torch.Tensor:
        return self.features[:, [self.names.index(n) for n in names]]

    @property
    def albedo(self) -> Optional[torch.Tensor]:
        return self.feature(("Mr", "Mg", "Mb")) if "Mr" in self.names else None

    @property
    def normal(self) -> Optional[torch.Tensor]:
        return self.feature(("Nx", "Ny", "Nz")) if "Nx" in self.names else None

    def groups(self) -> list:
        """The feature groups this dataset has (colour always)."""
        return [g for g, (chans, _) in GROUPS.items() if g == "colour" or all(c in self.names for c in chans)]


def _stack(d: dict, keys) -> torch.Tensor:
    return torch.from_numpy(np.stack([d[k] for k in keys]).astype(np.float32))


def load_mitsuba(frames=None, crop: Optional[int] = None) -> Dataset:
    """The Mitsuba 3 clip of ``/work/shared/data`` (12 frames 256x256), optionally a subset and a centre crop."""
    from torchmanifold.io import exr
    from torchmanifold.io.frames import read_render_frame

    if not DATA.is_dir():
        raise FileNotFoundError(f"Mitsuba sample data not found at {DATA} (set TORCHMANIFOLD_DATA)")
    frames = list(range(12)) if frames is None else list(frames)
    color, feats, ref, four = [], [], [], []
    for i in frames:
        d = exr.read_exr(DATA / f"frame_{i:04d}.exr")
        color.append(_stack(d, "RGB"))
        feats.append(_stack(d, list(_MITSUBA_NAMES)))
        ref.append(_stack(exr.read_exr(DATA / f"reference_{i:04d}.exr"), "RGB"))
        four.append(_stack(exr.read_exr(DATA / f"frame4spp_{i:04d}.exr", channels=["R", "G", "B"]), "RGB"))
    out = [torch.stack(x) for x in (color, feats, ref, four)]
    if crop is not None:
        h, w = out[0].shape[-2:]
        y0, x0 = (h - crop) // 2, (w - crop) // 2
        out = [x[..., y0 : y0 + crop, x0 : x0 + crop].contiguous() for x in out]
    return Dataset("mitsuba", out[0], out[1], list(_MITSUBA_NAMES.values()), out[2],
                   torch.tensor(frames, dtype=torch.float32), {1: (out[0], None), 4: (out[3], None)},
                   samples_per_pixel=read_render_frame(DATA / f"frame_{frames[0]:04d}.exr").samples_per_pixel)


def tracer_available() -> tuple[bool, str]:
    try:
        from torchmanifold.render import PathTracer, create_context, default_scene  # noqa: F401
        return True, ""
    except Exception as exc:  # the tracer is another developer's part and may not be there yet
        return False, f"{type(exc).__name__}: {exc}"


BUILTIN_SCENES = ("cornell_box", "torus_box")  # torchmanifold/render/scenes/<name>.toml


def builtin_dataset(quick: bool, scene: str = "cornell_box") -> Dataset:
    """A built-in scene at the size every benchmark file uses (so they share the render cache)."""
    size, frames, ref_spp, more = (32, 2, 16, (2, 4)) if quick else (64, 4, 256, (2, 4, 8, 16))
    return render_builtin(size, frames, ref_spp, more, scene=scene)


def _render_key(*args) -> str:
    """Cache key: the arguments and the tracer's sources (a changed shader or scene renders again)."""
    import hashlib

    h = hashlib.sha256(repr(args).encode())
    for path in sorted((ROOT / "torchmanifold" / "render").rglob("*")):
        if path.is_file() and path.suffix in (".py", ".comp", ".glsl", ".toml"):
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def render_builtin(size: int, frames: int, ref_spp: int, more_spp=(2, 4, 8), seed: int = 0,
                   scene: str = "cornell_box") -> Dataset:
    """The tracer's built-in scene: 1-spp frames with every feature, a ``ref_spp`` reference, and plain path
    tracing at ``more_spp`` samples, each with its measured render time per frame.

    Cached in ``results/cache/`` (never committed) so the benchmark files of one run render it once."""
    key = _render_key("v2", size, frames, ref_spp, tuple(more_spp), seed, scene)  # v2: with emission
    cache = RESULTS / "cache" / f"{scene}-{key}.pt"
    if cache.exists():
        d = torch.load(cache)
        return Dataset(scene, d["color"], d["features"], d["names"], d["reference"], d["times"], d["spp"],
                       d["emission"])
    ds = _render_builtin(size, frames, ref_spp, more_spp, seed, scene)
    cache.parent.mkdir(parents=True, exist_ok=True)
    (cache.parent / ".gitignore").write_text("*\n")
    torch.save({"color": ds.color, "features": ds.features, "names": ds.names, "reference": ds.reference,
                "times": ds.times, "spp": ds.spp_frames, "emission": ds.emission}, cache)
    return ds


def _render_builtin(size, frames, ref_spp, more_spp, seed, scene) -> Dataset:
    from torchmanifold.render import PathTracer, create_context, load_scene
    from torchmanifold.render.scene import SCENES_DIR

    tracer = PathTracer(load_scene(SCENES_DIR / f"{scene}.toml"), width=size, height=size, ctx=create_context())
    times = [float(t) for t in range(frames)]
    tracer.render(times=times[:1], spp=1, seed=seed + 99)  # warm-up: shader compile, buffers
    spp_frames = {}
    for i, spp in enumerate((1, *more_spp)):
        t0 = time.perf_counter()
        res = tracer.render(times=times, spp=spp, seed=seed + i, sample_offset=0)
        spp_frames[spp] = (res.color, 1000.0 * (time.perf_counter() - t0) / frames)
        if spp == 1:
            noisy = res
    ref = tracer.render(times=times, spp=ref_spp, seed=seed + 1000, sample_offset=0)
    return Dataset(scene, noisy.color, noisy.features, noisy.feature_names, ref.color, torch.tensor(times),
                   spp_frames, noisy.emission)


# ---------------------------------------------------------------------------------------------------- guides
def make_guide(ds: Dataset, use=DEFAULT_FEATURES, sigmas: Optional[dict] = None) -> tuple[torch.Tensor, tuple]:
    """(T, D, H, W) guide of the chosen feature groups, each divided by its sigma (so sigma_r = 1 fits all)."""
    sigmas = {**{g: s for g, (_, s) in GROUPS.items()}, **(sigmas or {})}
    parts, names = [], []
    for g in use:
        chans, _ = GROUPS[g]
        if g == "colour":
            x = torch.log1p(ds.color.clamp(min=0))
        elif g == "albedo":
            x = ds.feature(chans).clamp(0, 1)  # emitters report albedo > 1
        elif g == "depth":
            z = ds.feature(chans)
            x = z / z.flatten(1).median(1).values.clamp(min=1e-6).view(-1, 1, 1, 1)  # relative depth
        else:
            x = ds.feature(chans)
        parts.append(x / sigmas[g])
        names += list(chans)
    return torch.cat(parts, 1).contiguous(), tuple(names)


def demodulate(ds: Dataset) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """(irradiance, albedo): colour / albedo where an albedo exists (the filter smooths lighting, not texture)."""
    alb = ds.albedo
    if alb is None:
        return ds.color, None
    alb = alb.clamp(min=0.02)
    return ds.color / alb, alb


def clip_for(ds: Dataset, use=DEFAULT_FEATURES, sigmas=None, demod: bool = True) -> tuple[Clip, Optional[torch.Tensor]]:
    """The Clip a method sees and the albedo to multiply back (None when not demodulated)."""
    guide, names = make_guide(ds, use, sigmas)
    values, alb = demodulate(ds) if demod else (ds.color, None)
    clip = Clip(values.contiguous(), guide, ds.times, names,
                albedo=None if ds.albedo is None else ds.albedo.clamp(0, 1), normal=ds.normal,
                features=ds.features, feature_names=ds.names, emission=ds.emission,
                samples_per_pixel=ds.samples_per_pixel)
    return clip, alb


# ---------------------------------------------------------------------------------------------------- running
def prepare(method: Method, ds: Dataset, clip: Clip, alb: Optional[torch.Tensor], sigma_s=8.0, sigma_r=1.0,
            window: int = 2):
    """``(one, finish)``: ``one(q)`` runs the method on frame q (the timed part), ``finish(q, out)`` remodulates."""
    if method.raw_input:
        # OIDN and our pipeline take the renderer's colour and do their own preprocessing.
        clip = Clip(ds.color, clip.guide, clip.times, clip.guide_names, clip.albedo, clip.normal, clip.features,
                    clip.feature_names, clip.emission, clip.samples_per_pixel)
        alb = None

    def one(q):
        if method.temporal and not method.streams:
            sub, qq = clip.window(q, window)
            return method(sub, qq, sigma_s, sigma_r)
        return method(clip, q, sigma_s, sigma_r)

    def finish(q, out):
        return (out if alb is None else out * alb[q]).float()

    return one, finish


def run_method(method: Method, ds: Dataset, clip: Clip, alb: Optional[torch.Tensor], frames, sigma_s=8.0,
               sigma_r=1.0, window: int = 2) -> tuple[torch.Tensor, list]:
    """Denoise ``frames``; returns (outputs (F, 3, H, W), per-frame seconds), after one warm-up call."""
    one, finish = prepare(method, ds, clip, alb, sigma_s, sigma_r, window)
    one(frames[0])
    outs, secs = [], []
    for q in frames:
        t0 = time.perf_counter()
        out = one(q)
        secs.append(time.perf_counter() - t0)
        outs.append(finish(q, out))
    return torch.stack(outs), secs


def scores(out: torch.Tensor, ref: torch.Tensor, with_flip: bool = True) -> dict:
    """``torchmanifold.metrics.evaluate`` over frames (F, 3, H, W): PSNR (clamped sRGB, the data README's
    score), linear PSNR, relMSE, SSIM and FLIP, each a mean over frames."""
    from torchmanifold import metrics

    return {k: float(v) for k, v in metrics.evaluate(out, ref, with_flip=with_flip).items()}


def timing_summary(secs: list) -> dict:
    ms = sorted(1000.0 * s for s in secs)
    q = statistics.quantiles(ms, n=4) if len(ms) >= 2 else [ms[0]] * 3
    return {"ms_median": statistics.median(ms), "ms_min": ms[0], "ms_iqr": q[2] - q[0], "ms_all": ms}


# ---------------------------------------------------------------------------------------------------- metadata
def _version(mod: str) -> Optional[str]:
    try:
        from importlib.metadata import version
        return version(mod)
    except Exception:  # not installed
        return None


def metadata(quick: bool = False) -> dict:
    def git(*args):
        try:
            return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=10).stdout.strip()
        except Exception:  # no git: still record everything else
            return ""

    cpu = ""
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except Exception:  # not Linux
        cpu = platform.processor()
    import cv2

    try:  # which implementation "ours" ran: the C++ CPU kernel or the pure-torch fallback
        from torchmanifold.ops import has_kernel
        ours_backend = "cpp" if has_kernel("cpu") else "torch"
    except Exception as exc:  # the filter is not importable
        ours_backend = f"unavailable ({type(exc).__name__})"
    return {
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "git_commit": git("rev-parse", "HEAD"),
        "git_dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
        "quick": quick,
        "python": platform.python_version(),
        "versions": {m: _version(m) for m in ("torch", "numpy", "kornia", "opencv-contrib-python-headless", "pyoidn",
                                                "flip-evaluator", "moderngl", "torchmanifold")},
        "cv2": cv2.__version__,
        "torch_threads": torch.get_num_threads(),
        "cv2_threads": cv2.getNumThreads(),
        "ours_backend": ours_backend,
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        # The machine is shared: the load during the run says how far to trust the timings.
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def write_json(name: str, payload: dict, quick: bool = False) -> Path:
    """Write results/<name>.json (results/quick/<name>.json for a smoke run, so quick runs never clobber real ones)."""
    out = RESULTS / "quick" if quick else RESULTS
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps({"meta": metadata(quick), **payload}, indent=1))
    tmp.replace(path)
    return path
