"""Speed against accuracy: every method of ``baselines.benchmark_methods`` on the same frames, in one run.

Inputs: the Mitsuba clip of ``/work/shared/data`` (another renderer's 1-spp frames, 1024-spp references) and the
built-in scene of our tracer (1-spp frames, a long-render reference, plain path tracing at more spp for the
equal-time comparison). Per method: ms per frame (pytest-benchmark rounds = frames, plus median/IQR over frames),
PSNR (clamped sRGB), relMSE and FLIP against the reference. Also: time against pixels, guide channels and tree height.

    .venv/bin/python -m pytest benchmarks/bench_methods.py [--quick]

writes ``benchmarks/results/methods.json`` and ``scaling.json`` (``results/quick/`` with ``--quick``);
``benchmarks/charts.py`` draws them. Nothing here asserts a timing.
"""
from __future__ import annotations

import math
import time

import pytest
import torch
from tqdm import tqdm

import baselines
import harness

SIGMA_S, SIGMA_R = 4.0, 1.0  # the guide is pre-scaled per feature (harness.GROUPS), so sigma_r = 1
METHODS = baselines.benchmark_methods(sigma_s=SIGMA_S, sigma_r=SIGMA_R)
_RESULTS: dict = {}
_SCALING: dict = {}


@pytest.fixture(scope="session")
def datasets(quick):
    """name -> Dataset, every frame scored. Loaded/rendered once per session."""
    out = {}
    if harness.DATA.is_dir():
        out["mitsuba"] = harness.load_mitsuba([5, 6] if quick else None, crop=64 if quick else None)
    ok, _ = harness.tracer_available()
    if ok:
        out["cornell_box"] = harness.builtin_dataset(quick)
    return out


@pytest.fixture(scope="module", autouse=True)
def _write(quick):
    yield
    if _RESULTS:
        harness.write_json("methods", {"sigma_s": SIGMA_S, "sigma_r": SIGMA_R, "datasets": _RESULTS}, quick)
    if _SCALING:
        harness.write_json("scaling", {"scaling": _SCALING}, quick)


def _entry(ds_name: str, ds) -> dict:
    if ds_name not in _RESULTS:
        _RESULTS[ds_name] = {"size": list(ds.color.shape[-2:]), "frames": ds.times.tolist(),
                             "features": list(harness.DEFAULT_FEATURES), "methods": {}}
    return _RESULTS[ds_name]


def _record(ds_name, ds, name, family, out, secs, params=None, extra=None):
    res = {"family": family, "params": params or {}, **harness.timing_summary(secs)}
    finite = torch.isfinite(out)
    res["nonfinite_fraction"] = float((~finite).float().mean())
    if not bool(finite.all()):
        # Score what a user would see after the usual repair: the noisy input where the output is NaN/Inf.
        out = torch.where(finite, out, ds.color)
    res.update(harness.scores(out, ds.reference))
    res.update(extra or {})
    _entry(ds_name, ds)["methods"][name] = res
    return res


@pytest.mark.parametrize("ds_name", ["mitsuba", "cornell_box"])
def test_raw(ds_name, datasets):
    """Plain path tracing: the 1-spp frames and the frames with more samples, at their render time."""
    if ds_name not in datasets:
        pytest.skip(f"{ds_name} input not available")
    ds = datasets[ds_name]
    n = ds.color.shape[0]
    for spp, (frames, ms) in ds.spp_frames.items():
        _record(ds_name, ds, f"raw-{spp}spp", "raw", frames, [(ms or 0.0) / 1000.0] * n, {"spp": spp},
                {"render_ms_known": ms is not None})
    _entry(ds_name, ds)["trace_ms_1spp"] = ds.trace_ms


@pytest.mark.parametrize("method", METHODS, ids=[m.name for m in METHODS])
@pytest.mark.parametrize("ds_name", ["mitsuba", "cornell_box"])
def test_method(benchmark, ds_name, method, datasets, quick):
    if ds_name not in datasets:
        pytest.skip(f"{ds_name} input not available")
    if not method.available:
        pytest.skip(f"{method.name} not installed: {method.why}")
    ds = datasets[ds_name]
    benchmark.group = f"methods-{ds_name}"
    clip, alb = harness.clip_for(ds)
    one, finish = harness.prepare(method, ds, clip, alb, SIGMA_S, SIGMA_R)
    frames = list(range(ds.color.shape[0]))
    one(frames[0])  # warm-up: library start-up (OIDN device, OpenMP pool) is not a per-frame cost
    order = iter(frames)  # one round per frame: the fastest of 12 frames is a stable figure
    outs = {}

    def target(q):
        outs[q] = one(q)

    secs = _rounds(benchmark, target, lambda: ((next(order),), {}), len(frames))
    out = torch.stack([finish(q, outs[q]) for q in frames])
    res = _record(ds_name, ds, method.name, method.family, out, secs, method.params)
    benchmark.extra_info.update({k: res[k] for k in ("psnr", "relmse", "flip") if k in res})


# ---------------------------------------------------------------------------------------------------- scaling
# The filter doc's timing setting (sigma_s 16, sigma_r 0.4 on a [0, 1] guide), so the low-res grid is 4x smaller.
SCALE_S, SCALE_R = 16.0, 0.4
SCALING_METHODS = {m.name: m for m in baselines.benchmark_methods(sigma_s=SCALE_S, sigma_r=SCALE_R,
                                                                  bilateral_sigma_r=(SCALE_R,))
                   if m.name in ("ours-H2", "opencv-am", "gaussian-s4", f"joint-bilateral-r{SCALE_R:g}", "oidn")}
JBF = f"joint-bilateral-r{SCALE_R:g}"


def _synthetic(h: int, w: int, d: int, seed: int = 0) -> baselines.Clip:
    """Smooth noisy colour and a d-channel piecewise-smooth guide (a stand-in for features)."""
    g = torch.Generator().manual_seed(seed)
    low = torch.nn.functional.interpolate(torch.rand(1, 3 + d, 8, 8, generator=g), size=(h, w), mode="bilinear")
    colour = (low[:, :3] + 0.1 * torch.randn(1, 3, h, w, generator=g)).clamp(min=0)
    guide = (low[:, 3:] > 0.5).float() * 0.5 + 0.2 * low[:, 3:]
    return baselines.Clip(colour.contiguous(), guide.contiguous(), torch.zeros(1),
                          albedo=low[:, :3].clamp(0, 1), normal=None)


def _rounds(benchmark, fn, setup, rounds: int) -> list:
    """Per-round seconds from pytest-benchmark, or timed here when it is disabled (--benchmark-disable)."""
    if not getattr(benchmark, "disabled", False):
        benchmark.pedantic(fn, setup=setup, rounds=rounds)
        return list(benchmark.stats.stats.data)
    secs = []
    for _ in range(rounds):
        args, _kw = setup()
        t0 = time.perf_counter()
        fn(*args)
        secs.append(time.perf_counter() - t0)
    return secs


def _time(benchmark, method, clip, axis, value):
    benchmark.group = f"scaling-{axis}"
    method(clip, 0, SCALE_S, SCALE_R)  # warm-up
    secs = _rounds(benchmark, method, lambda: ((clip, 0, SCALE_S, SCALE_R), {}), 3)
    _SCALING.setdefault(axis, {}).setdefault(method.name, []).append({axis: value, **harness.timing_summary(secs)})


# Sizes are fixed at import (parametrisation); --quick runs only the first two of each axis.
AXES = {"pixels": [128, 256, 512, 1024], "channels": [1, 3, 7, 16, 32], "height": [1, 2, 3, 4]}


def _skip_unless(method, value, axis, quick):
    if not method.available:
        pytest.skip(f"{method.name} not installed: {method.why}")
    if quick and AXES[axis].index(value) >= 2:
        pytest.skip("--quick: first two sizes only")


@pytest.mark.parametrize("side", AXES["pixels"])
@pytest.mark.parametrize("name", list(SCALING_METHODS))
def test_scaling_pixels(benchmark, name, side, quick):
    """Time against image size (square, 7 guide channels, sigma_s 16): every method should be linear in pixels."""
    method = SCALING_METHODS[name]
    _skip_unless(method, side, "pixels", quick)
    side = side // 2 if quick else side
    _time(benchmark, method, _synthetic(side, side, 7), "pixels", side * side)


@pytest.mark.parametrize("d", AXES["channels"])
@pytest.mark.parametrize("name", ["ours-H2", "opencv-am", JBF])
def test_scaling_channels(benchmark, name, d, quick):
    """Time against guide channels at 256x256 (128x128 quick)."""
    method = SCALING_METHODS[name]
    _skip_unless(method, d, "channels", quick)
    side = 128 if quick else 256
    _time(benchmark, method, _synthetic(side, side, d), "channels", d)


@pytest.mark.parametrize("h", AXES["height"])
def test_scaling_height(benchmark, h, quick):
    """Our time against tree height at 256x256, 7 guide channels: 2^H - 1 manifolds."""
    base = SCALING_METHODS["ours-H2"]
    _skip_unless(base, h, "height", quick)
    side = 128 if quick else 256
    method = baselines.Method("ours", "ours", base.fn, {**base.params, "tree_height": h})
    _time(benchmark, method, _synthetic(side, side, 7), "height", h)


# ---------------------------------------------------------------------------------------------------- progressive
def test_progressive(quick):
    """Error against iteration and wall time for the pipeline's ``ProgressiveRenderer``: its raw progressive
    average, its Gaussian-filtered average and ours, on the built-in Cornell box (each iteration adds one sample
    per pixel per frame)."""
    if not harness.tracer_available()[0]:
        pytest.skip("tracer not available")
    from torchmanifold.pipeline.progressive import ProgressiveRenderer
    from torchmanifold.render import PathTracer, create_context, default_scene

    ref_ds = harness.builtin_dataset(quick)
    frames, size = ref_ds.color.shape[0], ref_ds.color.shape[-1]
    iterations = 4 if quick else 32
    tracer = PathTracer(default_scene(), width=size, height=size, ctx=create_context())
    pr = ProgressiveRenderer(tracer, times=[float(t) for t in range(frames)], seed=7)
    curves = {k: {"iteration": [], "psnr": [], "relmse": [], "seconds": []} for k in ("raw", "gaussian", "ours")}
    total = render = 0.0
    for _ in tqdm(range(iterations), desc="progressive", leave=False):
        st = pr.step()
        total += st.seconds
        render += st.render_seconds
        for key in curves:
            sc = harness.scores(getattr(st, key), ref_ds.reference, with_flip=False)
            c = curves[key]
            c["iteration"].append(st.iteration), c["psnr"].append(sc["psnr"]), c["relmse"].append(sc["relmse"])
            # One step computes all three; the raw average costs only its rendering.
            c["seconds"].append(render if key == "raw" else total)
    # The samples per pixel plain path tracing needs to match ours at the last iteration.
    target = curves["ours"]["psnr"][-1]
    match = next((it for it, p in zip(curves["raw"]["iteration"], curves["raw"]["psnr"]) if p >= target), None)
    below = [c for c, (o, r) in enumerate(zip(curves["ours"]["psnr"], curves["raw"]["psnr"]), 1) if o < r]
    harness.write_json("progressive", {
        "title": f"built-in Cornell box {size}x{size}, {frames} frames: error against iteration",
        "note": (f"`torchmanifold.pipeline.progressive.ProgressiveRenderer` with its defaults (temporal mode "
                 f"{pr.settings.mode!r}, radius {pr.settings.temporal_radius} frame(s), sigma_s {pr.settings.sigma_s:g} at "
                 f"iteration 1, a = {pr.schedule.alpha:g}): each iteration renders 1 spp per frame; `raw` is the "
                 "running average, `gaussian` and `ours` the running averages of the filtered iterations. "
                 f"Reference: {'16' if quick else '256'} spp. Wall time of `gaussian` includes ours (one step "
                 "computes both). "
                 + (f"Plain path tracing reaches ours' final PSNR at {match} spp. " if match else
                    f"Plain path tracing does not reach ours' final PSNR within {iterations} spp. ")
                 + (f"Ours falls below the raw average from iteration {below[0]} on." if below else
                    "Ours stays above the raw average at every iteration.")),
        "report_iterations": [i for i in (1, 2, 4, 8, 16, 32) if i <= iterations],
        "spp_to_match_ours": match, "first_iteration_below_raw": below[0] if below else None,
        "curves": curves}, quick)
    assert all(math.isfinite(p) for c in curves.values() for p in c["psnr"])
