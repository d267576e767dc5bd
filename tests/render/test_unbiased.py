"""Radiance is unbiased: furnace scenes with known answers, and many 1-spp frames vs a long render."""
import math
import tomllib

import pytest
import numpy as np
import torch

from torchmanifold.render import PathTracer, default_scene, scene_from_dict
from torchmanifold.render.scene import SCENES_DIR


def _box(albedo, emission, max_depth, rr_depth):
    """A closed box of six inward-facing diffuse quads that all emit; the camera sits inside."""
    faces = [  # origin, u, v with u x v pointing into the box [-1, 1]^3
        ([-1, -1, -1], [0, 0, 2], [2, 0, 0]), ([-1, 1, -1], [2, 0, 0], [0, 0, 2]),
        ([-1, -1, -1], [2, 0, 0], [0, 2, 0]), ([-1, -1, 1], [0, 2, 0], [2, 0, 0]),
        ([-1, -1, -1], [0, 2, 0], [0, 0, 2]), ([1, -1, -1], [0, 0, 2], [0, 2, 0]),
    ]
    return scene_from_dict({
        "render": {"max_depth": max_depth, "rr_depth": rr_depth},
        "camera": {"eye": [0.1, 0.2, 0.3], "target": [0.5, 0.0, -1.0], "fov": 70},
        "materials": {"m": {"color": [albedo] * 3, "emission": list(emission)}},
        "objects": [{"type": "quad", "origin": o, "u": u, "v": v, "material": "m"} for o, u, v in faces],
    })


def test_white_sphere_in_uniform_environment_is_invisible(ctx):
    """Albedo-1 diffuse convex object under uniform light: every sample returns the environment exactly."""
    bg = [0.5, 0.7, 0.9]
    scene = scene_from_dict({
        "render": {"background": bg, "max_depth": 4, "rr_depth": 100},
        "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "fov": 40},
        "materials": {"white": {"color": [1, 1, 1]}},
        "objects": [{"type": "sphere", "center": [0, 0, 0], "radius": 0.8, "material": "white"}],
    })
    assert "Sx" not in scene.needed_features()  # no lights, no shadow rays
    res = PathTracer(scene, 32, 32, ctx=ctx).render([0.0], spp=2, seed=1)
    assert (res.object_id == 0).sum() > 200
    torch.testing.assert_close(res.color, torch.tensor(bg).view(1, 3, 1, 1).expand_as(res.color), atol=2e-6, rtol=0)


def test_emissive_furnace_box_with_nee_and_roulette(ctx):
    """Closed box, albedo a, emission e everywhere: L = e / (1 - a), through NEE + Russian roulette."""
    a, e = 0.5, (1.0, 2.0, 0.5)
    scene = _box(a, e, max_depth=64, rr_depth=2)
    res = PathTracer(scene, 32, 32, features=["Sx", "Mr"], ctx=ctx).render([0.0], spp=8, seed=2)
    assert ctx.error == "GL_NO_ERROR"
    torch.testing.assert_close(res.emission, torch.tensor(e).view(1, 3, 1, 1).expand_as(res.emission))
    expected = torch.tensor(e) / (1 - a)
    per_pixel = res.color[0].flatten(1)  # (3, N) i.i.d. pixel estimates (8 spp each)
    mean = per_pixel.double().mean(1)
    se = per_pixel.double().std(1) / math.sqrt(per_pixel.shape[1])
    z = (mean - expected.double()) / se
    assert torch.all(z.abs() < 4.5), (mean, expected, z)
    # max_depth 2 keeps emission at 2 vertices + NEE from both: e (1 + a + a^2); a truncation is visible
    short = PathTracer(_box(a, e, max_depth=2, rr_depth=64), 32, 32, ctx=ctx).render([0.0], spp=8, seed=2)
    torch.testing.assert_close(short.color.mean((0, 2, 3)), torch.tensor(e) * (1 + a + a * a), rtol=0.02, atol=0)


def _sphere_light_scene():
    """The built-in box lit by a small sphere light instead of the ceiling quad (cone sampling in NEE)."""
    with open(SCENES_DIR / "cornell_box.toml", "rb") as fh:
        data = tomllib.load(fh)
    data["objects"] = [o for o in data["objects"] if o.get("name") != "light"]
    data["objects"].append({"type": "sphere", "center": [0.0, 1.75, 0.0], "radius": 0.12, "material": "lamp"})
    data["materials"]["lamp"]["emission"] = [40.0, 36.0, 30.0]
    return scene_from_dict(data)


@pytest.mark.parametrize("which", ["default", "sphere_light"])
def test_mean_of_1spp_frames_matches_long_render(ctx, which):
    """Per-region z-test: 1-spp frames (fresh sample offsets, seed 0) vs one 2048-spp render (seed 1)."""
    w = h = 16
    n_frames, long_spp, block = 256, 2048, 4
    scene = default_scene() if which == "default" else _sphere_light_scene()
    tr = PathTracer(scene, w, h, features=[], ctx=ctx)
    frames = torch.stack([tr.render([0.0], spp=1, seed=0, sample_offset=i).color[0] for i in range(n_frames)])
    long = tr.render([0.0], spp=long_spp, seed=1).color[0]
    lum = lambda x: x.double().mean(-3)  # noqa: E731  (colour -> grey)

    def blocks(x):  # (..., H, W) -> (..., H/b, W/b) block means
        return x.unflatten(-2, (h // block, block)).unflatten(-1, (w // block, block)).mean((-3, -1))

    fb = blocks(lum(frames))  # (n, 4, 4): per-frame block means, i.i.d. over frames
    m1, se1 = fb.mean(0), fb.std(0) / math.sqrt(n_frames)
    # the long render's standard error, from the spread of the 1-spp frames scaled to long_spp samples
    se2 = fb.std(0) / math.sqrt(long_spp)
    m2 = blocks(lum(long))
    z = (m1 - m2) / torch.sqrt(se1**2 + se2**2)
    assert torch.all(z.abs() < 4.5), z
    assert (z**2).mean() < 3.0, z  # about 1 if unbiased
    # and the test has power: a 10 % darker long render fails it
    z_bad = (m1 - 0.9 * m2) / torch.sqrt(se1**2 + se2**2)
    assert (z_bad.abs() > 4.5).any() or (z_bad**2).mean() >= 3.0


def test_direct_light_from_sphere_and_quad_matches_analytic(ctx):
    """max_depth 1 (first hit + NEE only) on a plane: sphere light E = pi Le (r/d)^2 cos(theta) exactly;
    a small distant quad light nearly a point light: E = Le A cos_l cos(theta) / d^2. Expected values
    are averaged over 8x8 sub-pixels (the tracer's pixel mean)."""
    from _render_helpers import pixel_dirs, plane_scene_dict

    w = h = 16
    albedo, le, sub = 0.6, 20.0, 8
    dirs = pixel_dirs(w, h, 30.0, (0, 0, -1), (1, 0, 0), (0, 1, 0), sub=sub)
    p = dirs * (2.0 / -dirs[..., 2:]) + np.array([0, 0, 2.0])  # sub-pixel hits on the plane z = 0

    def pixel_mean(x):
        return x.reshape(h, sub, w, sub).mean(axis=(1, 3))

    d = plane_scene_dict(albedo=(albedo,) * 3, light=False, max_depth=1)
    d["materials"]["lamp"]["emission"] = [le] * 3
    c, r = np.array([0.9, 0.1, 0.25]), 0.1  # close to the plane, grazing light, outside the view
    d["objects"].append({"type": "sphere", "center": c.tolist(), "radius": r, "material": "lamp"})
    res = PathTracer(scene_from_dict(d), w, h, features=[], ctx=ctx).render([0.0], spp=1024, seed=3)
    v = c - p
    dist2 = np.sum(v * v, axis=-1)
    expected = pixel_mean(albedo * le * r * r / dist2 * (v[..., 2] / np.sqrt(dist2)))
    np.testing.assert_allclose(res.color[0, 1].numpy(), expected, rtol=0.05)
    assert abs(res.color[0, 1].numpy().mean() / expected.mean() - 1) < 0.01

    d["objects"][-1] = {"type": "quad", "origin": [-0.01, -0.01, 3.0], "u": [0, 0.02, 0], "v": [0.02, 0, 0],
                        "material": "lamp"}  # faces -z, 3 units above the plane, behind the camera's eye
    d["materials"]["lamp"]["emission"] = [le * 1e3] * 3
    res = PathTracer(scene_from_dict(d), w, h, features=[], ctx=ctx).render([0.0], spp=16, seed=3)
    v = np.array([0.0, 0.0, 3.0]) - p
    dist2 = np.sum(v * v, axis=-1)
    cos = v[..., 2] / np.sqrt(dist2)
    expected = pixel_mean(albedo / np.pi * le * 1e3 * 4e-4 * cos * cos / dist2)
    np.testing.assert_allclose(res.color[0, 1].numpy(), expected, rtol=0.01)
