"""The feature table: the shader's slots agree with it, and a feature added to it alone flows through
EXR writing/reading, the renderer-layout reader and the denoiser's guide selection."""
import re
from dataclasses import replace

import numpy as np
import pytest
import torch

from torchmanifold import features as feature_table
from torchmanifold.io.exr import read_exr, write_exr
from torchmanifold.io.frames import read_render_frame
from torchmanifold.pipeline.denoise import (
    GROUP_SIGMAS,
    DenoiseSettings,
    _select_guide,
    canonical_name,
    default_guide_sigmas,
    denoise_frames,
    feature_group,
)
from torchmanifold.render import MATERIAL_TYPES, PRIM_KINDS, RenderResult, read_frame_exr, write_frame_exr
from torchmanifold.render.tracer import BINDINGS, SHADER_PATH, shader_defines

SYNTHETIC = feature_table.Feature(
    "Q", ("Q.U", "Q.V"), tracer=("Qu", "Qv"), mitsuba=("quux.U", "quux.V"), blender=("Quux.U", "Quux.V"),
    half=False, sigma=0.25, sigma_source="made up for this test", guides=True)


@pytest.fixture
def with_synthetic(monkeypatch):
    monkeypatch.setattr(feature_table, "FEATURES", feature_table.FEATURES)  # restored after the test
    feature_table.register(SYNTHETIC)
    return SYNTHETIC


def test_shader_slots_are_the_table():
    """Every tracer channel of the table is accumulated by the shader in its own slot, and the shader
    uses no slot, material, kind or binding name that Python does not define."""
    src = SHADER_PATH.read_text()
    written = set(re.findall(r"feat\[FEAT_(\w+)\] \+=", src))
    assert written == {n.upper() for n in feature_table.tracer_names()}
    assert not re.search(r"feat\[\d+\]", src), "a bare slot number in the shader"
    defined = set(re.findall(r"#define (\w+)", shader_defines()))
    used = set(re.findall(r"\b((?:FEAT|MAT|PRIM|BIND)_\w+|N_FEAT)\b", src))
    assert used <= defined, used - defined
    assert {f"BIND_{k.upper()}" for k in BINDINGS} <= used  # every binding is declared in the shader
    assert {f"MAT_{k.upper()}" for k in MATERIAL_TYPES} <= used
    assert {f"PRIM_{k.upper()}" for k in ("sphere", "quad")} <= used and set(PRIM_KINDS) == {"sphere", "quad", "mesh"}
    slots = dict(re.findall(r"#define FEAT_(\w+) (\d+)", shader_defines()))
    assert [int(slots[n.upper()]) for n in feature_table.tracer_names()] == list(range(len(slots)))


def test_table_lookups():
    assert canonical_name("Mr") == "albedo.R" == canonical_name("Denoising Albedo.R")
    assert canonical_name("Normal.Y") == "N.Y" and canonical_name("Denoising Normal.Y") == "Ncam.Y"
    assert canonical_name("Depth.Z") == "Zplane" and canonical_name("Denoising Depth.Z") == "Z"
    assert feature_group("Sx") == "S" and feature_group("emission.R") == "emission"
    assert feature_table.renderer_channel("N.X", "blender") == "Normal.X"
    assert feature_table.renderer_channel("D.X", "mitsuba") is None
    assert feature_table.default_sigma("Mr") == 0.1 and feature_table.default_sigma("T") is None
    assert feature_table.is_half("Nx") and not feature_table.is_half("Z") and not feature_table.is_half("emission.R")
    assert dict(GROUP_SIGMAS) == {f.group: f.sigma for f in feature_table.FEATURES if f.sigma is not None}
    # the default guide: D/S (random per sample) and T never; Z only without P; N only without Ncam
    names = ["T", "Z", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "D.X", "D.Y", "D.Z", "P.X", "P.Y", "P.Z"]
    chosen = [names[k] for k in _select_guide(names, DenoiseSettings())]
    assert chosen == ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z"]
    no_p = [n for n in names if not n.startswith("P")]
    assert [no_p[k] for k in _select_guide(no_p, DenoiseSettings())][0] == "Z"
    blender = ["Zplane", "N.X", "N.Y", "N.Z", "Ncam.X", "Ncam.Y", "Ncam.Z"]
    assert [blender[k] for k in _select_guide(blender, DenoiseSettings())] == blender[:1] + blender[4:]


def test_table_rejects_clashes_and_bad_rows():
    with pytest.raises(ValueError, match="'albedo.R' of group 'X' is already used by group 'albedo'"):
        feature_table.register(feature_table.Feature("X", ("albedo.R",)))
    with pytest.raises(ValueError, match="tracer must name 2 channels"):
        feature_table.Feature("X", ("X.a", "X.b"), tracer=("Xa",))
    with pytest.raises(ValueError, match="no default sigma"):
        feature_table.Feature("X", ("X.a",), guides=True)
    assert "X" not in feature_table.groups()


def test_synthetic_feature_flows_through(with_synthetic, tmp_path):
    assert "Qu" in feature_table.tracer_names()
    assert f"N_FEAT {len(feature_table.tracer_names())}" in feature_table.shader_defines()
    h, w = 6, 5
    rng = np.random.default_rng(0)
    q = rng.random((1, 2, h, w), dtype=np.float32)
    # our EXR files: tracer names -> the table's channel names (float32 as the row says) -> back
    res = RenderResult(color=torch.rand(1, 3, h, w), features=torch.from_numpy(q), feature_names=["Qu", "Qv"],
                       object_id=torch.zeros(1, h, w, dtype=torch.int32), motion=torch.zeros(1, 2, h, w),
                       emission=torch.zeros(1, 3, h, w), times=torch.zeros(1, dtype=torch.float64), spp=1,
                       sample_offset=0, seed=0)
    path = write_frame_exr(tmp_path / "ours.exr", res)
    assert np.array_equal(read_exr(path, ["Q.U"])["Q.U"], q[0, 0])
    _, feats, names = read_frame_exr(path)
    assert names == ["Qu", "Qv"] and np.array_equal(feats.numpy(), q[0])
    # Mitsuba's and Blender's channel names of the row are read as the canonical ones
    col = rng.random((3, h, w), dtype=np.float32)
    write_exr(tmp_path / "mi.exr", {"R": col[0], "G": col[1], "B": col[2], "quux.U": q[0, 0], "quux.V": q[0, 1]})
    fr = read_render_frame(tmp_path / "mi.exr")
    assert fr.feature_names == ["Q.U", "Q.V"] and np.array_equal(fr.features["Q.V"], q[0, 1])
    bl = {f"VL.Combined.{c}": col[k] for k, c in enumerate("RGB")} | {"VL.Quux.U": q[0, 0], "VL.Quux.V": q[0, 1]}
    write_exr(tmp_path / "bl.exr", bl)
    fr = read_render_frame(tmp_path / "bl.exr")
    assert fr.layout == "blender" and fr.sources["Q.U"] == "VL.Quux.U" and np.array_equal(fr.features["Q.U"], q[0, 0])
    # the denoiser: guides by default with the row's sigma
    names = ["albedo.R", "albedo.G", "albedo.B", "Q.U", "Q.V"]
    assert _select_guide(names, DenoiseSettings()) == [0, 1, 2, 3, 4]
    assert default_guide_sigmas(["Q.U", "Qv"]).tolist() == [[0.25, 0.25]]
    # and changes the result: a step in Q alone (flat colour guide otherwise) keeps an edge sharp
    c = torch.full((1, 3, 16, 16), 0.5)  # grey: one hue on both sides (the hue guides where no albedo does)
    c[..., 8:] = 1.0
    f = torch.zeros(1, 2, 16, 16)
    f[:, :, :, 8:] = 1.0
    s = DenoiseSettings(firefly="none", sigma_s=4.0, radiance_sigma=0.0, footprint_sigma=0.0)  # Q the only guide
    guided = denoise_frames(c, f, ["Q.U", "Q.V"], settings=s)
    blind = denoise_frames(c, f, ["Q.U", "Q.V"], settings=replace(s, guide_sigmas={"Q.U": 1e6, "Q.V": 1e6}))
    step = lambda y: float(y[0, 0, :, 8].mean() - y[0, 0, :, 7].mean())  # noqa: E731
    assert step(guided) > 0.45 > step(blind)


def test_registry_restored_after_synthetic():
    assert "Q" not in feature_table.groups() and "Qu" not in feature_table.tracer_names()
