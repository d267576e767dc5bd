"""Blender Cycles clips of the validation set, scenes built here in Python with ``bpy`` (no downloaded asset).

    /work/venvs/bpy/bin/python benchmarks/validation/render_blender.py bl_glass_caustic --out /work/valdata

Per clip and frame:

* ``frame_XXXX.exr``: 1 spp, the multilayer EXR exactly as Blender writes it (Blender 5: one part per pass):
  ``ViewLayer.Combined.R/G/B/A``, ``ViewLayer.Depth.Z``, ``ViewLayer.Normal.X/Y/Z`` (world space),
  ``ViewLayer.Denoising Normal.X/Y/Z`` (camera space), ``ViewLayer.Denoising Albedo.R/G/B``,
  ``ViewLayer.Denoising Depth.Z``; Blender's "Half" colour depth (it keeps normals and depths in float32 itself);
* ``frame4spp_XXXX.exr``: the same at 4 spp, independent samples;
* ``reference_XXXX.exr``: plain ``R,G,B`` float32, the float64 mean of Blender's Combined over independent chunks;
* ``ref_b_XXXX.exr``: a second independent reference of one frame (how far two references agree caps any score);
* ``mask_XXXX.exr`` (clips with moving objects): ``moving`` = 1 where Cycles' object-index pass of the first
  reference chunk is a moving object (Cycles writes that pass unfiltered, from one sample).

Fair noisy passes (shared/docs/foreign-renderers.md): no adaptive sampling, no denoising, no clamping, box pixel
filter, a new ``cycles.seed`` per frame, pass and chunk (``_common.seed``).
"""
from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

import bpy  # noqa: E402
from mathutils import Vector  # noqa: E402

MAX_BOUNCES = 8
THREADS = 2


# ---------------------------------------------------------------------------------------------------- scene parts
def reset() -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def _material(name: str) -> tuple:
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    return m, nt, out


def diffuse(name: str, rgb, texture=None) -> bpy.types.Material:
    """Diffuse BSDF; ``texture`` = ("checker", c1, c2, scale) or ("noise", c1, c2, scale) for a procedural colour."""
    m, nt, out = _material(name)
    bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Color"].default_value = (*rgb, 1.0)
    if texture is not None:
        kind, c1, c2, scale = texture
        if kind == "checker":
            tex = nt.nodes.new("ShaderNodeTexChecker")
            tex.inputs["Color1"].default_value = (*c1, 1.0)
            tex.inputs["Color2"].default_value = (*c2, 1.0)
            tex.inputs["Scale"].default_value = scale
            nt.links.new(tex.outputs["Color"], bsdf.inputs["Color"])
        elif kind == "noise":
            tex = nt.nodes.new("ShaderNodeTexNoise")
            tex.inputs["Scale"].default_value = scale
            tex.inputs["Detail"].default_value = 6.0
            ramp = nt.nodes.new("ShaderNodeValToRGB")
            ramp.color_ramp.elements[0].color = (*c1, 1.0)
            ramp.color_ramp.elements[1].color = (*c2, 1.0)
            nt.links.new(tex.outputs["Fac"], ramp.inputs["Fac"])
            nt.links.new(ramp.outputs["Color"], bsdf.inputs["Color"])
        else:
            raise ValueError(f"texture kind {kind!r}: expected 'checker' or 'noise'")
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return m


def metal(name: str, rgb, roughness: float) -> bpy.types.Material:
    m, nt, out = _material(name)
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
    bsdf.inputs["Metallic"].default_value = 1.0
    bsdf.inputs["Roughness"].default_value = roughness
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return m


def glass(name: str, ior: float = 1.5) -> bpy.types.Material:
    m, nt, out = _material(name)
    bsdf = nt.nodes.new("ShaderNodeBsdfGlass")
    bsdf.inputs["Roughness"].default_value = 0.0
    bsdf.inputs["IOR"].default_value = ior
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return m


def add(kind: str, mat, location=(0, 0, 0), rotation=(0, 0, 0), scale=(1, 1, 1), smooth=False, **kw):
    """A primitive mesh object with one material (``kind``: plane, cube, uv_sphere, cylinder, ico_sphere)."""
    getattr(bpy.ops.mesh, f"primitive_{kind}_add")(location=location, rotation=[math.radians(a) for a in rotation],
                                                   **kw)
    ob = bpy.context.object
    ob.scale = scale
    ob.data.materials.append(mat)
    if smooth:
        for p in ob.data.polygons:
            p.use_smooth = True
    return ob


def room(floor, back, left, right, ceiling) -> None:
    """Box x, y in [-1, 1], z in [0, 2], open towards -y (the camera)."""
    add("plane", floor, (0, 0, 0), size=2)
    add("plane", ceiling, (0, 0, 2), (180, 0, 0), size=2)
    add("plane", back, (0, 1, 1), (90, 0, 0), size=2)
    add("plane", left, (-1, 0, 1), (0, 90, 0), size=2)
    add("plane", right, (1, 0, 1), (0, -90, 0), size=2)


def camera(scene, origin, target, fov: float):
    cam = scene.camera
    if cam is None:
        cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
        scene.collection.objects.link(cam)
        scene.camera = cam
    cam.data.sensor_fit = "AUTO"
    cam.data.angle = math.radians(fov)
    cam.location = Vector(origin)
    cam.rotation_euler = (Vector(target) - Vector(origin)).to_track_quat("-Z", "Y").to_euler()


def light(kind: str, location, energy: float, rotation=(0, 0, 0), **props):
    data = bpy.data.lights.new(f"{kind.lower()}_light", type=kind)
    data.energy = energy
    for k, v in props.items():
        setattr(data, k, v)
    ob = bpy.data.objects.new(data.name, data)
    ob.location = location
    ob.rotation_euler = [math.radians(a) for a in rotation]
    bpy.context.scene.collection.objects.link(ob)
    return ob


def sky_world(zenith, horizon, strength: float) -> None:
    """World: a horizon-to-zenith gradient on the view direction's z (procedural, no HDRI file)."""
    w = bpy.data.worlds.new("sky")
    bpy.context.scene.world = w
    w.use_nodes = True
    nt = w.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    coord = nt.nodes.new("ShaderNodeTexCoord")
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (*horizon, 1.0)
    ramp.color_ramp.elements[1].color = (*zenith, 1.0)
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = strength
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(coord.outputs["Generated"], sep.inputs["Vector"])
    nt.links.new(sep.outputs["Z"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])


def black_world() -> None:
    w = bpy.data.worlds.new("black")
    bpy.context.scene.world = w
    w.use_nodes = True
    w.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0


def lerp(a, b, t):
    return [x + (y - x) * t for x, y in zip(a, b)]


# ---------------------------------------------------------------------------------------------------- clips
# Each builder makes the scene once and returns (animate(frame) -> per-frame info, description, moving objects).
def clip_glass_caustic(scene, n: int):
    room(diffuse("floor", (0.6, 0.6, 0.6), ("noise", (0.45, 0.3, 0.15), (0.75, 0.6, 0.4), 6.0)),
         diffuse("back", (0.7, 0.7, 0.7), ("checker", (0.75, 0.75, 0.75), (0.1, 0.25, 0.5), 6.0)),
         diffuse("left", (0.65, 0.25, 0.15)), diffuse("right", (0.7, 0.7, 0.7)), diffuse("ceil", (0.7, 0.7, 0.7)))
    add("uv_sphere", glass("glass"), (-0.3, -0.1, 0.33), radius=0.33, segments=64, ring_count=32, smooth=True)
    add("uv_sphere", metal("mirror", (0.95, 0.95, 0.95), 0.0), (0.45, 0.35, 0.25), radius=0.25, segments=64,
        ring_count=32, smooth=True)
    add("cube", glass("glass_block", 1.45), (0.35, -0.45, 0.2), (0, 0, 30), scale=(0.12, 0.12, 0.2))
    light("POINT", (0.1, 0.0, 1.75), 40.0, shadow_soft_size=0.02)
    black_world()

    def animate(f):
        t = f / max(1, n - 1)
        target = lerp([-0.3, 0, 0.6], [0.3, 0, 0.6], t)
        camera(scene, (0, -3.6, 1.0), target, 38)
        return {"camera": {"origin": [0, -3.6, 1.0], "target": target, "fov": 38}}

    desc = ("Box room lit only by a small point light (radius 0.02, 40 W) near the ceiling. A smooth glass sphere "
            "(ior 1.5) casts a caustic on a noise-textured floor; a mirror sphere (metallic, roughness 0); a glass "
            "block (ior 1.45); checker back wall. The camera pans.")
    return animate, desc, []


def clip_moving_metal(scene, n: int):
    room(diffuse("floor", (0.6, 0.6, 0.6), ("checker", (0.7, 0.7, 0.7), (0.08, 0.08, 0.08), 8.0)),
         diffuse("back", (0.6, 0.6, 0.6), ("noise", (0.2, 0.25, 0.35), (0.7, 0.7, 0.65), 4.0)),
         diffuse("left", (0.15, 0.3, 0.6)), diffuse("right", (0.6, 0.45, 0.15)), diffuse("ceil", (0.75, 0.75, 0.75)))
    # An area light set into the ceiling (visible to the camera), and rough metals of three roughnesses.
    light("AREA", (0, 0, 1.995), 40.0, size=0.5)
    add("uv_sphere", metal("gold", (1.0, 0.77, 0.35), 0.3), (-0.5, 0.3, 0.3), radius=0.3, segments=48,
        ring_count=24, smooth=True)
    add("uv_sphere", metal("steel", (0.6, 0.62, 0.65), 0.5), (0.5, 0.45, 0.25), radius=0.25, segments=48,
        ring_count=24, smooth=True)
    add("cylinder", metal("brushed", (0.9, 0.6, 0.5), 0.2), (0.05, 0.6, 0.35), radius=0.12, depth=0.7,
        vertices=48, smooth=True)
    mover = add("cube", diffuse("mover", (0.8, 0.8, 0.75)), (0, 0, 0.15), scale=(0.15, 0.15, 0.15))
    mover.pass_index = 1
    black_world()
    camera(scene, (0, -3.6, 1.0), (0, 0, 0.9), 40)

    def animate(f):
        t = f / max(1, n - 1)
        loc = (-0.6 + 1.1 * t, -0.35, 0.15)
        mover.location = loc
        mover.rotation_euler = (0, 0, math.radians(20 + 50 * t))
        return {"mover": {"location": list(loc), "rotate_z_deg": 20 + 50 * t}}

    desc = ("Box room lit by a 0.5x0.5 area light 5 mm below the ceiling (visible to the camera). Rough metals: "
            "gold sphere (roughness 0.3), steel sphere (0.5), copper cylinder (0.2); checker floor, noise-textured "
            "back wall; a white cube slides and turns over the floor (contact shadow). Static camera.")
    return animate, desc, ["mover"]


def clip_env_thin(scene, n: int):
    sky_world((0.25, 0.45, 0.9), (0.85, 0.85, 0.8), 1.0)
    light("SUN", (0, 0, 5), 3.0, rotation=(50, 0, 35), angle=math.radians(1.5))
    add("plane", diffuse("ground", (0.4, 0.4, 0.3), ("noise", (0.15, 0.25, 0.08), (0.5, 0.45, 0.3), 3.0)),
        (0, 0, 0), size=20)
    post = diffuse("post", (0.85, 0.85, 0.8))
    for i in range(13):
        # Rods 0.005-0.013 in radius: under a pixel (about 0.02 wide at the fence) to a little over half a pixel.
        add("cylinder", post, (-1.5 + 0.25 * i, 0.6, 0.55), radius=0.005 + 0.0007 * i, depth=1.1, vertices=8)
    rail = diffuse("rail", (0.5, 0.35, 0.2))
    for z in (0.4, 0.95):
        add("cylinder", rail, (0, 0.6, z), (0, 90, 0), radius=0.008, depth=3.2, vertices=8)
    # A wireframe ball: thin wires with holes between them.
    cage = add("ico_sphere", metal("wire", (0.9, 0.9, 0.92), 0.3), (0.75, 0.1, 0.35), radius=0.35, subdivisions=2)
    mod = cage.modifiers.new("wires", "WIREFRAME")
    mod.thickness = 0.008
    ball = add("uv_sphere", diffuse("ball", (0.7, 0.15, 0.1)), (0, 0, 0.22), radius=0.22, segments=48,
               ring_count=24, smooth=True)
    ball.pass_index = 1

    def animate(f):
        t = f / max(1, n - 1)
        ball.location = (-0.9 + 1.2 * t, -0.4, 0.22)
        origin = lerp([-0.5, -3.4, 1.1], [0.5, -3.4, 1.1], t)
        camera(scene, origin, (0, 0, 0.45), 40)
        return {"ball": {"location": list(ball.location)}, "camera": {"origin": origin, "target": [0, 0, 0.45]}}

    desc = ("Open scene: a procedural sky (horizon-to-zenith gradient world, strength 1) and a sun lamp (strength 3, "
            "1.5 degrees) over a noise-textured ground. Thin geometry: a fence of 13 rods (radius 0.005-0.013) with "
            "two rails and a wireframe ico-sphere (wires 8 mm). A red ball rolls over the ground (contact shadow); "
            "the camera dollies sideways.")
    return animate, desc, ["ball"]


def clip_indirect_dof(scene, n: int):
    """Closed room lit only by bounce light (a cove light on a shelf faces the ceiling); thin-lens camera; a ball
    rolls. The idea of render_mitsuba.py's mi_indirect_dof, built for Cycles."""
    # Closed box x in [-1, 1], y in [-2.6, 1], z in [0, 2]; the camera stands inside, 0.4 from the front wall.
    y0, y1 = -2.6, 1.0
    yc, depth = (y0 + y1) / 2, y1 - y0
    add("plane", _wood_floor(), (0, yc, 0), scale=(1, depth / 2, 1), size=2)
    add("plane", diffuse("ceil", (0.85, 0.85, 0.85)), (0, yc, 2), (180, 0, 0), scale=(1, depth / 2, 1), size=2)
    add("plane", diffuse("back", (0.7, 0.65, 0.55), ("noise", (0.45, 0.42, 0.35), (0.8, 0.72, 0.6), 5.0)),
        (0, y1, 1), (90, 0, 0), size=2)
    add("plane", diffuse("front", (0.7, 0.7, 0.7)), (0, y0, 1), (-90, 0, 0), size=2)
    add("plane", diffuse("left", (0.3, 0.45, 0.65), ("noise", (0.2, 0.35, 0.5), (0.45, 0.65, 0.8), 4.0)),
        (-1, yc, 1), (0, 90, 0), scale=(1, depth / 2, 1), size=2)
    add("plane", diffuse("right", (0.6, 0.55, 0.45)), (1, yc, 1), (0, -90, 0), scale=(1, depth / 2, 1), size=2)
    # A dark shelf along the back wall, above the camera's view: the light lies on it facing the ceiling, 0.7 below
    # it (a one-sided area light: nothing under its plane is lit directly). The camera's top rows see the shelf
    # from below; neither the light nor any surface it lights directly is in view.
    add("cube", diffuse("shelf", (0.1, 0.1, 0.1)), (0, 0.73, 1.27), scale=(0.99, 0.26, 0.025))
    light("AREA", (0, 0.72, 1.3), 120.0, rotation=(180, 0, 0), shape="RECTANGLE", size=1.2, size_y=0.24,
          color=(1.0, 0.87, 0.67))
    checker = ("checker", (0.8, 0.75, 0.6), (0.1, 0.15, 0.3), 3.0)
    box = add("cube", diffuse("checker_box", (0.8, 0.75, 0.6), checker), (0.05, -0.4, 0.25), (0, 0, 30),
              scale=(0.25, 0.25, 0.25))
    ball = add("uv_sphere", diffuse("ball", (0.7, 0.25, 0.1)), (-0.45, -0.9, 0.18), radius=0.18, segments=48,
               ring_count=24, smooth=True)
    ball.pass_index = 1
    # Close to the lens (0.95 ahead of it): far out of focus. At the back (2.9 ahead): out of focus too.
    add("cylinder", diffuse("near_post", (0.85, 0.85, 0.8), ("checker", (0.85, 0.85, 0.8), (0.2, 0.05, 0.05),
                                                                  10.0)),
        (0.35, -1.25, 0.65), radius=0.06, depth=1.3, vertices=32, smooth=True)
    add("uv_sphere", diffuse("far_vase", (0.5, 0.6, 0.4), ("checker", (0.2, 0.5, 0.3), (0.8, 0.8, 0.6), 12.0)),
        (-0.6, 0.7, 0.25), radius=0.25, segments=48, ring_count=24, smooth=True)
    black_world()
    origin, target, fov, fstop = (0.15, -2.2, 0.7), (0.0, 0.0, 0.25), 45, 0.36
    camera(scene, origin, target, fov)
    cam = scene.camera.data
    view = (Vector(target) - Vector(origin)).normalized()
    focus = (box.location - Vector(origin)).dot(view)  # the checker box's centre, along the view axis
    cam.dof.use_dof = True
    cam.dof.focus_distance = focus
    cam.dof.aperture_fstop = fstop  # aperture radius = focal length / (2 f-stop), about 0.06 here
    aperture_radius = cam.lens / 1000 / (2 * fstop)

    def animate(f):
        t = f / max(1, n - 1)
        ball.location = (-0.45 + 0.35 * t, -0.9, 0.18)
        ball.rotation_euler = (0, math.radians(-110 * t), 0)
        return {"ball": {"location": list(ball.location)},
                "camera": {"origin": list(origin), "target": list(target), "fov": fov, "aperture_fstop": fstop,
                           "aperture_radius": round(aperture_radius, 4), "focus_distance": round(focus, 4)}}

    desc = ("Closed box room (x -1..1, y -2.6..1, z 0..2, the camera inside) lit only indirectly: a 1.2x0.24 area "
            "light (120 W, warm) lies on a dark shelf along the back wall, above the camera's view, facing the "
            "ceiling 0.7 above it. The camera looks down a little so that its top rows see the shelf from below: "
            "neither the light nor any surface it lights directly is in view, everything seen is lit by bounce light "
            "only (sparse, high-energy 1-spp samples). Noise-textured back and left walls, striped wood floor (wave "
            "x noise). Thin-lens camera (Cycles depth of field, fov 45, f-stop 0.36: aperture radius about 0.06) "
            "focused on a checker box at mid depth: a checker post 0.95 ahead of the lens and a checker sphere at "
            "the back are out of focus, so albedo, normal and depth are blurred per sample. A red ball rolls a "
            "little (moving object, contact shadow). Static camera.")
    return animate, desc, ["ball"]


def _keyframe_path(obs_paths: dict, n: int, step: float = 0.125) -> None:
    """Keyframe ``{object: pose(u) -> (location, rotation_euler or None)}`` every ``step`` frames, linear between keys.

    ``u`` is the clip's frame index (render_clip shows frame ``u`` as Blender frame ``u + 1``); keys run from half a
    frame before the first frame to half a frame after the last, so Cycles' motion blur (which re-evaluates the
    animation at sub-frames inside the shutter) sees the true velocity at every frame, and dense keys keep curved
    paths (an orbit, a bounce, a spin) curved inside the shutter."""
    for k in range(int(round((n + 1) / step)) + 1):
        u = -0.5 + k * step
        for ob, pose in obs_paths.items():
            loc, rot = pose(u)
            ob.location = loc
            ob.keyframe_insert("location", frame=u + 1)
            if rot is not None:
                ob.rotation_euler = rot
                ob.keyframe_insert("rotation_euler", frame=u + 1)
    for ob in obs_paths:
        for fc in _fcurves(ob):
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"


def _fcurves(ob) -> list:
    """The object's f-curves (Blender 5 keeps them in layered actions: layers -> strips -> channelbags)."""
    act = ob.animation_data.action
    if hasattr(act, "fcurves"):
        return list(act.fcurves)
    out = []
    for layer in act.layers:
        for strip in layer.strips:
            for bag in strip.channelbags:
                out += list(bag.fcurves)
    return out


def clip_motion_blur(scene, n: int):
    """Fast movers under Cycles motion blur (shutter 0.5 frame): a ball rolling round an orbit, a spinning box
    sliding across the room, a bouncing ball; a gentle camera pan. Motion is keyframed (see ``_keyframe_path``)."""
    room(diffuse("floor", (0.6, 0.6, 0.6), ("checker", (0.75, 0.72, 0.65), (0.1, 0.1, 0.12), 10.0)),
         diffuse("back", (0.6, 0.6, 0.6), ("noise", (0.35, 0.3, 0.25), (0.75, 0.72, 0.62), 4.0)),
         diffuse("left", (0.6, 0.2, 0.12)), diffuse("right", (0.15, 0.4, 0.25)), diffuse("ceil", (0.75, 0.75, 0.75)))
    # Set into the ceiling; lights are hidden from camera rays by default (visible_camera False; the light of
    # bl_moving_metal is not seen directly): shown here.
    light("AREA", (0, 0, 1.995), 40.0, size=0.5).visible_camera = True
    r_ball, orbit_c, orbit_r, orbit_deg = 0.18, (0.0, -0.1), 0.42, 50.0
    ball = add("uv_sphere", diffuse("ball", (0.8, 0.3, 0.1), ("checker", (0.85, 0.35, 0.1), (0.9, 0.85, 0.75), 4.0)),
               radius=r_ball, segments=48, ring_count=24, smooth=True)
    box_half, box_y, box_x0, box_dx, box_spin = 0.15, 0.75, -0.7, 0.2, 60.0
    box = add("cube", diffuse("box", (0.7, 0.7, 0.7), ("checker", (0.15, 0.3, 0.6), (0.85, 0.85, 0.8), 3.0)),
              scale=(box_half, box_half, box_half))
    r_hop, hop_xy, hop_h, hop_period = 0.1, (0.78, 0.2), 0.8, 2.5
    hop = add("uv_sphere", diffuse("hop", (0.85, 0.85, 0.8)), radius=r_hop, segments=32, ring_count=16, smooth=True)
    for ob in (ball, box, hop):
        ob.pass_index = 1
        ob.cycles.motion_steps = 3  # more steps inside the shutter: orbits and spins stay curved
    black_world()
    scene.frame_start, scene.frame_end = 1, n
    scene.render.use_motion_blur = True
    scene.render.motion_blur_shutter = 0.5
    scene.render.motion_blur_position = "CENTER"
    cam_origin, fov = (0, -3.6, 1.2), 40  # sees the light in the ceiling
    camera(scene, cam_origin, (0, 0, 1.0), fov)
    cam = scene.camera

    def ball_pose(u):
        th = math.radians(-90 + orbit_deg * u)  # starts at the front of the orbit, runs anticlockwise
        loc = (orbit_c[0] + orbit_r * math.cos(th), orbit_c[1] + orbit_r * math.sin(th), r_ball)
        # Rolling without slipping: turn about the radial axis by -(arc / radius), then face along the orbit.
        return loc, (-(th + math.pi / 2) * orbit_r / r_ball, 0.0, th)

    def box_pose(u):
        return (box_x0 + box_dx * u, box_y, box_half), (0.0, 0.0, math.radians(box_spin * u))

    def hop_pose(u):
        s = (u % hop_period) / hop_period * 2 - 1  # a parabola per bounce, ground contact at s = +-1
        return (*hop_xy, r_hop + hop_h * (1 - s * s)), None

    def cam_target(u):
        return lerp([-0.15, 0, 1.0], [0.15, 0, 1.0], u / max(1, n - 1))

    def cam_pose(u):
        camera(scene, cam_origin, cam_target(u), fov)
        return tuple(cam.location), tuple(cam.rotation_euler)

    _keyframe_path({ball: ball_pose, box: box_pose, hop: hop_pose, cam: cam_pose}, n)

    def animate(f):
        # The keyframes move everything (render_clip shows frame f as Blender frame f + 1); this records the poses.
        info = {}
        for name, pose in (("ball", ball_pose), ("box", box_pose), ("hop", hop_pose)):
            loc, rot = pose(f)
            info[name] = {"location": [round(v, 4) for v in loc]}
            if rot is not None:
                info[name]["rotation_euler_deg"] = [round(math.degrees(v), 2) for v in rot]
        info["camera"] = {"origin": list(cam_origin), "target": cam_target(f), "fov": fov}
        return info

    desc = ("Box room lit by a 0.5x0.5 area light 5 mm below the ceiling (visible to the camera); checker floor, "
            "noise-textured back wall, red and green side walls. Cycles motion blur (shutter 0.5 frame, centred; "
            "keyframed motion, linear between keys every 1/8 frame): a checker ball (radius 0.18) rolls round an "
            "orbit of radius 0.42 at 50 degrees a frame (0.37 a frame), a checker box (0.3) slides 0.2 a frame while "
            "spinning 60 degrees a frame, a white ball (radius 0.1) bounces 0.8 high every 2.5 frames (1.3 a frame at "
            "contact); all cast contact shadows. The camera pans gently (target 0.3 across the clip, also blurred).")
    return animate, desc, ["ball", "box", "hop"]


def _wood_floor() -> bpy.types.Material:
    """Diffuse floor: wave-texture bands along x, broken up by noise, on a brown colour ramp (procedural wood)."""
    m, nt, out = _material("wood_floor")
    bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
    wave = nt.nodes.new("ShaderNodeTexWave")
    wave.wave_type = "BANDS"
    wave.bands_direction = "X"
    wave.inputs["Scale"].default_value = 6.0
    wave.inputs["Distortion"].default_value = 4.0
    wave.inputs["Detail"].default_value = 3.0
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (0.12, 0.07, 0.03, 1.0)
    ramp.color_ramp.elements[1].color = (0.55, 0.38, 0.2, 1.0)
    nt.links.new(wave.outputs["Fac"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], bsdf.inputs["Color"])
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return m


def clip_fog(scene, n: int):
    """The open scene of ``clip_env_thin`` in fog: a 12-unit cube around it holds a homogeneous scattering medium
    (a world volume would put the sun and the sky at an infinite optical depth). Where a path scatters in the
    medium before any surface, Cycles writes depth 0 and the medium's colour as the denoising albedo."""
    animate, desc, moving = clip_env_thin(scene, n)
    mat = bpy.data.materials.new("fog")
    mat.use_nodes = True
    nt = mat.node_tree
    for node in list(nt.nodes):
        nt.nodes.remove(node)
    vol = nt.nodes.new("ShaderNodeVolumeScatter")
    vol.inputs["Density"].default_value = 0.15
    vol.inputs["Color"].default_value = (0.9, 0.9, 0.9, 1.0)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(vol.outputs["Volume"], out.inputs["Volume"])
    add("cube", mat, (0, 0, 2.0), size=12)
    return animate, desc + (" A 12-unit cube around the scene and the camera holds fog (volume scatter, density 0.15 "
                            "per unit, colour 0.9)."), moving


def _principled(name: str, rgb, **inputs) -> tuple:
    """Principled BSDF with ``inputs`` set by socket name; returns (material, node tree, BSDF node)."""
    m, nt, out = _material(name)
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
    for k, v in inputs.items():
        bsdf.inputs[k].default_value = v
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return m, nt, bsdf


def clip_materials(scene, n: int):
    """Materials the other clips lack: subsurface scattering, a light that is an emissive mesh (Cycles writes
    its emission as its denoising albedo), a spot light's cone, alpha cut-outs and glossy plastic."""
    room(diffuse("floor", (0.6, 0.6, 0.6), ("checker", (0.7, 0.7, 0.7), (0.2, 0.2, 0.25), 8.0)),
         diffuse("back", (0.7, 0.7, 0.7)), diffuse("left", (0.6, 0.2, 0.15)), diffuse("right", (0.2, 0.5, 0.3)),
         diffuse("ceil", (0.75, 0.75, 0.75)))
    skin = _principled("skin", (0.9, 0.6, 0.45), **{"Subsurface Weight": 1.0, "Subsurface Scale": 0.1,
                                                     "Roughness": 0.4})[0]
    add("uv_sphere", skin, (-0.45, 0.2, 0.3), radius=0.3, segments=48, ring_count=24, smooth=True)
    add("cube", _principled("plastic", (0.1, 0.2, 0.7), Roughness=0.15)[0], (0.45, 0.4, 0.2), (0, 0, 25),
        scale=(0.2, 0.2, 0.2))
    neon, nt, out = _material("neon")
    emit = nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (1.0, 0.45, 0.1, 1.0)
    emit.inputs["Strength"].default_value = 15.0
    nt.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    add("cylinder", neon, (0, 0.95, 1.5), (0, 90, 0), radius=0.02, depth=1.2, vertices=16)
    leaf, nt, bsdf = _principled("leaf", (0.2, 0.6, 0.15), Roughness=0.6)
    holes = nt.nodes.new("ShaderNodeTexChecker")
    holes.inputs["Scale"].default_value = 5.0
    holes.inputs["Color1"].default_value = (1, 1, 1, 1)
    holes.inputs["Color2"].default_value = (0, 0, 0, 1)
    nt.links.new(holes.outputs["Fac"], bsdf.inputs["Alpha"])
    panel = add("plane", leaf, (0.1, -0.2, 0.9), (80, 0, 10), size=0.6)
    panel.pass_index = 1
    light("SPOT", (-0.6, -0.6, 1.9), 60.0, rotation=(40, 0, -35), spot_size=math.radians(35), spot_blend=0.05,
          shadow_soft_size=0.02)
    light("AREA", (0, 0, 1.995), 8.0, size=0.4)
    black_world()

    def animate(f):
        t = f / max(1, n - 1)
        target = lerp([-0.2, 0, 0.8], [0.2, 0, 0.8], t)
        panel.location = (0.1 + 0.2 * t, -0.2, 0.9)
        camera(scene, (0, -3.6, 1.0), target, 40)
        return {"panel": {"location": list(panel.location)}, "camera": {"origin": [0, -3.6, 1.0], "target": target}}

    desc = ("Box room with a checker floor: a subsurface sphere (Principled, subsurface weight 1, scale 0.1), a "
            "glossy blue plastic cube (roughness 0.15), a thin orange emissive tube (emission shader, strength 15) "
            "5 cm before the back wall, a panel with checker alpha cut-outs that slides, a spot light (35 degrees, "
            "blend 0.05) and a dim 0.4x0.4 area light in the ceiling. The camera pans.")
    return animate, desc, ["panel"]


def bumped(name: str, bsdf_kind: str, rgb, scale: float, strength: float, roughness: float = 0.0):
    """A diffuse or metal BSDF whose shading normal follows a bump map of procedural noise (``scale`` its
    frequency per object-space unit, ``strength`` its depth): the normals Cycles writes carry detail finer
    than a pixel."""
    m, nt, out = _material(name)
    if bsdf_kind == "diffuse":
        bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Color"].default_value = (*rgb, 1.0)
    else:
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
        bsdf.inputs["Metallic"].default_value = 1.0
        bsdf.inputs["Roughness"].default_value = roughness
    coord = nt.nodes.new("ShaderNodeTexCoord")
    tex = nt.nodes.new("ShaderNodeTexNoise")
    tex.inputs["Scale"].default_value = scale
    tex.inputs["Detail"].default_value = 8.0
    nt.links.new(coord.outputs["Object"], tex.inputs["Vector"])
    bump = nt.nodes.new("ShaderNodeBump")
    bump.inputs["Strength"].default_value = strength
    bump.inputs["Distance"].default_value = 0.1  # Blender 5's default, 1 mm, draws no visible bump here
    nt.links.new(tex.outputs["Fac"], bump.inputs["Height"])
    nt.links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return m


def clip_bump(scene, n: int):
    """Bump-mapped surfaces under a sun: a stucco wall and ground, a hammered-metal ball, a bumpy cube that
    slides; hard shadows. The normals Cycles writes vary within a pixel, so a guide that trusts them keeps
    the noise along with the bumps."""
    sky_world((0.3, 0.5, 0.9), (0.85, 0.85, 0.8), 0.4)
    light("SUN", (0, 0, 5), 2.0, rotation=(40, 0, -30), angle=math.radians(0.5))
    add("plane", bumped("ground", "diffuse", (0.55, 0.5, 0.42), 12.0, 0.6), (0, 0, 0), size=20)
    add("plane", bumped("wall", "diffuse", (0.75, 0.7, 0.62), 6.0, 0.5), (0, 1.2, 1.5), (90, 0, 0), size=6)
    add("uv_sphere", bumped("hammered", "metal", (0.95, 0.75, 0.5), 8.0, 0.4, roughness=0.25),
        (0.55, 0.3, 0.35), radius=0.35, segments=64, ring_count=32, smooth=True)
    cube = add("cube", bumped("stone", "diffuse", (0.45, 0.5, 0.6), 6.0, 0.8), (0, 0, 0.2),
               scale=(0.2, 0.2, 0.2))
    cube.pass_index = 1

    def animate(f):
        t = f / max(1, n - 1)
        cube.location = (-0.8 + 0.7 * t, -0.2, 0.2)
        cube.rotation_euler = (0, 0, math.radians(15 + 30 * t))
        origin = lerp([-0.3, -3.2, 1.1], [0.3, -3.2, 1.1], t)
        camera(scene, origin, (0, 0.3, 0.5), 40)
        return {"cube": {"location": list(cube.location), "rotate_z_deg": 15 + 30 * t},
                "camera": {"origin": origin, "target": [0, 0.3, 0.5]}}

    desc = ("Open scene under a procedural sky (strength 0.4) and a sun (strength 2, 0.5 degrees): "
            "bump-mapped noise (Cycles' Bump node) on the ground, a wall, a hammered gold-metal ball "
            "(roughness 0.25) and a stone cube that slides and turns (contact shadow). The camera dollies "
            "sideways.")
    return animate, desc, ["cube"]


def hairy(ob, count: int, length: float, radius_mm: float, rgb, seed: int):
    """Give mesh ``ob`` a particle system of ``count`` hair strands ``length`` long, rendered by Cycles as
    curves ``radius_mm`` thick at the root, in a Principled Hair BSDF of colour ``rgb``."""
    mod = ob.modifiers.new("hair", "PARTICLE_SYSTEM")
    ps = mod.particle_system
    ps.seed = seed
    st = ps.settings
    st.type = "HAIR"
    st.count = count
    st.hair_length = length
    st.use_advanced_hair = True
    st.brownian_factor = 0.02
    st.root_radius, st.tip_radius = radius_mm * 1e-3, 0.2 * radius_mm * 1e-3
    st.radius_scale = 1.0
    m, nt, out = _material(f"{ob.name}_hair")
    bsdf = nt.nodes.new("ShaderNodeBsdfHairPrincipled")
    bsdf.parametrization = "COLOR"
    bsdf.inputs["Color"].default_value = (*rgb, 1.0)
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    ob.data.materials.append(m)
    st.material = len(ob.data.materials)
    return ob


def clip_hair(scene, n: int):
    """A furry ball rolling over a patch of grass strands in a room lit by an area light: thousands of
    curves thinner than a pixel, each sample's features one strand's or what lies behind."""
    back = diffuse("back", (0.6, 0.6, 0.6), ("noise", (0.3, 0.35, 0.4), (0.7, 0.7, 0.65), 4.0))
    room(diffuse("floor", (0.5, 0.45, 0.35)), back, diffuse("left", (0.6, 0.25, 0.15)),
         diffuse("right", (0.2, 0.45, 0.3)), diffuse("ceil", (0.75, 0.75, 0.75)))
    light("AREA", (0, -0.2, 1.995), 45.0, size=0.6)
    patch = add("plane", diffuse("soil", (0.25, 0.18, 0.1)), (0.25, 0.2, 0.002), scale=(0.55, 0.45, 1),
                size=2)
    hairy(patch, 6000, 0.12, 0.6, (0.25, 0.45, 0.1), 1)
    ball = add("uv_sphere", diffuse("skin", (0.6, 0.5, 0.4)), (0, 0, 0.25), radius=0.18, segments=32,
               ring_count=16, smooth=True)
    hairy(ball, 4000, 0.06, 0.4, (0.75, 0.55, 0.3), 2)
    ball.pass_index = 1

    def animate(f):
        t = f / max(1, n - 1)
        ball.location = (-0.6 + 0.6 * t, -0.45, 0.25)
        ball.rotation_euler = (0, math.radians(-60 * t), 0)
        origin = lerp([-0.2, -3.4, 1.1], [0.2, -3.4, 1.1], t)
        camera(scene, origin, (0, 0, 0.45), 34)
        return {"ball": {"location": list(ball.location)},
                "camera": {"origin": origin, "target": [0, 0, 0.45]}}

    desc = ("Box room lit by a 0.6x0.6 area light under the ceiling: a patch of 6000 grass strands (Cycles "
            "hair curves, 0.6 mm at the root) on the floor and a ball with 4000 strands of fur that rolls "
            "beside it (contact shadow); the camera slides sideways.")
    return animate, desc, ["ball"]


def clip_still(scene, n: int, pan: bool = False):
    """A checkered cube sliding and a checkered ball turning in place (its points keep their positions, its
    texture moves) before a checkered floor, under a still camera or, ``pan``, one sliding sideways about
    half a pixel a frame at 128x128: the two cases a window albedo from depth alone (no Position pass) must
    tell apart."""
    room(diffuse("floor", (0.6, 0.6, 0.6), ("checker", (0.7, 0.7, 0.7), (0.1, 0.1, 0.12), 8.0)),
         diffuse("back", (0.6, 0.6, 0.6), ("noise", (0.2, 0.25, 0.35), (0.7, 0.7, 0.65), 4.0)),
         diffuse("left", (0.6, 0.2, 0.15)), diffuse("right", (0.2, 0.5, 0.3)),
         diffuse("ceil", (0.75, 0.75, 0.75)))
    light("AREA", (0, 0, 1.995), 40.0, size=0.5)
    cube = add("cube", diffuse("box", (0.8, 0.8, 0.8), ("checker", (0.9, 0.85, 0.7), (0.15, 0.2, 0.5), 3.0)),
               (0, 0, 0.2), scale=(0.2, 0.2, 0.2))
    checkered = diffuse("ball", (0.8, 0.8, 0.8), ("checker", (0.9, 0.3, 0.2), (0.9, 0.9, 0.85), 6.0))
    ball = add("uv_sphere", checkered, (0.45, 0.4, 0.3), radius=0.3, segments=48, ring_count=24, smooth=True)
    cube.pass_index = ball.pass_index = 1
    black_world()

    def animate(f):
        t = f / max(1, n - 1)
        cube.location = (-0.6 + 0.4 * t, -0.3, 0.2)
        ball.rotation_euler = (0, 0, math.radians(40 * t))
        dx = 0.012 * f if pan else 0.0
        camera(scene, (dx, -3.6, 1.0), (dx, 0, 0.9), 40)
        return {"cube": {"location": list(cube.location)}, "ball": {"rotate_z_deg": 40 * t},
                "camera": {"origin": [dx, -3.6, 1.0], "target": [dx, 0, 0.9]}}

    desc = ("Box room lit by a 0.5x0.5 area light under the ceiling, checker floor, noise-textured back "
            "wall: a checkered cube slides, a checkered ball turns 40 degrees in place. " +
            ("The camera slides sideways 12 mm a frame." if pan else "Static camera."))
    return animate, desc, ["box", "ball"]


def clip_window(scene, n: int):
    """A room lit by the sun through a window in its left wall and by the sky and bounce light: a sharp
    sun patch on a wood floor, walls lit by bounce light alone, a table, a checkered box, a glossy plastic
    ball and a brushed-metal can; the camera pans and moves in (a scene of the kind people render, not built
    for a hazard)."""
    floor = _wood_floor()
    wall, ceil = diffuse("wall", (0.75, 0.72, 0.65)), diffuse("ceil", (0.8, 0.8, 0.8))
    add("plane", floor, (0, 0, 0), size=2)
    add("plane", ceil, (0, 0, 2), (180, 0, 0), size=2)
    add("plane", wall, (0, 1, 1), (90, 0, 0), size=2)
    add("plane", wall, (1, 0, 1), (0, -90, 0), size=2)
    # the left wall around a window 0.8 wide and 0.7 high, its sill 0.7 above the floor
    for loc, scl in (((-1.0, 0.0, 0.35), (0.02, 1.0, 0.35)), ((-1.0, 0.0, 1.7), (0.02, 1.0, 0.3)),
                     ((-1.0, -0.7, 1.05), (0.02, 0.3, 0.35)), ((-1.0, 0.7, 1.05), (0.02, 0.3, 0.35))):
        add("cube", wall, loc, scale=scl)
    add("cube", diffuse("table", (0.45, 0.3, 0.18)), (0.25, 0.3, 0.35), scale=(0.45, 0.3, 0.35))
    box = add("cube", diffuse("box", (0.7, 0.7, 0.7), ("checker", (0.85, 0.8, 0.7), (0.15, 0.2, 0.4), 6.0)),
              (0.1, 0.25, 0.85), (0, 0, 20), scale=(0.12, 0.12, 0.12))
    add("uv_sphere", _principled("plastic_red", (0.7, 0.08, 0.05), Roughness=0.2)[0], (0.5, 0.2, 0.85),
        radius=0.13, segments=48, ring_count=24, smooth=True)
    add("cylinder", metal("can", (0.8, 0.8, 0.82), 0.3), (-0.35, 0.5, 0.25), radius=0.12, depth=0.5,
        vertices=48)
    light("SUN", (0, 0, 3), 6.0, rotation=(55, 0, -65), angle=math.radians(1.0))
    sky_world((0.25, 0.45, 0.9), (0.8, 0.85, 0.9), 1.0)

    def animate(f):
        t = f / max(1, n - 1)
        origin = lerp([0.35, -2.9, 1.1], [0.1, -2.4, 1.0], t)
        target = lerp([0.2, 0.3, 0.7], [-0.1, 0.3, 0.7], t)
        box.rotation_euler = (0, 0, math.radians(20 + 25 * t))
        camera(scene, origin, target, 45)
        return {"box": {"rotation_z": 20 + 25 * t}, "camera": {"origin": origin, "target": target}}

    desc = ("Room lit by a sun (1 degree) through a 0.8 x 0.7 window in the left wall and by a blue sky "
            "gradient: a sun patch on a procedural wood floor, a table with a turning checkered box, a "
            "glossy red plastic ball (roughness 0.2) and a brushed-metal can (roughness 0.3) on the floor. "
            "The camera pans and moves in.")
    return animate, desc, ["box"]


CLIPS = {
    # name: (builder, clip id for seeds, hazards, reference spp, frame of the second reference). 256 spp at 128x128
    # keeps a clip near 3 min of rendering on the 2 shared cores here (glass clip: 21 s per 128-spp frame under load).
    # The closed metal room is the slowest (every path runs all 8 bounces): no second reference there.
    "bl_glass_caustic": (clip_glass_caustic, 11, ["glass", "mirror", "small_bright_light", "caustics", "camera_pan",
                                                  "textures"], 256, 4),
    "bl_moving_metal": (clip_moving_metal, 12, ["rough_metal", "area_light_in_ceiling", "moving_object",
                                                "contact_shadow", "textures"], 256, None),
    "bl_env_thin": (clip_env_thin, 13, ["environment_lit_open_scene", "thin_geometry", "moving_object",
                                        "contact_shadow", "camera_pan", "textures"], 256, 4),
    # Bounce light alone: 256 spp is still grainy (two 256-spp renders agree to 22 dB). 3072 spp took 54 s a frame
    # here (load about 1), the clip with its second reference 8 min; the two references agree to 32.7 dB.
    "bl_indirect_dof": (clip_indirect_dof, 14, ["indirect_light_only", "splotches", "depth_of_field",
                                                "blurred_features", "moving_object", "contact_shadow", "textures"],
                        3072, 4),
    # Direct light from a ceiling area light converges fast: two 128-spp renders of one frame agree to 36.9 dB at
    # 128x128 (0.4 Mpaths/s here, load about 1); at 1024 spp and 80x80 they agree to 45.8 dB (the clip took 4 min 17 s
    # of wall time, nice 10, load 2-3). Its mask (object index, one sample) is dithered along the streaks.
    "bl_motion_blur": (clip_motion_blur, 15, ["motion_blur", "moving_object", "contact_shadow", "camera_pan",
                                              "area_light_in_ceiling"], 1024, 4),
    # The sky rule's hazard rendered by Cycles (render_mitsuba.py's mi_fog): rendered on demand, not committed.
    "bl_fog": (clip_fog, 16, ["medium", "noisy_depth_zero_pixels", "environment_lit_open_scene", "thin_geometry",
                              "moving_object", "camera_pan"], 256, None),
    # Rendered on demand as a probe, not committed: two 512-spp references of frame 4 agree to the figure in
    # benchmarks/results/validation/probes (the walls lit by the small tube stay grainy).
    "bl_materials": (clip_materials, 17, ["subsurface", "emissive_mesh", "spot_light", "alpha_cutout", "plastic",
                                          "moving_object", "camera_pan"], 512, 4),
    # Probes of a still camera without a Position pass, and of a camera slower than a still test can tell
    # from one (benchmarks/validation/findings.md): rendered on demand, not committed.
    "bl_still": (clip_still, 18, ["still_camera", "texture_turning_in_place", "moving_object", "textures"],
                 512, None),
    "bl_slowpan": (lambda scene, n: clip_still(scene, n, pan=True), 19,
                   ["slow_camera_pan", "texture_turning_in_place", "moving_object", "textures"], 512, None),
    # A probe of shading normals finer than a pixel (bump maps): rendered on demand, not committed. Two renders
    # with the same seeds differ in a few pixels (Cycles' threads move its bumped normals by up to 1e-3).
    "bl_bump": (clip_bump, 20, ["bump_mapping", "sun", "hard_shadows", "moving_object", "camera_pan"], 512,
                None),
    # A room lit through a window, rendered on demand as a probe, not committed: a scene of the ordinary kind,
    # held out from every setting (added after them).
    "bl_window": (clip_window, 22, ["sun_through_window", "indirect_light", "textures", "plastic",
                                    "rough_metal", "moving_object", "camera_pan"], 512, None),
    # A probe of hair (curves thinner than a pixel, by the thousand): rendered on demand, not committed.
    "bl_hair": (clip_hair, 21, ["hair", "thin_geometry", "moving_object", "contact_shadow", "camera_pan",
                                "area_light_in_ceiling"], 512, None),
}


# The closed metal room took 5 min of wall time per 128-spp chunk at 128x128 on the shared 2 cores (load average 15
# when measured), too long for the session that made the set: rendered at 64x64 (49 CPU-s for the clip). Drop the
# entry to render it at 128x128 (about 4x the CPU).
# Motion blur mixes depths and normals along every streak, so Blender's float32 feature passes barely compress: at
# 128x128 a frame's three files take 765 KB (6.3 MB for the clip); at 80x80 the clip takes 2.5 MB.
SIZE = {"bl_moving_metal": (64, 64), "bl_motion_blur": (80, 80)}


# ---------------------------------------------------------------------------------------------------- rendering
def setup_render(scene, width: int, height: int, renderer_defaults: bool = False) -> None:
    r, c = scene.render, scene.cycles
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
    r.threads_mode, r.threads = "FIXED", THREADS
    r.film_transparent = False
    r.use_persistent_data = True  # keep the BVH between the passes of a frame
    c.device = "CPU"
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.pixel_filter_type = "BOX"
    if renderer_defaults:  # what a new scene has
        c.sample_clamp_indirect, c.pixel_filter_type, c.filter_width = 10.0, "BLACKMAN_HARRIS", 1.5
    c.use_animated_seed = False
    c.max_bounces = c.diffuse_bounces = c.glossy_bounces = c.transmission_bounces = MAX_BOUNCES
    c.transparent_max_bounces = MAX_BOUNCES
    img = r.image_settings
    img.media_type = "MULTI_LAYER_IMAGE"
    img.file_format = "OPEN_EXR_MULTILAYER"
    img.exr_codec = "ZIP"


def set_passes(scene, features: bool, object_index: bool = False, depth: str = "16",
               position: bool = False) -> None:
    vl = scene.view_layers[0]
    vl.cycles.denoising_store_passes = features
    vl.use_pass_normal = features
    vl.use_pass_z = features
    vl.use_pass_position = features and position
    vl.use_pass_object_index = object_index
    scene.render.image_settings.color_depth = depth


def render_to(scene, path: Path, spp: int, seed: int) -> None:
    scene.cycles.samples = spp
    scene.cycles.seed = seed
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def render_clip(name: str, out_root: Path, frames: int = C.FRAMES, ref_spp: int | None = None,
                ref_chunk: int = 128, renderer_defaults: bool = False,
                size: tuple[int, int] | None = None, position: bool = False) -> Path:
    """Render clip ``name`` into ``out_root / name``; ``renderer_defaults``: Cycles' own pixel filter
    (Blackman-Harris, 1.5 px) and indirect clamp (10) instead of box and none; ``size``: (width, height)
    instead of the clip's own (a probe at another resolution); ``position``: the noisy frames also carry
    Blender's Position pass (``ViewLayer.Position.X/Y/Z``, world space)."""
    builder, clip_id, hazards, default_ref, ref_b_frame = CLIPS[name]
    ref_spp = ref_spp or default_ref
    if ref_spp % ref_chunk:
        raise ValueError(f"ref_spp {ref_spp} must be a multiple of ref_chunk {ref_chunk}")
    out = Path(out_root) / name
    out.mkdir(parents=True, exist_ok=True)
    width, height = size or SIZE.get(name, (C.WIDTH, C.HEIGHT))
    scene = reset()
    setup_render(scene, width, height, renderer_defaults)
    animate, desc, moving = builder(scene, frames)
    version = bpy.app.version_string
    timer = C.Timer()
    per_frame, seeds = [], {p: [] for p in C.PASSES if p != "mask"}
    with tempfile.TemporaryDirectory(prefix="valset_bl_") as tmp:
        tmp = Path(tmp)
        for f in tqdm(range(frames), desc=name, unit="frame"):
            scene.frame_current = f + 1
            per_frame.append(animate(f))
            set_passes(scene, True, position=position)
            for pass_name, spp, fname in (("noisy1", 1, "frame"), ("noisy4", 4, "frame4spp")):
                s = C.seed(clip_id, pass_name, f)
                seeds[pass_name].append(s)
                t0 = time.perf_counter()
                render_to(scene, out / f"{fname}_{f:04d}.exr", spp, s)
                timer.add(pass_name, t0)
            refs = [("reference", f"reference_{f:04d}.exr")]
            if ref_b_frame is not None and f == ref_b_frame:
                refs.append(("ref_b", f"ref_b_{f:04d}.exr"))
            for pass_name, fname in refs:
                acc = np.zeros((height, width, 3))
                chunk_seeds = []
                t0 = time.perf_counter()
                for c in range(ref_spp // ref_chunk):
                    want_mask = bool(moving) and pass_name == "reference" and c == 0
                    set_passes(scene, False, object_index=want_mask, depth="32")
                    s = C.seed(clip_id, pass_name, f, c)
                    chunk_seeds.append(s)
                    tmp_file = tmp / f"chunk_{c}.exr"
                    render_to(scene, tmp_file, ref_chunk, s)
                    acc += C.read_rgb(tmp_file, "ViewLayer.Combined.")
                    if want_mask:
                        idx = C.read_channel(tmp_file, "ViewLayer.Object Index.X")
                        C.write_exr(out / f"mask_{f:04d}.exr", {"moving": (np.round(idx) == 1).astype(np.float32)},
                                    ("moving",))
                timer.add(pass_name, t0)
                seeds[pass_name].append(chunk_seeds)
                acc /= ref_spp // ref_chunk
                C.write_exr(out / fname, {ch: acc[..., i] for i, ch in enumerate("RGB")}, (),
                            {"renderer": f"Blender {version} Cycles", "spp": ref_spp})
    manifest = {
        "scene": name,
        "renderer": f"Blender {version} (bpy), Cycles CPU",
        "frames": frames, "width": width, "height": height,
        "spp": {"noisy1": 1, "noisy4": 4, "reference": ref_spp, "ref_chunk_spp": ref_chunk},
        "cycles": {"max_bounces": MAX_BOUNCES, "diffuse/glossy/transmission/transparent_bounces": MAX_BOUNCES,
                   "use_adaptive_sampling": False, "use_denoising": False, "sample_clamp_direct": 0,
                   "sample_clamp_indirect": scene.cycles.sample_clamp_indirect,
                   "pixel_filter_type": scene.cycles.pixel_filter_type,
                   **({"filter_width": scene.cycles.filter_width} if renderer_defaults else {}),
                   "caustics": "Cycles defaults (on)",
                   "threads": THREADS},
        "layout": ("frame_/frame4spp_: Blender's multilayer EXR as written (one part per pass in Blender 5): "
                   "ViewLayer.Combined.R/G/B/A (half), ViewLayer.Depth.Z, ViewLayer.Normal.X/Y/Z (world space), "
                   "ViewLayer.Denoising Normal.X/Y/Z (camera space), ViewLayer.Denoising Albedo.R/G/B (half), "
                   "ViewLayer.Denoising Depth.Z"
                   + (", ViewLayer.Position.X/Y/Z (world space)" if position else "")
                   + "; Blender's 'Half' colour depth (normals and depths stay float32)"),
        "description": desc,
        "hazards": hazards,
        "moving_objects": moving,
        "seeds": seeds,
        "seed_rule": "clip_id*100000 + pass*10000 + frame*100 + chunk (pass: noisy1 1, noisy4 2, reference 3, ref_b 4)",
        "clip_id": clip_id,
        "ref_b": C.ref_b_entry(ref_b_frame),
        "render_seconds": timer.secs,
        "render_cpu_seconds": timer.cpu,
        "host": C.host(),
        "files": {
            "frame_XXXX.exr": "1 spp, Blender's multilayer EXR as written (see layout)",
            "frame4spp_XXXX.exr": "the same at 4 spp (independent samples)",
            "reference_XXXX.exr": f"R,G,B float32, {ref_spp} spp: float64 mean of {ref_spp // ref_chunk} chunks of "
                                  "Blender's Combined",
            **C.ref_b_files(ref_b_frame),
            **({"mask_XXXX.exr": "moving: 1 where Cycles' object index (first sample of reference chunk 0) is a "
                                 "moving object"} if moving else {}),
        },
        "per_frame_animation": per_frame,
    }
    C.write_manifest(out, manifest)
    return out


def render_iterations(name: str, out_root: Path, frames: int, count: int) -> Path:
    """The progressive loop of clip ``name``, already rendered in ``out_root``: per frame, what Cycles holds
    after n samples per pixel of the 1-spp frame's own sample sequence (its seed, the set's box filter, the
    frame's own size), written as Blender writes it, ``iter<n>_XXXX.exr`` for n in ``C.ITERATION_LEVELS``
    up to ``count``. Cycles continues one low-discrepancy sequence per pixel as its samples accumulate;
    1-spp renders with other seeds are not independent draws of the pixel (they share the pixel's
    position: averaging 16 of them left `bl_env_thin`'s wires aliased, 6 dB under Cycles' own 4 spp)."""
    builder, clip_id = CLIPS[name][:2]
    out = Path(out_root) / name
    first = out / "frame_0000.exr"
    if not first.exists():
        raise FileNotFoundError(f"{first}: render the clip first (without --iterations)")
    height, width = C.read_rgb(first, "ViewLayer.Combined.").shape[:2]
    total = C.clip_frames(out)
    scene = reset()
    setup_render(scene, width, height)
    animate = builder(scene, total)[0]
    for f in tqdm(range(min(frames, total)), desc=f"{name} iterations", unit="frame"):
        scene.frame_current = f + 1
        animate(f)
        set_passes(scene, True)
        for n in (n for n in C.ITERATION_LEVELS if n <= count):
            render_to(scene, out / f"iter{n}_{f:04d}.exr", n, C.seed(clip_id, "noisy1", f))
    return out


def main(argv=None):
    C.clip_main(__doc__.split("\n")[0], CLIPS, render_clip, argv, render_iterations)


if __name__ == "__main__":
    main()
