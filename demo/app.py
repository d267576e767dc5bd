"""The real-time demo window: watch the adaptive-manifold filter converge, iteration by iteration.

Panels of the same frame side by side: the raw progressive average, a Gaussian-filtered average,
ours, and an error heat map against a reference rendered at start; below them a live plot of PSNR
against iteration and the iteration count, spp and milliseconds per stage. The tracer renders in the
window's own GL context; the filter runs in torch, so each frame costs one read-back (the tracer's)
and one upload of the packed panels.

Run ``python -m demo`` (``--help`` for options, ``H`` in the window for keys).
"""
from __future__ import annotations

import importlib.util
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch


def prepare_torch_before_gl() -> None:
    """Import ``torch._dynamo`` before any GL context exists when triton is importable.

    triton loaded after Mesa's LLVM crashes; the tracer's ``create_context`` does the same, but the
    demo's context is made by moderngl-window, so it has to happen here.
    """
    if importlib.util.find_spec("triton") is not None:
        import torch._dynamo  # noqa: F401


prepare_torch_before_gl()

import moderngl  # noqa: E402
import moderngl_window  # noqa: E402
from moderngl_window.context.base import WindowConfig  # noqa: E402
from PIL import Image  # noqa: E402
from tqdm import tqdm  # noqa: E402

from demo import controls  # noqa: E402
from demo.overlay import render_overlay  # noqa: E402
from demo.panels import MODE_DISPLAY, MODE_HEAT, MODE_IMAGE, SLOTS, Layout, PanelRenderer  # noqa: E402
from demo.controls import FEATURE_SETS, FEATURE_VIEWS, TEMPORAL_MODES, FilterParams  # noqa: E402
from demo.session import DemoSession, torch_threads  # noqa: E402
from torchmanifold.timewindow import bracket, frame_at  # noqa: E402

PANEL_TITLES = {"raw": "raw average", "gaussian": "Gaussian", "ours": "ours (AM)"}


def render_reference(tracer, times, spp: int, seed: int, chunk: int = 8) -> torch.Tensor:
    """Converged frames ``(T,3,H,W)``: ``spp`` samples in chunks (progress bar), on their own seed."""
    total = None
    done = 0
    with tqdm(total=spp, desc="reference", unit="spp", leave=False) as bar:
        while done < spp:
            n = min(chunk, spp - done)
            res = tracer.render(times=list(times), spp=n, seed=seed, sample_offset=done)
            part = res.color.float() * n
            total = part if total is None else total + part
            done += n
            bar.update(n)
    return total / spp


def resolve_scene(name: str | None):
    """``None`` -> the default scene; a built-in scene's name (e.g. ``torus_box``) or a TOML path -> that."""
    from torchmanifold.render import default_scene, load_scene
    from torchmanifold.render.scene import SCENES_DIR

    if name is None:
        return default_scene()
    builtin = SCENES_DIR / f"{name}.toml"
    if not Path(name).suffix and builtin.is_file():
        return load_scene(builtin)
    if not Path(name).is_file():
        known = sorted(p.stem for p in SCENES_DIR.glob("*.toml"))
        raise ValueError(f"--scene: expected a built-in scene {known} or a TOML file, got {name!r}")
    return load_scene(name)


class DemoApp(WindowConfig):
    """moderngl-window app: progressive rendering + filtering of a short clip, live.

    Command-line options (see ``python -m demo --help``) pick the image size, clip length, reference
    samples and initial filter parameters; keys change them live (:mod:`demo.controls`).
    """

    title = "torchmanifold demo: adaptive manifolds, progressive"
    gl_version = (4, 3)  # compute shaders for the tracer in the same context
    aspect_ratio = None
    resizable = False
    vsync = False
    clear_color = (0.06, 0.06, 0.07, 1.0)
    window_size = Layout(96, 96).window_size
    log_level = logging.WARNING

    @classmethod
    def add_arguments(cls, parser) -> None:
        add_demo_arguments(parser)

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        args = self.argv
        self.layout = Layout(args.width, args.height, scale=args.scale)
        self.frame_times = [float(i) for i in range(args.clip)]
        self.max_iterations = args.max_iterations
        from torchmanifold.render import PathTracer

        scene = resolve_scene(args.scene)
        self.tracer = PathTracer(scene, width=args.width, height=args.height, ctx=self.ctx)
        reference = None
        if args.reference_spp > 0:
            reference = render_reference(self.tracer, self.frame_times, args.reference_spp, seed=args.seed + 7919)
        params = FilterParams(
            sigma_s=args.sigma_s, sigma_r=args.sigma_r, a=args.a, time_window=args.time_window,
            tree_height=args.tree_height, feature_set=args.feature_set, clamp=args.clamp,
            temporal_mode=args.temporal_mode,
        )
        self.progression = DemoSession(self.tracer, self.frame_times, params, seed=args.seed, reference=reference,
                                       threads=args.threads or None)
        self.make_current()
        self.panels = PanelRenderer(self.ctx, args.width, args.height)
        if reference is not None:
            self.panels.upload_reference(reference[0].permute(1, 2, 0).numpy())
        self.show_time = self.frame_times[0]
        self.playing = not args.paused
        self.progressing = True
        self.clip_fps = args.clip_fps
        self._last_advance = None
        self.feature_view: str | None = None
        self.heat_slot = SLOTS.index("ours")
        self.exposure = args.exposure
        self.show_help = False
        self.display_ms = 0.0
        self.frames_drawn = 0
        self.stage_log: list[tuple[float, float, float]] = []
        self._shown_timing = None
        self._overlay_key = None
        self._images_key = None
        self._key_actions = {}
        for key_name, action, _ in controls.BINDINGS:
            key = getattr(self.wnd.keys, key_name, None)
            if key not in (None, "undefined"):
                self._key_actions[key] = action

    def make_current(self) -> None:
        """Make the window's context current again after the tracer ran in it.

        A ``with ctx:`` block (the tracer may use one) leaves no context current when it exits; the
        window's clear/swap and our draws need it current. Re-entering an already current context is
        a no-op.
        """
        self.ctx.__enter__()

    # ------------------------------------------------------------------------------- controls
    def on_key_event(self, key, action, modifiers) -> None:
        if action != self.wnd.keys.ACTION_PRESS:
            return
        name = self._key_actions.get(key)
        if name is not None:
            self.apply_action(name)

    def on_mouse_press_event(self, x: int, y: int, button: int) -> None:
        """A click on the clip bar jumps there (snapped to 1/4 frame, in-between frames included)."""
        x0, x1, ty = self.layout.timeline_span()
        if abs(y - ty) > 12 or not x0 - 8 <= x <= x1 + 8 or len(self.frame_times) < 2:
            return
        lo, hi = self.frame_times[0], self.frame_times[-1]
        t = lo + (min(max(x, x0), x1) - x0) / (x1 - x0) * (hi - lo)
        self.playing = False
        self.set_time(round(t * 4) / 4)

    def set_time(self, t: float) -> None:
        """Show time ``t``; an in-between time starts being tracked before the next iteration."""
        self.show_time = t
        self.progression.track(t)

    def on_mouse_drag_event(self, x: int, y: int, dx: int, dy: int) -> None:
        self.on_mouse_press_event(x, y, 1)

    def apply_action(self, action: str) -> None:
        """Run one named action from :data:`demo.controls.ACTIONS`."""
        if action not in controls.ACTIONS:
            raise ValueError(f"action: expected one of {controls.ACTIONS}, got {action!r}")
        params = controls.adjust_params(self.progression.params, action)
        if params is not None:
            self.progression.restart(params)
        elif action == "play":
            self.playing = not self.playing
            self._last_advance = None
        elif action in ("scrub_back", "scrub_forward"):
            self.playing = False
            step = 0.25 if action == "scrub_forward" else -0.25
            lo, hi = self.frame_times[0], self.frame_times[-1]
            self.set_time(min(hi, max(lo, round((self.show_time + step) * 4) / 4)))
        elif action == "pause_progression":
            self.progressing = not self.progressing
        elif action == "restart":
            self.progression.restart()
        elif action == "feature_view":
            available = [None] + [g for g in FEATURE_VIEWS if self.progression.feature_view(self.show_time, g) is not None]
            self.feature_view = controls.next_in(available, self.feature_view)
        elif action == "heat_source":
            self.heat_slot = (self.heat_slot + 1) % len(SLOTS)
        elif action == "exposure_down":
            self.exposure /= 1.5
        elif action == "exposure_up":
            self.exposure *= 1.5
        elif action == "help":
            self.show_help = not self.show_help
        elif action == "quit":
            self.wnd.close()

    # -------------------------------------------------------------------------------- frame
    def _advance_playback(self) -> None:
        now = time.perf_counter()
        if not self.playing or len(self.frame_times) < 2:
            return
        if self._last_advance is None:
            self._last_advance = now
        if now - self._last_advance >= 1.0 / self.clip_fps:
            self._last_advance = now
            i0, i1, w = bracket(self.frame_times, self.show_time)
            nxt = i1 if w > 0 else i0 + 1  # the next frame after the shown time
            self.show_time = self.frame_times[nxt] if nxt < len(self.frame_times) else self.frame_times[0]

    def on_render(self, time_s: float, frame_time: float) -> None:
        prog = self.progression
        # the whole frame with the demo's torch thread count: tiny tensor ops on a shared CPU are
        # 100x slower with idle OpenMP threads to wake (24 ms vs 0.1 ms for the panel packing)
        with torch_threads(prog.threads):
            if self.progressing and prog.iteration < self.max_iterations:
                prog.step()
                self.make_current()
            self._advance_playback()
            t0 = time.perf_counter()
            self.draw()
            self.ctx.finish()
            self.display_ms = (time.perf_counter() - t0) * 1e3
        self.frames_drawn += 1
        timing = prog.timing
        self.stage_log.append((timing.trace_ms, timing.filter_ms, self.display_ms))

    def stage_summary(self) -> dict[str, float]:
        """Median ms per stage over the frames drawn so far (the first frame, with its warm-up, left out)."""
        log = self.stage_log[1:] or self.stage_log
        if not log:
            return {}
        med = np.median(np.asarray(log), axis=0)
        return {"trace_ms": float(med[0]), "filter_ms": float(med[1]), "display_ms": float(med[2])}

    def panel_images(self) -> np.ndarray:
        """The packed ``(H, 3W, 3)`` float32 upload of the shown time: raw (or a feature), gaussian, ours."""
        prog, t = self.progression, self.show_time
        images = {"raw": prog.raw(t), "gaussian": prog.gaussian(t), "ours": prog.ours(t)}
        if self.feature_view is not None:
            view = prog.feature_view(t, self.feature_view)
            if view is not None:
                images["raw"] = view
        packed = torch.cat([images[s] for s in SLOTS], dim=2)  # (3, H, 3W)
        return packed.permute(1, 2, 0).contiguous().numpy().astype(np.float32, copy=False)

    def _reference_image(self) -> np.ndarray | None:
        prog = self.progression
        k = frame_at(prog.frame_times, self.show_time)
        if prog.reference is None or k is None:
            return None  # in-between times have no reference frame: the heat map hides
        return prog.reference[k].permute(1, 2, 0).contiguous().numpy()

    def draw(self) -> None:
        layout, prog = self.layout, self.progression
        key = (prog.version, self.show_time, self.feature_view)
        reference = self._reference_image()
        if key != self._images_key:  # one upload per new result, none while nothing changes
            self._images_key = key
            self.panels.upload_images(self.panel_images())
            self.panels.upload_reference(reference)
        buffer_size = self.wnd.buffer_size
        self.ctx.disable(moderngl.DEPTH_TEST)
        for i, slot in enumerate(SLOTS):
            mode = MODE_DISPLAY if (i == 0 and self.feature_view is not None) else MODE_IMAGE
            self.panels.draw_panel(layout.gl_viewport(layout.panel_rect(i), buffer_size), i, mode, self.exposure)
        if reference is not None:
            self.panels.draw_panel(layout.gl_viewport(layout.panel_rect(3), buffer_size), self.heat_slot,
                                   MODE_HEAT, self.exposure)
        overlay = self._overlay(reference is not None)
        if overlay is not None:
            self.panels.upload_overlay(overlay)
        if self.show_help:
            regions = [(0, 0, *layout.window_size)]
        else:  # only where there is something: the label strip and the bottom strip (half the fragments)
            w, h = layout.window_size
            top = layout.label_height + layout.panel_size[1]
            regions = [(0, 0, w, layout.label_height), (0, top, w, h - top)]
        for rect in regions:
            self.panels.draw_overlay(layout.gl_viewport(rect, buffer_size), layout.uv_rect(rect))

    def _overlay(self, has_heat: bool) -> np.ndarray | None:
        """The overlay image, or None when nothing on it changed since the last upload."""
        layout, prog = self.layout, self.progression
        now = time.perf_counter()
        if self._shown_timing is None or now - self._shown_timing[0] > 0.5:
            # stage times refresh twice a second: readable, and the overlay is not redrawn every frame
            self._shown_timing = (now, prog.timing.trace_ms, prog.timing.filter_ms, self.display_ms)
        labels = []
        for i, slot in enumerate(SLOTS):
            title = PANEL_TITLES[slot]
            if i == 0 and self.feature_view is not None:
                title = f"feature: {self.feature_view}"
            if slot != "ours" and frame_at(prog.frame_times, self.show_time) is None:
                # only "ours" is filtered at the in-between time; the others interpolate rendered frames
                title += " (lerp)"
            labels.append((layout.panel_rect(i)[:2], title))
        if has_heat:
            labels.append((layout.panel_rect(3)[:2], f"|error| {SLOTS[self.heat_slot]}"))
        else:
            x, y = layout.panel_rect(3)[:2]
            labels.append(((x, y), "(no reference)"))
        # Labels sit in the strip above the panels, cut to the panel width.
        labels = [((x, 0), text, layout.panel_size[0]) for (x, _), text in labels]
        p = prog.params
        sigma_s, sigma_r = prog.bandwidth()
        guide = ",".join(prog.guide_channels()) or "default"
        _, trace_ms, filter_ms, display_ms = self._shown_timing
        lines = [
            f"iteration {prog.iteration}   spp {prog.spp}   t = {self.show_time:.2f}"
            f"{'' if self.playing else '  (paused)'}{'' if self.progressing else '  [iterations paused]'}",
            f"trace {trace_ms:7.1f} ms   filter {filter_ms:7.1f} ms   display {display_ms:6.1f} ms",
            f"sigma_s {p.sigma_s:.2f} -> {sigma_s:.2f}   sigma_r {p.sigma_r:.3f} -> {sigma_r:.3f}   a {p.a:.2f}",
            f"time window +-{p.time_window} ({p.temporal_mode})   tree height {p.tree_height}   clamp "
            + (f"{p.clamp:g}" if p.clamp else "off"),
            f"feature set {p.feature_set}: {guide}",
            f"clip {len(prog.frame_times)} frames  {self.tracer.width}x{self.tracer.height}   exposure "
            f"{self.exposure:.2f}",
            "",
            "H: help   SPACE: play/pause   arrows: scrub   R: restart",
        ]
        key = (tuple(labels), tuple(lines), tuple(tuple(h[-1:]) + (len(h),) for h in prog.history.values()),
               self.show_help)
        if key == self._overlay_key:
            return None
        self._overlay_key = key
        return render_overlay(
            layout.window_size, labels, layout.plot_rect(), prog.history, layout.text_rect(), lines,
            controls.help_lines() if self.show_help else None, (prog.frame_times, self.show_time, layout.timeline_span()),
        )

    # ------------------------------------------------------------------------------ capture
    def read_frame(self) -> np.ndarray:
        """The window's current image as uint8 ``(H, W, 3)``, top row first."""
        fbo = self.wnd.fbo
        w, h = fbo.size
        data = fbo.read(viewport=(0, 0, w, h), components=3, alignment=1)
        return np.frombuffer(data, np.uint8).reshape(h, w, 3)[::-1].copy()

    def screenshot(self, path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(self.read_frame()).save(path)
        return path

    def on_close(self) -> None:
        self.panels.release()


def add_demo_arguments(parser) -> None:
    """The demo's own command-line options (moderngl-window adds its window options beside them)."""
    d = FilterParams()
    g = parser.add_argument_group("demo")
    g.add_argument("--width", type=int, default=64, help="image width in pixels (default 64)")
    g.add_argument("--height", type=int, default=64, help="image height in pixels (default 64)")
    g.add_argument("--scale", type=int, default=3, help="panel zoom factor (default 3)")
    g.add_argument("--clip", type=int, default=3, help="clip length in frames (default 3)")
    g.add_argument("--clip-fps", type=float, default=4.0, help="playback speed in frames/s (default 4)")
    g.add_argument("--scene", default=None,
                   help="built-in scene name (cornell_box, torus_box) or a scene TOML file (default: cornell_box)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--reference-spp", type=int, default=32, help="reference samples per pixel, 0 = none")
    g.add_argument("--max-iterations", type=int, default=1024)
    g.add_argument("--sigma-s", type=float, default=d.sigma_s, help=f"spatial sigma, pixels (default {d.sigma_s})")
    g.add_argument("--sigma-r", type=float, default=d.sigma_r,
                   help=f"range scale: {d.sigma_r} keeps the engine's per-feature range sigmas, others scale them "
                        f"(default {d.sigma_r})")
    g.add_argument("--a", type=float, default=d.a, help=f"bandwidth reduction, in (0, 1) (default {d.a})")
    g.add_argument("--time-window", type=int, default=d.time_window,
                   help=f"temporal radius in frames (default {d.time_window})")
    g.add_argument("--temporal-mode", default=d.temporal_mode, choices=TEMPORAL_MODES,
                   help="window: mean of the window then filter; spacetime: joint filter, no ghosts (slower)")
    g.add_argument("--tree-height", type=int, default=d.tree_height, help=f"manifold tree height (default {d.tree_height})")
    g.add_argument("--feature-set", default=d.feature_set,
                   help=f"guide channels: {', '.join(FEATURE_SETS)} (default {d.feature_set})")
    g.add_argument("--clamp", type=float, default=d.clamp,
                   help="firefly clamp: 1-spp samples above this multiple of the running estimate are clamped; "
                        f"it grows as sqrt(iteration); 0 = off (default {d.clamp})")
    g.add_argument("--exposure", type=float, default=1.0)
    g.add_argument("--threads", type=int, default=1,
                   help="torch threads for the filter, 0 = torch's default (default 1: the images are small)")
    g.add_argument("--paused", action="store_true", help="start with playback paused")
    g.add_argument("--headless", action="store_true", help="EGL headless window (no display needed)")
    g.add_argument("--frames", type=int, default=0, help="stop after N frames (0 = run until closed)")
    g.add_argument("--screenshot", default=None, help="save the final window image to this PNG")


def validate_args(args) -> None:
    """Bad option values -> ValueError naming the option and what was expected."""
    for name in ("width", "height"):
        if not 8 <= getattr(args, name) <= 4096:
            raise ValueError(f"--{name}: expected 8..4096 pixels, got {getattr(args, name)}")
    if not 1 <= args.scale <= 16:
        raise ValueError(f"--scale: expected 1..16, got {args.scale}")
    if args.clip < 1:
        raise ValueError(f"--clip: expected at least 1 frame, got {args.clip}")
    if args.reference_spp < 0:
        raise ValueError(f"--reference-spp: expected >= 0, got {args.reference_spp}")
    if args.threads < 0:
        raise ValueError(f"--threads: expected >= 0 (0 = torch's default), got {args.threads}")
    if args.frames < 0:
        raise ValueError(f"--frames: expected >= 0, got {args.frames}")
    if args.clip_fps <= 0:
        raise ValueError(f"--clip-fps: expected > 0, got {args.clip_fps}")
    if args.screenshot is not None and args.frames == 0 and args.headless:
        raise ValueError("--screenshot with --headless needs --frames N > 0")
    FilterParams(sigma_s=args.sigma_s, sigma_r=args.sigma_r, a=args.a, time_window=args.time_window,
                 tree_height=args.tree_height, feature_set=args.feature_set, clamp=args.clamp,
                 temporal_mode=args.temporal_mode)


def create_app(argv: list[str]) -> DemoApp:
    """Parse ``argv`` (demo + moderngl-window options), open the window (headless if asked), build the app."""
    import argparse

    pre = argparse.ArgumentParser(add_help=False)
    add_demo_arguments(pre)
    args, _ = pre.parse_known_args(argv)
    validate_args(args)
    extra = []
    window_flag = any(a in ("-wnd", "--window") or a.startswith("--window=") for a in argv)
    if not args.headless and not window_flag and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ValueError("no display (DISPLAY is not set): use --headless, or run under xvfb-run")
    if args.headless:
        extra += ["--window", "headless", "--backend", "egl"]
    if "--size" not in argv:
        w, h = Layout(args.width, args.height, scale=args.scale).window_size
        extra += ["--size", f"{w}x{h}"]
    return moderngl_window.create_window_config_instance(DemoApp, args=list(argv) + extra)


def run(argv: list[str]) -> DemoApp:
    """Run the demo until the window closes or ``--frames`` frames were drawn; save ``--screenshot``."""
    app = create_app(argv)
    args = app.argv
    window, timer = app.wnd, app.timer
    timer.start()
    try:
        while not window.is_closing:
            current, delta = timer.next_frame()
            window.clear(*app.clear_color)
            window.use()
            window.render(current, delta)
            if args.frames and app.frames_drawn >= args.frames:
                if args.screenshot:
                    app.screenshot(args.screenshot)
                break
            if not window.is_closing:
                window.swap_buffers()
    finally:
        timer.stop()
        window.destroy()
    return app
