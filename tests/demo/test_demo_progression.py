"""The demo's progressive loop on the real tracer and filter: schedule, determinism, in-between times."""
from __future__ import annotations

import math

import pytest
import torch

from demo.progression import FEATURE_SETS, FilterParams, Progression


@pytest.fixture(scope="module")
def tracer():
    from torchmanifold.render import PathTracer, create_context, default_scene

    return PathTracer(default_scene(), width=32, height=32, ctx=create_context())


def test_bandwidth_follows_the_recurrence():
    p = FilterParams(sigma_s=12.0, sigma_r=0.4, a=0.6)
    s2, r2 = p.sigma_s**2, p.sigma_r**2
    for i in range(1, 40):
        s, r = p.bandwidth(i)
        assert s == pytest.approx(max(1.0, math.sqrt(s2)), rel=1e-9)
        assert r == pytest.approx(math.sqrt(r2), rel=1e-9)
        s2, r2 = s2 * (i + p.a) / (i + 1), r2 * (i + p.a) / (i + 1)


@pytest.mark.parametrize("kwargs, name", [
    (dict(sigma_s=0.5), "sigma_s"), (dict(sigma_r=0.0), "sigma_r"), (dict(a=1.0), "a"),
    (dict(time_window=-1), "time_window"), (dict(tree_height=0), "tree_height"),
    (dict(feature_set="x"), "feature_set"), (dict(clamp=-1.0), "clamp"),
    (dict(temporal_mode="both"), "temporal_mode"),
])
def test_bad_params_name_the_field(kwargs, name):
    with pytest.raises(ValueError, match=name):
        FilterParams(**kwargs)


def test_threads_setting_is_restored(tracer):
    before = torch.get_num_threads()
    prog = Progression(tracer, [0.0], threads=1)
    prog.step()
    assert torch.get_num_threads() == before
    with pytest.raises(ValueError, match="threads"):
        Progression(tracer, [0.0], threads=0)


def test_bad_frame_times_and_reference(tracer):
    with pytest.raises(ValueError, match="frame_times"):
        Progression(tracer, [1.0, 0.0])
    with pytest.raises(ValueError, match="reference"):
        Progression(tracer, [0.0], reference=torch.zeros(1, 3, 8, 8))


def test_same_seed_same_result_other_seed_differs(tracer):
    def run(seed):
        prog = Progression(tracer, [0.0, 1.0], seed=seed)
        for _ in range(2):
            prog.step()
        return prog.ours(1.0), prog.raw(1.0)

    a, b, c = run(3), run(3), run(4)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0], c[0])


def test_time_window_weights(tracer):
    prog = Progression(tracer, [0.0, 1.0, 2.0, 3.0], FilterParams(time_window=1))
    idx, w = prog._window(1.0)
    assert idx == [0, 1, 2] and w.sum().item() == pytest.approx(1.0)
    assert w[0] == pytest.approx(w[2].item()) and w[1] > w[0]
    idx, w = prog._window(1.5)
    assert idx == [1, 2] and w[0] == pytest.approx(w[1].item())
    prog.restart(FilterParams(time_window=0))
    assert prog._window(2.0)[0] == [2]
    assert prog._window(2.25)[0] == [2]  # no frame inside: the nearest one


def test_every_feature_set_filters(tracer):
    prog = Progression(tracer, [0.0])
    for name in FEATURE_SETS:
        prog.restart(prog.params.with_(feature_set=name))
        prog.step()
        assert set(prog.guide_channels()) <= set(prog.feature_names)
        out = prog.ours(0.0)
        assert out.shape == (3, 32, 32) and out.isfinite().all()


def test_in_between_time_joins_late_and_keeps_up(tracer):
    prog = Progression(tracer, [0.0, 1.0], FilterParams(time_window=1))
    prog.step()
    prog.step()
    mid = prog.ours(0.5)  # joins at iteration 2 with the filtered raw average
    assert prog.tracks[0.5].count == 2 and mid.isfinite().all()
    prog.step()
    assert prog.tracks[0.5].count == 3
    # an in-between frame of a slow clip looks like its neighbours, not like black or noise
    both = 0.5 * (prog.ours(0.0) + prog.ours(1.0))
    assert (prog.ours(0.5) - both).abs().mean() < 0.5 * both.abs().mean()
    with pytest.raises(ValueError, match="t:"):
        prog.track(5.0)


def test_spacetime_equals_spatial_filter_without_neighbours(tracer):
    """With a window of one frame both temporal modes reduce to the same spatial filter."""
    outs = []
    for mode in ("window", "spacetime"):
        prog = Progression(tracer, [0.0, 1.0], FilterParams(time_window=0, temporal_mode=mode, tree_height=1))
        prog.step()
        outs.append(prog.ours(1.0))
    assert torch.allclose(outs[0], outs[1], rtol=1e-3, atol=1e-3)


def test_spacetime_keeps_moving_object_sharper(tracer):
    """Space-time filtering ghosts less than the window mean: where the scene moved between frames,
    its result stays nearer the frame filtered alone."""
    def run(params):
        prog = Progression(tracer, [0.0, 2.0, 4.0], params)
        for _ in range(2):
            prog.step()
        return prog

    alone = run(FilterParams(time_window=0))
    window = run(FilterParams(time_window=2, temporal_mode="window")).ours(2.0)
    spacetime = run(FilterParams(time_window=2, temporal_mode="spacetime")).ours(2.0)
    moved = (alone.feat_sum[0] - alone.feat_sum[2]).abs().sum(0) > 0.5  # features changed from t=0 to 4
    assert moved.sum() > 10
    ghost_window = (window - alone.ours(2.0)).abs().sum(0)[moved].mean()
    ghost_spacetime = (spacetime - alone.ours(2.0)).abs().sum(0)[moved].mean()
    assert ghost_spacetime < ghost_window


def test_pipeline_engine_is_the_progressive_renderer(tracer):
    """The adapter drives torchmanifold.pipeline's ProgressiveRenderer: same samples, same result."""
    from torchmanifold.pipeline import BandwidthSchedule
    from torchmanifold.pipeline.progressive import ProgressiveRenderer

    from demo.pipeline_engine import PipelineProgression

    params = FilterParams(sigma_r=0.45, a=0.7)
    prog = PipelineProgression(tracer, [0.0, 1.0], params, seed=5)
    pr = ProgressiveRenderer(tracer, [0.0, 1.0], settings=prog.settings(), alpha=0.7, seed=5)
    pr.schedule = BandwidthSchedule(params.sigma_s, 0.45 / 0.3, 0.7)
    for _ in range(2):
        prog.step()
        state = pr.step()
    assert prog.iteration == prog.spp == 2
    for k, t in enumerate([0.0, 1.0]):
        assert torch.equal(prog.ours(t), state.ours[k])
        assert torch.equal(prog.raw(t), state.raw[k])
        assert torch.equal(prog.gaussian(t), state.gaussian[k])
    # the feature view shows the mean of the very samples the pipeline used
    mean = sum(tracer.render(times=[1.0], spp=1, seed=5, sample_offset=i).features[0] for i in range(2)) / 2
    n = [prog.feature_names.index(c) for c in ("Nx", "Ny", "Nz")]
    assert torch.allclose(prog.feature_view(1.0, "N"), (0.5 + 0.5 * mean[n]).clamp(0, 1), atol=1e-6)


def test_pipeline_engine_in_between_time_restarts_with_it(tracer):
    from demo.pipeline_engine import PipelineProgression

    prog = PipelineProgression(tracer, [0.0, 1.0], FilterParams(time_window=1))
    prog.step()
    prog.track(0.5)
    assert prog.iteration == 0  # the pipeline keeps one running sum per query time: it starts over
    prog.step()
    mid = prog.ours(0.5)
    assert mid.isfinite().all() and mid.mean() > 0
    assert not torch.equal(mid, prog.ours(0.0)) and not torch.equal(mid, prog.ours(1.0))
