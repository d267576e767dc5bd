"""Blender's multilayer EXR (Blender 5's multi-part and older single-part files) read as it is and
denoised through the CLI, and every kind of bad Blender input refused with file, layer and channel."""
import json

import numpy as np
import OpenEXR
import pytest

from torchmanifold.cli import main
from torchmanifold.io import read_exr, read_render_frame, write_exr

LAYER = "ViewLayer"
CROP = (slice(96, 160), slice(80, 176))  # 64 x 96 of the Mitsuba clip: the sphere, the box, walls
# a fixed rotation standing in for the world-to-camera turn of Blender's camera-space normal
ROT = np.array([[0.0, 1.0, 0.0], [0.6, 0.0, -0.8], [-0.8, 0.0, -0.6]], np.float32)


def blender_passes(data, i: int) -> dict[str, dict[str, np.ndarray]]:
    """Frame i of the Mitsuba clip in ``data`` as Blender 5 would lay it out: ``{pass: {channel: (H, W)}}``."""
    d = read_exr(data / f"frame_{i:04d}.exr")
    d = {k: v[CROP] for k, v in d.items()}
    n = np.stack([d[f"N.{c}"] for c in "XYZ"])
    ncam = np.einsum("ij,jhw->ihw", ROT, n)
    z = d["Z"].copy()
    z[:4, :4] = 0.0  # rays that leave the scene (the crop has none of its own)
    passes = {
        "Combined": {c: d[c] for c in "RGB"} | {"A": np.ones_like(z)},
        "Depth": {"Z": np.where(z > 0, z * 0.9, 1e10).astype(np.float32)},  # planar; 1e10 = no hit
        "Normal": {c: d[f"N.{c}"] for c in "XYZ"},
        "Position": {c: d[f"P.{c}"] for c in "XYZ"},
        "Denoising Normal": dict(zip("XYZ", ncam)),
        "Denoising Albedo": {c: d[f"albedo.{c}"] for c in "RGB"},
        "Denoising Depth": {"Z": z},
    }
    return passes


def write_blender(path, passes, multipart=True, layer=LAYER):
    """Write ``passes`` as Blender does: one part per pass (Blender 5) or one part with everything."""
    h, w = next(iter(passes["Combined" if "Combined" in passes else "Normal"].values())).shape
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "BlenderMultiChannel": "Blender V2.55.1 and newer",
              "displayWindow": (np.array([0, 0], np.int32), np.array([w - 1, h - 1], np.int32))}
    full = {p: {f"{layer}.{p}.{c}": np.ascontiguousarray(a, np.float32) for c, a in chans.items()}
            for p, chans in passes.items()}
    if multipart:
        parts = [OpenEXR.Part(dict(header), chans, name=f"{layer}.{p}") for p, chans in full.items()]
        with OpenEXR.File(parts) as f:
            f.write(str(path))
    else:
        with OpenEXR.File(header, {k: v for chans in full.values() for k, v in chans.items()}) as f:
            f.write(str(path))
    return path


def run(capsys, *args):
    rc = main(["denoise", *map(str, args), "--quiet", "--temporal-radius", "0", "--tree-height", "2"])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_multipart_and_single_part_read_the_same(tmp_path, mitsuba_dir):
    passes = blender_passes(mitsuba_dir, 0)
    a = read_render_frame(write_blender(tmp_path / "multi.exr", passes, multipart=True))
    with OpenEXR.File(str(tmp_path / "multi.exr"), separate_channels=True) as f:
        assert len(f.parts) == len(passes)  # really one part per pass
    b = read_render_frame(write_blender(tmp_path / "single.exr", passes, multipart=False))
    for fr in (a, b):
        assert fr.layout == "blender" and fr.layer == LAYER
        assert fr.feature_names == ["Z", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y",
                                    "P.Z", "Ncam.X", "Ncam.Y", "Ncam.Z", "Zplane"]
        np.testing.assert_array_equal(fr.color, np.stack([passes["Combined"][c] for c in "RGB"]))
        np.testing.assert_array_equal(fr.alpha, passes["Combined"]["A"])
        np.testing.assert_array_equal(fr.features["albedo.G"], passes["Denoising Albedo"]["G"])
        np.testing.assert_array_equal(fr.features["Ncam.Z"], passes["Denoising Normal"]["Z"])
        np.testing.assert_array_equal(fr.features["N.X"], passes["Normal"]["X"])
        np.testing.assert_array_equal(fr.features["Z"], passes["Denoising Depth"]["Z"])
        depth = passes["Depth"]["Z"]
        np.testing.assert_array_equal(fr.features["Zplane"], np.where(depth >= 1e10, 0, depth))
        assert fr.sources["albedo.R"] == f"{LAYER}.Denoising Albedo.R"
        assert any("Depth.Z" in n and "1e+10" in n for n in fr.notes)


def test_blender_diffuse_color_read_as_albedo_without_denoising_data(tmp_path, mitsuba_dir):
    """A Blender render without its denoising data but with the Diffuse Color pass (``DiffCol``): that pass
    is the albedo, read with a note; beside the denoising albedo it is left alone."""
    passes = blender_passes(mitsuba_dir, 0)
    albedo = passes.pop("Denoising Albedo")
    fr = read_render_frame(write_blender(tmp_path / "diffcol.exr", {**passes, "DiffCol": albedo}))
    assert {"albedo.R", "albedo.G", "albedo.B"} <= set(fr.feature_names)
    np.testing.assert_array_equal(fr.features["albedo.G"], albedo["G"])
    assert any(f"{LAYER}.DiffCol.R" in n and "as albedo.R" in n for n in fr.notes)
    both = read_render_frame(write_blender(tmp_path / "both.exr", {**passes, "Denoising Albedo": albedo,
                                                                   "DiffCol": passes["Normal"]}))
    np.testing.assert_array_equal(both.features["albedo.R"], albedo["R"])
    assert not any("as albedo" in n for n in both.notes)


def test_blender_clip_denoised_by_the_cli(tmp_path, capsys, mitsuba_dir):
    import torch

    from torchmanifold import metrics as M

    src, flat = tmp_path / "blender", tmp_path / "flat"
    src.mkdir()
    flat.mkdir()
    for i in range(2):
        passes = blender_passes(mitsuba_dir, i)
        write_blender(src / f"frame_{i:04d}.exr", passes, multipart=i == 0)  # both kinds in one clip
        d = read_exr(mitsuba_dir / f"frame_{i:04d}.exr")
        write_exr(flat / f"frame_{i:04d}.exr", {k: v[CROP] for k, v in d.items()})
    paths = sorted(src.glob("*.exr"))
    rc, out, err = run(capsys, *paths, "--out", tmp_path / "out")
    assert rc == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["layout"] == "blender" and summary["layer"] == LAYER and summary["frames"] == 2
    assert "Ncam.X" in summary["feature_channels"] and "note: " in err
    for i, p in enumerate(paths):
        d = read_exr(tmp_path / "out" / p.name)
        assert sorted(d) == [f"{LAYER}.Combined.{c}" for c in "ABGR"]  # the input's layout, alpha kept
        np.testing.assert_array_equal(d[f"{LAYER}.Combined.A"], 1.0)
        den = torch.from_numpy(np.stack([d[f"{LAYER}.Combined.{c}"] for c in "RGB"]))
        ref = read_exr(mitsuba_dir / f"reference_{i:04d}.exr")
        ref = torch.from_numpy(np.stack([ref[c][CROP] for c in "RGB"]))
        raw = torch.from_numpy(np.stack([blender_passes(mitsuba_dir, i)["Combined"][c] for c in "RGB"]))
        assert M.psnr(den, ref) > M.psnr(raw, ref) + 5
    # with the same features, the Blender clip gives exactly what the Mitsuba files of it give
    same = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z"]
    blender_names = [f"Denoising Albedo.{c}" for c in "RGB"] + [f"{LAYER}.Normal.{c}" for c in "XYZ"] + \
        [f"Position.{c}" for c in "XYZ"]
    assert run(capsys, *paths, "--out", tmp_path / "b", "--features", *blender_names, "--output-layout",
               "plain")[0] == 0
    assert run(capsys, *sorted(flat.glob("*.exr")), "--out", tmp_path / "f", "--features", *same)[0] == 0
    for p in paths:
        b, f = read_exr(tmp_path / "b" / p.name), read_exr(tmp_path / "f" / p.name)
        assert sorted(b) == ["B", "G", "R"]
        for c in "RGB":
            np.testing.assert_array_equal(b[c], f[c])


def test_combined_only_is_denoised_and_says_so(tmp_path, capsys, mitsuba_dir):
    p = write_blender(tmp_path / "c.exr", {"Combined": blender_passes(mitsuba_dir, 0)["Combined"]})
    rc, out, err = run(capsys, p, "--out", tmp_path / "out")
    assert rc == 0, err
    assert json.loads(out.strip().splitlines()[-1])["feature_channels"] == []
    assert "no feature channels" in err and "no feature channel guides" in err
    assert np.isfinite(read_exr(tmp_path / "out" / "c.exr")[f"{LAYER}.Combined.R"]).all()


def _drop(passes, key):
    return {k: v for k, v in passes.items() if k != key}


def _set(passes, key, chans):
    return {**passes, key: chans}


def _sizes(passes):
    small = {c: a[:32, :48] for c, a in passes["Denoising Albedo"].items()}
    return _set(passes, "Denoising Albedo", small)


BAD = {
    "no_combined": (lambda p: _drop(p, "Combined"), [f"layer '{LAYER}'", "no Combined pass",
                                                     "Denoising Albedo"]),
    "two_channel_normal": (lambda p: _set(p, "Denoising Normal", {c: p["Denoising Normal"][c] for c in "XY"}),
                           [f"layer '{LAYER}'", "'Denoising Normal'", f"missing {LAYER}.Denoising Normal.Z"]),
    "four_channel_normal": (lambda p: _set(p, "Normal", {**p["Normal"], "W": p["Normal"]["X"]}),
                            [f"unexpected {LAYER}.Normal.W"]),
    "rg_combined": (lambda p: _set(p, "Combined", {c: p["Combined"][c] for c in "RG"}),
                    [f"missing {LAYER}.Combined.B"]),
    "smaller_albedo": (_sizes, [f"{LAYER}.Denoising Albedo.R", "48x32", "96x64"]),
    "zero_albedo": (lambda p: _set(p, "Denoising Albedo", {c: 0 * a for c, a in p["Denoising Albedo"].items()}),
                    [f"{LAYER}.Denoising Albedo.R", "every value is 0"]),
    "nan_depth": (lambda p: _set(p, "Denoising Depth", {"Z": np.full_like(p["Denoising Depth"]["Z"], np.nan)}),
                  [f"{LAYER}.Denoising Depth.Z", "no finite value"]),
}


# every case in both Blender 5's multi-part and the older single-part file, except a pass of another
# size: one part has one data window, so only a multi-part file can hold it
CASES = [(c, m) for c in sorted(BAD) for m in (True, False) if m or c != "smaller_albedo"]


@pytest.mark.parametrize("case,multipart", CASES)
def test_bad_blender_input_is_refused_by_name(tmp_path, capsys, mitsuba_dir, case, multipart):
    edit, expected = BAD[case]
    good = write_blender(tmp_path / "good.exr", blender_passes(mitsuba_dir, 1))
    bad = write_blender(tmp_path / f"{case}.exr", edit(blender_passes(mitsuba_dir, 0)), multipart)
    out = tmp_path / "out"
    rc, _, err = run(capsys, good, bad, "--out", out)  # the bad frame second: fails after reading the first
    assert rc == 2
    assert bad.name in err, err
    for e in expected:
        assert e in err, (e, err)
    assert not out.exists() or not list(out.rglob("*.exr"))  # nothing written half-way


def test_partly_nan_features_are_masked_and_reported(tmp_path, capsys, mitsuba_dir):
    passes = blender_passes(mitsuba_dir, 0)
    passes["Denoising Albedo"]["G"][10:12, 10:13] = np.nan
    rc, out, err = run(capsys, write_blender(tmp_path / "n.exr", passes), "--out", tmp_path / "out")
    assert rc == 0, err
    assert json.loads(out.strip().splitlines()[-1])["nonfinite_features"] == 6
    assert "6 non-finite samples" in err
    assert np.isfinite(read_exr(tmp_path / "out" / "n.exr")[f"{LAYER}.Combined.G"]).all()


def test_several_view_layers_need_a_choice(tmp_path, capsys, mitsuba_dir):
    passes = blender_passes(mitsuba_dir, 0)
    chans = {}
    for layer in ("Front", "Back.001"):  # Blender names copies with a dot: the layer name holds one
        for p, cs in passes.items():
            chans |= {f"{layer}.{p}.{c}": np.ascontiguousarray(a, np.float32) for c, a in cs.items()}
    path = tmp_path / "two.exr"
    write_exr(path, chans)
    rc, _, err = run(capsys, path, "--out", tmp_path / "out")
    assert rc == 2 and "two.exr" in err and "'Back.001', 'Front'" in err and "--layer" in err
    rc, out, err = run(capsys, path, "--out", tmp_path / "out2", "--layer", "Back.001")
    assert rc == 0, err
    assert json.loads(out.strip().splitlines()[-1])["layer"] == "Back.001"
    assert sorted(read_exr(tmp_path / "out2" / "two.exr")) == [f"Back.001.Combined.{c}" for c in "ABGR"]


def test_a_real_blender5_frame_through_the_cli(tmp_path, capsys):
    """The frame Blender 5.0.1 wrote (tests/io/data): denoised, its emitter kept out of the filter, and
    given back as Blender multilayer."""
    from pathlib import Path

    src = Path(__file__).parents[1] / "io" / "data" / "blender5_frame.exr"
    rc, out, err = run(capsys, src, "--out", tmp_path / "out")
    assert rc == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["sources"]["albedo.R"] == f"{LAYER}.Denoising Albedo.R"
    assert summary["sources"]["Ncam.X"] == f"{LAYER}.Denoising Normal.X"
    d = read_exr(tmp_path / "out" / src.name)
    assert sorted(d) == [f"{LAYER}.Combined.{c}" for c in "ABGR"]
    assert all(np.isfinite(v).all() for v in d.values())
    emission = read_render_frame(src).emission
    lit = emission.sum(0) > 0
    den = np.stack([d[f"{LAYER}.Combined.{c}"] for c in "RGB"])
    assert lit.any() and np.all(den[:, lit] >= emission[:, lit] - 1e-4)  # the tile is not blurred away
    with OpenEXR.File(str(tmp_path / "out" / src.name)) as f:
        assert f.header()["BlenderMultiChannel"] == "Blender V2.55.1 and newer"
