"""Scene files: the built-in scene, meshes through the BVH, EXR frames, and errors that name file + field."""
import re

import numpy as np
import pytest
import torch
import trimesh

from torchmanifold import features as feature_table
from torchmanifold.io.exr import read_exr
from torchmanifold.render import (
    PathTracer,
    default_scene,
    load_scene,
    read_frame_exr,
    write_frame_exr,
)
from torchmanifold.render.bvh import build_bvh

GOOD = """
[render]
shutter = 0.5
[camera]
eye = [0, 1, 3]
target = [0, 1, 0]
[materials]
white = { color = [0.7, 0.7, 0.7] }
[[objects]]
type = "sphere"
center = [0, 1, 0]
radius = 0.5
material = "white"
"""


def test_default_scene_features_and_exr(ctx, tmp_path):
    scene = default_scene()
    assert scene.is_dynamic and scene.has_lights and scene.shutter > 0
    assert scene.needed_features() == feature_table.tracer_names()
    assert any(scene.materials[o.material].type == "glass" for o in scene.objects)
    res = PathTracer(scene, 24, 16, ctx=ctx).render([0.0, 0.5], spp=2, seed=4)
    assert res.color.shape == (2, 3, 16, 24) and res.features.shape == (2, 15, 16, 24)
    assert res.object_id.dtype == torch.int32 and res.motion.shape == (2, 2, 16, 24)
    assert torch.isfinite(res.color).all() and (res.color >= 0).all()
    path = write_frame_exr(tmp_path / "f.exr", res, 1)
    chans = read_exr(path)
    assert {"R", "G", "B", "Z", "albedo.R", "N.X", "D.Z", "S.Y", "T", "caustic", "motion.X",
            "objectId"} <= set(chans)
    np.testing.assert_array_equal(chans["R"], res.color[1, 0].numpy())
    np.testing.assert_array_equal(chans["objectId"], res.object_id[1].numpy())
    color, feats, names = read_frame_exr(path)
    assert names == res.feature_names and torch.equal(color, res.color[1])
    # half-float channels (albedo, normal, directions) round to 1e-3; T and Z stay float32
    torch.testing.assert_close(feats, res.features[1], atol=1e-3, rtol=1e-3)
    assert torch.equal(feats[names.index("T")], res.feature("T")[1])


def test_static_scene_without_lights_drops_t_and_s(tmp_path):
    (tmp_path / "s.toml").write_text(GOOD)
    scene = load_scene(tmp_path / "s.toml")
    assert not scene.is_dynamic and not scene.has_lights
    assert scene.needed_features() == ["Z", "Mr", "Mg", "Mb", "Nx", "Ny", "Nz", "Dx", "Dy", "Dz"]


def test_mesh_matches_the_same_box_made_of_quads(ctx, tmp_path):
    """A cube as a triangle mesh (BVH in the shader) and as six quads: same first hits."""
    box = trimesh.creation.box((0.6, 0.6, 0.6))
    box.apply_translation([0.1, 1.0, 0.0])
    box.export(tmp_path / "cube.obj")
    quads = "".join(
        f'[[objects]]\ntype = "quad"\norigin = {o}\nu = {u}\nv = {v}\nmaterial = "white"\n'
        for o, u, v in [
            ([-0.2, 0.7, 0.3], [0.6, 0, 0], [0, 0.6, 0]), ([0.4, 0.7, -0.3], [0, 0.6, 0], [0, 0, 0.6]),
            ([-0.2, 1.3, -0.3], [0, 0, 0.6], [0.6, 0, 0]), ([-0.2, 0.7, -0.3], [0, 0.6, 0], [0, 0, 0.6]),
            ([-0.2, 0.7, -0.3], [0.6, 0, 0], [0, 0, 0.6]), ([-0.2, 0.7, -0.3], [0, 0.6, 0], [0.6, 0, 0]),
        ]
    )
    head = GOOD.split("[[objects]]")[0].replace("eye = [0, 1, 3]", "eye = [1.2, 1.8, 2.5]")
    (tmp_path / "mesh.toml").write_text(head + '[[objects]]\ntype = "mesh"\nfile = "cube.obj"\nmaterial = "white"\n')
    (tmp_path / "quads.toml").write_text(head + quads)
    feats = ["Z", "Nx", "Ny", "Nz"]
    a = PathTracer(load_scene(tmp_path / "mesh.toml"), 32, 32, features=feats, ctx=ctx).render([0.0], spp=2)
    b = PathTracer(load_scene(tmp_path / "quads.toml"), 32, 32, features=feats, ctx=ctx).render([0.0], spp=2)
    hit_a, hit_b = a.object_id >= 0, b.object_id >= 0
    assert hit_a.sum() > 100 and torch.equal(hit_a, hit_b)
    # same first hit where both renders sample the cube for both samples
    both = (a.feature("Z") > 0) & (b.feature("Z") > 0)
    torch.testing.assert_close(a.feature("Z")[both], b.feature("Z")[both], atol=1e-4, rtol=1e-4)
    same_n = (a.features[:, 1:] - b.features[:, 1:]).abs().amax(1) < 1e-4
    assert same_n[both].float().mean() > 0.97  # the rest are pixels on cube edges (jitter hits two faces)
    assert ctx.error == "GL_NO_ERROR"


def test_bvh_structure():
    rng = np.random.default_rng(0)
    tris = rng.normal(size=(101, 3, 3))
    nodes, order = build_bvh(tris, leaf_size=4)
    assert sorted(order.tolist()) == list(range(101))
    leaves = nodes[nodes[:, 7] > 0]
    assert leaves[:, 7].sum() == 101 and leaves[:, 7].max() <= 4
    # every leaf's box contains its triangles, every node's box contains its children
    for row in nodes:
        if row[7] > 0:
            t = tris[order[int(row[3]):int(row[3] + row[7])]]
            assert np.all(t.min(axis=(0, 1)) >= row[:3]) and np.all(t.max(axis=(0, 1)) <= row[4:7])
    centroids = tris.mean(axis=1)

    def subtree_centroids(i):  # centroids of the triangles under node i
        stack, out = [i], []
        while stack:
            j = stack.pop()
            if nodes[j, 7] > 0:
                out.append(centroids[order[int(nodes[j, 3]):int(nodes[j, 3] + nodes[j, 7])]])
            else:
                stack += [j + 1, int(nodes[j, 3])]
        return np.concatenate(out)

    for i, row in enumerate(nodes):
        if row[7] <= 0:
            for c in (i + 1, int(row[3])):
                assert np.all(nodes[c, :3] >= row[:3]) and np.all(nodes[c, 4:7] <= row[4:7])
            axis = int(-1 - row[7])  # the split axis: the left child's centroids are the lower ones
            assert subtree_centroids(i + 1)[:, axis].max() <= subtree_centroids(int(row[3]))[:, axis].min()


@pytest.mark.parametrize(
    "edit, field, expected",
    [
        (('radius = 0.5', 'radius = -1'), "objects[0].radius", "a number >= 1e-09"),
        (('radius = 0.5', 'radius = "big"'), "objects[0].radius", "a finite number"),
        (('center = [0, 1, 0]', 'center = [0, 1]'), "objects[0].center", "a list of 3 finite numbers"),
        (('type = "sphere"', 'type = "cone"'), "objects[0].type", "one of ['mesh', 'quad', 'sphere']"),
        (('material = "white"', 'material = "gold"'), "objects[0].material", "one of the materials ['white']"),
        (('white = {', 'white = { type = "metal",'), "materials.white.type", "one of ['diffuse', 'glass', 'mirror']"),
        (('shutter = 0.5', 'shutter = -0.5'), "render.shutter", "a number >= 0"),
        (('shutter = 0.5', 'shuter = 0.5'), "render.shuter", "one of the fields"),
        (('eye = [0, 1, 3]', 'eye = [0, 1, 0]'), "camera", "target != eye"),
        (('target = [0, 1, 0]', ''), "camera.target", "a list of 3 numbers"),
        (('radius = 0.5', 'radius = 0.5\nmotion = [{ time = 1, offset = [0, 0, 0] }, { time = 0, offset = [1, 0, 0] }]'),
         "objects[0].motion", "strictly increasing time"),
        (('type = "sphere"\ncenter = [0, 1, 0]\nradius = 0.5', 'type = "mesh"\nfile = "nope.obj"'),
         "objects[0].file", "an existing mesh file"),
        (('[camera]', '[camera\n'), "", "valid TOML"),
    ],
)
def test_bad_scene_files_name_file_field_and_expectation(tmp_path, edit, field, expected):
    path = tmp_path / "bad.toml"
    assert edit[0] in GOOD
    path.write_text(GOOD.replace(edit[0], edit[1], 1))
    with pytest.raises(ValueError) as info:
        load_scene(path)
    msg = str(info.value)
    assert msg.startswith(str(path)), msg
    assert field in msg and "expected" in msg and expected in msg, msg


def test_missing_scene_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "none.toml"))):
        load_scene(tmp_path / "none.toml")


def test_every_bundled_scene_renders(ctx):
    from torchmanifold.render.scene import SCENES_DIR

    files = sorted(SCENES_DIR.glob("*.toml"))
    assert len(files) >= 2
    for f in files:
        scene = load_scene(f)
        res = PathTracer(scene, 16, 12, ctx=ctx).render([0.0, 5.5], spp=1, seed=1)
        assert torch.isfinite(res.color).all() and torch.isfinite(res.features).all(), f.name
        assert res.color.mean() > 0 and (res.object_id >= 0).float().mean() > 0.5, f.name
        assert ctx.error == "GL_NO_ERROR", f.name


def test_a_collected_tracer_frees_its_objects_in_its_own_context():
    """A tracer garbage-collected while another context is current (a window's) must not delete that
    context's objects: GL names are per context, and a delete goes to whichever one is current."""
    import gc

    import moderngl

    from torchmanifold.render.context import make_current

    tracer = PathTracer(default_scene(), 16, 12)
    tracer.render(times=[0.0], spp=1, seed=0)
    own = tracer.ctx
    other = moderngl.create_context(standalone=True, backend="egl")  # stands in for a window
    try:
        other.__enter__()
        data = np.arange(4096, dtype="f4")
        bufs = [other.buffer(data.tobytes()) for _ in range(64)]  # names that collide with the tracer's
        del tracer
        gc.collect()
        assert all(np.array_equal(np.frombuffer(b.read(), "f4"), data) for b in bufs)
        assert other.error == "GL_NO_ERROR"
        make_current(own)  # the tracer's objects go now, with their context current
        assert len(own.objects) == 0 and own.error == "GL_NO_ERROR"
    finally:
        other.release()
