"""First-hit depth, normals and object ids agree with an independent rasteriser (pyrender, EGL)."""
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import trimesh

from torchmanifold.render import PathTracer, Quad, Sphere, load_scene


W, H, FOV = 48, 32, 50.0
SS = 8  # pyrender renders SS x SS sub-pixels per pixel: our jittered pixel means are box-filter means
EYE, TARGET = np.array([0.4, 1.2, 2.4]), np.array([0.0, 0.6, 0.0])

SCENE = """
[render]
max_depth = 2
[camera]
eye = [0.4, 1.2, 2.4]
target = [0.0, 0.6, 0.0]
fov = 50
[materials]
white = {{ color = [0.7, 0.7, 0.7] }}
lamp = {{ color = [0, 0, 0], emission = [5, 5, 5] }}
[[objects]]
type = "quad"
origin = [-1, 0, -1]
u = [0, 0, 2]
v = [2, 0, 0]
material = "white"
[[objects]]
type = "quad"
origin = [-1, 0, -1]
u = [2, 0, 0]
v = [0, 2, 0]
material = "white"
[[objects]]
type = "quad"
origin = [-1, 0, -1]
u = [0, 2, 0]
v = [0, 0, 2]
material = "white"
[[objects]]
type = "quad"
origin = [-0.3, 1.99, -0.3]
u = [0.6, 0, 0]
v = [0, 0, 0.6]
material = "lamp"
[[objects]]
type = "sphere"
center = [0.45, 0.4, -0.3]
radius = 0.4
material = "white"
[[objects]]
type = "mesh"
file = "{mesh}"
scale = 1.0
translate = [-0.4, 0.35, 0.3]
material = "white"
"""


def _look_at_pose(eye, target, up=(0.0, 1.0, 0.0)):
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, cam_up, -fwd, eye
    return pose


def _tri_mesh(obj):
    if isinstance(obj, Quad):
        o, u, v = (np.asarray(a) for a in (obj.origin, obj.u, obj.v))
        return trimesh.Trimesh([o, o + u, o + u + v, o + v], [[0, 1, 2], [0, 2, 3]], process=False)
    if isinstance(obj, Sphere):
        m = trimesh.creation.icosphere(subdivisions=5, radius=obj.radius)
        return m.apply_translation(obj.center)
    return trimesh.Trimesh(obj.vertices, obj.faces, process=False)


def _rasterise(scene, tmp_path):
    """pyrender depth (camera z), face normals (flat colours) and object index per pixel (subprocess)."""
    arrays = {"pose": _look_at_pose(EYE, TARGET), "yfov": math.radians(FOV), "size": np.array([W * SS, H * SS])}
    for i, obj in enumerate(scene.objects):
        m = _tri_mesh(obj)
        arrays[f"verts_{i}"], arrays[f"faces_{i}"] = np.asarray(m.vertices), np.asarray(m.faces)
    np.savez(tmp_path / "in.npz", **arrays)
    worker = Path(__file__).with_name("_pyrender_worker.py")
    subprocess.run([sys.executable, str(worker), str(tmp_path / "in.npz"), str(tmp_path / "out.npz")],
                   check=True, timeout=300)
    out = np.load(tmp_path / "out.npz")
    return out["depth"], out["normals"], out["ids"]


def _interior(ids):
    """Pixels whose 3x3 neighbourhood shows one object (edges mix objects in one of the two renderers)."""
    p = np.pad(ids, 1, mode="constant", constant_values=-2)
    same = np.ones_like(ids, dtype=bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            same &= p[1 + dy:1 + dy + H, 1 + dx:1 + dx + W] == ids
    return same


def _pixels(x):
    """(H*SS, W*SS, ...) sub-pixels -> (H, W, SS*SS, ...)."""
    return x.reshape(H, SS, W, SS, *x.shape[2:]).swapaxes(1, 2).reshape(H, W, SS * SS, *x.shape[2:])


def test_depth_normals_ids_match_pyrender(ctx, tmp_path):
    mesh = trimesh.creation.box((0.8, 0.6, 0.5))
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.6, [0.2, 1, 0.1]))
    mesh.export(tmp_path / "box.obj")
    (tmp_path / "scene.toml").write_text(SCENE.format(mesh="box.obj"))
    scene = load_scene(tmp_path / "scene.toml")
    zbuf, n_sub, ids_sub = _rasterise(scene, tmp_path)

    # reference per pixel: sub-pixel ids must agree; depth -> distance along each sub-pixel's ray
    t = math.tan(math.radians(FOV) / 2)
    nx = 2 * (np.arange(W * SS) + 0.5) / (W * SS) - 1
    ny = 1 - 2 * (np.arange(H * SS) + 0.5) / (H * SS)
    stretch = np.sqrt(1 + (nx[None, :] * t * W / H) ** 2 + (ny[:, None] * t) ** 2)  # 1 / cos(ray, axis)
    sub_ids = _pixels(ids_sub)
    ids_ref = sub_ids[:, :, 0]
    pure = np.all(sub_ids == ids_ref[..., None], axis=-1)
    dist_sub = _pixels(zbuf * stretch)
    dist_ref = dist_sub.mean(-1)
    spp = 64
    dist_se = dist_sub.std(-1) / math.sqrt(spp)  # standard error of a mean of spp jittered samples
    n_ref = _pixels(n_sub).mean(-2)
    n_ref /= np.linalg.norm(n_ref, axis=-1, keepdims=True) + 1e-12
    # pixels on a crease (two box faces) get a coverage-weighted mean normal: compare smooth pixels only
    smooth = np.min(np.sum(_pixels(n_sub) * n_ref[:, :, None], axis=-1), axis=-1) > 0.99

    res = PathTracer(scene, W, H, features=["Z", "Nx", "Ny", "Nz"], ctx=ctx).render([0.0], spp=spp, seed=0)
    assert ctx.error == "GL_NO_ERROR"
    ids = res.object_id[0].numpy()
    inner = _interior(np.where(pure, ids_ref, -3)) & _interior(ids)
    assert inner.sum() > 0.5 * W * H
    for k in range(len(scene.objects)):
        if k != 3:  # every object but the small lamp is well visible
            assert (inner & (ids_ref == k)).sum() > 10, k
    assert np.all(ids[inner] == ids_ref[inner])

    z = res.feature("Z")[0].numpy()
    hit = inner & (ids_ref >= 0)
    err = np.abs(z[hit] - dist_ref[hit])
    assert np.median(err / dist_ref[hit]) < 1e-3
    # llvmpipe's rasterised depth is itself only good to ~1e-3 relative on tilted planes (exact head-on)
    bad = err > 5 * dist_se[hit] + 2e-3 * dist_ref[hit]
    assert not bad.any(), np.c_[ids_ref[hit][bad], err[bad], dist_se[hit][bad], dist_ref[hit][bad]].tolist()
    assert np.all(z[inner & (ids < 0)] == 0)

    n = np.stack([res.feature(c)[0].numpy() for c in ("Nx", "Ny", "Nz")], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    sel = hit & smooth
    assert sel.sum() > 0.9 * hit.sum()
    cosang = np.sum(n * n_ref, axis=-1)[sel]
    assert np.min(cosang) > 0.998 and np.mean(cosang) > 0.9999
