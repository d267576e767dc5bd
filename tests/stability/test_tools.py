"""The suite's own tools: the verdict rule, the method registry's clip windows, and the charts' Pareto front."""
import math
import random

import pytest
import torch

import baselines
import charts
from torchmanifold.pipeline import DenoiseSettings
from cases import CASES, Problem, judge


def _problem(constant=None):
    v = torch.full((1, 3, 8, 8), 0.5) if constant is not None else torch.rand(1, 3, 8, 8,
                                                                              generator=torch.Generator().manual_seed(0))
    ref = v[0].clone()
    return Problem(baselines.Clip(v, v.clone(), torch.zeros(1)), reference=ref, constant=constant)


def test_judge_flags_each_failure_kind():
    p = _problem()
    good = p.clip.values[0] * 0.9 + 0.05
    v = judge(p, lambda: good)
    mse = float(((good.double() - p.reference.double()) ** 2).mean())
    assert not v.failed and math.isclose(v.psnr, -10 * math.log10(mse), rel_tol=1e-9)
    nan = good.clone()
    nan[0, 0, 0] = float("nan")
    assert judge(p, lambda: nan).failed and "NaN" in judge(p, lambda: nan).reason
    assert judge(p, lambda: good * 100).reason.startswith("left the input range")
    assert judge(p, lambda: good[:2]).reason.startswith("shape")

    def boom():
        raise RuntimeError("x")
    assert judge(p, boom).reason == "raised RuntimeError"
    c = _problem(constant=0.5)
    assert not judge(c, lambda: c.clip.values[0].clone()).failed
    assert judge(c, lambda: c.clip.values[0] + 1e-3).reason.startswith("constant moved")


def test_judge_range_rule_is_tight():
    """Any convex combination of the samples passes; leaving their range by more than the rounding slack
    (RANGE_ULPS float32 ulps of the scale) fails, even by a percent."""
    from cases import RANGE_ULPS

    p = _problem()
    v = p.clip.values[0]
    lo, hi = float(v.min()), float(v.max())
    assert not judge(p, lambda: v.mean((1, 2), keepdim=True).expand_as(v)).failed  # a convex combination
    assert not judge(p, lambda: torch.full_like(v, hi)).failed
    ulp = torch.finfo(torch.float32).eps * max(hi - lo, abs(lo), abs(hi))
    inside = v.double().clone()
    inside[0, 0, 0] = hi + (RANGE_ULPS - 1) * ulp
    assert not judge(p, lambda: inside).failed
    for over in (hi + (RANGE_ULPS + 1) * ulp, hi * 1.01, lo - 0.01 * (hi - lo)):
        bad = v.double().clone()
        bad[0, 0, 0] = over
        assert judge(p, lambda: bad).reason.startswith("left the input range"), over


def test_cases_are_deterministic_and_well_formed():
    for case in CASES:
        a, b = case.build(), case.build()
        assert torch.equal(torch.nan_to_num(a.clip.values), torch.nan_to_num(b.clip.values)), case.name
        t, c, h, w = a.clip.values.shape
        assert a.clip.guide.shape[0] == t and a.clip.guide.shape[-2:] == (h, w)
        assert 0 <= a.query < t
        if a.reference is not None:
            assert a.reference.shape == (c, h, w)
        if a.mask is not None:
            assert a.mask.shape == (h, w) and bool(a.mask.any()), f"{case.name}: empty error mask"


def test_clip_window():
    clip = baselines.Clip(torch.arange(5.0).view(5, 1, 1, 1), torch.zeros(5, 1, 1, 1), torch.arange(5.0))
    sub, q = clip.window(1, 2)
    assert sub.times.tolist() == [0.0, 1.0, 2.0, 3.0] and q == 1
    sub, q = clip.window(4, 1)
    assert sub.times.tolist() == [3.0, 4.0] and q == 1
    with pytest.raises(ValueError, match="times"):
        baselines.Clip(torch.zeros(2, 1, 1, 1), torch.zeros(2, 1, 1, 1), torch.zeros(3))


def test_streamed_pipeline_gives_each_window_bytes():
    """The command's default in the benchmarks prepares each frame once across the queries: the same bytes as
    the pipeline on each query's window, queried in order, again from the start, and after a clip change."""
    g = torch.Generator().manual_seed(3)
    t, h, w = 6, 12, 10
    names = ("albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z")
    feats = torch.rand(t, len(names), h, w, generator=g)
    clip = baselines.Clip(torch.rand(t, 3, h, w, generator=g) ** 4, torch.zeros(t, 1, h, w),
                          torch.arange(t * 1.0), features=feats, feature_names=names, samples_per_pixel=1)
    other = baselines.Clip(clip.values.flip(0).contiguous(), clip.guide, clip.times, features=feats.flip(0),
                           feature_names=names, samples_per_pixel=1)
    method = next(m for m in baselines.benchmark_methods() if m.name == "ours-pipeline-spacetime")
    assert method.streams and method.temporal
    radius = DenoiseSettings(**method.params).window_radius  # the albedo's window is wider than the filter's
    for c, queries in ((clip, [0, 0, 1, 2, 3, 4, 5]), (clip, [2, 3]), (other, [0, 5])):
        for q in queries:
            sub, k = c.window(q, radius)
            want = baselines._pipeline(sub, k, 8.0, 0.3, **method.params)
            assert torch.equal(method(c, q), want), (q, queries)


def test_pareto_front_matches_brute_force():
    rng = random.Random(0)
    for _ in range(50):
        pts = [(rng.choice([1, 2, 3, 5, 8]), rng.choice([10, 20, 25, 30])) for _ in range(rng.randint(1, 12))]
        brute = {i for i, (x, y) in enumerate(pts)
                 if not any((x2 <= x and y2 >= y) and (x2, y2) != (x, y) for x2, y2 in pts)}
        # Among duplicates of one point the front keeps one; compare the points, not the indices.
        assert {pts[i] for i in charts.pareto(pts)} == {pts[i] for i in brute}


def _write_flat_clip(folder, frames, levels, noise, seed=0):
    """A Mitsuba-layout clip: a smooth reference, and per level n its frames with noise / sqrt(n)."""
    import json

    import numpy as np

    from torchmanifold.io.exr import write_exr

    rng = np.random.default_rng(seed)
    h, w = 20, 24
    yy, xx = np.mgrid[0:h, 0:w] / 24.0
    folder.mkdir(parents=True)
    for f in range(frames):
        ref = {c: (0.2 + 0.5 * xx + 0.1 * k * yy).astype(np.float32) for k, c in enumerate("RGB")}
        write_exr(folder / f"reference_{f:04d}.exr", ref)
        geometry = {"albedo.R": np.full((h, w), 0.5), "albedo.G": np.full((h, w), 0.5),
                    "albedo.B": np.full((h, w), 0.5), "N.X": np.zeros((h, w)), "N.Y": np.zeros((h, w)),
                    "N.Z": np.ones((h, w)), "Z": np.full((h, w), 2.0), "P.X": xx, "P.Y": yy,
                    "P.Z": np.zeros((h, w))}
        for n in levels:
            name = "frame" if n == 1 else f"iter{n}"
            color = {c: np.maximum(v + rng.normal(0, noise / n ** 0.5, (h, w)), 0) for c, v in ref.items()}
            write_exr(folder / f"{name}_{f:04d}.exr", {**color, **geometry}, attributes={"spp": str(n)})
    (folder / "manifest.json").write_text(json.dumps({"frames": frames}))


def test_iterations_scores_every_level_and_names_clips_without_them(tmp_path):
    """benchmarks/validation/iterations.py: real EXR files, the command's path and OIDN at every iteration; a
    clip without its iterations is left out by name, not scored from what it has."""
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "validation"))
    import iterations

    _write_flat_clip(tmp_path / "full", 2, iterations.ITERATIONS, 0.3)
    _write_flat_clip(tmp_path / "first_only", 2, (1,), 0.3, seed=1)
    split = {"scenes": {"full": {"split": "tune", "path": str(tmp_path / "full")},
                        "first_only": {"split": "test", "path": str(tmp_path / "first_only")}}}
    (tmp_path / "split.json").write_text(json.dumps(split))
    res = iterations.main(["--split", str(tmp_path / "split.json"), "--out", str(tmp_path / "out"),
                           "--threads", "1"])
    assert list(res["scenes"]) == ["full"] and "first_only" in res["left_out"]
    sc = res["scenes"]["full"]
    raw = [sc[str(n)]["raw"] for n in iterations.ITERATIONS]
    assert all(b > a + 1.5 for a, b in zip(raw, raw[1:]))  # the noise halves its variance per level
    assert all(sc[str(n)]["ours"] > sc[str(n)]["raw"] + 3 for n in iterations.ITERATIONS)
    assert (tmp_path / "out" / "iterations.png").stat().st_size > 0
    assert "first_only" in (tmp_path / "out" / "iterations.md").read_text()
