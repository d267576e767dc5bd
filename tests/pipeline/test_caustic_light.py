"""Caustic light (our tracer's ``caustic`` share) takes the narrowest bandwidth where it is sparse and
narrow: the rule on share maps, the blend it moves, the bytes it leaves alone, and the progressive loop on
the built-in scene, with the real tracer."""
import pytest
import torch

from torchmanifold.pipeline import DenoiseSettings, denoise_frames
from torchmanifold.pipeline import denoise as D
from torchmanifold.pipeline import selection as SEL

NAMES = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z", "caustic"]


def _floor(T: int, H: int, W: int, share: torch.Tensor, seed: int = 0):
    """A diffuse floor at 10 spp under light 1 whose samples carry ``share`` ``(T, 1, H, W)`` of caustic
    light: each pixel's mean light is 1 + 10 times its share (a caustic sample brings 10 more)."""
    g = torch.Generator().manual_seed(seed)
    light = 1.0 + 10.0 * share + 0.3 * torch.randn(T, 1, H, W, generator=g)
    f = torch.zeros(T, len(NAMES), H, W)
    f[:, :3], f[:, 5], f[:, 6], f[:, 7:] = 0.5, 1.0, 3.0, share
    return (0.5 * light).expand(T, 3, H, W).contiguous(), f


def _weight(share: torch.Tensor) -> torch.Tensor:
    f = torch.cat([torch.ones_like(share), share], 1)
    return SEL._caustic_light(f, ["Z", "caustic"], torch.ones_like(share))


def test_the_weight_marks_a_sparse_narrow_caustic_not_speckle_nor_a_wide_caustic():
    """A sliver 3 px wide lit by one sample in eight takes the narrow bandwidth; one caustic sample of ten
    alone does not, nor the inside of a caustic wider than the pool (all light through a window), though its
    edge, where the light changes, does. Without the feature there is no weight."""
    share = torch.zeros(1, 1, 48, 64)
    share[..., 30:33, 40:50] = 0.125
    share[..., 10, 50] = 0.1
    share[..., :, :16] = 0.5
    w = _weight(share)[0, 0]
    assert float(w.min()) >= 0.0 and float(w.max()) <= 1.0
    assert float(w[30:33, 40:50].mean()) > 0.5
    assert float(w[4:17, 44:57].max()) == 0.0
    assert float(w[:, :10].max()) == 0.0 and float(w[:, 14:20].max()) > 0.3
    assert float(_weight(torch.zeros(1, 1, 16, 16)).max()) == 0.0
    assert SEL._caustic_light(torch.ones(1, 1, 8, 8), ["Z"], torch.ones(1, 1, 8, 8)) is None


def test_the_weight_moves_the_blend_to_the_narrowest_candidate():
    """Weight 1: the narrowest bandwidth's candidate itself; 0: the blend's bytes; between: their mix."""
    st = DenoiseSettings()
    share = torch.zeros(1, 1, 40, 40)
    color, f = _floor(1, 40, 40, share)
    e, m = color / 0.5, torch.ones(1, 1, 40, 40)
    guide, sig, _ = D._guide(f, NAMES, e, m, st)
    args = (e, m, guide, sig, st, [0.0], [0.0], st.sigma_s, 1.0, None)
    narrowest = SEL._bandwidth_candidates(*args).fulls[min(range(len(st.bandwidths)),
                                                            key=lambda k: st.bandwidths[k])]
    blend = SEL._select_bandwidth(*args)
    assert torch.equal(SEL._select_bandwidth(*args, caustic=torch.ones_like(m)), narrowest)
    assert torch.equal(SEL._select_bandwidth(*args, caustic=torch.zeros_like(m)), blend)
    half = SEL._select_bandwidth(*args, caustic=torch.full_like(m, 0.5))
    torch.testing.assert_close(half, 0.5 * (blend + narrowest))
    assert not torch.equal(blend, narrowest)


def test_a_caustic_changes_the_output_around_it_alone():
    """Through the whole denoiser (3 frames joined in time): a caustic channel of zeros gives the bytes of
    none; a sliver of caustic light changes the output near it alone and keeps more of its light."""
    T, H, W = 3, 48, 48
    share = torch.zeros(T, 1, H, W)
    share[..., 22:25, 16:30] = 0.125
    color, f = _floor(T, H, W, share)
    # a soft blend, which takes the wide candidates in too, as the loop's did at a sparse caustic
    st = DenoiseSettings(temporal_radius=1, mode="spacetime", selection_softness=3.0)
    none = denoise_frames(color, f[:, :7], NAMES[:7], settings=st, samples_per_pixel=10)
    zeros = f.clone()
    zeros[:, 7] = 0.0
    assert torch.equal(denoise_frames(color, zeros, NAMES, settings=st, samples_per_pixel=10), none)
    out = denoise_frames(color, f, NAMES, settings=st, samples_per_pixel=10)
    far = torch.ones(H, W, dtype=torch.bool)
    far[10:37, 4:42] = False
    # far from it only by what the frame's means carry (float rounding)
    torch.testing.assert_close(out[..., far], none[..., far], rtol=1e-5, atol=1e-6)
    assert float((out - none).abs().max()) > 1e-2
    truth = 0.5 * (1.0 + 10.0 * share)
    sliver = (..., slice(22, 25), slice(16, 30))
    assert float(out[sliver].sum()) / float(truth.expand_as(out)[sliver].sum()) > \
        float(none[sliver].sum()) / float(truth.expand_as(out)[sliver].sum())


@pytest.fixture(scope="module")
def tracers():
    from torchmanifold.render import PathTracer, default_scene

    with_share = PathTracer(default_scene(), 64, 64)
    assert "C" in with_share.feature_names
    return with_share, PathTracer(default_scene(), 64, 64, features=[n for n in with_share.feature_names
                                                                     if n != "C"])


def test_the_loop_keeps_more_of_the_caustic_under_the_glass_ball(tracers):
    """The built-in scene at 64x64, 2 frames, 10 iterations, three loop seeds: the light kept where the
    caustic under the glass ball lands (a 256-spp render's share above 0.1, measured against another 256-spp
    render) grows with the tracer's caustic share, in every seed."""
    from torchmanifold.pipeline.progressive import ProgressiveRenderer

    with_share, without = tracers
    times = [0.0, 1.0]
    share = with_share.render(times=times, spp=256, seed=998).feature("C")
    region = (share > 0.1)[:, None].expand(-1, 3, -1, -1)
    ref = with_share.render(times=times, spp=256, seed=999).color
    assert int(region.sum()) >= 3 * 8

    def kept(tracer, seed):
        ours = ProgressiveRenderer(tracer, times, seed=seed).run(10).ours
        return float(ours[region].sum() / ref[region].sum())
    gains = [kept(with_share, s) - kept(without, s) for s in range(3)]
    assert min(gains) > 0.0 and sum(gains) / 3 > 0.05
