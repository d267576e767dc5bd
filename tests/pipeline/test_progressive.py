"""The progressive loop on the built-in scene with the real tracer (llvmpipe) and the real filter."""
import pytest
import torch

from torchmanifold import metrics as M
from torchmanifold.pipeline import DenoiseSettings
from torchmanifold.pipeline.job import moving_mask
from torchmanifold.pipeline.progressive import ProgressiveRenderer

W = H = 64
TIMES = [0.0, 1.0]
ITER = 10


@pytest.fixture(scope="module")
def tracer():
    from torchmanifold.render import PathTracer, default_scene

    return PathTracer(default_scene(), W, H)


@pytest.fixture(scope="module")
def reference(tracer):
    # 128 spp: its own noise is ~1/128 of a 1-spp frame's, far below the errors compared here
    return tracer.render(times=TIMES, spp=128, seed=999)


@pytest.fixture(scope="module")
def run(tracer, reference):
    pr = ProgressiveRenderer(tracer, TIMES, settings=DenoiseSettings(temporal_radius=1, mode="window"), seed=0)
    states = [pr.step() for _ in range(ITER)]
    return pr, states


def test_consistency_and_bars(run, reference):
    pr, states = run
    ref = reference.color
    ours = [M.psnr(s.ours, ref) for s in states]
    raw = [M.psnr(s.raw, ref) for s in states]
    gauss = [M.psnr(s.gaussian, ref) for s in states]
    # error keeps falling and stays below the raw progressive average
    for i in range(1, ITER):
        assert ours[i] > ours[i - 1] - 0.05, ours
    assert ours[-1] > ours[0] + 1.0
    assert all(o > r for o, r in zip(ours, raw)), (ours, raw)
    # the bars at test size
    assert ours[0] >= raw[0] + 6.0, (ours[0], raw[0])
    assert ours[-1] > gauss[-1], (ours[-1], gauss[-1])
    if M.flip_available():
        assert M.flip(states[-1].ours, ref) < M.flip(states[-1].gaussian, ref)
    # the raw average really is plain progressive path tracing: it matches spp=ITER rendering
    plain = pr.tracer.render(times=TIMES, spp=ITER, seed=0, sample_offset=0).color
    torch.testing.assert_close(states[-1].raw, plain, atol=2e-3, rtol=2e-3)
    assert states[-1].sigma_s < states[0].sigma_s  # the bandwidth shrinks


def test_memory_bounded_by_window():
    """Each frame is rendered once per iteration and at most 2r+1 frames are held, for any clip length."""
    from torchmanifold.render import PathTracer, default_scene

    class Counting:
        def __init__(self, tr):
            self.tr, self.calls = tr, []

        def render(self, times, spp, seed, sample_offset):
            self.calls.append((tuple(times), sample_offset))
            return self.tr.render(times=times, spp=spp, seed=seed, sample_offset=sample_offset)

    ct = Counting(PathTracer(default_scene(), 16, 12))
    pr = ProgressiveRenderer(ct, [0, 1, 2, 3, 4], settings=DenoiseSettings(temporal_radius=1, sigma_s=2.0))
    pr.step()
    pr.step()
    assert sorted(ct.calls) == sorted([((float(t),), i) for t in range(5) for i in (0, 1)])
    assert pr.memory_frames == 3
    assert pr.history[-1].ours.shape == (5, 3, 12, 16)


def test_inbetween_frames_and_errors():
    from torchmanifold.render import PathTracer, default_scene

    tr = PathTracer(default_scene(), 16, 12)
    pr = ProgressiveRenderer(tr, [0, 1], query_times=[0, 0.5, 1], settings=DenoiseSettings(sigma_s=2.0))
    s = pr.step()
    assert s.ours.shape == (3, 3, 12, 16) and torch.isfinite(s.ours).all()
    with pytest.raises(ValueError, match="times"):
        ProgressiveRenderer(tr, [1, 0])
    with pytest.raises(TypeError, match="tracer"):
        ProgressiveRenderer(object(), [0, 1])
    with pytest.raises(ValueError, match="iterations"):
        pr.run(0)


def test_spacetime_reduces_ghosting(tracer):
    """Around the moving sphere a plain time window mixes frames (ghosts); space-time keeps them apart.

    Frames of 16 spp, so the ghost, not the noise, dominates the error inside the mask.
    """
    from torchmanifold.pipeline import denoise_frames
    from torchmanifold.render import default_scene

    scene = default_scene()
    moving = [k for k, o in enumerate(scene.objects) if len(o.motion) > 1]
    assert moving, "the built-in scene has a moving object"
    times = [3.0, 4.0, 5.0]
    r = tracer.render(times=times, spp=16, seed=3)
    ref = tracer.render(times=[4.0], spp=256, seed=7).color
    # where the object is in any frame of the window: its ghosts land there
    mask = moving_mask(r.object_id, moving, dilate=1).amax(0, keepdim=True)
    assert mask.sum() > 20
    res = {}
    for mode in ("window", "spacetime"):
        out = denoise_frames(r.color, r.features, r.feature_names, r.emission,
                             DenoiseSettings(temporal_radius=1, mode=mode), frame_times=times, query_times=[4.0])
        res[mode] = (M.psnr(out, ref, mask=mask), M.psnr(out, ref))
    assert res["spacetime"][0] > res["window"][0] + 1.0, res  # less ghosting on the moving object
    assert res["spacetime"][1] > res["window"][1] - 0.2, res  # and no worse elsewhere
