"""The table of inputs where filters are known to fail, and the rule that says whether a method failed.

Every case builds a small deterministic :class:`baselines.Clip` (a procedural scene of flat-coloured boxes
on a shaded, textured background, with exact noise-free features as the guide), the frame to denoise, the sigmas, and
where one exists the clean reference. ``judge`` turns a method's output into a verdict:

* failed when the call raised, the output has the wrong shape, any NaN/Inf, a constant input did not come back
  constant (relative 1e-5; 1e-2 in float16), or the output left the range of the input's finite samples (all
  frames of the clip) by more than ``RANGE_ULPS`` units in the last place of its scale, max(range, |min|, |max|).
  A normalised filter's output is a convex combination of its samples, so it cannot leave their range; the
  slack is for rounding only (measured at most 2.7 float32 ulps: OpenCV's amFilter on the constant image; 0 for
  ours on every case). A method that is not a normalised filter (a network such as OIDN, which can ring at an
  edge) fails the rule where it overshoots;
* otherwise ok, with PSNR (peak 1) against the reference over the case's mask where there is a reference.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch

from baselines import Clip
from torchmanifold.metrics import psnr_linear

SIGMA_S, SIGMA_R = 8.0, 0.3
#: rounding slack of the range rule, in units in the last place of the input's scale (see the module docstring)
RANGE_ULPS = 8


@dataclass
class Case:
    name: str
    what: str
    build: Callable[[], "Problem"]


@dataclass
class Problem:
    clip: Clip
    query: int = 0
    sigma_s: float = SIGMA_S
    sigma_r: float = SIGMA_R
    reference: Optional[torch.Tensor] = None  # (C, H, W) clean query frame
    mask: Optional[torch.Tensor] = None       # (H, W) bool: where the error is measured
    constant: Optional[float] = None          # the value a constant input must keep


# ---------------------------------------------------------------------------------------------------- scenes
def _scene(h: int, w: int, seed: int = 0, boxes=None, noise: float = 0.08):
    """Noisy colour, clean colour and guide (albedo RGB + depth, in [0, 1]) of a box scene, each (C, H, W)."""
    g = torch.Generator().manual_seed(seed)
    y = torch.linspace(0, 1, h).view(h, 1).expand(h, w)
    x = torch.linspace(0, 1, w).view(1, w).expand(h, w)
    # Background: a soft colour gradient with a fine checker texture (detail a blur destroys).
    checker = ((torch.arange(h).view(h, 1) // 3 + torch.arange(w).view(1, w) // 3) % 2).float()
    albedo = torch.stack([0.35 + 0.3 * x, 0.4 + 0.2 * y, 0.5 - 0.2 * x]) * (0.8 + 0.2 * checker)
    depth = (0.7 + 0.2 * y).expand(1, h, w).clone()
    boxes = boxes if boxes is not None else [
        (0.15, 0.2, 0.45, 0.5, (0.9, 0.2, 0.1), 0.3), (0.55, 0.5, 0.9, 0.85, (0.1, 0.6, 0.9), 0.45)]
    for x0, y0, x1, y1, colour, z in boxes:
        m = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        albedo[:, m] = torch.tensor(colour).view(3, 1)
        depth[0, m] = z
    shading = 0.4 + 0.6 * (1 - y) * (0.8 + 0.2 * x)
    clean = (albedo * shading).clamp(0, 1)
    noisy = clean + noise * torch.randn(clean.shape, generator=g)
    return noisy, clean, torch.cat([albedo, depth])


def _single(noisy, clean, guide, **kw) -> Problem:
    clip = Clip(noisy[None], guide[None], torch.zeros(1), ("Mr", "Mg", "Mb", "Z")[: guide.shape[0]],
                albedo=guide[None, :3] if guide.shape[0] >= 3 else None)
    return Problem(clip, reference=clean, **kw)


def _default(h=48, w=48, **kw):
    return _single(*_scene(h, w), **kw)


def _nan_inf():
    noisy, clean, guide = _scene(48, 48)
    g = torch.Generator().manual_seed(1)
    idx = torch.randperm(48 * 48, generator=g)
    noisy.view(3, -1)[0, idx[:20]] = float("nan")
    noisy.view(3, -1)[1, idx[20:30]] = float("inf")
    noisy.view(3, -1)[2, idx[30:35]] = float("-inf")
    guide.view(4, -1)[3, idx[40:50]] = float("nan")
    guide.view(4, -1)[0, idx[50:55]] = float("inf")
    return _single(noisy, clean, guide)


def _firefly():
    noisy, clean, guide = _scene(48, 48)
    noisy[:, 20, 30] = 1e4
    return _single(noisy, clean, guide)


def _constant_image():
    _, _, guide = _scene(48, 48)
    c = 0.37
    value = torch.full((3, 48, 48), c)
    return _single(value, value.clone(), guide, constant=c)


def _constant_guide():
    noisy, clean, _ = _scene(48, 48)
    return _single(noisy, clean, torch.full((4, 48, 48), 0.5))


def _zero_centre_guide():
    noisy, clean, guide = _scene(47, 47)
    guide[:, 23, 23] = 0.0  # OpenCV seeds its eigenvector from the centre pixel
    return _single(noisy, clean, guide)


def _half_black_white():
    v = torch.zeros(3, 48, 48)
    v[:, :, 24:] = 1.0
    return _single(v, v.clone(), v.clone())


def _odd_size():
    return _default(37, 23)


def _tiny():
    return _default(1, 1)


def _guide_128():
    noisy, clean, guide = _scene(40, 40)
    rand = torch.rand(124, 40, 40, generator=torch.Generator().manual_seed(2))
    return _single(noisy, clean, torch.cat([guide, rand]))


def _float16():
    noisy, clean, guide = _scene(48, 48)
    return _single(noisy.half(), clean, guide.half())


def _moving(frames: int, speed: int, size: int, colour, z: float, dark_occluder: bool, seed: int = 3):
    """A box crossing a static background, one noisy frame per time step; the query is the middle frame."""
    h = w = 48
    out_noisy, out_clean, out_guide, covered = [], [], [], []
    for t in range(frames):
        x0 = (6 + speed * t) / w
        box = [(x0, 0.3, x0 + size / w, 0.3 + size / h, colour, z)]
        noisy, clean, guide = _scene(h, w, seed=seed + t, boxes=box)
        out_noisy.append(noisy), out_clean.append(clean), out_guide.append(guide)
        covered.append((guide[3] - z).abs() < 1e-6)
    q = frames // 2
    if dark_occluder:  # disocclusion: visible now, hidden behind the box in an earlier frame
        mask = ~covered[q] & torch.stack(covered[:q]).any(0)
    else:  # ghosting: where the box is now or was within the window
        mask = torch.stack(covered).any(0)
    clip = Clip(torch.stack(out_noisy), torch.stack(out_guide), torch.arange(frames, dtype=torch.float32),
                ("Mr", "Mg", "Mb", "Z"), albedo=torch.stack(out_guide)[:, :3])
    return Problem(clip, query=q, reference=out_clean[q], mask=mask)


CASES = [
    Case("nan_inf", "NaN and +-Inf samples in colour and guide", _nan_inf),
    Case("firefly_1e4", "one firefly of 1e4", _firefly),
    Case("constant_image", "constant colour 0.37, textured guide", _constant_image),
    Case("constant_guide", "constant guide", _constant_guide),
    Case("zero_centre_guide", "guide zero at the centre pixel", _zero_centre_guide),
    Case("half_black_white", "black/white step, self-guided", _half_black_white),
    Case("sigma_r_0.01", "sigma_r = 0.01", lambda: _default(sigma_r=0.01)),
    Case("sigma_r_1e4", "sigma_r = 1e4", lambda: _default(sigma_r=1e4)),
    Case("sigma_s_1", "sigma_s = 1", lambda: _default(sigma_s=1.0)),
    Case("sigma_s_256", "sigma_s = 256 (image 48 px)", lambda: _default(sigma_s=256.0)),
    Case("size_1x1", "a 1x1 image", _tiny),
    Case("size_37x23", "odd size 37x23", _odd_size),
    Case("guide_128ch", "128 guide channels (124 random)", _guide_128),
    Case("float16", "float16 colour and guide", _float16),
    Case("ghosting", "box moving 6 px/frame over a 5-frame window", lambda: _moving(5, 6, 12, (0.95, 0.95, 0.9), 0.2,
                                                                                   False)),
    Case("disocclusion", "dark box moving 8 px/frame uncovers background",
         lambda: _moving(5, 8, 14, (0.05, 0.05, 0.05), 0.25, True)),
]


# ---------------------------------------------------------------------------------------------------- verdict
@dataclass
class Verdict:
    failed: bool
    reason: str = ""
    psnr: Optional[float] = None
    finite: bool = True

    def cell(self) -> str:
        if self.failed:
            return f"**FAIL** {self.reason}"
        if self.psnr is None:
            return "ok"
        return "ok exact" if self.psnr > 100 else f"ok {self.psnr:.1f}"


def judge(problem: Problem, run: Callable[[], torch.Tensor]) -> Verdict:
    """Run a method on a problem and decide whether it failed (see the module docstring)."""
    values = problem.clip.values
    want = values.shape[1:]
    try:
        out = run()
    except Exception as exc:  # a method that raises on a valid input has failed that case
        kind = type(exc).__name__ if type(exc).__module__ == "builtins" else f"{type(exc).__module__}.{type(exc).__name__}"
        return Verdict(True, f"raised {kind}", finite=False)
    if tuple(out.shape) != tuple(want):
        return Verdict(True, f"shape {tuple(out.shape)}")
    out64 = out.detach().double()
    finite = bool(torch.isfinite(out64).all())
    if not finite:
        bad = 100.0 * float((~torch.isfinite(out64)).double().mean())
        return Verdict(True, f"NaN/Inf in {bad:.3g}% of values", finite=False)
    if problem.constant is not None:
        tol = (1e-2 if values.dtype == torch.float16 else 1e-5) * (1 + abs(problem.constant))
        dev = float((out64 - problem.constant).abs().max())
        if dev > tol:
            return Verdict(True, f"constant moved by {dev:.2g}")
    vals = values.detach().double()
    vals = vals[torch.isfinite(vals)]
    lo, hi = float(vals.min()), float(vals.max())
    # the coarser of the input's precision and float32 (what every method computes in at least)
    eps = max(torch.finfo(values.dtype).eps, torch.finfo(torch.float32).eps) if values.dtype.is_floating_point \
        else torch.finfo(torch.float32).eps
    slack = RANGE_ULPS * eps * max(hi - lo, abs(lo), abs(hi), 1e-3)
    if float(out64.min()) < lo - slack or float(out64.max()) > hi + slack:
        return Verdict(True, f"left the input range [{lo:.3g}, {hi:.3g}]: [{float(out64.min()):.3g}, "
                             f"{float(out64.max()):.3g}]")
    score = None if problem.reference is None else psnr_linear(out64, problem.reference.double(), problem.mask,
                                                               peak=1.0)
    return Verdict(False, psnr=score)
