"""Features, object ids and motion on analytic scenes built inline, and the RNG contract."""
import math

import numpy as np
import pytest
import torch
from _render_helpers import pixel_dirs, plane_scene_dict

from torchmanifold import features as feature_table
from torchmanifold.render import PathTracer, scene_from_dict

W = H = 32


def test_plane_features_exact(ctx):
    dist, fov, albedo = 2.0, 30.0, (0.2, 0.4, 0.6)
    scene = scene_from_dict(plane_scene_dict(dist, albedo, fov))
    assert scene.needed_features() == ["Z", "Mr", "Mg", "Mb", "Nx", "Ny", "Nz", "Dx", "Dy", "Dz", "Sx", "Sy", "Sz"]
    tr = PathTracer(scene, W, H, ctx=ctx)
    res = tr.render([0.0], spp=1, seed=3)
    assert ctx.error == "GL_NO_ERROR"
    f = {n: res.feature(n)[0].numpy() for n in res.feature_names}

    # depth = distance along the ray = dist * sqrt(1 + (x tan)^2 + (y tan)^2) at image-plane point (x, y);
    # one jittered sample lies between the values nearest to and farthest from the image centre
    t = math.tan(math.radians(fov) / 2)
    e = 2 * np.arange(W + 1) / W - 1  # pixel edges in NDC (square image)
    near = np.where(e[:-1] * e[1:] <= 0, 0.0, np.minimum(abs(e[:-1]), abs(e[1:])))
    far = np.maximum(abs(e[:-1]), abs(e[1:]))
    lo = dist * np.sqrt(1 + (near[:, None] * t) ** 2 + (near[None, :] * t) ** 2)
    hi = dist * np.sqrt(1 + (far[:, None] * t) ** 2 + (far[None, :] * t) ** 2)
    assert np.all(f["Z"] >= lo - 1e-5) and np.all(f["Z"] <= hi + 1e-5)
    assert np.mean(hi - lo) < 0.01  # the bound is tight
    for name, val in zip(("Mr", "Mg", "Mb", "Nx", "Ny", "Nz"), (*albedo, 0.0, 0.0, 1.0)):
        np.testing.assert_allclose(f[name], val, atol=1e-6, err_msg=name)
    # scattered direction: a unit vector in the upper hemisphere
    d = np.stack([f["Dx"], f["Dy"], f["Dz"]])
    np.testing.assert_allclose(np.linalg.norm(d, axis=0), 1.0, atol=1e-4)
    assert np.all(d[2] > 0)
    # shadow ray: from the hit point towards the (tiny) lamp at (0.8, 0.8, 1)
    dirs = pixel_dirs(W, H, fov, (0, 0, -1), (1, 0, 0), (0, 1, 0))
    hit = dirs * (dist / -dirs[..., 2:]) + np.array([0, 0, dist])
    s_ref = np.array([0.8005, 0.8005, 1.0]) - hit
    s_ref /= np.linalg.norm(s_ref, axis=-1, keepdims=True)
    s = np.stack([f["Sx"], f["Sy"], f["Sz"]], axis=-1)
    assert np.max(np.abs(s - s_ref)) < 0.03
    assert torch.all(res.object_id == 0)
    assert torch.all(res.emission == 0)
    assert torch.allclose(res.motion, torch.zeros(()), atol=1e-3)


def test_emitter_seen_directly_is_its_emission(ctx):
    d = plane_scene_dict(light=False)
    d["materials"]["wall"] = {"type": "diffuse", "color": [0, 0, 0], "emission": [1.5, 2.5, 3.5]}
    tr = PathTracer(scene_from_dict(d), W, H, ctx=ctx)
    res = tr.render([0.0], spp=4)
    e = torch.tensor([1.5, 2.5, 3.5]).view(1, 3, 1, 1)
    torch.testing.assert_close(res.color, e.expand_as(res.color))
    torch.testing.assert_close(res.emission, e.expand_as(res.color))
    # emitters report their colour, normalised, as albedo
    torch.testing.assert_close(res.feature("Mb"), torch.ones(1, H, W))
    assert ctx.error == "GL_NO_ERROR"


def test_time_feature_and_motion(ctx):
    """A small quad moving in +x at 0.04 units/frame in front of a static wall; camera static."""
    dist, fov, speed, shutter = 2.0, 30.0, 0.04, 0.5
    d = plane_scene_dict(dist, fov=fov, light=False, shutter=shutter)
    d["objects"].append({"type": "quad", "origin": [-0.2, -0.2, 0.5], "u": [0.4, 0, 0], "v": [0, 0.4, 0],
                         "material": "wall", "motion": [{"time": 0, "offset": [0, 0, 0]},
                                                        {"time": 10, "offset": [10 * speed, 0, 0]}]})
    scene = scene_from_dict(d)
    assert scene.needed_features()[0] == "T" and scene.moving_objects() == [1]
    tr = PathTracer(scene, W, H, features=["T", "Z"], ctx=ctx)
    res = tr.render([2.0, 4.5], spp=16, seed=1)
    t = res.feature("T")
    # each sample draws its time uniformly in [t - s/2, t + s/2]: mean of 16 within a few sigma of t
    sigma = shutter / math.sqrt(12 * 16)
    for k, ft in enumerate((2.0, 4.5)):
        assert t[k].min() >= ft - shutter / 2 and t[k].max() <= ft + shutter / 2
        assert abs(t[k].mean().item() - ft) < 5 * sigma / math.sqrt(W * H) + 1e-4
    # motion: the moving quad shifts by speed * focal / depth pixels per frame, the wall does not move
    focal = (W / 2) / math.tan(math.radians(fov) / 2)
    expected = speed * focal / (dist - 0.5)
    on_quad = res.object_id == 1
    assert on_quad.sum() > 20 and (res.object_id == 0).sum() > 20
    mx, my = res.motion[:, 0], res.motion[:, 1]
    torch.testing.assert_close(mx[on_quad], torch.full_like(mx[on_quad], expected), atol=1e-3, rtol=1e-3)
    assert my[on_quad].abs().max() < 1e-3
    wall = res.object_id == 0
    assert mx[wall].abs().max() < 1e-3 and my[wall].abs().max() < 1e-3
    # the quad's pixel-centre footprint follows the keyframes: 0.1 units further at t=4.5 than at 2
    shift = (on_quad[1].float().nonzero()[:, 1].float().mean() - on_quad[0].float().nonzero()[:, 1].float().mean())
    assert abs(shift.item() - 2.5 * expected) < 0.6


def test_adding_features_keeps_colour(ctx):
    from torchmanifold.render import default_scene

    scene = default_scene()
    base = PathTracer(scene, 24, 24, features=[], ctx=ctx).render([1.0], spp=2, seed=5)
    names = feature_table.tracer_names()
    every = PathTracer(scene, 24, 24, features=names, ctx=ctx).render([1.0], spp=2, seed=5)
    assert torch.equal(every.color, base.color)
    for feats in (["Z"], ["Sz", "T", "Mr"], names[::-1]):
        # each feature set compiles its own shader (output slots are constants): same colour, same channels
        res = PathTracer(scene, 24, 24, features=feats, ctx=ctx).render([1.0], spp=2, seed=5)
        assert torch.equal(res.color, base.color), feats
        assert res.features.shape == (1, len(feats), 24, 24) and res.feature_names == feats
        assert torch.equal(res.features, every.features[:, [names.index(f) for f in feats]]), feats
    assert base.features.shape == (1, 0, 24, 24)


def test_determinism_tiles_batches_offsets(ctx):
    from torchmanifold.render import default_scene

    tr = PathTracer(default_scene(), 24, 20, ctx=ctx, spp_per_dispatch=2)
    a = tr.render([0.0, 3.0], spp=3, seed=7)
    b = tr.render([0.0, 3.0], spp=3, seed=7)
    for x, y in ((a.color, b.color), (a.features, b.features), (a.motion, b.motion), (a.object_id, b.object_id)):
        assert torch.equal(x, y)
    # another tiling / dispatch shape / chunking of samples gives the same frame
    for tile in (8, (16, 5), 7):
        c = tr.render([0.0, 3.0], spp=3, seed=7, tile=tile)
        assert torch.equal(c.color, a.color) and torch.equal(c.features, a.features), tile
    one = PathTracer(default_scene(), 24, 20, ctx=ctx, spp_per_dispatch=64).render([0.0, 3.0], spp=3, seed=7)
    torch.testing.assert_close(one.color, a.color, rtol=1e-6, atol=1e-6)
    # a frame does not depend on which other frames are in the batch
    c = tr.render([3.0], spp=3, seed=7)
    assert torch.equal(c.color[0], a.color[1])
    # another seed or sample offset: other samples; spp=2 is the mean of offsets 0 and 1
    assert not torch.equal(tr.render([0.0], spp=1, seed=8).color, tr.render([0.0], spp=1, seed=7).color)
    s0 = tr.render([0.0], spp=1, seed=7, sample_offset=0)
    s1 = tr.render([0.0], spp=1, seed=7, sample_offset=1)
    s01 = tr.render([0.0], spp=2, seed=7, sample_offset=0)
    assert not torch.equal(s0.color, s1.color)
    torch.testing.assert_close((s0.color + s1.color) / 2, s01.color, rtol=1e-6, atol=1e-6)
    assert ctx.error == "GL_NO_ERROR"


@pytest.mark.parametrize("cache_bytes", [None, 1])
def test_ids_and_motion_follow_each_calls_frame_times(ctx, monkeypatch, cache_bytes):
    """Object ids and motion come from a sample-free pass the tracer runs only for frame times it has not kept
    (``cache_bytes=1`` keeps none): whatever the order of calls, each result matches a fresh tracer's."""
    from torchmanifold.render import default_scene, tracer as tracer_module

    if cache_bytes is not None:
        monkeypatch.setattr(tracer_module, "AUX_CACHE_BYTES", cache_bytes)
    scene = default_scene()
    tr = PathTracer(scene, 20, 16, features=[], ctx=ctx)
    calls = [([0.0, 6.0], 0), ([6.0, 0.0], 1), ([6.0, 0.0], 2), ([6.0], 3), ([0.0, 6.0], 4), ([3.0, 6.0], 5)]
    for times, offset in calls:
        res = tr.render(times, spp=1, seed=2, sample_offset=offset)
        ref = PathTracer(scene, 20, 16, features=[], ctx=ctx).render(times, spp=1, seed=2, sample_offset=offset)
        assert torch.equal(res.object_id, ref.object_id) and torch.equal(res.motion, ref.motion), times
        assert torch.equal(res.color, ref.color), times
    assert not torch.equal(res.motion[0], res.motion[1])  # the two frame times do differ


def test_sample_offsets_are_independent(ctx):
    """Noise of different sample indices (and of neighbouring pixels) is uncorrelated."""
    d = plane_scene_dict(light=False, background=[1.0, 1.0, 1.0], max_depth=3, rr_depth=1)
    tr = PathTracer(scene_from_dict(d), 64, 64, features=["Dx", "Dy"], ctx=ctx)
    r0, r1 = tr.render([0.0], sample_offset=0), tr.render([0.0], sample_offset=1)
    for a, b in ((r0.feature("Dx"), r1.feature("Dx")), (r0.feature("Dx"), r0.feature("Dy")),
                 (r0.feature("Dx")[:, :, 1:], r0.feature("Dx")[:, :, :-1])):
        a, b = a.flatten().double(), b.flatten().double()
        corr = torch.corrcoef(torch.stack([a, b]))[0, 1]
        assert abs(corr) < 4 / math.sqrt(a.numel())  # 4 sigma of the null distribution


def test_bad_arguments(ctx):
    from torchmanifold.render import default_scene

    with pytest.raises(ValueError, match="features"):
        PathTracer(default_scene(), 8, 8, features=["Q"], ctx=ctx)
    with pytest.raises(TypeError, match="scene"):
        PathTracer({"objects": []}, 8, 8, ctx=ctx)
    with pytest.raises(TypeError, match="ctx"):
        PathTracer(default_scene(), 8, 8, ctx="gl")
    with pytest.raises(ValueError, match="width"):
        PathTracer(default_scene(), 0, 8, ctx=ctx)
    tr = PathTracer(default_scene(), 8, 8, ctx=ctx)
    with pytest.raises(ValueError, match="spp"):
        tr.render([0.0], spp=0)
    with pytest.raises(TypeError, match="times"):
        tr.render(1.0)
    with pytest.raises(ValueError, match="times"):
        tr.render([float("nan")])
    with pytest.raises(ValueError, match="seed"):
        tr.render([0.0], seed=-1)


def test_baked_scene_equals_storage_buffer_scene(ctx):
    """The scene pasted into the shader as constants and read from storage buffers: the same frames, up to
    float rounding in colour and the features made from normals and directions (the compiler folds the
    baked scene's constant maths, e.g. a quad's normalised normal, a few ulps away from the run-time result)."""
    from torchmanifold.render import default_scene

    scene = default_scene()
    a = PathTracer(scene, 24, 16, ctx=ctx, bake_scene=True)
    b = PathTracer(scene, 24, 16, ctx=ctx, bake_scene=False)
    assert a.baked and not b.baked
    ra, rb = a.render([0.0, 2.5], spp=2, seed=9), b.render([0.0, 2.5], spp=2, seed=9)
    for x, y in ((ra.motion, rb.motion), (ra.object_id, rb.object_id), (ra.emission, rb.emission)):
        assert torch.equal(x, y)
    torch.testing.assert_close(ra.color, rb.color, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ra.features, rb.features, rtol=1e-5, atol=1e-5)
    exact = [ra.feature_names.index(n) for n in ("T", "Z", "Mr", "Mg", "Mb")]  # no folded maths on their way
    assert torch.equal(ra.features[:, exact], rb.features[:, exact])


def test_unrolled_scene_equals_scene_loop(ctx, monkeypatch):
    """A baked scene tested object by object in straight-line code (the default for small scenes) and in a
    loop (scenes over MAX_UNROLLED_OBJECTS): the same frames up to the float rounding of folded constants."""
    from torchmanifold.render import default_scene, tracer as tracer_module

    scene = default_scene()
    a = PathTracer(scene, 24, 16, ctx=ctx)
    monkeypatch.setattr(tracer_module, "MAX_UNROLLED_OBJECTS", 0)
    b = PathTracer(scene, 24, 16, ctx=ctx)
    assert a.baked and b.baked
    ra, rb = a.render([0.0, 2.5], spp=2, seed=9), b.render([0.0, 2.5], spp=2, seed=9)
    for x, y in ((ra.motion, rb.motion), (ra.object_id, rb.object_id), (ra.emission, rb.emission)):
        assert torch.equal(x, y)
    torch.testing.assert_close(ra.color, rb.color, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ra.features, rb.features, rtol=1e-5, atol=1e-5)


def test_context_manager_releases(ctx):
    from torchmanifold.render import default_scene

    with PathTracer(default_scene(), 8, 8, ctx=ctx) as tr:
        first = tr.render([0.0], spp=1).color
    with pytest.raises(RuntimeError, match="released"):
        tr.render([0.0])
    tr.release()  # twice is harmless
    again = PathTracer(default_scene(), 8, 8, ctx=ctx).render([0.0], spp=1).color
    assert torch.equal(first, again) and ctx.error == "GL_NO_ERROR"


def test_frames_split_over_buffer_batches(ctx):
    """Frames beyond one storage block's size go to further buffers: the same frames either way."""
    from torchmanifold.render import default_scene

    scene, times = default_scene(), [0.0, 1.0, 2.5, 3.0, 7.0]
    one = PathTracer(scene, 16, 12, ctx=ctx)
    n_feat = len(scene.needed_features())
    split = PathTracer(scene, 16, 12, ctx=ctx, max_buffer_bytes=2 * 16 * 12 * n_feat * 4)  # 2 frames a batch
    assert one.frames_per_batch >= 5 and split.frames_per_batch == 2
    a, b = one.render(times, spp=2, seed=1), split.render(times, spp=2, seed=1)
    assert [(f0, n) for f0, n, _ in split.buffers] == [(0, 2), (2, 2), (4, 1)]
    for x, y in ((a.color, b.color), (a.features, b.features), (a.object_id, b.object_id), (a.motion, b.motion)):
        assert torch.equal(x, y)
    c = split.render(times[:3], spp=2, seed=1)  # fewer frames reuse the buffers
    assert torch.equal(c.color, a.color[:3]) and len(split.buffers) == 2
    with pytest.raises(ValueError, match="storage-block limit"):
        PathTracer(scene, 64, 64, ctx=ctx, max_buffer_bytes=1000)


def test_camera_motion_moves_static_points_the_other_way(ctx):
    """Camera keyframes: eye and target slide +x at 0.05/frame over a static wall 2 units away."""
    dist, fov, speed = 2.0, 30.0, 0.05
    d = plane_scene_dict(dist, fov=fov, light=False)
    del d["camera"]["eye"], d["camera"]["target"]
    d["camera"]["keyframes"] = [{"time": 0, "eye": [0, 0, dist], "target": [0, 0, 0]},
                                {"time": 10, "eye": [10 * speed, 0, dist], "target": [10 * speed, 0, 0]}]
    tr = PathTracer(scene_from_dict(d), W, H, features=["Z", "T"], ctx=ctx)
    res = tr.render([1.0, 9.5], spp=1)
    focal = (W / 2) / math.tan(math.radians(fov) / 2)
    torch.testing.assert_close(res.motion[0, 0], torch.full((H, W), -speed * focal / dist), atol=1e-3, rtol=1e-4)
    # at 9.5 the next frame (10.5) is past the last key: the camera holds still
    torch.testing.assert_close(res.motion[1, 0], torch.full((H, W), -0.5 * speed * focal / dist), atol=1e-3, rtol=1e-4)
    assert res.motion[:, 1].abs().max() < 1e-3


def _panel_lit_floor(panel: str):
    """The plane lit only through a panel above it: a lamp between them faces the panel, away from the plane
    (quads emit from their front face), so no light reaches the plane directly."""
    d = plane_scene_dict(light=False, max_depth=4)
    d["materials"]["lamp"] = {"type": "diffuse", "color": [0, 0, 0], "emission": [20.0, 20.0, 20.0]}
    d["materials"]["panel"] = {"type": panel, "color": [0.9, 0.9, 0.9]}
    d["objects"] += [
        {"type": "quad", "origin": [0.7, 0.7, 1.0], "u": [0.4, 0, 0], "v": [0, 0.4, 0], "material": "lamp"},
        {"type": "quad", "origin": [0.2, 0.2, 1.5], "u": [0, 1.6, 0], "v": [1.6, 0, 0], "material": "panel"}]
    return scene_from_dict(d)


@pytest.mark.parametrize("panel", ["mirror", "diffuse"])
def test_caustic_share_is_the_light_through_a_mirror(ctx, panel):
    """Under a mirror panel every sample that sees light got it through the mirror: its caustic share is
    exactly 1, and 0 where it saw none; under a diffuse panel the plane is lit as brightly, by bounce light,
    and no sample's share is above 0. A scene with no specular surface does not make the feature."""
    scene = _panel_lit_floor(panel)
    assert ("C" in scene.needed_features()) == (panel != "diffuse")
    tr = PathTracer(scene, W, H, ctx=ctx, features=["Z", "C"])  # the camera sees only the plane
    lit = 0
    for offset in range(8):
        res = tr.render([0.0], spp=1, seed=1, sample_offset=offset)
        seen = (res.color.sum(1)[0] > 0).float()
        lit += int(seen.sum())
        expected = seen if panel != "diffuse" else torch.zeros_like(seen)
        assert torch.equal(res.feature("C")[0], expected)
    assert lit >= 20
