"""The demo's session on the real tracer: its controls land on the one progressive engine."""
from __future__ import annotations

import pytest
import torch

from demo.controls import FilterParams
from demo.session import DemoSession
from torchmanifold.pipeline import DEFAULT_ALPHA, DenoiseSettings
from torchmanifold.pipeline.progressive import ProgressiveRenderer

ALBEDO_NORMAL = ["Mr", "Mg", "Mb", "Nx", "Ny", "Nz"]


@pytest.fixture(scope="module")
def tracer():
    from torchmanifold.render import PathTracer, create_context, default_scene

    return PathTracer(default_scene(), width=32, height=32, ctx=create_context())


def test_every_control_lands_on_the_engine(tracer):
    session = DemoSession(tracer, [0.0, 1.0])
    session.restart(FilterParams(sigma_s=5.0, sigma_r=0.6, a=0.5, time_window=2, tree_height=3,
                                 feature_set="albedo+normal", clamp=3.0, temporal_mode="spacetime"))
    s, schedule = session.engine.settings, session.engine.schedule
    assert (s.sigma_s, s.temporal_radius, s.sigma_t, s.mode, s.tree_height) == (5.0, 2, 1.0, "spacetime", 3)
    assert list(s.guide) == ALBEDO_NORMAL
    assert (s.firefly, s.firefly_k) == ("clamp", 3.0)
    assert (schedule.sigma_s0, schedule.sigma_r0, schedule.alpha) == (5.0, 2.0, 0.5)  # sigma_r 0.6 = 2x the groups'
    session.restart(session.params.with_(clamp=0.0, feature_set="all", time_window=0))
    s = session.engine.settings
    assert s.firefly == "none" and "T" not in s.guide and {"Dx", "Sx", "Z", "Mr", "Nx"} <= set(s.guide)
    assert (s.temporal_radius, s.sigma_t) == (0, 0.5)
    assert tuple(s.bandwidths) == (1.0,)  # the demo's default: one bandwidth, the fast step
    session.restart(session.params.with_(adaptive=True))
    assert tuple(session.engine.settings.bandwidths) == tuple(DenoiseSettings().bandwidths)


def test_session_shows_the_engine_run_built_by_hand(tracer):
    """The window's images are those of a ProgressiveRenderer with the documented defaults, built here
    with literal settings; the feature view is the mean of the very samples it rendered."""
    session = DemoSession(tracer, [0.0, 1.0], seed=5)
    by_hand = ProgressiveRenderer(tracer, [0.0, 1.0], seed=5, alpha=DEFAULT_ALPHA, settings=DenoiseSettings(
        sigma_s=3.0, temporal_radius=0, sigma_t=0.5, mode="window", tree_height=2,
        guide=["Z"] + ALBEDO_NORMAL, firefly="clamp", firefly_k=5.0, bandwidths=(1.0,)))
    for _ in range(2):
        session.step()
        state = by_hand.step()
    assert session.iteration == session.spp == 2
    for k, t in enumerate([0.0, 1.0]):
        assert torch.equal(session.ours(t), state.ours[k])
        assert torch.equal(session.raw(t), state.raw[k])
        assert torch.equal(session.gaussian(t), state.gaussian[k])
    mean = sum(tracer.render(times=[1.0], spp=1, seed=5, sample_offset=i).features[0] for i in range(2)) / 2
    n = [session.feature_names.index(c) for c in ("Nx", "Ny", "Nz")]
    assert torch.allclose(session.feature_view(1.0, "N"), (0.5 + 0.5 * mean[n]).clamp(0, 1), atol=1e-6)


def test_in_between_time_joins_without_a_restart(tracer):
    session = DemoSession(tracer, [0.0, 1.0], max_extra_times=2)
    session.step()
    session.step()
    session.track(0.5)
    assert session.iteration == 2  # the iterations done are kept
    session.step()
    mid = session.ours(0.5)
    assert mid.isfinite().all() and mid.mean() > 0
    assert not torch.equal(mid, session.ours(0.0)) and not torch.equal(mid, session.ours(1.0))
    session.track(0.25)
    session.track(0.75)  # a third in-between time: the oldest one goes
    assert session.engine.query_times == [0.0, 1.0, 0.25, 0.75]
    with pytest.raises(ValueError, match="t:"):
        session.track(5.0)


def test_same_seed_same_result_other_seed_differs(tracer):
    def run(seed):
        session = DemoSession(tracer, [0.0, 1.0], seed=seed)
        session.step()
        return session.ours(1.0), session.raw(1.0)

    a, b, c = run(3), run(3), run(4)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0], c[0])


def test_threads_setting_is_restored_and_bad_input_is_named(tracer):
    before = torch.get_num_threads()
    session = DemoSession(tracer, [0.0], threads=1)
    session.step()
    assert torch.get_num_threads() == before
    with pytest.raises(ValueError, match="threads"):
        DemoSession(tracer, [0.0], threads=0)
    with pytest.raises(ValueError, match="frame_times"):
        DemoSession(tracer, [1.0, 0.0])
    with pytest.raises(ValueError, match="reference"):
        DemoSession(tracer, [0.0], reference=torch.zeros(1, 3, 8, 8))


@pytest.mark.parametrize("kwargs, name", [
    (dict(sigma_s=0.5), "sigma_s"), (dict(sigma_r=0.0), "sigma_r"), (dict(a=1.0), "a"),
    (dict(time_window=-1), "time_window"), (dict(tree_height=0), "tree_height"),
    (dict(feature_set="x"), "feature_set"), (dict(clamp=-1.0), "clamp"),
    (dict(temporal_mode="both"), "temporal_mode"),
])
def test_bad_params_name_the_field(kwargs, name):
    with pytest.raises(ValueError, match=name):
        FilterParams(**kwargs)


@pytest.fixture(scope="module")
def tracer_proc():
    from demo.tracing import TracerProcess, TracerSpec
    from torchmanifold.render import default_scene

    thread = TracerProcess(TracerSpec(default_scene(), 32, 32), [0.0, 1.0, 2.0])
    yield thread
    thread.close()


def test_tracer_process_renders_what_the_tracer_renders(tracer, tracer_proc):
    """A frame cut out of the worker's whole-clip render is the frame rendered alone, bit for bit; the
    first frame of sample i queues sample i + 1 of the clip."""
    tracer_proc.drop_lookahead()
    for offset in (0, 1):
        for t in (2.0, 0.0):
            got = tracer_proc.render(times=[t], spp=1, seed=9, sample_offset=offset)
            want = tracer.render(times=[t], spp=1, seed=9, sample_offset=offset)
            for name in ("color", "features", "emission"):
                assert torch.equal(getattr(got, name), getattr(want, name)), (offset, t, name)
        assert set(tracer_proc._clip) == {(9, offset), (9, offset + 1)}  # the next sample is on its way
    # other calls (the reference: many samples) run in the worker as they are
    ref = tracer_proc.render(times=[0.5, 1.0], spp=3, seed=2)
    assert torch.equal(ref.color, tracer.render(times=[0.5, 1.0], spp=3, seed=2).color)
    tracer_proc.drop_lookahead()
    assert not tracer_proc._clip


def test_session_through_the_tracer_process_is_the_same_progression(tracer, tracer_proc):
    times = [0.0, 1.0, 2.0]
    direct = DemoSession(tracer, times, seed=4)
    ahead = DemoSession(tracer_proc, times, seed=4)
    for _ in range(2):
        direct.step()
        timing = ahead.step()
    assert timing.trace_ms > 0 and timing.filter_ms > 0
    for t in times:
        assert torch.equal(direct.ours(t), ahead.ours(t))
        assert torch.equal(direct.raw(t), ahead.raw(t))
    # the upload: raw, gaussian, ours per row, RGB texels
    assert torch.equal(ahead.planes()[:, 2], ahead.state.ours.permute(0, 2, 3, 1))
    assert torch.equal(ahead.planes([2, 0]), ahead.planes()[[2, 0]])
    ahead.restart()  # the look-ahead of the old progression is dropped, the new one starts at sample 0
    assert not tracer_proc._clip
    ahead.step()
    direct.restart()
    direct.step()
    assert torch.equal(direct.ours(1.0), ahead.ours(1.0))


def test_tracer_process_reports_a_bad_tracer():
    """The child's error comes back to the caller, named."""
    from demo.tracing import TracerProcess, TracerSpec

    with pytest.raises(TypeError, match="scene must be"):
        TracerProcess(TracerSpec(None, 32, 32), [0.0])
    with pytest.raises(ValueError, match="clip_times"):
        TracerProcess(TracerSpec(None, 32, 32), [])
