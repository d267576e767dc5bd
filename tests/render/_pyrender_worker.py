"""Rasterise triangle meshes with pyrender in a separate process.

pyrender's EGL platform calls ``eglTerminate`` on the process-wide display when a renderer is
deleted, which would destroy the tracer's moderngl context too; a subprocess keeps them apart.

Usage: ``python _pyrender_worker.py in.npz out.npz`` with ``in.npz`` holding ``verts_<i>``,
``faces_<i>`` per object, ``pose (4, 4)``, ``yfov``, ``size (W, H)``. Writes ``depth (H, W)`` camera z
(0 = background), ``normals (H, W, 3)`` flat face normals (8-bit), ``ids (H, W)`` object index or -1.
"""
import os
import sys

os.environ["PYOPENGL_PLATFORM"] = "egl"  # before pyrender / OpenGL are imported

import numpy as np  # noqa: E402
import pyrender  # noqa: E402
import trimesh  # noqa: E402


def main(src: str, dst: str) -> None:
    data = np.load(src)
    w, h = (int(x) for x in data["size"])
    scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[1, 1, 1])
    seg = {}
    i = 0
    while f"verts_{i}" in data:
        m = trimesh.Trimesh(data[f"verts_{i}"], data[f"faces_{i}"], process=False)
        n = m.face_normals
        m.visual.face_colors = np.c_[np.round((n + 1) / 2 * 255).astype(np.uint8), np.full(len(n), 255, np.uint8)]
        node = scene.add(pyrender.Mesh.from_trimesh(m, smooth=False))
        seg[node] = (i + 1, 0, 0)
        i += 1
    cam = pyrender.PerspectiveCamera(yfov=float(data["yfov"]), aspectRatio=w / h, znear=0.5, zfar=10.0)
    scene.add(cam, pose=data["pose"])
    r = pyrender.OffscreenRenderer(w, h)
    try:
        cull = pyrender.RenderFlags.SKIP_CULL_FACES
        col, depth = r.render(scene, flags=pyrender.RenderFlags.FLAT | cull)
        ids, _ = r.render(scene, flags=pyrender.RenderFlags.SEG | cull, seg_node_map=seg)
    finally:
        r.delete()
    np.savez(dst, depth=depth, normals=col.astype(np.float64) / 255 * 2 - 1, ids=ids[..., 0].astype(np.int64) - 1)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
