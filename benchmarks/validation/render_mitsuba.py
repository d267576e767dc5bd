"""Mitsuba 3 clips of the validation set, scenes built here in Python (no downloaded asset).

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \
        /work/venvs/mitsuba/bin/python benchmarks/validation/render_mitsuba.py mi_ceiling_light --out /work/valdata

Per clip and frame, the same conventions as ``shared/data/mitsuba/cbox_glossy_tex``:

* ``frame_XXXX.exr``: 1 spp, ``R,G,B`` (float32) and, from the same samples (``aov`` integrator), ``albedo.R/G/B``,
  ``N.X/Y/Z`` (shading normal, world space), ``P.X/Y/Z`` (world position) as half, ``Z`` (hit distance) float32;
* ``frame4spp_XXXX.exr``: the same at 4 spp, independent samples;
* ``reference_XXXX.exr``: ``R,G,B`` float32, the float64 mean of ``ref_spp / ref_chunk`` independent chunks;
* ``ref_b_XXXX.exr``: a second independent reference of one frame (how far two references agree caps any score);
* ``mask_XXXX.exr`` (clips with moving objects): ``moving`` = fraction of the pixel's first hits on a moving object.

``box`` reconstruction filter (each sample lands in one pixel), ``independent`` sampler, a new seed per frame,
pass and chunk (``_common.seed``). ``manifest.json`` records every setting and the render time of each pass.
"""
from __future__ import annotations

import copy
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

import mitsuba as mi  # noqa: E402
import drjit as dr  # noqa: E402

MAX_DEPTH = 8
AOVS = "albedo:albedo,N:sh_normal,Z:depth,P:position"
FEATURE_CHANNELS = {"albedo": ("albedo.R", "albedo.G", "albedo.B"), "N": ("N.X", "N.Y", "N.Z"), "Z": ("Z",),
                    "P": ("P.X", "P.Y", "P.Z")}
HALF = ("albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z")


def pick_variant() -> str:
    """``llvm_ad_rgb`` where Dr.Jit finds a libLLVM it works with (see shared/docs/foreign-renderers.md), else
    ``scalar_rgb`` (same images up to sampling, slower)."""
    want = os.environ.get("VALSET_MITSUBA_VARIANT")
    if want:
        mi.set_variant(want)
        return want
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        try:
            mi.set_variant("llvm_ad_rgb")
            return "llvm_ad_rgb"
        except Exception as exc:  # no usable LLVM: fall back, and the manifest says which variant ran
            print(f"llvm_ad_rgb unavailable ({exc}); using scalar_rgb", file=sys.stderr)
    mi.set_variant("scalar_rgb")
    return "scalar_rgb"


# ---------------------------------------------------------------------------------------------------- scene parts
def T():
    return mi.ScalarTransform4f()


def diffuse(rgb) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}}


def bitmap_bsdf(img: np.ndarray, uv_scale: float = 1.0) -> dict:
    """Diffuse BSDF with an (H, W, 3) linear texture made in numpy."""
    return {"type": "diffuse", "reflectance": {
        "type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)), "raw": True,
        "filter_type": "bilinear", "to_uv": mi.ScalarTransform4f().scale([uv_scale, uv_scale, 1])}}


def checker_bsdf(c0, c1, scale: float) -> dict:
    return {"type": "diffuse", "reflectance": {
        "type": "checkerboard", "color0": {"type": "rgb", "value": list(c0)},
        "color1": {"type": "rgb", "value": list(c1)}, "to_uv": mi.ScalarTransform4f().scale([scale, scale, 1])}}


def room(floor: dict, back: dict, left: dict, right: dict, ceiling: dict) -> dict:
    """The five walls of the box [-1, 1]^3, open towards +z (the camera), normals inwards."""
    return {
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90), "bsdf": floor},
        "ceiling": {"type": "rectangle", "to_world": T().translate([0, 1, 0]).rotate([1, 0, 0], 90), "bsdf": ceiling},
        "back": {"type": "rectangle", "to_world": T().translate([0, 0, -1]), "bsdf": back},
        "left": {"type": "rectangle", "to_world": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90), "bsdf": left},
        "right": {"type": "rectangle", "to_world": T().translate([1, 0, 0]).rotate([0, 1, 0], -90), "bsdf": right},
    }


def sensor(origin, target, fov: float, up=(0, 1, 0)) -> dict:
    return {"type": "perspective", "fov": fov, "fov_axis": "smaller",
            "to_world": T().look_at(origin=list(origin), target=list(target), up=list(up)),
            "sampler": {"type": "independent", "sample_count": 1},
            "film": {"type": "hdrfilm", "width": C.WIDTH, "height": C.HEIGHT, "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "component_format": "float32"}}


def lerp(a, b, t):
    return [x + (y - x) * t for x, y in zip(a, b)]


# ---------------------------------------------------------------------------------------------------- clips
def clip_ceiling_light(f: int, n: int) -> tuple[dict, dict]:
    """Room lit only by a rectangle light flush with the ceiling; a small box slides over a checker floor."""
    rng = np.random.default_rng(11)
    noise = C.value_noise(128, 128, 4, rng)
    back = np.stack([0.25 + 0.5 * noise, 0.25 + 0.45 * noise, 0.2 + 0.3 * noise], -1)
    ceiling_bsdf = diffuse([0.75, 0.75, 0.75])
    t = f / max(1, n - 1)
    mover_x = -0.6 + 1.1 * t
    scene = {
        "type": "scene",
        **room(checker_bsdf([0.75, 0.72, 0.65], [0.1, 0.1, 0.12], 8), bitmap_bsdf(back), diffuse([0.6, 0.08, 0.06]),
               diffuse([0.12, 0.45, 0.15]), ceiling_bsdf),
        # Flush with the ceiling (1 mm below it) and given the ceiling's BSDF: no AOV tells it from the ceiling.
        "light": {"type": "rectangle", "to_world": T().translate([0, 0.999, 0]).rotate([1, 0, 0], 90).scale(
            [0.28, 0.28, 1]), "bsdf": ceiling_bsdf, "emitter": {"type": "area", "radiance": {
                "type": "rgb", "value": [17.0, 15.0, 12.0]}}},
        "tall_box": {"type": "cube", "to_world": T().translate([-0.38, -0.45, -0.35]).rotate([0, 1, 0], 20).scale(
            [0.25, 0.55, 0.25]), "bsdf": diffuse([0.7, 0.7, 0.7])},
        "mover": {"type": "cube", "to_world": T().translate([mover_x, -0.82, 0.3]).rotate([0, 1, 0], 30 + 40 * t)
                  .scale([0.18, 0.18, 0.18]), "bsdf": diffuse([0.65, 0.55, 0.2])},
        "sensor": sensor([0, 0, 3.6], [0, 0, 0], 40),
    }
    info = {"description": ("Box room [-1,1]^3 open towards the camera, lit only by a 0.56x0.56 rectangle light "
                            "1 mm below the ceiling with the ceiling's diffuse BSDF (Mitsuba has no emission AOV: "
                            "albedo, normal and position of the light equal the ceiling's). Checkerboard floor "
                            "(scale 8), value-noise textured back wall, red/green side walls, a tall static box and a "
                            "small yellow box sliding over the floor (contact shadow)."),
            "moving": {"mover": {"x": mover_x, "rotate_y_deg": 30 + 40 * t}}, "camera": "static"}
    return scene, info


def clip_glass_mirror(f: int, n: int) -> tuple[dict, dict]:
    """Glass sphere, mirror panel and rough copper under a small bright sphere light; the camera pans."""
    rng = np.random.default_rng(12)
    wood = C.value_noise(128, 128, 5, rng)
    floor = np.stack([0.35 + 0.3 * wood, 0.22 + 0.2 * wood, 0.1 + 0.1 * wood], -1)
    t = f / max(1, n - 1)
    target = lerp([-0.3, -0.25, 0], [0.3, -0.25, 0], t)
    scene = {
        "type": "scene",
        **room(bitmap_bsdf(floor, 2.0), checker_bsdf([0.7, 0.7, 0.75], [0.15, 0.2, 0.45], 6), diffuse([0.7] * 3),
               diffuse([0.55, 0.5, 0.4]), diffuse([0.75] * 3)),
        "small_light": {"type": "sphere", "center": [0.25, 0.72, 0.25], "radius": 0.04,
                        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [700.0, 640.0, 560.0]}}},
        "glass": {"type": "sphere", "center": [-0.3, -0.68, 0.15], "radius": 0.32,
                  "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}},
        # A silver mirror panel standing near the left wall, turned 35 degrees towards the camera.
        "mirror": {"type": "rectangle", "to_world": T().translate([-0.72, -0.4, -0.6]).rotate([0, 1, 0], 35).scale(
            [0.3, 0.55, 1]), "bsdf": {"type": "conductor", "material": "Ag"}},
        "rough_metal": {"type": "sphere", "center": [0.45, -0.74, -0.35], "radius": 0.26,
                        "bsdf": {"type": "roughconductor", "material": "Cu", "distribution": "ggx", "alpha": 0.25}},
        "thin_glass_slab": {"type": "cube", "to_world": T().translate([0.35, -0.6, 0.45]).rotate([0, 1, 0], -25).scale(
            [0.2, 0.4, 0.03]), "bsdf": {"type": "thindielectric", "int_ior": 1.5}},
        "sensor": sensor([0, 0, 3.6], target, 38),
    }
    info = {"description": ("Box room lit only by a small bright sphere light (radius 0.04). A glass sphere "
                            "(dielectric, ior 1.5) on a value-noise wood floor casts a caustic; a silver mirror "
                            "panel (smooth conductor) against the left wall; a rough copper sphere (GGX alpha 0.25); "
                            "a thin glass slab (thindielectric); checkerboard back wall. The camera pans."),
            "camera": {"origin": [0, 0, 3.6], "target": target, "fov": 38}}
    return scene, info


def sky(h: int = 128, w: int = 256, sun_elev: float = 35.0, sun_azim: float = 60.0) -> np.ndarray:
    """(h, w, 3) lat-long sky made here: zenith-to-horizon gradient, dim ground, a sun disc of 2.5 degrees."""
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    elev = (90.0 - 180.0 * v)[:, None] * np.ones((1, w))
    azim = (360.0 * u)[None, :] * np.ones((h, 1))
    s = np.clip(elev / 90.0, 0, 1)[..., None]
    zen, hor = np.array([0.25, 0.45, 1.0]) * 0.6, np.array([1.0, 0.95, 0.9]) * 0.8
    img = np.where((elev >= 0)[..., None], hor + (zen - hor) * s ** 0.5, np.array([0.25, 0.22, 0.2]) * 0.4)
    e, a, se, sa = map(np.radians, (elev, azim, sun_elev, sun_azim))
    cosang = np.sin(e) * np.sin(se) + np.cos(e) * np.cos(se) * np.cos(a - sa)
    sun = np.degrees(np.arccos(np.clip(cosang, -1, 1))) < 2.5
    img[sun] = np.array([1.0, 0.92, 0.8]) * 600.0
    return img.astype(np.float32)


def clip_env_thin(f: int, n: int) -> tuple[dict, dict]:
    """Open ground under a sky with a sun; a fence of thin rods and a wire grid; a ball rolls; the camera dollies."""
    rng = np.random.default_rng(13)
    g = C.value_noise(256, 256, 6, rng)
    ground = np.stack([0.2 + 0.25 * g, 0.3 + 0.3 * g, 0.12 + 0.1 * g], -1)
    t = f / max(1, n - 1)
    ball_x = 0.9 - 1.5 * t
    scene = {
        "type": "scene",
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky())},
        "ground": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90).scale([8, 8, 1]),
                   "bsdf": bitmap_bsdf(ground, 6.0)},
        "ball": {"type": "sphere", "center": [ball_x, -0.75, 0.45], "radius": 0.25,
                 "bsdf": {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": [0.7, 0.15, 0.1]}}},
        "sensor": sensor(lerp([-0.5, 0.1, 3.4], [0.5, 0.1, 3.4], t), [0, -0.45, 0], 40),
    }
    # Fence: vertical rods 0.005-0.012 in radius (a pixel is about 0.02 wide at the fence) and two rails.
    for i in range(13):
        x = -1.5 + 0.25 * i
        scene[f"rod{i}"] = {"type": "cylinder", "p0": [x, -1.0, -0.6], "p1": [x, 0.1, -0.6],
                            "radius": 0.005 + 0.0007 * i, "bsdf": diffuse([0.85, 0.85, 0.8])}
    for j, y in enumerate((-0.6, -0.05)):
        scene[f"rail{j}"] = {"type": "cylinder", "p0": [-1.6, y, -0.6], "p1": [1.6, y, -0.6], "radius": 0.008,
                             "bsdf": diffuse([0.5, 0.35, 0.2])}
    # A wire grid leaning on the right: 1.5 mm wires, finer than a pixel.
    for k in range(9):
        z = -0.2 + 0.08 * k
        scene[f"wire{k}"] = {"type": "cylinder", "p0": [0.9, -1.0, z], "p1": [1.1, -0.2, z], "radius": 0.003,
                             "bsdf": {"type": "roughconductor", "material": "Al", "alpha": 0.3}}
    info = {"description": ("Open scene lit by a lat-long sky made in numpy (gradient, dim ground, a 2.5-degree sun "
                            "disc of radiance 600) on a value-noise textured ground. Thin geometry: a fence of 13 "
                            "rods (radius 0.005-0.013) with two rails, and a grid of 9 aluminium wires (radius "
                            "0.003, under a pixel). A red plastic ball rolls over the ground (contact shadow); the "
                            "camera dollies sideways."),
            "moving": {"ball": {"x": ball_x}},
            "camera": {"origin": lerp([-0.5, 0.1, 3.4], [0.5, 0.1, 3.4], t), "target": [0, -0.45, 0], "fov": 40}}
    return scene, info


def clip_fog(f: int, n: int) -> tuple[dict, dict]:
    """The open scene of ``clip_env_thin`` in fog: the camera sits in a homogeneous medium (``volpath``), so a ray
    that meets no surface still scatters light, and Mitsuba's depth AOV reads 0 there as under a clear sky."""
    scene, info = clip_env_thin(f, n)
    scene["sensor"]["medium"] = {"type": "homogeneous", "sigma_t": 0.15,
                                 "albedo": {"type": "rgb", "value": [0.9, 0.9, 0.9]}}
    info["description"] += (" The camera sits in a homogeneous medium (sigma_t 0.15 per unit, albedo 0.9): where its "
                            "ray meets no surface the pixel is in-scattered light, as noisy as any other, with depth 0.")
    return scene, info


def clip_materials(f: int, n: int) -> tuple[dict, dict]:
    """The room of ``clip_ceiling_light`` with BSDFs the set lacks: a near-mirror principled metal (its albedo
    AOV is its base colour, where a smooth conductor's is 0), smooth plastic, a clear coat and a blend."""
    scene, info = clip_ceiling_light(f, n)
    rgb = lambda v: {"type": "rgb", "value": v}  # noqa: E731
    scene["tall_box"] = {"type": "sphere", "center": [-0.4, -0.62, -0.35], "radius": 0.38,
                         "bsdf": {"type": "principled", "base_color": rgb([0.92, 0.92, 0.95]), "metallic": 1.0,
                                  "roughness": 0.04}}
    scene["plastic_ball"] = {"type": "sphere", "center": [0.45, -0.75, -0.45], "radius": 0.25,
                             "bsdf": {"type": "plastic", "diffuse_reflectance": rgb([0.1, 0.25, 0.6])}}
    scene["coated_ball"] = {"type": "sphere", "center": [0.05, -0.82, -0.6], "radius": 0.18,
                            "bsdf": {"type": "principled", "base_color": rgb([0.7, 0.2, 0.1]), "roughness": 0.5,
                                     "clearcoat": 1.0, "clearcoat_gloss": 0.9}}
    scene["mover"]["bsdf"] = {"type": "blendbsdf", "weight": 0.5, "bsdf_0": diffuse([0.65, 0.55, 0.2]),
                              "bsdf_1": {"type": "roughconductor", "material": "Au", "alpha": 0.2}}
    info["description"] += (" The tall box is now a near-mirror sphere (principled, metallic, roughness 0.04), beside "
                            "a smooth plastic ball and a clear-coated principled ball; the sliding box is half "
                            "diffuse, half rough gold (blendbsdf).")
    return scene, info


def clip_spin(f: int, n: int) -> tuple[dict, dict]:
    """mi_ceiling_light's room with a checkered ball turning in place: its points keep their world positions
    while its texture moves (a turntable)."""
    scene, info = clip_ceiling_light(f, n)
    t = f / max(1, n - 1)
    turned = T().translate([0.45, -0.7, -0.3]).rotate([0, 1, 0], 40 * t).scale(0.3)
    scene["ball"] = {"type": "sphere", "to_world": turned,
                     "bsdf": checker_bsdf([0.9, 0.3, 0.2], [0.9, 0.9, 0.85], 12)}
    info["description"] += " A checkered ball (radius 0.3) turns 40 degrees in place over the clip."
    info["moving"]["ball"] = {"rotate_y_deg": 40 * t}
    return scene, info


def clip_screen(f: int, n: int) -> tuple[dict, dict]:
    """mi_ceiling_light's room with a screen on its back wall: a rectangle emitting a blotchy two-tone picture
    (nearest-neighbour texture) whose surface is black, so Mitsuba's albedo there is 0 as on glass, while each
    sample of it is the picture's exact radiance."""
    scene, info = clip_ceiling_light(f, n)
    rng = np.random.default_rng(5)
    picture = np.stack([C.value_noise(64, 64, 5, rng) for _ in range(3)], -1)
    picture = ((picture > 0.5) * 0.8 + 0.1).astype(np.float32)
    radiance = {"type": "bitmap", "bitmap": mi.Bitmap(picture), "raw": True, "filter_type": "nearest"}
    placed = T().translate([0.0, 0.1, -0.98]).scale([0.5, 0.35, 1])
    scene["screen"] = {"type": "rectangle", "to_world": placed, "bsdf": diffuse([0.0, 0.0, 0.0]),
                       "emitter": {"type": "area", "radiance": radiance}}
    info["description"] += (" A screen (1 x 0.7, black surface) on the back wall emits a two-tone "
                            "value-noise picture.")
    return scene, info


def clip_chrome(f: int, n: int) -> tuple[dict, dict]:
    """mi_env_thin's open scene with a smooth silver ball: flat pixels (albedo 0, as on glass) whose top shows
    the sky and whose bottom shows the ground's texture compressed into fine detail."""
    scene, info = clip_env_thin(f, n)
    scene["chrome"] = {"type": "sphere", "center": [-0.3, -0.6, 0.0], "radius": 0.4,
                       "bsdf": {"type": "conductor", "material": "Ag"}}
    info["description"] += " A smooth silver ball (radius 0.4) stands on the ground left of centre."
    return scene, info


def clip_glass_open(f: int, n: int) -> tuple[dict, dict]:
    """mi_env_thin's open scene (a pan, a rolling ball) with a glass ball and a thick glass block on the
    ground: flat pixels (albedo 0) that show the sky and the ground's texture, refracted, while the view
    moves."""
    scene, info = clip_env_thin(f, n)
    scene["glass_ball"] = {"type": "sphere", "center": [-0.35, -0.62, 0.1], "radius": 0.38,
                           "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}}
    scene["glass_block"] = {"type": "cube", "to_world": T().translate([0.45, -0.7, -0.2]).rotate(
        [0, 1, 0], 30).scale([0.22, 0.3, 0.12]),
        "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}}
    info["description"] += (" A glass ball (radius 0.38) stands on the ground left of centre and a glass "
                            "block right of it.")
    return scene, info


def clip_window(f: int, n: int) -> tuple[dict, dict]:
    """A room lit by the sky and sun through a window in its left wall: a sharp sun patch on a wood floor,
    walls lit by bounce light, a table, a turning checkered box, a plastic ball and a rough aluminium can;
    the camera pans and moves in (a scene of the ordinary kind, not built for one hazard)."""
    rng = np.random.default_rng(24)
    wood = C.value_noise(128, 128, 5, rng)
    floor = np.stack([0.35 + 0.3 * wood, 0.22 + 0.2 * wood, 0.1 + 0.1 * wood], -1)
    t = f / max(1, n - 1)
    walls = room(bitmap_bsdf(floor, 2.0), diffuse([0.72, 0.7, 0.62]), diffuse([0.72, 0.7, 0.62]),
                 diffuse([0.72, 0.7, 0.62]), diffuse([0.78] * 3))
    del walls["left"]
    scene = {"type": "scene", **walls,
             "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky(sun_elev=45.0, sun_azim=270.0))}}
    # the left wall (x = -1) around a window 0.8 deep (z) and 0.7 high, its sill 0.6 above the floor
    pieces = ((-0.7, 0.0, 0.3, 1.0), (0.65, 0.0, 0.35, 1.0), (-0.05, -0.7, 0.35, 0.3),
              (-0.05, 0.7, 0.35, 0.3))
    for i, (cy, cz, sy, sz) in enumerate(pieces):
        scene[f"wall{i}"] = {"type": "rectangle", "bsdf": diffuse([0.72, 0.7, 0.62]),
                             "to_world": T().translate([-1, cy, cz]).rotate([0, 1, 0], 90).scale([sz, sy, 1])}
    scene["table"] = {"type": "cube", "to_world": T().translate([0.3, -0.7, -0.3]).scale([0.45, 0.3, 0.3]),
                      "bsdf": diffuse([0.45, 0.3, 0.18])}
    scene["box"] = {"type": "cube", "bsdf": checker_bsdf([0.85, 0.8, 0.7], [0.15, 0.2, 0.4], 3),
                    "to_world": T().translate([0.15, -0.28, -0.3]).rotate([0, 1, 0], 20 + 25 * t).scale(0.12)}
    red = {"type": "rgb", "value": [0.7, 0.08, 0.05]}
    scene["ball"] = {"type": "sphere", "center": [0.55, -0.27, -0.2], "radius": 0.13,
                     "bsdf": {"type": "plastic", "diffuse_reflectance": red}}
    scene["can"] = {"type": "cylinder", "p0": [-0.4, -1.0, -0.5], "p1": [-0.4, -0.5, -0.5], "radius": 0.12,
                    "bsdf": {"type": "roughconductor", "material": "Al", "alpha": 0.3}}
    scene["can_top"] = {"type": "disk", "to_world": T().translate([-0.4, -0.5, -0.5]).rotate([1, 0, 0], -90)
                        .scale(0.12), "bsdf": {"type": "roughconductor", "material": "Al", "alpha": 0.3}}
    origin = lerp([0.35, -0.1, 3.4], [0.1, -0.2, 2.9], t)
    target = lerp([0.2, -0.4, -0.3], [-0.1, -0.4, -0.3], t)
    scene["sensor"] = sensor(origin, target, 45)
    info = {"description": ("Box room lit by the numpy sky (a 2.5-degree sun of radiance 600, 45 degrees "
                            "high) through a 0.8 x 0.7 window in the left wall: a sun patch on a value-noise "
                            "wood floor, walls lit by bounce light, a table with a turning checkered box, a "
                            "red plastic ball, a rough aluminium can (alpha 0.3). The camera pans and moves "
                            "in."),
            "moving": {"box": {"rotation_y": 20 + 25 * t}},
            "camera": {"origin": origin, "target": target, "fov": 45}}
    return scene, info


def clip_yard(f: int, n: int) -> tuple[dict, dict]:
    """A sunlit courtyard: the sun casts the hard shadows of a side wall and of a pergola's slats across a
    back wall and a bench (borders no feature shows, in stripes), a ball rolls over tiled ground, the camera
    pans (a scene of the ordinary kind, held out from every setting)."""
    rng = np.random.default_rng(31)
    g = C.value_noise(256, 256, 5, rng)
    tiles = ((np.arange(256)[:, None] // 32 + np.arange(256)[None, :] // 32) % 2).astype(np.float32)
    stone = np.stack([0.42 + 0.12 * tiles + 0.15 * g, 0.38 + 0.1 * tiles + 0.13 * g,
                      0.33 + 0.08 * tiles + 0.1 * g], -1)
    t = f / max(1, n - 1)
    plaster = diffuse([0.75, 0.68, 0.58])
    scene = {"type": "scene",
             "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky(sun_elev=40.0, sun_azim=210.0))},
             "ground": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90)
                        .scale([6, 6, 1]), "bsdf": bitmap_bsdf(stone, 4.0)},
             "back_wall": {"type": "cube", "to_world": T().translate([0.0, 0.0, -1.6]).scale([2.4, 1.0, 0.1]),
                           "bsdf": plaster},
             "side_wall": {"type": "cube", "bsdf": plaster,
                           "to_world": T().translate([-1.8, -0.2, -0.4]).scale([0.1, 0.8, 1.3])},
             "bench": {"type": "cube", "to_world": T().translate([0.8, -0.8, -0.9]).scale([0.5, 0.2, 0.18]),
                       "bsdf": diffuse([0.35, 0.22, 0.12])}}
    for i in range(7):  # the pergola's slats, 0.06 wide and 0.3 apart, 0.9 above the ground
        scene[f"slat{i}"] = {"type": "cube", "bsdf": diffuse([0.5, 0.36, 0.22]),
                             "to_world": T().translate([-0.9 + 0.3 * i, -0.1, -0.5]).scale([0.03, 0.03, 0.9])}
    for i, x in enumerate((-1.0, 0.9)):  # its posts
        scene[f"post{i}"] = {"type": "cylinder", "p0": [x, -1.0, 0.35], "p1": [x, -0.1, 0.35], "radius": 0.04,
                             "bsdf": diffuse([0.5, 0.36, 0.22])}
    ball_x = -0.8 + 1.4 * t
    blue = {"type": "rgb", "value": [0.15, 0.35, 0.7]}
    scene["ball"] = {"type": "sphere", "center": [ball_x, -0.82, 0.0], "radius": 0.18,
                     "bsdf": {"type": "plastic", "diffuse_reflectance": blue}}
    origin = lerp([-0.6, 0.5, 3.6], [0.6, 0.4, 3.4], t)
    target = [0.0, -0.5, -0.4]
    scene["sensor"] = sensor(origin, target, 45)
    info = {"description": ("A courtyard under the numpy sky (a 2.5-degree sun of radiance 600, 40 "
                            "degrees high, behind the camera's right): a tiled, value-noise stone ground, a "
                            "back wall and a side wall of plaster, a pergola of seven slats on two posts "
                            "whose shadows stripe the back wall and the bench, the side wall's shadow on the "
                            "back wall, a blue plastic ball rolling through the light. The camera pans."),
            "moving": {"ball": {"x": ball_x}},
            "camera": {"origin": origin, "target": target, "fov": 45}}
    return scene, info


def clip_glass_room(f: int, n: int) -> tuple[dict, dict]:
    """The room of ``clip_ceiling_light`` with a glass ball, a thick glass pane in front of the sliding box and
    a silver mirror: flat pixels (albedo 0) that show sharp detail (the floor's checkerboard refracted by the
    ball) beside smooth, noisy light (the box behind the pane, lit by bounce light; the reflected wall)."""
    scene, info = clip_ceiling_light(f, n)
    scene["glass_ball"] = {"type": "sphere", "center": [0.35, -0.72, 0.1], "radius": 0.28,
                           "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}}
    scene["pane"] = {"type": "cube", "to_world": T().translate([-0.1, -0.55, 0.55]).rotate([0, 1, 0], 15).scale(
        [0.3, 0.45, 0.02]), "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}}
    scene["mirror"] = {"type": "rectangle", "to_world": T().translate([0.8, -0.35, -0.3]).rotate(
        [0, 1, 0], -40).scale([0.25, 0.6, 1]), "bsdf": {"type": "conductor", "material": "Ag"}}
    info["description"] += (" A glass ball (radius 0.28) stands on the floor right of centre, a glass pane 0.04 "
                            "thick in front of the sliding box, a silver mirror near the right wall.")
    return scene, info


def clip_fast_motion(f: int, n: int) -> tuple[dict, dict]:
    """The room of ``clip_ceiling_light`` seen by a camera that orbits 32 degrees over the clip (large parallax,
    the open side and the outside coming into view) while a ball rolls across the floor about 11 px a frame:
    pixels that were hidden a frame before, and features that move faster than the window's filter reaches."""
    scene, info = clip_ceiling_light(f, n)
    t = f / max(1, n - 1)
    angle = np.radians(-16.0 + 32.0 * t)
    origin = [3.4 * float(np.sin(angle)), 0.1, 3.4 * float(np.cos(angle))]
    ball_x = -0.8 + 1.6 * t
    scene["mover"] = {"type": "sphere", "center": [ball_x, -0.8, 0.25], "radius": 0.2,
                      "bsdf": diffuse([0.2, 0.35, 0.7])}
    scene["sensor"] = sensor(origin, [0, -0.2, 0], 42)
    info["description"] += (" Here the camera orbits the room's centre, 32 degrees over the clip at 3.4 units, and "
                            "the sliding box is a blue ball rolling across the floor from x = -0.8 to 0.8 (about "
                            "11 px a frame at 128x128).")
    info["moving"] = {"mover": {"x": ball_x}}
    info["camera"] = {"origin": origin, "target": [0, -0.2, 0], "fov": 42}
    return scene, info


def bumped(bsdf: dict, height: np.ndarray, scale: float, uv_scale: float = 1.0) -> dict:
    """``bsdf`` under Mitsuba's ``bumpmap`` of an (H, W) height texture made in numpy (its ``sh_normal`` AOV
    shows the bumped normals)."""
    to_uv = mi.ScalarTransform4f().scale([uv_scale, uv_scale, 1])
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(height[..., None], dtype=np.float32)),
           "raw": True, "filter_type": "bilinear", "to_uv": to_uv}
    return {"type": "bumpmap", "arbitrary": tex, "scale": scale, "bsdf": bsdf}


def clip_bump(f: int, n: int) -> tuple[dict, dict]:
    """mi_ceiling_light's room with bump-mapped stucco walls and floor, and a hammered-copper ball beside the
    sliding box: normals that vary within a pixel."""
    scene, info = clip_ceiling_light(f, n)
    rng = np.random.default_rng(20)
    stucco = C.value_noise(256, 256, 6, rng)
    hammered = C.value_noise(128, 128, 4, rng)
    walls = {"back": [0.7, 0.66, 0.58], "left": [0.6, 0.12, 0.08], "floor": [0.55, 0.52, 0.48]}
    for wall, rgb in walls.items():
        scene[wall]["bsdf"] = bumped(diffuse(rgb), stucco, 0.6, 2.0)
    scene["tall_box"] = {"type": "sphere", "center": [-0.4, -0.65, -0.35], "radius": 0.35,
                         "bsdf": bumped({"type": "roughconductor", "material": "Cu", "distribution": "ggx",
                                         "alpha": 0.2}, hammered, 0.3, 3.0)}
    info["description"] += (" Here the back wall, the left wall and the floor are plain diffuse colours "
                            "under a bump map of value noise (Mitsuba's bumpmap, scale 0.6), and the tall "
                            "box is a hammered rough-copper ball (GGX alpha 0.2 under a bump map, scale "
                            "0.3).")
    return scene, info


def thinlens(origin, target, fov: float, aperture: float, focus: float, up=(0, 1, 0)) -> dict:
    """``sensor`` with a thin lens: ``aperture`` radius, in focus at ``focus`` along the view axis."""
    return {**sensor(origin, target, fov, up), "type": "thinlens", "aperture_radius": aperture,
            "focus_distance": focus}


def clip_indirect_dof(f: int, n: int) -> tuple[dict, dict]:
    """Room lit only by bounce light: a cove light on a shelf faces the ceiling; thin-lens camera; a ball rolls."""
    rng = np.random.default_rng(14)
    plaster = C.value_noise(128, 128, 5, rng)
    back = np.stack([0.45 + 0.35 * plaster, 0.42 + 0.3 * plaster, 0.35 + 0.25 * plaster], -1)
    side = C.value_noise(128, 128, 4, rng)
    left = np.stack([0.2 + 0.25 * side, 0.35 + 0.3 * side, 0.5 + 0.3 * side], -1)
    wood = C.value_noise(128, 128, 6, rng)
    stripes = 0.5 + 0.5 * np.sin(np.linspace(0, 24 * np.pi, 128))[None, :]
    floor = np.stack([0.3 + 0.25 * wood * stripes, 0.2 + 0.18 * wood * stripes, 0.1 + 0.1 * wood], -1)
    t = f / max(1, n - 1)
    ball_x = -0.45 + 0.35 * t
    origin, target = [0.15, -0.3, 2.2], [0.0, -0.75, 0.0]  # the top edge sees the shelf from below
    focus = float(np.linalg.norm(np.subtract(origin, [0.05, -0.55, -0.1])))  # on the checker box
    zc, hz = 0.8, 1.8  # closed room, z from -1 to 2.6, the camera inside: no bounce light escapes
    scene = {
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, zc]).rotate([1, 0, 0], -90).scale(
            [1, hz, 1]), "bsdf": bitmap_bsdf(floor, 2.0)},
        "ceiling": {"type": "rectangle", "to_world": T().translate([0, 1, zc]).rotate([1, 0, 0], 90).scale(
            [1, hz, 1]), "bsdf": diffuse([0.85, 0.85, 0.85])},
        "back": {"type": "rectangle", "to_world": T().translate([0, 0, -1]), "bsdf": bitmap_bsdf(back)},
        "left": {"type": "rectangle", "to_world": T().translate([-1, 0, zc]).rotate([0, 1, 0], 90).scale(
            [hz, 1, 1]), "bsdf": bitmap_bsdf(left)},
        "right": {"type": "rectangle", "to_world": T().translate([1, 0, zc]).rotate([0, 1, 0], -90).scale(
            [hz, 1, 1]), "bsdf": diffuse([0.6, 0.55, 0.45])},
        "front": {"type": "rectangle", "to_world": T().translate([0, 0, 2 * zc + 1]).rotate([0, 1, 0], 180),
                  "bsdf": diffuse([0.7, 0.7, 0.7])},
        # A dark shelf along the back wall, above the camera: the light on it faces the ceiling, 0.7 below it
        # (a broad bounce, not a hot spot), and neither it nor what it lights directly is ever in view.
        "shelf": {"type": "cube", "to_world": T().translate([0, 0.27, -0.72]).scale([0.98, 0.025, 0.26]),
                  "bsdf": diffuse([0.1, 0.1, 0.1])},
        "cove_light": {"type": "rectangle", "to_world": T().translate([0, 0.3, -0.7]).rotate([1, 0, 0], -90)
                       .scale([0.6, 0.12, 1]), "emitter": {"type": "area", "radiance": {
                           "type": "rgb", "value": [180.0, 156.0, 120.0]}}},
        "checker_box": {"type": "cube", "to_world": T().translate([0.05, -0.75, -0.1]).rotate([0, 1, 0], 30).scale(
            [0.25, 0.25, 0.25]), "bsdf": checker_bsdf([0.8, 0.75, 0.6], [0.1, 0.15, 0.3], 6)},
        "ball": {"type": "sphere", "center": [ball_x, -0.82, 0.45], "radius": 0.18,
                 "bsdf": diffuse([0.7, 0.25, 0.1])},
        # Close to the lens: far out of focus.
        "near_post": {"type": "cylinder", "p0": [0.42, -1.0, 1.25], "p1": [0.42, 0.3, 1.25], "radius": 0.06,
                      "bsdf": checker_bsdf([0.85, 0.85, 0.8], [0.2, 0.05, 0.05], 10)},
        "far_vase": {"type": "sphere", "center": [-0.6, -0.75, -0.7], "radius": 0.25,
                     "bsdf": checker_bsdf([0.2, 0.5, 0.3], [0.8, 0.8, 0.6], 12)},
        "sensor": thinlens(origin, target, 45, 0.04, focus),
    }
    info = {"description": ("Closed box room (z from -1 to 2.6, the camera inside) lit only indirectly: a 1.2x0.24 "
                            "area light lies on a dark shelf along the back wall, above the camera, facing the "
                            "ceiling 0.7 above it. The camera is tilted down so that its top edge sees the shelf "
                            "from below: neither the light nor any surface it lights directly is in view, everything "
                            "seen is lit by bounce light only (sparse, high-energy 1-spp samples). Value-noise "
                            "textured back and left walls, striped value-noise wood floor. Thin-lens camera "
                            "(aperture radius 0.04, fov 45) focused on a checker box at mid depth: a checker post "
                            "near the lens and a checker sphere at the back are out of focus, so albedo, normal and "
                            "depth are blurred per sample. A red ball rolls a little (moving object, contact "
                            "shadow)."),
            "moving": {"ball": {"x": ball_x}},
            "camera": {"origin": origin, "target": target, "fov": 45, "aperture_radius": 0.04,
                       "focus_distance": focus}}
    return scene, info


def clip_dark_glossy(f: int, n: int) -> tuple[dict, dict]:
    """Dark room, rough glossy tiled floor reflecting four small bright lights; textured objects; slow pan."""
    rng = np.random.default_rng(15)
    g = C.value_noise(256, 256, 5, rng)
    u = np.arange(256)
    tiles = ((u[:, None] // 32 + u[None, :] // 32) % 2)[..., None]
    floor = np.where(tiles, [0.06, 0.05, 0.05], [0.25, 0.22, 0.2]) * (0.6 + 0.8 * g[..., None])
    w = C.value_noise(128, 128, 4, rng)
    wall = np.stack([0.05 + 0.05 * w, 0.05 + 0.04 * w, 0.06 + 0.05 * w], -1)
    spot = C.value_noise(128, 128, 6, rng)
    ball_tex = np.stack([0.15 + 0.6 * spot, 0.3 + 0.4 * spot, 0.5 * spot], -1)
    t = f / max(1, n - 1)
    target = lerp([-0.2, -0.35, 0], [0.2, -0.35, 0], t)
    origin = [0, -0.1, 2.6]
    scene = {
        "type": "scene",
        **room({"type": "roughplastic", "distribution": "ggx", "alpha": 0.18, "int_ior": 1.5,
                "diffuse_reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(floor.astype(np.float32)),
                                        "raw": True, "to_uv": T().scale([2, 2, 1])}},
               bitmap_bsdf(wall), bitmap_bsdf(wall), bitmap_bsdf(wall), diffuse([0.04, 0.04, 0.04])),
        "textured_ball": {"type": "sphere", "center": [-0.45, -0.7, -0.3], "radius": 0.3,
                          "bsdf": bitmap_bsdf(ball_tex)},
        "checker_box": {"type": "cube", "to_world": T().translate([0.45, -0.75, -0.45]).rotate([0, 1, 0], -25).scale(
            [0.22, 0.25, 0.22]), "bsdf": checker_bsdf([0.7, 0.65, 0.55], [0.08, 0.08, 0.1], 5)},
        "metal_post": {"type": "cylinder", "p0": [0.1, -1.0, -0.75], "p1": [0.1, -0.1, -0.75], "radius": 0.07,
                       "bsdf": {"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha": 0.15}},
        "sensor": sensor(origin, target, 45),
    }
    lights = [([-0.7, -0.2, -0.6], 0.025, [900.0, 600.0, 300.0]),  # (centre, radius, radiance)
              ([0.35, 0.05, -0.2], 0.02, [300.0, 500.0, 1400.0]),
              ([-0.1, -0.5, 0.35], 0.015, [2500.0, 2200.0, 1800.0]),
              ([0.75, -0.35, 0.2], 0.02, [1200.0, 250.0, 200.0])]
    for i, (c, r, rad) in enumerate(lights):
        scene[f"lamp{i}"] = {"type": "sphere", "center": c, "radius": r,
                             "emitter": {"type": "area", "radiance": {"type": "rgb", "value": rad}}}
    info = {"description": ("Dark box room (textured walls of albedo about 0.05-0.1, ceiling 0.04) lit only by four "
                            "small coloured sphere lights (radius 0.015-0.025, radiance up to 2500) hanging above a "
                            "rough plastic floor (GGX alpha 0.18) with a dark/light value-noise tile texture: "
                            "glossy reflections of the lights, high dynamic range, fireflies. A value-noise textured "
                            "sphere, a checker box and a rough gold post (alpha 0.15). The camera pans slowly."),
            "camera": {"origin": origin, "target": target, "fov": 45}}
    return scene, info


def stripes(n: int, count: int, axis: int = 1) -> np.ndarray:
    """(n, n) of 0/1: ``count`` sharp stripes across the texture (along its columns for ``axis`` 1, rows for 0)."""
    k = (np.arange(n) * count // n) % 2
    return np.broadcast_to(k[None, :] if axis == 1 else k[:, None], (n, n)).astype(np.float64)


def clip_still_textures(f: int, n: int) -> tuple[dict, dict]:
    """Closed room full of fine textures seen by a camera that never moves; a small sphere light; a box slides."""
    rng = np.random.default_rng(16)
    m = 512
    # Striped wallpaper on the back wall: 20 stripes over its 2 units (about 2.5 px each at 64x64), a thin dark
    # pinstripe (a third of a pixel) in every light stripe, value noise on top.
    wall_noise = C.value_noise(m, m, 7, rng)
    paper = stripes(m, 20)
    pin = ((np.arange(m) % (m // 20)) < 3)[None, :] * (1 - paper)
    base = np.where(paper[..., None] > 0, [0.55, 0.18, 0.14], [0.78, 0.72, 0.58])
    base = base * (0.8 + 0.35 * wall_noise)[..., None]
    back = base * (1 - 0.7 * pin[..., None])
    # Wood floor: 8 planks along z, grain lines (1-2 px) warped by noise, plank ends at random z.
    grain_noise = C.value_noise(m, m, 6, rng)
    col = np.arange(m)[None, :]
    row = np.arange(m)[:, None]
    grain = (np.sin(2 * np.pi * (col * 30 / m + 2.5 * grain_noise)) > 0.2).astype(np.float64)
    plank = col // (m // 8)
    tone = (0.75 + 0.5 * rng.random(8))[plank]
    ends = (row + (rng.integers(0, m, 8)[plank])) % (m // 3) < 2
    wood = np.stack([0.42 - 0.2 * grain, 0.27 - 0.13 * grain, 0.12 - 0.06 * grain], -1) * tone[..., None]
    wood = wood * (1 - 0.75 * (ends | (col % (m // 8) < 2))[..., None])
    # Left wall (3.6 x 2 units): a fine checker of 0.075 (about 2 px), square on the wall; right wall: fine noise.
    nz, ny = 48, 27
    u = np.arange(m)
    chk = ((u[:, None] * ny // m + u[None, :] * nz // m) % 2)[..., None]
    left = np.where(chk, [0.75, 0.75, 0.7], [0.12, 0.2, 0.35])
    fine = C.value_noise(m, m, 8, rng)
    fine = np.clip((fine - 0.5) * 3 + 0.5, 0, 1)  # more contrast at the finest octaves
    right = np.stack([0.15 + 0.55 * fine, 0.35 + 0.4 * fine, 0.2 + 0.2 * fine], -1)
    ceil_noise = C.value_noise(128, 128, 5, rng)
    ceiling = np.stack([0.7 + 0.15 * ceil_noise] * 3, -1)
    # Objects: a sphere with stripes round it and noise, a box with a fine checker, the mover with fine stripes.
    sph_noise = C.value_noise(256, 256, 6, rng)
    sph = np.where(stripes(256, 40)[..., None] > 0, [0.8, 0.65, 0.2], [0.15, 0.3, 0.55])
    sph = sph * (0.7 + 0.5 * sph_noise)[..., None]
    mover_tex = np.where(stripes(256, 8, 0)[..., None] > 0, [0.85, 0.85, 0.8], [0.6, 0.1, 0.1])
    t = f / max(1, n - 1)
    mover_x = -0.55 + 0.4 * t  # about 2 px per frame
    origin, target = [0.3, -0.1, 2.3], [-0.12, -0.45, -0.4]
    zc, hz = 0.8, 1.8  # closed room, z from -1 to 2.6, the camera inside
    scene = {
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, zc]).rotate([1, 0, 0], -90).scale(
            [1, hz, 1]), "bsdf": bitmap_bsdf(wood)},
        "ceiling": {"type": "rectangle", "to_world": T().translate([0, 1, zc]).rotate([1, 0, 0], 90).scale(
            [1, hz, 1]), "bsdf": bitmap_bsdf(ceiling)},
        "back": {"type": "rectangle", "to_world": T().translate([0, 0, -1]), "bsdf": bitmap_bsdf(back)},
        "left": {"type": "rectangle", "to_world": T().translate([-1, 0, zc]).rotate([0, 1, 0], 90).scale(
            [hz, 1, 1]), "bsdf": bitmap_bsdf(left)},
        "right": {"type": "rectangle", "to_world": T().translate([1, 0, zc]).rotate([0, 1, 0], -90).scale(
            [hz, 1, 1]), "bsdf": bitmap_bsdf(right)},
        "front": {"type": "rectangle", "to_world": T().translate([0, 0, 2 * zc + 1]).rotate([0, 1, 0], 180),
                  "bsdf": diffuse([0.7, 0.7, 0.7])},
        # The only light, in view near the top of the frame, 0.7 in front of the wallpaper.
        "lamp": {"type": "sphere", "center": [0.05, 0.42, -0.3], "radius": 0.05,
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [300.0, 270.0, 230.0]}}},
        "checker_box": {"type": "cube", "to_world": T().translate([0.45, -0.7, -0.45]).rotate([0, 1, 0], -30).scale(
            [0.22, 0.3, 0.22]), "bsdf": checker_bsdf([0.8, 0.78, 0.7], [0.1, 0.1, 0.12], 5)},
        "striped_ball": {"type": "sphere", "center": [-0.5, -0.68, -0.5], "radius": 0.32, "bsdf": bitmap_bsdf(sph)},
        "mover": {"type": "cube", "to_world": T().translate([mover_x, -0.86, 0.25]).rotate([0, 1, 0], 25).scale(
            [0.14, 0.14, 0.14]), "bsdf": bitmap_bsdf(mover_tex)},
        "sensor": sensor(origin, target, 42),
    }
    info = {"description": ("Closed box room (z from -1 to 2.6, the camera inside) seen by a camera that does not "
                            "move, every surface finely textured with numpy-made bitmaps, so that each pixel's 1-spp "
                            "albedo is a point sample of texture that varies inside the pixel: striped wallpaper on "
                            "the back wall (20 stripes, about 2.5 px each, sub-pixel pinstripes, noise), a wood floor "
                            "(planks, noise-warped grain lines of 1-2 px, plank ends), a fine checker (about 2 px) on "
                            "the left wall, 8-octave value noise on the right wall, a striped noisy sphere, a fine "
                            "checker box (squares about 1 px). Lit by one small sphere light (radius 0.05, radiance "
                            "300) seen near the top of the frame: direct light and shadows plus bounce light. A box "
                            "with fine stripes slides about 2 px per frame over the floor (moving object, contact "
                            "shadow); all else static. 64x64."),
            "moving": {"mover": {"x": mover_x}},
            "camera": {"static": True, "origin": origin, "target": target, "fov": 42}}
    return scene, info


CLIPS = {
    # name: (builder, clip id for seeds, hazards, moving shape keys, reference spp, frame of the second reference).
    # 512 spp at 128x128 keeps a clip near 3 min of rendering on the 2 shared cores here (0.4 Mpaths/s measured
    # under load); the caustic clip gets a second reference to show how far 512 spp is from converged.
    # mi_indirect_dof (all light bounced at least once: 256 spp is still grainy) and mi_dark_glossy (small lights
    # seen in a rough floor) need more; with the LLVM variant they took 3-4 min each here, second reference included.
    "mi_ceiling_light": (clip_ceiling_light, 1, ["area_light_in_ceiling_no_emission_aov", "moving_object",
                                                 "contact_shadow", "textures"], ["mover"], 512, None),
    "mi_glass_mirror": (clip_glass_mirror, 2, ["glass", "mirror", "small_bright_light", "rough_metal",
                                               "caustics", "camera_pan", "textures"], [], 512, 4),
    "mi_env_thin": (clip_env_thin, 3, ["environment_lit_open_scene", "thin_geometry", "moving_object",
                                       "contact_shadow", "camera_pan", "textures"], ["ball"], 512, None),
    "mi_indirect_dof": (clip_indirect_dof, 4, ["indirect_light_only", "splotches", "depth_of_field",
                                               "blurred_features", "moving_object", "contact_shadow", "textures"],
                        ["ball"], 4096, 4),
    "mi_dark_glossy": (clip_dark_glossy, 5, ["dark_scene", "high_dynamic_range", "small_bright_lights",
                                             "glossy_floor_reflections", "fireflies", "camera_pan", "textures"],
                       [], 2048, 4),
    # A camera that never moves over fine textures (the albedo of each 1-spp sample is a point sample of texture
    # that varies inside the pixel); 64x64 (see SIZE), so 1024 spp stays cheap.
    "mi_still_textures": (clip_still_textures, 6, ["still_camera", "textures", "moving_object", "contact_shadow",
                                                   "small_bright_light"], ["mover"], 1024, 4),
    # The sky rule's hazard (a pixel of depth 0 is not always noise-free): rendered on demand, not committed (the
    # committed set is at its 60 MB budget).
    "mi_fog": (clip_fog, 7, ["medium", "noisy_depth_zero_pixels", "environment_lit_open_scene", "thin_geometry",
                             "moving_object", "camera_pan"], ["ball"], 1024, None),
    # Mitsuba BSDFs the set lacks: rendered on demand as a probe, not committed. The near-mirror sphere throws
    # caustics over the room, which 256 spp leaves grainy: 2048.
    "mi_materials": (clip_materials, 8, ["principled_metal", "near_mirror", "smooth_plastic", "clearcoat",
                                         "blend", "moving_object", "contact_shadow"], ["mover"], 2048, None),
    # Fast motion, rendered on demand as a probe, not committed: an orbiting camera and a fast ball.
    "mi_fast_motion": (clip_fast_motion, 9, ["camera_orbit", "parallax", "disocclusion", "fast_moving_object",
                                             "contact_shadow", "area_light_in_ceiling_no_emission_aov"],
                       ["mover"], 512, None),
    # A turntable, rendered on demand as a probe, not committed: a texture turning in place, a still camera.
    "mi_spin": (clip_spin, 10, ["texture_turning_in_place", "still_camera", "moving_object", "contact_shadow",
                                "area_light_in_ceiling_no_emission_aov"], ["mover", "ball"], 512, None),
    # A picture on an emitter whose surface is black, rendered on demand as a probe, not committed: flat
    # pixels (albedo 0, as on glass) whose colour has no noise.
    # A mirror ball in the open scene, rendered on demand as a probe, not committed: flat pixels that show
    # detail.
    "mi_chrome": (clip_chrome, 12, ["mirror_ball", "flat_pixels_with_detail", "environment_lit_open_scene",
                                    "thin_geometry", "moving_object", "camera_pan"], ["ball"], 512, None),
    "mi_screen": (clip_screen, 11, ["emitter_texture", "flat_pixels_without_noise", "moving_object",
                                    "area_light_in_ceiling_no_emission_aov", "contact_shadow"],
                  ["mover"], 512, None),
    # a probe at 256x256, the size of the clips scored outside the set, where glass cost the most against OIDN
    "mi_glass_room": (clip_glass_room, 21, ["glass", "mirror", "flat_pixels_with_detail", "moving_object",
                                            "area_light_in_ceiling_no_emission_aov"], ["mover"], 512, None),
    # Glass in the open scene, rendered on demand as a probe, not committed: flat pixels that show the sky and
    # the ground refracted while the view pans (held out: added after the flat pixels' colour guide was set).
    "mi_glass_open": (clip_glass_open, 23, ["glass", "flat_pixels_with_detail", "environment_lit_open_scene",
                                            "moving_object", "camera_pan"], ["ball"], 512, None),
    # A room lit through a window, rendered on demand as a probe, not committed: a scene of the ordinary kind,
    # held out from every setting (added after them).
    "mi_window": (clip_window, 24, ["sun_through_window", "indirect_light", "textures", "plastic",
                                    "rough_metal", "moving_object", "camera_pan"], ["box"], 1024, None),
    # A sunlit courtyard, rendered on demand as a probe, not committed: hard shadows no feature shows, held
    # out from every setting (added after them).
    "mi_yard": (clip_yard, 25, ["sun", "hard_shadows", "textures", "environment_lit_open_scene",
                                "moving_object", "camera_pan"], ["ball"], 1024, None),
    # Bump maps (normals that vary within a pixel), rendered on demand as a probe, not committed.
    "mi_bump": (clip_bump, 22, ["bump_mapping", "rough_metal", "moving_object", "contact_shadow",
                                "area_light_in_ceiling_no_emission_aov"], ["mover"], 512, None),
}

# Clips rendered with another integrator than ``path`` (inside the ``aov`` integrator for the noisy passes too).
INTEGRATOR = {"mi_fog": "volpath"}

# Clips rendered at another size than C.WIDTH x C.HEIGHT (as render_blender.py's SIZE): the film of the builder's
# sensor is resized. mi_still_textures: Mitsuba's float32 R,G,B (1 spp, 4 spp, reference) does not compress at all
# (12 bytes a pixel) and fine textures make the features dear too: at 80x80 the clip took 3.2 MB, at 64x64 2.1 MB.
# The point of the clip (texture varying inside a pixel, a still camera) needs no more pixels.
SIZE = {"mi_still_textures": (64, 64), "mi_glass_room": (256, 256)}


# ---------------------------------------------------------------------------------------------------- rendering
def _mask_scene(scene: dict, moving: list) -> dict:
    """The same geometry with every BSDF black except the moving shapes (white), no lights: an ``albedo`` AOV of it
    is the fraction of each pixel's first hits on a moving object."""
    out = {}
    for k, v in scene.items():
        if isinstance(v, dict) and v.get("type") in ("rectangle", "cube", "sphere", "cylinder"):
            v = {kk: vv for kk, vv in v.items() if kk not in ("emitter", "bsdf")}
            v["bsdf"] = diffuse([1.0, 1.0, 1.0] if k in moving else [0.0, 0.0, 0.0])
        elif isinstance(v, dict) and v.get("type") == "envmap":
            continue
        out[k] = v
    return out


def _channels(scene) -> dict:
    """name -> (H, W) of the last render of ``scene``'s film (aov integrator), in this project's channel names."""
    parts = dict(scene.sensors()[0].film().bitmap().split())
    rgb = np.array(parts["integrator"])[..., :3]
    out = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2]}
    for key, names in FEATURE_CHANNELS.items():
        a = np.array(parts[key])
        a = a.reshape(*a.shape[:2], -1)
        for i, name in enumerate(names):
            out[name] = a[..., i]
    return out


def render_clip(name: str, out_root: Path, frames: int = C.FRAMES, ref_spp: int | None = None,
                ref_chunk: int = 128, renderer_defaults: bool = False,
                size: tuple[int, int] | None = None, position: bool = False) -> Path:
    """Render clip ``name`` into ``out_root / name``; ``renderer_defaults``: Mitsuba's own reconstruction
    filter (gaussian, which splats each sample into the pixels around) instead of box; ``size``: (width, height)
    instead of the clip's own (a probe at another resolution); ``position``: Blender's flag of the common
    command line, ignored here: these clips always carry world positions (``P``)."""
    builder, clip_id, hazards, moving, default_ref, ref_b_frame = CLIPS[name]
    ref_spp = ref_spp or default_ref
    if ref_spp % ref_chunk:
        raise ValueError(f"ref_spp {ref_spp} must be a multiple of ref_chunk {ref_chunk}")
    variant = pick_variant()
    width, height = size or SIZE.get(name, (C.WIDTH, C.HEIGHT))
    out = Path(out_root) / name
    out.mkdir(parents=True, exist_ok=True)
    light = {"type": INTEGRATOR.get(name, "path"), "max_depth": MAX_DEPTH}
    noisy = mi.load_dict({"type": "aov", "aovs": AOVS, "integrator": light})
    path = mi.load_dict(light)
    albedo_only = mi.load_dict({"type": "aov", "aovs": "albedo:albedo"})
    timer = C.Timer()
    per_frame, seeds = [], {p: [] for p in C.PASSES}
    hdr = {"renderer": f"Mitsuba {mi.__version__} (drjit {dr.__version__}), variant {variant}"}
    for f in tqdm(range(frames), desc=name, unit="frame"):
        scene_dict, info = builder(f, frames)
        scene_dict["sensor"]["film"].update(width=width, height=height)
        if renderer_defaults:
            del scene_dict["sensor"]["film"]["rfilter"]
        per_frame.append({k: v for k, v in info.items() if k != "description"})
        scene = mi.load_dict(copy.copy(scene_dict))
        for pass_name, spp, fname in (("noisy1", 1, "frame"), ("noisy4", 4, "frame4spp")):
            s = C.seed(clip_id, pass_name, f)
            seeds[pass_name].append(s)
            t0 = time.perf_counter()
            mi.render(scene, integrator=noisy, seed=s, spp=spp)
            ch = _channels(scene)
            timer.add(pass_name, t0)
            C.write_exr(out / f"{fname}_{f:04d}.exr", ch, HALF, {**hdr, "spp": spp})
        refs = [("reference", f"reference_{f:04d}.exr", ref_spp)]
        if ref_b_frame is not None and f == ref_b_frame:
            refs.append(("ref_b", f"ref_b_{f:04d}.exr", ref_spp))
        for pass_name, fname, spp in refs:
            acc = np.zeros((height, width, 3))
            t0 = time.perf_counter()
            chunk_seeds = []
            for c in range(spp // ref_chunk):
                s = C.seed(clip_id, pass_name, f, c)
                chunk_seeds.append(s)
                acc += np.array(mi.render(scene, integrator=path, seed=s, spp=ref_chunk), dtype=np.float64)[..., :3]
            timer.add(pass_name, t0)
            seeds[pass_name].append(chunk_seeds)
            acc /= spp // ref_chunk
            C.write_exr(out / fname, {c: acc[..., i] for i, c in enumerate("RGB")}, (), {**hdr, "spp": spp})
        if moving:
            s = C.seed(clip_id, "mask", f)
            seeds["mask"].append(s)
            t0 = time.perf_counter()
            mscene = mi.load_dict(_mask_scene(scene_dict, moving))
            mi.render(mscene, integrator=albedo_only, seed=s, spp=16)
            img = np.array(dict(mscene.sensors()[0].film().bitmap().split())["albedo"])
            timer.add("mask", t0)
            C.write_exr(out / f"mask_{f:04d}.exr", {"moving": img.mean(-1)}, ("moving",))
    _, info0 = builder(0, frames)
    manifest = {
        "scene": name,
        "renderer": hdr["renderer"],
        "frames": frames, "width": width, "height": height,
        "spp": {"noisy1": 1, "noisy4": 4, "reference": ref_spp, "ref_chunk_spp": ref_chunk, "mask": 16 if moving else 0},
        "integrator_noisy": {"type": "aov", "aovs": AOVS, "integrator": light},
        "integrator_ref": light,
        "film": f"hdrfilm {width}x{height} rgb float32, rfilter {'gaussian (default)' if renderer_defaults else 'box'}; "
                "sampler independent",
        "description": info0["description"],
        "hazards": hazards,
        "moving_objects": moving,
        "seeds": seeds,
        "seed_rule": "clip_id*100000 + pass*10000 + frame*100 + chunk (pass: noisy1 1, noisy4 2, reference 3, "
                     "ref_b 4, mask 5)",
        "clip_id": clip_id,
        "ref_b": C.ref_b_entry(ref_b_frame),
        "render_seconds": timer.secs,
        "render_cpu_seconds": timer.cpu,
        "host": {**C.host(), "threads": dr.thread_count() if hasattr(dr, "thread_count") else None},
        "files": {
            "frame_XXXX.exr": "1 sample per pixel: R,G,B (float32, linear HDR) and features of the same samples: "
                              "albedo.R/G/B, N.X/Y/Z (shading normal, world space), P.X/Y/Z (world position) half; "
                              "Z (distance along the camera ray, 0 on a miss) float32",
            "frame4spp_XXXX.exr": "the same at 4 samples per pixel (independent samples)",
            "reference_XXXX.exr": f"R,G,B float32, {ref_spp} spp: float64 mean of {ref_spp // ref_chunk} chunks",
            **C.ref_b_files(ref_b_frame),
            **({"mask_XXXX.exr": "moving: fraction of the pixel's first hits (16 spp) on a moving object"}
               if moving else {}),
        },
        "per_frame_animation": per_frame,
    }
    C.write_manifest(out, manifest)
    return out


class RunningMean:
    """Mitsuba's progressive loop, one frame: the mean of ``n`` independent 1-spp passes, each added as a
    channel dict."""

    def __init__(self):
        self.sums: dict = {}
        self.n = 0

    def add(self, channels: dict) -> None:
        for name, a in channels.items():
            a = np.asarray(a, dtype=np.float64)
            if name in self.sums:
                self.sums[name] += a
            else:
                self.sums[name] = a.copy()
        self.n += 1

    def mean(self) -> dict:
        return {k: v / self.n for k, v in self.sums.items()}


def iteration_seeds(clip_id: int, frame: int, count: int) -> list:
    """Seeds of iterations 2..count of a frame (iteration 1 is the 1-spp frame, seed ``noisy1``)."""
    if count > 100:
        raise ValueError(f"iterations: at most 100, got {count}")
    return [C.seed(clip_id, "iteration", frame, k) for k in range(2, count + 1)]


def render_iterations(name: str, out_root: Path, frames: int, count: int) -> Path:
    """The progressive loop of clip ``name``, already rendered in ``out_root``: per frame, ``count - 1`` more
    independent 1-spp passes after ``frame_XXXX.exr`` (the set's box filter, the frame's own size), their
    running means written as ``iter<n>_XXXX.exr`` (``C.ITERATION_LEVELS``, header ``spp`` n): what a user
    who adds one sample per pixel per iteration holds after n iterations."""
    builder, clip_id = CLIPS[name][:2]
    out = Path(out_root) / name
    pick_variant()
    noisy = mi.load_dict({"type": "aov", "aovs": AOVS,
                          "integrator": {"type": INTEGRATOR.get(name, "path"), "max_depth": MAX_DEPTH}})
    hdr = {"renderer": f"Mitsuba {mi.__version__} (drjit {dr.__version__}), variant {mi.variant()}"}
    total = C.clip_frames(out)
    for f in tqdm(range(min(frames, total)), desc=f"{name} iterations", unit="frame"):
        first = out / f"frame_{f:04d}.exr"
        if not first.exists():
            raise FileNotFoundError(f"{first}: render the clip first (without --iterations)")
        acc = RunningMean()
        acc.add(C.read_all(first))
        height, width = acc.sums["R"].shape
        scene_dict, _ = builder(f, total)
        scene_dict["sensor"]["film"].update(width=width, height=height)
        scene = mi.load_dict(scene_dict)
        for k, s in enumerate(iteration_seeds(clip_id, f, count), start=2):
            mi.render(scene, integrator=noisy, seed=s, spp=1)
            acc.add(_channels(scene))
            if k in C.ITERATION_LEVELS:
                C.write_exr(out / f"iter{k}_{f:04d}.exr", acc.mean(), HALF, {**hdr, "spp": k})
    return out


def main(argv=None):
    C.clip_main(__doc__.split("\n")[0], CLIPS, render_clip, argv, render_iterations)


if __name__ == "__main__":
    main()
