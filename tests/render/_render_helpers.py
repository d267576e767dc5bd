"""Inline scenes and camera maths shared by the path-tracer tests (independent of the tracer code)."""
import math

import numpy as np


def plane_scene_dict(dist=2.0, albedo=(0.2, 0.4, 0.6), fov=30.0, light=True, **render):
    """A camera at (0, 0, dist) looking down -z at a big diffuse quad in the plane z = 0 (facing +z)."""
    d = {
        "render": {"max_depth": 4, **render},
        "camera": {"eye": [0.0, 0.0, dist], "target": [0.0, 0.0, 0.0], "fov": fov},
        "materials": {
            "wall": {"type": "diffuse", "color": list(albedo)},
            "lamp": {"type": "diffuse", "color": [0, 0, 0], "emission": [50.0, 50.0, 50.0]},
        },
        "objects": [{"type": "quad", "origin": [-10, -10, 0], "u": [20, 0, 0], "v": [0, 20, 0], "material": "wall"}],
    }
    if light:  # a tiny lamp facing the plane, between camera and plane but off to the side
        d["objects"].append({"type": "quad", "origin": [0.8, 0.8, 1.0], "u": [0, 0.001, 0], "v": [0.001, 0, 0],
                             "material": "lamp"})
    return d


def pixel_dirs(w, h, fov, fwd, right, up, sub=1):
    """Unit camera-ray directions (H*sub, W*sub, 3) at sub-pixel centres (y down), the tracer's camera model."""
    t = math.tan(math.radians(fov) / 2)
    xs = (np.arange(w * sub) + 0.5) / sub
    ys = (np.arange(h * sub) + 0.5) / sub
    nx = 2 * xs / w - 1
    ny = 1 - 2 * ys / h
    v = (np.asarray(fwd)[None, None] + nx[None, :, None] * t * (w / h) * np.asarray(right)[None, None]
         + ny[:, None, None] * t * np.asarray(up)[None, None])
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
