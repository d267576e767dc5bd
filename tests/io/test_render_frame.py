"""read_render_frame on flat files (ours, Mitsuba's) and write_color's layouts; the Blender layout is
tested end to end in tests/pipeline/test_blender_input.py."""
import numpy as np
import pytest

from torchmanifold.io import read_exr, read_render_frame, write_color, write_exr
from torchmanifold.io.frames import mixed_count, samples_per_pixel_shown

H, W = 6, 7
RNG = np.random.default_rng(1)


def _rand(*names):
    return {n: RNG.random((H, W), dtype=np.float32) + 0.1 for n in names}


def mitsuba_like(path, **extra):
    chans = _rand("R", "G", "B", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z", "P.X", "P.Y", "P.Z")
    chans.update(extra)
    write_exr(path, chans)
    return chans


def test_flat_file_features_in_table_order(tmp_path):
    chans = mitsuba_like(tmp_path / "m.exr", **_rand("emission.R", "emission.G", "emission.B", "T"))
    fr = read_render_frame(tmp_path / "m.exr")
    assert fr.layout == "flat" and fr.layer is None and fr.notes == []
    assert fr.feature_names == ["T", "Z", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y",
                                "P.Z"]
    np.testing.assert_array_equal(fr.color[1], chans["G"])
    np.testing.assert_array_equal(fr.stack(["P.Z", "Z"]), np.stack([chans["P.Z"], chans["Z"]]))
    np.testing.assert_array_equal(fr.emission[2], chans["emission.B"])
    # an AOV under a name the table does not know is not read, and the notes say so
    mitsuba_like(tmp_path / "nn.exr", **_rand("nn.X", "nn.Y", "nn.Z"))
    fr = read_render_frame(tmp_path / "nn.exr")
    assert "nn.X" not in fr.feature_names and any("not read" in n and "nn.X, nn.Y, nn.Z" in n for n in fr.notes)
    # chosen by any alias; a channel the table does not know is read under its own name
    fr = read_render_frame(tmp_path / "m.exr", feature_channels=["Mg", "Normal.X", "emission.R"])
    assert fr.feature_names == ["albedo.G", "N.X", "emission.R"]
    np.testing.assert_array_equal(fr.features["N.X"], chans["N.X"])


def test_other_renderers_names_read_where_ours_are_missing(tmp_path):
    """pbrt-v4's gbuffer film writes Albedo.R/G/B and its shading normal as Ns.X/Y/Z; a user's Mitsuba AOVs
    may be albedo.r and normal.x, pbrt's AOV film Px/Py/Pz: each is read as the table's feature, and a note
    says what was read as what. Where a file has the table's own names they win, but a shading normal beside
    the geometric N is read in its place; a group with a component missing is not guessed."""
    pbrt = _rand("R", "G", "B", "Albedo.R", "Albedo.G", "Albedo.B", "Ns.X", "Ns.Y", "Ns.Z", "P.X", "P.Y", "P.Z")
    write_exr(tmp_path / "pbrt.exr", pbrt)
    fr = read_render_frame(tmp_path / "pbrt.exr")
    assert fr.feature_names == ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z"]
    np.testing.assert_array_equal(fr.features["albedo.G"], pbrt["Albedo.G"])
    np.testing.assert_array_equal(fr.features["N.Z"], pbrt["Ns.Z"])
    assert any("Albedo.R, Albedo.G, Albedo.B as albedo.R, albedo.G, albedo.B" in n for n in fr.notes)
    assert not any("not read" in n for n in fr.notes)
    user = _rand("R", "G", "B", "albedo.r", "albedo.g", "albedo.b", "normal.x", "normal.y", "normal.z", "Px",
                 "Py", "Pz")
    write_exr(tmp_path / "user.exr", user)
    fr = read_render_frame(tmp_path / "user.exr")
    assert fr.feature_names == ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z"]
    np.testing.assert_array_equal(fr.features["P.Y"], user["Py"])
    # the Mitsuba documentation's own example of its aov integrator: dd.y:depth, nn:sh_normal
    write_exr(tmp_path / "doc.exr", _rand("R", "G", "B", "albedo.R", "albedo.G", "albedo.B", "dd.y", "nn.X",
                                          "nn.Y", "nn.Z"))
    fr = read_render_frame(tmp_path / "doc.exr")
    assert fr.feature_names == ["Z", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z"]
    # pbrt-v4's gbuffer holds its geometric normal as N too: the shading normal is read in its place
    write_exr(tmp_path / "both_normals.exr", {**pbrt, **_rand("N.X", "N.Y", "N.Z")})
    fr = read_render_frame(tmp_path / "both_normals.exr")
    np.testing.assert_array_equal(fr.features["N.X"], pbrt["Ns.X"])
    assert any("Ns.X, Ns.Y, Ns.Z as N.X, N.Y, N.Z" in n and "in place of N.X, N.Y, N.Z" in n for n in fr.notes)
    # our names win (but for a shading normal); an incomplete group is no feature
    mitsuba_like(tmp_path / "both.exr", **_rand("Albedo.R", "Albedo.G", "Albedo.B"))
    fr = read_render_frame(tmp_path / "both.exr")
    assert any("not read" in n and "Albedo.B" in n for n in fr.notes) and not any("as albedo" in n for n in fr.notes)
    write_exr(tmp_path / "part.exr", _rand("R", "G", "B", "Albedo.R", "Albedo.G", "N.X", "N.Y", "N.Z"))
    fr = read_render_frame(tmp_path / "part.exr")
    assert fr.feature_names == ["N.X", "N.Y", "N.Z"] and any("not read" in n and "Albedo.R" in n for n in fr.notes)


def test_sample_count_told_by_the_normals(tmp_path):
    """Without a count in the header, unit normals at every pixel that hits mean 1 sample per pixel and
    one pixel averaging two directions at least 2; too few hits or no normals leave the count unknown; a
    header's count is taken as it is."""
    n = RNG.normal(size=(3, 32, 32)).astype(np.float32)
    n /= np.linalg.norm(n, axis=0)
    n[:, :4] = 0  # rows whose rays left the scene
    chans = {c: RNG.random((32, 32), dtype=np.float32) for c in "RGB"}
    chans.update({f"N.{c}": n[k] for k, c in enumerate("XYZ")})
    write_exr(tmp_path / "one.exr", chans, half=["N.X", "N.Y", "N.Z"])
    fr = read_render_frame(tmp_path / "one.exr")
    assert fr.samples_per_pixel == 1 and any("no sample count" in note for note in fr.notes)
    mixed = n.copy()
    mixed[:, 8, 8] = 0.5 * (n[:, 8, 8] + n[:, 8, 9])  # one pixel, the mean of two samples
    assert np.linalg.norm(mixed[:, 8, 8]) < 0.99
    write_exr(tmp_path / "mixed.exr", {**chans, **{f"N.{c}": mixed[k] for k, c in enumerate("XYZ")}})
    fr = read_render_frame(tmp_path / "mixed.exr")
    assert fr.samples_per_pixel == 2 and any("taken as 2" in note for note in fr.notes)
    assert samples_per_pixel_shown({f"N.{c}": n[k, 3:19] for k, c in enumerate("XYZ")}) is None  # 480 hits
    assert samples_per_pixel_shown({f"N.{c}": n[k, 3:21] for k, c in enumerate("XYZ")}) == 1  # 544
    assert samples_per_pixel_shown({f"N.{c}": mixed[k, 3:21] for k, c in enumerate("XYZ")}) == 2
    assert samples_per_pixel_shown({"R": chans["R"]}) is None
    write_exr(tmp_path / "four.exr", chans, attributes={"spp": "4"})
    assert read_render_frame(tmp_path / "four.exr").samples_per_pixel == 4


def _discs(n: int, size: int = 64, weighted: bool = False, seed: int = 3) -> dict:
    """Features of a scene of flat discs over a plane (each its own albedo, normal and depth) rendered with
    ``n`` jittered samples per pixel, averaged as a box filter does, or ``weighted`` by a Gaussian of each
    sample's offset from the pixel's centre (a renderer's gaussian pixel filter)."""
    rng = np.random.default_rng(seed)
    k = 14
    centre, radius = rng.uniform(0, size, (k, 2)), rng.uniform(4, 12, k)
    albedo, depth = rng.uniform(0.05, 0.95, (k + 1, 3)), np.sort(rng.uniform(1, 9, k + 1))
    normal = rng.normal(size=(k + 1, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    y, x = np.mgrid[:size, :size].astype(np.float64)
    acc, total = np.zeros((size, size, 7)), np.zeros((size, size, 1))
    for _ in range(n):
        jy, jx = rng.random((size, size)), rng.random((size, size))
        py, px = y + jy, x + jx
        hit = np.full((size, size), k)  # the plane behind every disc
        for i in range(k - 1, -1, -1):  # nearest last
            inside = (py - centre[i, 0]) ** 2 + (px - centre[i, 1]) ** 2 < radius[i] ** 2
            hit = np.where(inside, i, hit)
        w = np.exp(-((jy - 0.5) ** 2 + (jx - 0.5) ** 2) / 0.18)[..., None] if weighted else 1.0
        acc += w * np.concatenate([albedo[hit], normal[hit], depth[hit][..., None]], -1)
        total += w
    v = (acc / total).astype(np.float32)
    names = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z"]
    return {c: v[..., i] for i, c in enumerate(names)}


@pytest.mark.parametrize("n", [2, 3, 4, 8, 16])
def test_sample_count_told_by_the_edges_mixes(tmp_path, n):
    """Without a count in the header, a pixel across an edge holds k/n of one surface's features: the
    count is read from those fractions (a brute-force render of discs at n samples per pixel)."""
    feats = _discs(n)
    write_exr(tmp_path / "f.exr", {**feats, **{c: feats["albedo.R"] for c in "RGB"}})
    fr = read_render_frame(tmp_path / "f.exr")
    assert fr.samples_per_pixel == n and any(f"fractions k/{n}" in note for note in fr.notes)


def test_sample_count_from_weighted_samples_is_the_least():
    """Samples weighted by a pixel filter put the mixes off the grid of k/n: no count shows, and the count
    taken is 2, the least the shortened normals allow; one sample per pixel stays 1."""
    assert mixed_count(_discs(4, weighted=True)) is None
    assert samples_per_pixel_shown(_discs(4, weighted=True)) == 2
    assert samples_per_pixel_shown(_discs(1)) == 1


def test_flat_file_errors_name_file_and_channel(tmp_path):
    chans = _rand("R", "G", "B", "albedo.R", "albedo.G")
    write_exr(tmp_path / "a.exr", chans)
    with pytest.raises(ValueError, match=r"a\.exr: feature 'albedo' has channels \['albedo.G', 'albedo.R'\] "
                                         r"but not 'albedo.B'"):
        read_render_frame(tmp_path / "a.exr")
    mitsuba_like(tmp_path / "z.exr", **{"N.X": np.zeros((H, W), np.float32), "N.Y": np.zeros((H, W), np.float32),
                                        "N.Z": np.zeros((H, W), np.float32)})
    with pytest.raises(ValueError, match=r"z\.exr: channel\(s\) N\.X, N\.Y, N\.Z: every value is 0"):
        read_render_frame(tmp_path / "z.exr")
    # time may be 0 everywhere (frame 0 without motion blur)
    mitsuba_like(tmp_path / "t.exr", T=np.zeros((H, W), np.float32))
    assert "T" in read_render_frame(tmp_path / "t.exr").features
    with pytest.raises(ValueError, match=r"t\.exr: feature channel 'Q' not found"):
        read_render_frame(tmp_path / "t.exr", feature_channels=["Q"])
    with pytest.raises(ValueError, match="color_channels must name 3 channels"):
        read_render_frame(tmp_path / "t.exr", color_channels=["R", "G"])


def test_write_color_layouts(tmp_path):
    mitsuba_like(tmp_path / "m.exr", **_rand("beauty.R", "beauty.G", "beauty.B"))
    fr = read_render_frame(tmp_path / "m.exr", color_channels=["beauty.R", "beauty.G", "beauty.B"])
    col = RNG.random((3, H, W), dtype=np.float32)
    assert sorted(read_exr(write_color(tmp_path / "o1.exr", col, fr))) == ["beauty.B", "beauty.G", "beauty.R"]
    d = read_exr(write_color(tmp_path / "o2.exr", col, fr, layout="plain"))
    assert sorted(d) == ["B", "G", "R"] and np.array_equal(d["G"], col[1])
    with pytest.raises(ValueError, match=r"color must be \(3, H, W\)"):
        write_color(tmp_path / "o3.exr", col[:2], fr)
    assert not (tmp_path / "o3.exr").exists()


def test_a_real_blender5_file(tmp_path):
    """A frame Blender 5.0.1 wrote (tests/io/data/make_blender5_frame.py): one part per pass, all read,
    with the meanings the feature table gives them (camera at (0, -4, 2), clip start 0.1)."""
    import OpenEXR

    from torchmanifold.io.exr import read_exr as raw_read
    from pathlib import Path

    path = Path(__file__).parent / "data" / "blender5_frame.exr"
    with OpenEXR.File(str(path), separate_channels=True) as f:
        assert len(f.parts) == 8 and f.parts[0].name() == "ViewLayer.Combined"
        assert list(f.channels()) == [f"ViewLayer.Combined.{c}" for c in "ABGR"]  # the first part alone
    fr = read_render_frame(path)
    assert fr.layout == "blender" and fr.layer == "ViewLayer" and fr.size == (24, 32)
    assert fr.feature_names == ["Z", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z",
                                "Ncam.X", "Ncam.Y", "Ncam.Z", "Zplane"]
    raw = raw_read(path)
    hit = fr.features["Z"] > 0
    assert 0 < hit.sum() < hit.size  # some rays leave the scene
    # Depth: planar, 1e10 where nothing is hit (read as 0); Denoising Depth: ray distance from the clip start
    assert np.all(raw["ViewLayer.Depth.Z"][~hit] == 1e10) and np.all(fr.features["Zplane"][~hit] == 0)
    p = fr.stack(["P.X", "P.Y", "P.Z"]) - np.array([0, -4, 2], np.float32)[:, None, None]
    fwd = np.array([0, np.sin(1.2), -np.cos(1.2)], np.float32)
    planar, ray = np.einsum("i,ihw->hw", fwd, p)[hit], np.linalg.norm(p, axis=0)[hit]
    np.testing.assert_allclose(fr.features["Zplane"][hit], planar, atol=1e-4)
    # the ray starts on the near plane: clip_start 0.1 along the axis is 0.1 * ray / planar along the ray
    np.testing.assert_allclose(fr.features["Z"][hit], ray - 0.1 * ray / planar, atol=1e-4)
    # Denoising Normal is in camera space: facing the camera means Z < 0; Normal is world space (+Z floor)
    assert np.all(fr.features["Ncam.Z"][hit] < 0)
    assert np.median(fr.features["N.Z"][hit]) > 0.9
    # Emission: the tile's radiance where the camera sees it, part of Combined
    lit = fr.emission.sum(0) > 0
    assert lit.any() and np.allclose(fr.emission[:, lit], np.array([5.0, 2.5, 1.0])[:, None])
    assert np.all(fr.color >= fr.emission - 1e-5) and fr.sources["emission.G"] == "ViewLayer.Emission.G"
