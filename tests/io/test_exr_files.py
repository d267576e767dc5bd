"""EXR channels from every part of a file, and writes that leave no half-written file behind."""
import numpy as np
import OpenEXR
import pytest

from torchmanifold.io import atomic_path, read_exr, write_exr
from torchmanifold.io.files import staged_dir

RNG = np.random.default_rng(0)


def _parts(path, parts, origins=None):
    out = []
    for k, (name, chans) in enumerate(parts.items()):
        h = {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION}
        out.append(OpenEXR.Part(h, chans, name=name))
    with OpenEXR.File(out) as f:
        f.write(str(path))
    return path


def test_multipart_channels_are_merged(tmp_path):
    a, b, c = (RNG.random((4, 5), dtype=np.float32) for _ in range(3))
    path = _parts(tmp_path / "m.exr", {"L.Combined": {"L.Combined.R": a}, "L.Depth": {"L.Depth.Z": b},
                                       "extra": {"Y": c}})
    d = read_exr(path)
    assert sorted(d) == ["L.Combined.R", "L.Depth.Z", "Y"]
    np.testing.assert_array_equal(d["L.Depth.Z"], b)
    np.testing.assert_array_equal(read_exr(path, ["Y"])["Y"], c)


def test_short_names_two_parts_share_get_their_part_name(tmp_path):
    a, b = RNG.random((3, 3), dtype=np.float32), RNG.random((3, 3), dtype=np.float32)
    path = _parts(tmp_path / "s.exr", {"diffuse": {"R": a}, "specular": {"R": b}})
    d = read_exr(path)
    assert sorted(d) == ["diffuse.R", "specular.R"]
    np.testing.assert_array_equal(d["specular.R"], b)


def test_parts_that_do_not_line_up_are_refused(tmp_path):
    h0 = {"type": OpenEXR.scanlineimage}
    h1 = {"type": OpenEXR.scanlineimage,
          "dataWindow": (np.array([1, 0], np.int32), np.array([3, 2], np.int32)),
          "displayWindow": (np.array([0, 0], np.int32), np.array([2, 2], np.int32))}
    parts = [OpenEXR.Part(h0, {"R": np.zeros((3, 3), np.float32)}, name="a"),
             OpenEXR.Part(h1, {"Z": np.zeros((3, 3), np.float32)}, name="b")]
    with OpenEXR.File(parts) as f:
        f.write(str(tmp_path / "o.exr"))
    with pytest.raises(ValueError, match=r"o\.exr: the parts' data windows start at different pixels"):
        read_exr(tmp_path / "o.exr")


def test_atomic_path_all_or_nothing(tmp_path):
    target = tmp_path / "sub" / "clip.mp4"
    with atomic_path(target) as tmp:
        assert tmp.name == "clip.tmp.mp4" and tmp.parent == target.parent
        tmp.write_text("new")
    assert target.read_text() == "new"
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert target.read_text() == "new" and sorted(p.name for p in target.parent.iterdir()) == ["clip.mp4"]


def test_write_exr_failure_leaves_nothing(tmp_path):
    with pytest.raises(ValueError, match="one shape"):
        write_exr(tmp_path / "f.exr", {"R": np.zeros((2, 2)), "G": np.zeros((3, 2))})
    assert list(tmp_path.iterdir()) == []


def test_staged_dir_moves_all_or_nothing(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(RuntimeError):
        with staged_dir(out) as stage:
            (stage / "a.txt").write_text("a")
            raise RuntimeError("second file failed")
    assert list(out.iterdir()) == []
    with staged_dir(out) as stage:
        for n in ("a.txt", "b.txt"):
            (stage / n).write_text(n)
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "b.txt"]


def test_samples_per_pixel_from_the_header(tmp_path):
    """The sample count a renderer records: ``spp`` (the shared Mitsuba clips), Blender's
    ``cycles.<layer>.samples``; nothing, or something not a positive count, gives None."""
    import numpy as np

    from torchmanifold.io.exr import exr_samples_per_pixel, header_samples_per_pixel, read_exr, write_exr

    px = {"R": np.zeros((2, 3), np.float32)}
    cases = {"mitsuba": ({"spp": "4"}, 4), "blender": ({"cycles.ViewLayer.samples": "16"}, 16),
             "none": ({}, None), "text": ({"spp": "many"}, None), "zero": ({"spp": "0"}, None)}
    for name, (attrs, want) in cases.items():
        path = write_exr(tmp_path / f"{name}.exr", px, attributes=attrs)
        assert exr_samples_per_pixel(path) == want, name
        headers = []  # the headers of the one open that reads the pixels say the same
        assert list(read_exr(path, headers=headers)) == ["R"], name
        assert header_samples_per_pixel(headers) == want, name
    assert exr_samples_per_pixel(tmp_path / "missing.exr") is None
