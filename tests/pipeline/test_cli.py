"""The two commands end to end at tiny sizes, and their bad-input errors."""
import json
import math
import shutil

import numpy as np
import pytest

from torchmanifold.cli import main
from torchmanifold.io import read_exr, write_exr


def test_render_end_to_end(tmp_path, capsys):
    out = tmp_path / "render"
    rc = main(["render", "--out", str(out), "--frames", "2", "--iterations", "2", "--width", "24",
               "--height", "16", "--reference-spp", "8", "--inbetween", "1", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    q = 3  # 2 frames + 1 in-between
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"frame_{i:04d}.exr" for i in range(q)]
    assert len(list((out / "png").glob("*.png"))) == q
    for name in ("clip.mp4", "compare.mp4", "chart.png", "metrics.json"):
        assert (out / name).stat().st_size > 0, name
    m = json.loads((out / "metrics.json").read_text())
    assert [r["iteration"] for r in m["per_iteration"]] == [1, 2]
    for method in ("raw", "gaussian", "ours"):
        for r in m["per_iteration"]:
            assert math.isfinite(r[method]["psnr"]) and 0 < r[method]["ssim"] <= 1
            assert r[method]["seconds"] > 0
    assert m["per_iteration"][1]["raw"]["psnr"] > m["per_iteration"][0]["raw"]["psnr"]
    assert m["spp_plain_to_match_ours_final"] >= 1
    f = read_exr(out / "frames" / "frame_0000.exr")
    assert {"R", "G", "B", "raw.R", "reference.R", "albedo.R", "N.X", "Z"} <= set(f)
    assert f["R"].shape == (16, 24)
    # --out reuse needs --overwrite
    assert main(["render", "--out", str(out), "--frames", "1", "--iterations", "1", "--width", "8",
                 "--height", "8", "--reference-spp", "0", "--quiet"]) == 2
    assert "--overwrite" in capsys.readouterr().err


def _link_frames(tmp_path, data, n=2):
    src = tmp_path / "in"
    src.mkdir()
    paths = []
    for i in range(n):
        p = src / f"frame_{i:04d}.exr"
        shutil.copy(data / f"frame_{i:04d}.exr", p)
        paths.append(p)
    return paths


def test_denoise_sample_count_from_the_features(tmp_path, capsys, mitsuba_dir):
    """Frames whose header records no sample count: the shared clip's 1-spp frames have unit normals
    everywhere, so the command takes them for 1 spp, says so, and gives the bytes the header's count
    gives; its 4-spp frames average normals at edges, whose mixes take fractions k/4: taken as 4, the
    bytes of --spp 4."""
    outs = {}
    for name, src, extra in (("header", "frame", []), ("normals", "frame", []), ("averaged", "frame4spp", []),
                             ("flag", "frame4spp", ["--spp", "4"])):
        paths = []
        for i in range(2):
            p = tmp_path / name / "in" / f"frame_{i:04d}.exr"
            p.parent.mkdir(parents=True, exist_ok=True)
            if name == "header":
                shutil.copy(mitsuba_dir / f"{src}_{i:04d}.exr", p)
            else:  # every channel, no header attribute
                write_exr(p, read_exr(mitsuba_dir / f"{src}_{i:04d}.exr"))
            paths.append(p)
        rc = main(["denoise", *map(str, paths), "--out", str(tmp_path / name / "out"), "--temporal-radius", "0",
                   "--tree-height", "2", "--quiet", *extra])
        captured = capsys.readouterr()
        assert rc == 0, captured.err
        outs[name] = (json.loads(captured.out.strip().splitlines()[-1]), captured.err,
                      read_exr(tmp_path / name / "out" / paths[0].name)["R"])
    assert outs["header"][0]["samples_per_pixel"] == 1 and "sample count" not in outs["header"][1]
    assert outs["normals"][0]["samples_per_pixel"] == 1 and "no sample count" in outs["normals"][1]
    np.testing.assert_array_equal(outs["normals"][2], outs["header"][2])
    assert outs["averaged"][0]["samples_per_pixel"] == 4 and "fractions k/4" in outs["averaged"][1]
    assert outs["flag"][0]["samples_per_pixel"] == 4
    np.testing.assert_array_equal(outs["averaged"][2], outs["flag"][2])


def test_denoise_end_to_end(tmp_path, capsys, mitsuba_dir):
    from torchmanifold import metrics as M

    paths = _link_frames(tmp_path, mitsuba_dir)
    before = {p: p.read_bytes() for p in paths}
    out = tmp_path / "out"
    rc = main(["denoise", *map(str, paths), "--out", str(out), "--temporal-radius", "0", "--tree-height", "2",
               "--quiet"])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["frames"] == 2 and "P.X" in summary["feature_channels"]
    for i, p in enumerate(paths):
        assert p.read_bytes() == before[p]  # inputs untouched
        d = read_exr(out / p.name)
        assert sorted(d) == ["B", "G", "R"]
        ref = read_exr(mitsuba_dir / f"reference_{i:04d}.exr")
        den = np.stack([d[c] for c in "RGB"])
        raw = np.stack([read_exr(p)[c] for c in "RGB"])
        r = np.stack([ref[c] for c in "RGB"])
        import torch

        assert M.psnr(torch.from_numpy(den), torch.from_numpy(r)) > M.psnr(torch.from_numpy(raw), torch.from_numpy(r)) + 5
    assert not (out / ".partial").exists()


def test_denoise_reads_other_renderers_names(tmp_path, capsys, mitsuba_dir):
    """Frames of the shared clip with their AOVs under pbrt-v4's gbuffer names (Albedo.R/G/B, Ns.X/Y/Z for the
    normal, no depth) give the command's bytes for the same AOVs under ours, and the summary says what it
    read as what."""
    rename = {"albedo.R": "Albedo.R", "albedo.G": "Albedo.G", "albedo.B": "Albedo.B", "N.X": "Ns.X", "N.Y": "Ns.Y",
              "N.Z": "Ns.Z"}
    crop = (slice(96, 160), slice(80, 176))
    ours, pbrt = tmp_path / "ours", tmp_path / "pbrt"
    ours.mkdir()
    pbrt.mkdir()
    for i in range(2):
        d = read_exr(mitsuba_dir / f"frame_{i:04d}.exr")
        d = {k: v[crop] for k, v in d.items() if k in ("R", "G", "B", "P.X", "P.Y", "P.Z") or k in rename}
        write_exr(ours / f"frame_{i:04d}.exr", d)
        write_exr(pbrt / f"frame_{i:04d}.exr", {rename.get(k, k): v for k, v in d.items()})
    for src in (ours, pbrt):
        rc = main(["denoise", *map(str, sorted(src.glob("*.exr"))), "--out", str(tmp_path / f"out_{src.name}"),
                   "--tree-height", "2"])
        assert rc == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["feature_channels"] == ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y",
                                           "P.Z"]
    assert any("Ns.X, Ns.Y, Ns.Z as N.X, N.Y, N.Z" in n for n in summary["notes"])
    for i in range(2):
        a, b = (read_exr(tmp_path / f"out_{name}" / f"frame_{i:04d}.exr") for name in ("ours", "pbrt"))
        for c in "RGB":
            np.testing.assert_array_equal(a[c], b[c])


def test_denoise_bad_inputs(tmp_path, capsys, mitsuba_dir):
    paths = _link_frames(tmp_path, mitsuba_dir)
    out = tmp_path / "out"

    def run(*args):
        rc = main(["denoise", *map(str, args), "--quiet"])
        return rc, capsys.readouterr().err

    rc, err = run(tmp_path / "missing.exr", "--out", out)
    assert rc == 2 and "missing.exr" in err and "not found" in err
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"not an exr at all")
    rc, err = run(paths[0], junk, "--out", out)
    assert rc == 2 and "junk.exr" in err and "not a readable EXR" in err
    small = tmp_path / "small.exr"
    d = read_exr(paths[1])
    write_exr(small, {k: v[:64, :64] for k, v in d.items()})
    rc, err = run(paths[0], small, "--out", out)
    assert rc == 2 and "small.exr" in err and "size" in err
    nocolor = tmp_path / "nocolor.exr"
    write_exr(nocolor, {k: v for k, v in d.items() if k != "G"})
    rc, err = run(nocolor, "--out", out)
    assert rc == 2 and "nocolor.exr" in err and "'G'" in err
    rc, err = run(paths[0], "--features", "N.X", "Q.W", "--out", out)
    assert rc == 2 and "Q.W" in err and paths[0].name in err
    rc, err = run(paths[0], "--guide", "Q.W", "--out", out)
    assert rc == 2 and "Q.W" in err
    # nothing was written half-way by any failure
    assert not out.exists() or not any(p for p in out.iterdir() if p.suffix == ".exr")
    out.mkdir(exist_ok=True)
    (out / "keep.txt").write_text("x")
    rc, err = run(paths[0], "--out", out)
    assert rc == 2 and "--overwrite" in err


def test_denoise_nonfinite_reported(tmp_path, capsys, mitsuba_dir):
    paths = _link_frames(tmp_path, mitsuba_dir, 1)
    d = read_exr(paths[0])
    d["R"][5:9, 5:9] = np.nan
    d["N.X"][100, 100] = np.inf
    write_exr(paths[0], d)
    out = tmp_path / "out"
    rc = main(["denoise", str(paths[0]), "--out", str(out), "--temporal-radius", "0", "--tree-height", "2",
               "--quiet"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "17 non-finite samples" in cap.err
    res = read_exr(out / paths[0].name)
    assert all(np.isfinite(v).all() for v in res.values())


def test_denoise_our_tracer_frames_keeps_emission(tmp_path, capsys):
    """EXRs from our tracer carry emission.R/G/B: the light stays exactly as rendered, walls get denoised."""
    import torch

    from torchmanifold.render import PathTracer, default_scene, write_frame_exr

    res = PathTracer(default_scene(), 48, 32).render(times=[0.0, 1.0], spp=1, seed=3)
    paths = [write_frame_exr(tmp_path / f"f{i}.exr", res, i) for i in range(2)]
    out = tmp_path / "out"
    assert main(["denoise", *map(str, paths), "--out", str(out), "--quiet"]) == 0, capsys.readouterr().err
    d = read_exr(out / "f0.exr")
    den = torch.from_numpy(np.stack([d[c] for c in "RGB"]))
    light = res.emission[0].sum(0) > 0
    assert light.any()
    # at emitter pixels the output is at least the emission (nothing blurred away) and not far above it
    assert (den[:, light] >= res.emission[0][:, light] - 1e-3).all()
    assert torch.isfinite(den).all()


def test_tree_height_is_checked_and_its_default_shown(tmp_path, capsys):
    """--tree-height 0 is an error (it used to become the default silently); each command's help shows
    the height it really uses."""
    from torchmanifold.cli import build_parser

    for argv in (["render", "--out", str(tmp_path / "r")], ["denoise", str(tmp_path / "x.exr"), "--out",
                                                             str(tmp_path / "d")]):
        for bad in ("0", "31"):
            assert main(argv + ["--tree-height", bad, "--quiet"]) == 2
            assert f"--tree-height must be an int in [1, 30], got {bad}" in capsys.readouterr().err
        assert not (tmp_path / "r").exists() and not (tmp_path / "d").exists()
    assert main(["render", "--out", str(tmp_path / "t"), "--threads", "0", "--quiet"]) == 2
    assert "--threads must be an int >= 1, got 0" in capsys.readouterr().err
    sub = build_parser()._subparsers._group_actions[0].choices
    for command, height in (("render", 2), ("denoise", 3)):
        assert sub[command].parse_args((["x"] if command == "denoise" else []) + ["--out", "o"]).tree_height == height
        assert f"(1 to 30; default {height})" in " ".join(sub[command].format_help().split())


def test_each_command_filters_with_its_engine_defaults():
    """Every setting the CLI exposes defaults to what its engine uses: the progressive loop's
    (PROGRESSIVE_FILTER) for render, the command's own (COMMAND_FILTER) for denoise."""
    from torchmanifold.cli import _settings, build_parser
    from torchmanifold.pipeline import DenoiseSettings
    from torchmanifold.pipeline.denoise_files import COMMAND_FILTER
    from torchmanifold.pipeline.progressive import PROGRESSIVE_FILTER

    sub = build_parser()._subparsers._group_actions[0].choices
    render = _settings(sub["render"].parse_args(["--out", "o"]))
    denoise = _settings(sub["denoise"].parse_args(["x", "--out", "o"]))
    assert render == DenoiseSettings(**PROGRESSIVE_FILTER)
    assert denoise == DenoiseSettings(**COMMAND_FILTER)
    assert render.selection_softness != denoise.selection_softness
    args = sub["render"].parse_args(["--out", "o", "--selection-softness", "0.8"])
    assert _settings(args).selection_softness == 0.8
    assert render.frame_alone == () and denoise.frame_alone == (0.5,)
    for command, given, alone in (("render", ["0.5", "1"], (0.5, 1.0)), ("denoise", [], ())):
        clip = ["x"] if command == "denoise" else []
        args = sub[command].parse_args(clip + ["--out", "o", "--frame-alone", *given])
        assert _settings(args).frame_alone == alone


@pytest.mark.parametrize("flag, setting", [("--filter-sky", "keep_sky"), ("--no-align", "align_frames")])
def test_flags_that_turn_a_rule_off(flag, setting):
    """--filter-sky turns the sky rule off (DenoiseSettings.keep_sky), --no-align the window's alignment
    (align_frames), for both commands."""
    from torchmanifold.cli import _settings, build_parser

    sub = build_parser()._subparsers._group_actions[0].choices
    for command in ("render", "denoise"):
        args = (["x"] if command == "denoise" else []) + ["--out", "o"]
        assert getattr(_settings(sub[command].parse_args(args)), setting)
        assert not getattr(_settings(sub[command].parse_args(args + [flag])), setting)


def test_denoise_sample_count_from_header_or_flag(tmp_path, capsys, mitsuba_dir):
    """The shared clip's header says 1 spp (footprint 0.7 px); --spp overrides it (16: the log-radiance
    channel narrows); a bad count is named."""
    paths = _link_frames(tmp_path, mitsuba_dir)
    outs = {}
    for name, extra in (("header", []), ("flag", ["--spp", "4"]), ("many", ["--spp", "16"])):
        rc = main(["denoise", *map(str, paths), "--out", str(tmp_path / name), "--temporal-radius", "0",
                   "--tree-height", "2", "--quiet", *extra])
        assert rc == 0, capsys.readouterr().err
        outs[name] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert outs["header"]["samples_per_pixel"] == 1 and outs["header"]["footprint_sigma"] == pytest.approx(0.7)
    assert outs["flag"]["samples_per_pixel"] == 4 and outs["flag"]["footprint_sigma"] == pytest.approx(0.5)
    assert outs["header"]["radiance_sigma"] == outs["flag"]["radiance_sigma"] == 0.5  # narrows beyond 4 spp
    assert outs["many"]["radiance_sigma"] == pytest.approx(0.5 / 2 ** 0.5)
    assert outs["header"]["sigma_s"] == 4.0 and outs["flag"]["sigma_s"] == pytest.approx(4.0 / 2 ** 0.5)
    a, b = (read_exr(tmp_path / n / paths[0].name)["R"] for n in ("header", "flag"))
    assert not np.array_equal(a, b)
    rc = main(["denoise", *map(str, paths), "--out", str(tmp_path / "bad"), "--spp", "0", "--quiet"])
    assert rc == 2 and "samples_per_pixel" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()  # refused before anything was created
