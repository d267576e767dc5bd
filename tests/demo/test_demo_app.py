"""The demo window, headless (EGL) and under Xvfb: panels, overlay, screenshot, controls."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, ImageDraw

from demo import controls
from demo.app import create_app, validate_args
from demo.panels import SLOTS
from _demo_helpers import SMALL, crop, srgb_u8, upscale

REPO = Path(__file__).resolve().parents[2]


def test_screenshot_written_with_window_size(headless_run):
    app, shot = headless_run
    img = np.asarray(Image.open(shot).convert("RGB"))
    w, h = app.layout.window_size
    assert img.shape == (h, w, 3)
    assert app.frames_drawn == 3 and app.progression.iteration == 3
    assert app.progression.spp == 3


def test_stats_file(headless_run):
    """The numbers the window shows, written for checks from outside."""
    import json

    from demo.app import STATS_FIELDS

    app, shot = headless_run
    stats = json.loads(shot.with_suffix(".json").read_text())
    for name in STATS_FIELDS:
        assert np.isfinite(stats[name]) and stats[name] > 0, (name, stats[name])
    assert stats["ms_per_iteration"] == pytest.approx(1e3 / stats["iterations_per_second"])
    assert (stats["iterations"], stats["frames"], stats["width"], stats["height"], stats["clip"]) == (3, 3, 48, 32, 2)
    assert stats["overlap"] is True and stats["temporal_radius"] == app.progression.params.time_window
    assert stats == {**stats, **app.stage_summary()}  # the same numbers as the window's


def test_summary_of_the_stage_log():
    """Iterations per second from the end times (the real pace); stages are medians."""
    from demo.app import summarize

    log = [(10.0, 5.0, 1.0, 20.0, 2.0), (10.5, 7.0, 0.0, 30.0, 4.0), (11.0, 6.0, 3.0, 10.0, 3.0)]
    s = summarize(log)
    assert s["iterations_per_second"] == pytest.approx(2.0) and s["ms_per_iteration"] == pytest.approx(500.0)
    assert (s["trace_ms"], s["trace_wait_ms"], s["filter_ms"], s["display_ms"]) == (6.0, 1.0, 20.0, 3.0)
    assert summarize([]) == {}


def test_on_screen_numbers_are_the_summary(headless_run):
    from demo.app import SCREEN_WINDOW

    app, _ = headless_run
    st = app.stage_summary(SCREEN_WINDOW)
    texts = [t for t in _canvas_texts(app)]
    assert any(f"{st['iterations_per_second']:5.1f} it/s" in t and f"filter {st['filter_ms']:6.1f}" in t
               for t in texts), texts


def _canvas_texts(app):
    """The strings the overlay draws this frame (recorded from the canvas calls)."""
    from demo.overlay import Canvas

    seen = []
    original = Canvas.text

    def record(self, xy, text, *args, **kwargs):
        seen.append(text)
        return original(self, xy, text, *args, **kwargs)

    Canvas.text = record
    try:
        _, backdrop, _ = app.overlay_layers(True)
        backdrop()
    finally:
        Canvas.text = original
    return seen


def test_size_option():
    from demo.app import image_size_argv

    assert image_size_argv(["--size", "128x96", "--clip", "3"]) == ["--width", "128", "--height", "96", "--clip", "3"]
    assert image_size_argv(["--size=40X24"]) == ["--width", "40", "--height", "24"]
    for bad in (["--size", "128"], ["--size"], ["--size=ax3"]):
        with pytest.raises(ValueError, match="--size"):
            image_size_argv(bad)


def test_panels_differ_from_each_other(headless_run):
    app, shot = headless_run
    img = np.asarray(Image.open(shot).convert("RGB"))
    panels = [crop(img, app.layout.panel_rect(i)) for i in range(4)]
    for a, b in itertools.combinations(range(4), 2):
        assert np.abs(panels[a] - panels[b]).mean() > 3.0, f"panels {a} and {b} look the same"
    for p in panels:
        assert p.std() > 5.0  # not blank


def test_filtered_panel_closer_to_reference_than_raw(headless_run):
    app, shot = headless_run
    img = np.asarray(Image.open(shot).convert("RGB"))
    prog = app.progression
    k = prog.frame_times.index(app.show_time)
    ref = upscale(srgb_u8(prog.reference[k].permute(1, 2, 0).numpy()), app.layout.scale)
    err = {s: ((crop(img, app.layout.panel_rect(i)) - ref) ** 2).mean() for i, s in enumerate(SLOTS)}
    assert err["ours"] < err["raw"], err
    # The clip-wide curves agree: ours above raw at every iteration so far.
    for (_, raw), (_, ours) in zip(prog.history["raw"], prog.history["ours"]):
        assert ours > raw


def test_panels_show_the_progression_state(headless_run):
    """The GL path (packed float upload, shader tone map) against numpy doing the same on the tensors."""
    app, shot = headless_run
    img = np.asarray(Image.open(shot).convert("RGB"))
    prog, t = app.progression, app.show_time
    for i, tensor in enumerate((prog.raw(t), prog.gaussian(t), prog.ours(t))):
        want = upscale(srgb_u8(tensor.permute(1, 2, 0).numpy()), app.layout.scale)
        diff = np.abs(crop(img, app.layout.panel_rect(i)) - want)
        assert np.percentile(diff, 99) <= 2.0, f"panel {i}: max diff {diff.max()}"


def test_heat_map_follows_the_error_of_ours(headless_run):
    """The heat map is computed in the shader; its brightness must rank pixels like numpy's |error|."""
    from scipy.stats import spearmanr

    app, shot = headless_run
    img = np.asarray(Image.open(shot).convert("RGB"))
    prog, t = app.progression, app.show_time
    ref = srgb_u8(prog.reference[prog.frame_times.index(t)].permute(1, 2, 0).numpy())
    ours = srgb_u8(prog.ours(t).permute(1, 2, 0).numpy())
    err = upscale(np.abs(ours - ref).mean(-1), app.layout.scale)
    heat = crop(img, app.layout.panel_rect(3)) @ np.array([0.2126, 0.7152, 0.0722])
    unsaturated = err < 0.9 * 255 / 5.0  # the ramp saturates at |error| = 1/5 (u_heat_gain)
    rho = spearmanr(err[unsaturated], heat[unsaturated]).statistic
    assert rho > 0.9, rho


def test_overlay_has_plot_and_text(headless_run):
    app, shot = headless_run
    img = np.asarray(Image.open(shot).convert("RGB")).astype(np.int32)
    plot = crop(img, app.layout.plot_rect())
    # the three curves in their colours (see demo.overlay.CURVE_COLOURS)
    for colour in [(170, 170, 170), (90, 160, 255), (255, 150, 40)]:
        assert (np.abs(plot - np.array(colour)).sum(-1) < 30).sum() > 10, colour
    text = crop(img, app.layout.text_rect())
    assert (text.max(-1) > 200).sum() > 200  # light text on the dark box


def _draw_curves(canvas, rect, curves):
    """The plot's curves as the app draws them: the lists as arrays, on their axes."""
    from demo.overlay import CurveArrays, draw_curves, plot_axes

    arrays = CurveArrays()(curves)
    draw_curves(canvas, rect, arrays, plot_axes(arrays))


def test_plot_draws_finite_points_two_pixels_thick():
    """A curve's non-finite values are skipped; a curve is two rows of segments one pixel apart; a curve
    of one point is a dot."""
    from demo.overlay import CURVE_COLOURS, Canvas, GlyphAtlas, _plot_mapping

    rect = (4, 100, 356, 198)
    atlas = GlyphAtlas()
    canvas = Canvas(atlas)
    _draw_curves(canvas, rect, {"raw": [(1, 20.0), (2, float("nan")), (3, 22.0)], "ours": [(1, 25.0)]})
    quads, lines = canvas.arrays()
    raw = lines[np.all(np.isclose(lines[:, 2:5] * 255, CURVE_COLOURS["raw"]), 1)]
    to_px = _plot_mapping(rect, 4, 19.0, 26.0)  # axis to the next power of two; values padded to whole dB
    ends = np.stack([to_px(1, 20.0), to_px(3, 22.0)]).astype(np.float32)
    assert np.allclose(raw[:, :2], np.concatenate([ends, ends + (0, 1)]))
    solid = np.all(quads[:, 4:8] == atlas.solid, 1)  # boxes, not glyphs
    dots = quads[np.all(np.isclose(quads[:, 8:11] * 255, CURVE_COLOURS["ours"]), 1) & solid]
    assert len(dots) == 1 and np.allclose(dots[0, :2], to_px(1, 25.0) - 2)


def test_long_curves_keep_one_point_per_pixel_column():
    """However many iterations, a curve draws at most one point per pixel column of the plot, and ends at its
    last value."""
    from demo.overlay import Canvas, CurveArrays, GlyphAtlas, _plot_mapping, plot_axes

    rect = (4, 100, 356, 198)
    curve = [(i, 20.0 + np.log(i)) for i in range(1, 5001)]
    canvas = Canvas(GlyphAtlas())
    _draw_curves(canvas, rect, {"ours": curve})
    _, lines = canvas.arrays()
    ours = lines[np.all(np.isclose(lines[:, 2:5] * 255, (255, 150, 40)), 1)]
    ours = ours.reshape(2, -1, 2, 6)[0]  # the upper of the two pixel rows
    xs = np.concatenate([ours[:, 0, 0], ours[-1:, 1, 0]])
    assert len(xs) <= rect[2] and np.all(np.diff(np.floor(xs)) > 0)
    to_px = _plot_mapping(rect, *plot_axes(CurveArrays()({"ours": curve})))
    assert np.allclose(ours[-1, 1, :2], to_px(*curve[-1]))


def test_curve_arrays_convert_what_was_appended():
    """The curves as arrays of their finite points, converted as the lists grow: the same as a fresh
    conversion at every step; a new list (a restart) starts again."""
    from demo.overlay import CurveArrays

    arrays, curve = CurveArrays(), []
    for i in range(1, 200):
        curve.append((i, float("nan") if i % 7 == 0 else 20.0 + 1.0 / i))
        got = arrays({"ours": curve})["ours"]
        want = np.array([(it, v) for it, v in curve if np.isfinite(v)], np.float64).T
        assert np.array_equal(got, want)
    restarted = [(1, 30.0)]
    assert np.array_equal(arrays({"ours": restarted})["ours"], [[1.0], [30.0]])


def test_glyph_quads_hold_all_of_each_glyphs_ink():
    """A glyph's quad is cut to its ink: pasting the quads of a string gives the same alpha as pasting
    each character's whole atlas cell at its pen position (PIL draws every printable character)."""
    from demo.overlay import FIRST, LAST, SIZES, GlyphAtlas, font

    atlas = GlyphAtlas()
    text = "".join(chr(c) for c in range(FIRST, LAST))
    for size in SIZES:
        cw, ch = atlas.cell_size[size]
        quads, width = atlas.layout(text, size)
        assert len(quads) == len(text) - 1  # all but the space
        assert (quads[:, 2] * quads[:, 3]).sum() < 0.5 * len(text) * cw * ch  # most of a cell is blank
        cut = np.zeros((ch, int(width) + cw), np.uint8)
        for x, y, w, h, u0, v0, u1, v1 in quads.astype(int):
            assert (w, h) == (u1 - u0, v1 - v0)
            np.maximum(cut[y:y + h, x:x + w], atlas.image[v0:v1, u0:u1], out=cut[y:y + h, x:x + w])
        whole = np.zeros_like(cut)
        pen = np.concatenate([[0.0], np.cumsum(atlas.advance[size])]).astype(np.float32)  # as layout() adds
        for c, x in zip(text, np.round(pen[:-1]).astype(int)):
            cell = Image.new("L", (cw, ch), 0)
            ImageDraw.Draw(cell).text((0, 0), c, font=font(size), fill=255)
            np.maximum(whole[:, x:x + cw], np.asarray(cell), out=whole[:, x:x + cw])
        assert whole.any() and np.array_equal(cut, whole), size


def step_frame(app):
    """One frame as the main loop does it: clear, render."""
    app.wnd.clear(*app.clear_color)
    app.wnd.use()
    app.on_render(0.0, 0.0)
    return app.read_frame()


@pytest.fixture(scope="module")
def live_app():
    app = create_app(SMALL + ["--headless", "--reference-spp", "8", "--width", "32", "--height", "32"])
    step_frame(app)
    yield app
    app.on_close()
    app.wnd.destroy()


@pytest.mark.parametrize("action, field, direction", [
    ("sigma_s_up", "sigma_s", 1), ("sigma_s_down", "sigma_s", -1),
    ("sigma_r_up", "sigma_r", 1), ("sigma_r_down", "sigma_r", -1),
    ("a_up", "a", 1), ("a_down", "a", -1),
    ("window_up", "time_window", 1), ("window_down", "time_window", -1),
    ("height_up", "tree_height", 1), ("height_down", "tree_height", -1),
    ("clamp", "clamp", -1), ("clamp", "clamp", 1), ("adaptive", "adaptive", 1), ("adaptive", "adaptive", -1),
])
def test_parameter_keys_change_and_restart(live_app, action, field, direction):
    app = live_app
    step_frame(app)
    before = getattr(app.progression.params, field)
    app.apply_action(action)
    after = getattr(app.progression.params, field)
    assert (after - before) * direction > 0
    assert app.progression.iteration == 0  # the running buffer was built with the old value
    step_frame(app)
    assert app.progression.iteration == 1


def test_temporal_mode_key_switches_to_spacetime(live_app):
    app = live_app
    app.apply_action("temporal_mode")
    assert app.progression.params.temporal_mode == "spacetime" and app.progression.iteration == 0
    step_frame(app)
    assert app.progression.ours(app.show_time).isfinite().all()
    app.apply_action("temporal_mode")
    assert app.progression.params.temporal_mode == "window"


def test_feature_set_switch_changes_guide(live_app):
    app = live_app
    seen = set()
    for _ in range(len(controls.FEATURE_SETS)):
        app.apply_action("feature_set")
        step_frame(app)
        seen.add(tuple(app.progression.guide_channels()))
    assert len(seen) >= 3  # several guides


def test_feature_view_replaces_raw_panel(live_app):
    app = live_app
    app.feature_view = None
    before = crop(step_frame(app), app.layout.panel_rect(0))
    app.apply_action("feature_view")
    assert app.feature_view == "Z"
    frame = step_frame(app)
    z = app.progression.feature_view(app.show_time, "Z")
    want = upscale(z.permute(1, 2, 0).numpy() * 255.0, app.layout.scale)
    got = crop(frame, app.layout.panel_rect(0))
    assert np.abs(got - want).max() <= 1.5
    assert np.abs(got - before).mean() > 3.0
    app.feature_view = None


def test_scrub_shows_in_between_frame(live_app):
    app = live_app
    app.apply_action("scrub_forward")
    assert app.show_time == 0.25 and not app.playing
    frame = step_frame(app)
    prog = app.progression
    ours = prog.ours(0.25)
    assert ours.isfinite().all() and ours.mean() > 0
    # synthesised at 0.25, not a copy of a rendered frame
    assert not torch.equal(ours, prog.ours(0.0)) and not torch.equal(ours, prog.ours(1.0))
    # no reference exists in between: the heat map panel is left empty
    assert crop(frame, app.layout.panel_rect(3)).std(axis=(0, 1)).max() < 1.0
    app.apply_action("scrub_back")
    assert app.show_time == 0.0


def test_pass_one_shows_a_row_or_blends_two(live_app):
    """Pass 1 against numpy: a shown clip frame reads its row, a time between two rows blends them (its own
    program each); the texels come from the upload's (rows, estimates, H, W, RGB) layout."""
    from demo.panels import MODE_IMAGE

    app = live_app
    panels = app.panels
    w, h = panels.image_size
    g = torch.Generator().manual_seed(5)
    planes = torch.rand(2, len(SLOTS), h, w, 3, generator=g)
    panels.upload_estimates(planes)
    shown = [(MODE_IMAGE, i % len(SLOTS)) for i in range(panels.n_panels)]
    for rows, blend in (((1, 1), 0.0), ((0, 1), 0.25)):
        panels.draw_panels(shown, rows, blend, None, 1.0)
        got = np.frombuffer(panels.small.read(), np.uint8).reshape(h, panels.n_panels * w, 4)[::-1, :, :3]
        for i in range(panels.n_panels):
            x = (1 - blend) * planes[rows[0], i % len(SLOTS)] + blend * planes[rows[1], i % len(SLOTS)]
            diff = np.abs(got[:, i * w:(i + 1) * w].astype(np.float64) - srgb_u8(x.numpy()))
            assert diff.max() <= 1.5, (rows, blend, i, diff.max())
    app._uploaded = None  # the next frame uploads the engine's estimates again


def test_playback_steps_through_the_clip_and_wraps(live_app):
    app = live_app
    app.set_time(0.0)
    app.apply_action("play")
    app.clip_fps = 1e9  # every call is "late enough" to advance
    seen = []
    for _ in range(4):
        app._advance_playback()
        seen.append(app.show_time)
    app.apply_action("play")
    assert seen == [0.0, 1.0, 0.0, 1.0]  # the first call starts the clock; a 2-frame clip wraps


def test_click_on_clip_bar_scrubs(live_app):
    app = live_app
    x0, x1, y = app.layout.timeline_span()
    app.on_mouse_press_event(x1, y, 1)
    assert app.show_time == app.frame_times[-1]
    app.on_mouse_press_event(x0 + (x1 - x0) * 0.26, y, 1)  # 0.26 of a 1-frame clip -> 0.25
    assert app.show_time == 0.25
    app.on_mouse_press_event(x0, y - 100, 1)  # elsewhere: nothing happens
    assert app.show_time == 0.25
    app.on_mouse_press_event(x0, y, 1)
    assert app.show_time == 0.0


def test_backdrop_follows_its_inputs(live_app):
    """The cached backdrop (labels, settings lines, the plot's frame, the clip bar) is redrawn whenever what
    it shows changes: each frame equals the same frame drawn with the backdrop rebuilt from scratch."""
    app = live_app
    app.progressing = False  # the same panels in both draws
    before = step_frame(app)
    try:
        for change in (lambda: app.apply_action("exposure_up"), lambda: app.apply_action("heat_source"),
                       lambda: app.set_time(0.5), lambda: app.apply_action("help")):
            change()
            cached = step_frame(app)
            app.overlay._backdrop_key = None
            rebuilt = step_frame(app)
            assert np.array_equal(cached, rebuilt)
            assert not np.array_equal(cached, before)
            before = cached
    finally:
        app.apply_action("help")
        app.set_time(0.0)
        app.progressing = True


def test_play_pause_restart_help(live_app):
    app = live_app
    app.apply_action("play")
    assert app.playing
    app.apply_action("play")
    assert not app.playing
    app.apply_action("pause_progression")
    it = app.progression.iteration
    step_frame(app)
    assert app.progression.iteration == it
    app.apply_action("pause_progression")
    app.apply_action("restart")
    assert app.progression.iteration == 0
    plain = step_frame(app)
    app.apply_action("help")
    with_help = step_frame(app)
    app.apply_action("help")
    assert with_help.mean() < plain.mean()  # the help screen darkens the window
    with pytest.raises(ValueError, match="action"):
        app.apply_action("nonsense")


def test_scene_names_and_files(tmp_path):
    from demo.app import resolve_scene
    from torchmanifold.render.scene import SCENES_DIR

    assert resolve_scene("torus_box").objects  # a built-in scene by name
    assert len(resolve_scene(str(SCENES_DIR / "cornell_box.toml")).objects) == len(resolve_scene(None).objects)
    with pytest.raises(ValueError, match="--scene"):
        resolve_scene("no_such_scene")
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\nfov = 'wide'\n")
    with pytest.raises(ValueError, match="bad.toml"):
        resolve_scene(str(bad))


def test_default_zoom_is_the_largest_that_fits():
    from demo.panels import MAX_WINDOW_WIDTH, Layout

    for width in (8, 48, 64, 100, 128, 256, 700):
        scale = Layout.fitting_scale(width)
        assert scale == 1 or Layout(width, width, scale).window_size[0] <= MAX_WINDOW_WIDTH
        assert Layout(width, width, scale + 1).window_size[0] > MAX_WINDOW_WIDTH


def test_window_without_scale_uses_the_fitting_zoom():
    from demo.panels import Layout

    i = SMALL.index("--scale")
    argv = SMALL[:i] + SMALL[i + 2:] + ["--headless", "--reference-spp", "0"]
    app = create_app(argv)
    try:
        assert app.layout.scale == Layout.fitting_scale(48) and app.wnd.size == app.layout.window_size
    finally:
        app.on_close()
        app.wnd.destroy()


@pytest.mark.parametrize("argv, match", [
    (["--width", "2"], "--width"),
    (["--scale", "-1"], "--scale"),
    (["--clip", "0"], "--clip"),
    (["--a", "1.5"], "a: expected"),
    (["--feature-set", "nope"], "feature_set"),
    (["--headless", "--screenshot", "x.png"], "--frames"),
])
def test_bad_options_name_the_option(argv, match):
    import argparse

    from demo.app import add_demo_arguments

    parser = argparse.ArgumentParser()
    add_demo_arguments(parser)
    with pytest.raises(ValueError, match=match):
        validate_args(parser.parse_args(argv))


def test_no_display_gives_a_clear_error(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ValueError, match="--headless"):
        create_app(["--frames", "1"])


def test_real_window_under_xvfb(tmp_path):
    shot = tmp_path / "xvfb.png"
    cmd = ["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", sys.executable, "-m", "demo",
           "--size", "32x32", "--clip", "1", "--reference-spp", "0",
           "--frames", "2", "--screenshot", str(shot), "--stats", str(tmp_path / "stats.json")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    img = np.asarray(Image.open(shot).convert("RGB")).astype(np.float64)
    assert img.std() > 10.0  # not blank
    assert img[22:86, 4:68].std() > 10.0  # the raw panel has an image in it
    import json

    stats = json.loads((tmp_path / "stats.json").read_text())
    assert (stats["width"], stats["height"], stats["iterations"]) == (32, 32, 2) and stats["display_ms"] > 0
