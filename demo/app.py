"""The real-time demo window: watch the adaptive-manifold filter converge, iteration by iteration.

Panels of the same frame side by side: the raw progressive average, a Gaussian-filtered average,
ours, and an error heat map against a reference rendered at start; below them a live plot of PSNR
against iteration, iterations per second and milliseconds per stage. The tracer renders in its own
process and GL context, one iteration ahead (:mod:`demo.tracing`); the filter runs in torch; the
display uploads the engine's estimates once per iteration and draws everything else in shaders.

Run ``python -m demo`` (``--help`` for options, ``H`` in the window for keys).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import statistics
import time
from pathlib import Path
from typing import Callable

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
from demo.controls import FEATURE_SETS, FEATURE_VIEWS, TEMPORAL_MODES, FilterParams  # noqa: E402
from demo.overlay import (BACKGROUND, Canvas, CurveArrays, OverlayRenderer, draw_backdrop,  # noqa: E402
                          draw_live, plot_axes)
from demo.panels import (MAX_WINDOW_WIDTH, MODE_DISPLAY, MODE_HEAT, MODE_IMAGE, SLOTS, Layout,  # noqa: E402
                         PanelRenderer)
from demo.session import DemoSession  # noqa: E402
from demo.tracing import TracerProcess, TracerSpec  # noqa: E402
from torchmanifold._threads import torch_threads  # noqa: E402
from torchmanifold.timewindow import bracket, frame_at  # noqa: E402

PANEL_TITLES = {"raw": "raw average", "gaussian": "Gaussian", "ours": "ours (AM)"}

#: Fields of the ``--stats`` file (medians over the iterations after the first, which warms up).
STATS_FIELDS = ("iterations_per_second", "ms_per_iteration", "trace_ms", "trace_wait_ms", "filter_ms",
                "display_ms")

#: Iterations the on-screen numbers summarise (the most recent ones).
SCREEN_WINDOW = 16

#: The stats block's first lines change every iteration (iteration, stage times, the shrinking
#: bandwidth); the rest change with the settings and live in the cached backdrop.
LIVE_LINES = 3


def summarize(log: list[tuple[float, float, float, float, float]]) -> dict[str, float]:
    """Stage numbers of iteration records ``(end time s, trace ms, trace wait ms, filter ms, display ms)``.

    Iterations per second come from the end times (the real pace, overlap included); the stages are
    medians. The file and the window both show this, the window over its last iterations.
    """
    if not log:
        return {}
    if len(log) >= 2:
        ips = (len(log) - 1) / max(log[-1][0] - log[0][0], 1e-9)
    else:
        ips = float("nan")
    # per frame on screen: statistics.median of a few numbers costs a tenth of np.median
    med = [statistics.median(column) for column in list(zip(*log))[1:]]
    return {"iterations_per_second": float(ips), "ms_per_iteration": float(1e3 / ips),
            "trace_ms": float(med[0]), "trace_wait_ms": float(med[1]), "filter_ms": float(med[2]),
            "display_ms": float(med[3])}


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
    gl_version = (3, 3)  # the window only draws; the tracer has its own 4.3 context in its process
    aspect_ratio = None
    resizable = False
    vsync = False
    clear_color = tuple(c / 255.0 for c in BACKGROUND)
    window_size = Layout(96, 96).window_size
    log_level = logging.WARNING

    @classmethod
    def add_arguments(cls, parser) -> None:
        add_demo_arguments(parser)

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        args = self.argv
        if self.wnd.samples:
            raise ValueError(f"--samples: the demo draws into a single-sampled window (its backdrop is "
                             f"copied in, which a multisampled one does not take), got {self.wnd.samples}")
        self.layout = Layout(args.width, args.height, scale=args.scale)
        self.frame_times = [float(i) for i in range(args.clip)]
        self.max_iterations = args.max_iterations
        scene = resolve_scene(args.scene)
        self.tracer = TracerProcess(TracerSpec(scene, args.width, args.height), self.frame_times,
                                    prefetch=args.overlap)
        reference = None
        if args.reference_spp > 0:
            reference = render_reference(self.tracer, self.frame_times, args.reference_spp, seed=args.seed + 7919)
        params = FilterParams(
            sigma_s=args.sigma_s, sigma_r=args.sigma_r, a=args.a, time_window=args.time_window,
            tree_height=args.tree_height, feature_set=args.feature_set, clamp=args.clamp,
            temporal_mode=args.temporal_mode, adaptive=args.adaptive,
        )
        self.progression = DemoSession(self.tracer, self.frame_times, params, seed=args.seed, reference=reference,
                                       threads=args.threads or None)
        self.panels = PanelRenderer(self.ctx, args.width, args.height, n_panels=self.layout.n_panels)
        self.panels.upload_reference(reference)
        self.overlay = OverlayRenderer(self.ctx)
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
        #: one record per iteration: (end time s, trace ms, trace wait ms, filter ms, display ms)
        self.stage_log: list[tuple[float, float, float, float, float]] = []
        self._uploaded = None  # (session version, rows) of the estimates on the GPU
        self._curves = CurveArrays()  # the PSNR curves as arrays, converted as they grow
        self._view_key = None
        self._key_actions = {}
        for key_name, action, _ in controls.BINDINGS:
            key = getattr(self.wnd.keys, key_name, None)
            if key not in (None, "undefined"):
                self._key_actions[key] = action

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
        # 100x slower with idle OpenMP threads to wake
        with torch_threads(prog.threads):
            stepped = self.progressing and prog.iteration < self.max_iterations
            if stepped:
                prog.step()
            self._advance_playback()
            t0 = time.perf_counter()
            self.draw()
            self.ctx.finish()  # the display's GPU work belongs to the display's time
            self.display_ms = (time.perf_counter() - t0) * 1e3
        self.frames_drawn += 1
        if stepped:
            timing = prog.timing
            self.stage_log.append((time.perf_counter(), timing.trace_ms, timing.trace_wait_ms, timing.filter_ms,
                                   self.display_ms))

    def stage_summary(self, last: int | None = None) -> dict[str, float]:
        """:func:`summarize` of the iterations so far (the first, with its warm-up, left out), or of the
        ``last`` ones."""
        log = self.stage_log[1:] if len(self.stage_log) > 2 else self.stage_log
        return summarize(log[-last:] if last else log)

    def write_stats(self, path) -> Path:
        """The ``--stats`` JSON: :data:`STATS_FIELDS` and what was measured."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        p = self.progression.params
        stats = dict(self.stage_summary())
        stats.update(iterations=self.progression.iteration, frames=self.frames_drawn,
                     width=self.tracer.width, height=self.tracer.height, clip=len(self.frame_times),
                     overlap=self.tracer.prefetch, temporal_radius=p.time_window, temporal_mode=p.temporal_mode,
                     threads=self.progression.threads, load_average=os.getloadavg()[0])
        path.write_text(json.dumps(stats, indent=1) + "\n")
        return path

    def shown_rows(self) -> tuple[tuple[int, int], float]:
        """The two uploaded rows around the shown time and the weight of the second (the engine's
        :func:`~torchmanifold.timewindow.interpolate` between clip frames for a time not filtered yet)."""
        rows = self.progression.row_times
        j = frame_at(rows, self.show_time)
        if j is not None:
            return (j, j), 0.0
        i0, i1, w = bracket(self.frame_times, self.show_time)
        return (rows.index(self.frame_times[i0]), rows.index(self.frame_times[i1])), float(w)

    def draw(self) -> None:
        layout, prog = self.layout, self.progression
        rows, blend = self.shown_rows() if prog.state is not None else ((0, 0), 0.0)
        if prog.state is not None and self._uploaded != (prog.version, rows):
            # the rows shown, once per iteration or shown time: the upload stays one or two rows however
            # long the clip
            self._uploaded = (prog.version, rows)
            self.panels.upload_estimates(prog.planes(list(dict.fromkeys(rows))))
        rows = (0, int(rows[1] != rows[0]))  # their layers in the upload
        view = None
        if self.feature_view is not None:
            key = (prog.version, self.show_time, self.feature_view)
            view = prog.feature_view(self.show_time, self.feature_view) if prog.state is not None else None
            if view is not None and key != self._view_key:
                self._view_key = key
                self.panels.upload_view(view)
        ref_frame = frame_at(prog.frame_times, self.show_time) if prog.reference is not None else None
        panels = [(MODE_DISPLAY if (i == 0 and view is not None) else MODE_IMAGE, i) for i in range(len(SLOTS))]
        panels.append((MODE_HEAT, self.heat_slot))
        self.ctx.disable(moderngl.DEPTH_TEST)
        self.panels.draw_panels(panels, rows, blend, ref_frame, self.exposure)
        key, backdrop, live = self.overlay_layers(ref_frame is not None)
        # the backdrop replaces the window's clear (here, not in the loop: it is display time too)
        self.overlay.draw_backdrop(self.wnd.fbo, key, backdrop, layout.window_size)
        buffer_size = self.wnd.buffer_size
        viewports = [layout.gl_viewport(layout.panel_rect(i), buffer_size) for i in range(layout.n_panels)]
        self.panels.draw_magnified(self.wnd.fbo, viewports, buffer_size)
        self.overlay.draw(live, layout.window_size, (0, 0, *buffer_size))

    def overlay_layers(self, has_heat: bool) -> tuple[tuple, Callable[[], Canvas], Canvas]:
        """The overlay of this frame in two layers (built from cached glyph quads: no rasterising).

        Returns ``(key, backdrop, live)``: ``backdrop()`` builds what changes rarely (panel labels, the
        plot's frame, the settings lines, the clip bar), drawn into the cached backdrop only when ``key``,
        its inputs, changes; ``live`` holds what changes every iteration or frame (the first three stats
        lines, the curves, the clip bar's marker, help).
        """
        layout, prog = self.layout, self.progression
        labels = []
        for i, slot in enumerate(SLOTS):
            title = PANEL_TITLES[slot]
            if i == 0 and self.feature_view is not None:
                title = f"feature: {self.feature_view}"
            if slot != "ours" and frame_at(prog.frame_times, self.show_time) is None:
                # only "ours" is filtered at the in-between time; the others interpolate rendered frames
                title += " (lerp)"
            labels.append((layout.panel_rect(i)[:2], title))
        labels.append((layout.panel_rect(3)[:2], f"|error| {SLOTS[self.heat_slot]}" if has_heat else "(no reference)"))
        # Labels sit in the strip above the panels, cut to the panel width.
        labels = [((x, 0), text, layout.panel_size[0]) for (x, _), text in labels]
        p = prog.params
        sigma_s, sigma_r = prog.bandwidth()
        guide = ",".join(prog.guide_channels()) or "default"
        st = self.stage_summary(SCREEN_WINDOW) or dict.fromkeys(STATS_FIELDS, float("nan"))
        lines = [
            f"iteration {prog.iteration}   spp {prog.spp}   t = {self.show_time:.2f}"
            f"{'' if self.playing else '  (paused)'}{'' if self.progressing else '  [iterations paused]'}",
            f"{st['iterations_per_second']:5.1f} it/s   trace {st['trace_ms']:6.1f} ms"
            f" (waited {st['trace_wait_ms']:5.1f})   filter {st['filter_ms']:6.1f}   display {st['display_ms']:5.1f}",
            f"sigma_s {p.sigma_s:.2f} -> {sigma_s:.2f}   sigma_r {p.sigma_r:.3f} -> {sigma_r:.3f}   a {p.a:.2f}",
            f"time window +-{p.time_window} ({p.temporal_mode})   tree height {p.tree_height}   clamp "
            + (f"{p.clamp:g}" if p.clamp else "off") + f"   bandwidth {'adaptive' if p.adaptive else 'fixed'}",
            f"feature set {p.feature_set}: {guide}",
            f"clip {len(prog.frame_times)} frames  {self.tracer.width}x{self.tracer.height}   exposure "
            f"{self.exposure:.2f}   trace {'ahead' if self.tracer.prefetch else 'in turn'}",
            "",
            "H: help   SPACE: play/pause   arrows: scrub   R: restart",
        ]
        live_lines = lines[:LIVE_LINES] + [None] * (len(lines) - LIVE_LINES)
        still_lines = [None] * LIVE_LINES + lines[LIVE_LINES:]
        curves = self._curves(prog.history)
        axes = plot_axes(curves)
        atlas, times = self.overlay.atlas, prog.frame_times
        key = (tuple(labels), tuple(still_lines), axes, tuple(times), layout.window_size)

        def backdrop() -> Canvas:
            return draw_backdrop(Canvas(atlas), labels, layout.plot_rect(), axes, layout.text_rect(),
                                 still_lines, (times, layout.timeline_span()))

        live = draw_live(Canvas(atlas), layout.window_size, layout.plot_rect(), curves, axes,
                         layout.text_rect(), live_lines, controls.help_lines() if self.show_help else None,
                         (times, self.show_time, layout.timeline_span()))
        return key, backdrop, live

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
        """Free the GL objects and stop the tracer process (once; closing the window and :func:`run` both
        call it)."""
        if getattr(self, "_closed", False):
            return
        self._closed = True
        self.panels.release()
        self.overlay.release()
        self.tracer.close()


def add_demo_arguments(parser) -> None:
    """The demo's own command-line options (moderngl-window adds its window options beside them).

    ``--size WxH`` is taken by :func:`image_size_argv` before parsing (moderngl-window's ``--size`` is
    the window's, which follows from the image size and ``--scale``)."""
    d = FilterParams()
    g = parser.add_argument_group("demo")
    g.add_argument("--width", type=int, default=64, help="image width in pixels (default 64)")
    g.add_argument("--height", type=int, default=64, help="image height in pixels (default 64)")
    g.add_argument("--scale", type=int, default=0,
                   help=f"panel zoom factor, 0 = the largest with the window at most {MAX_WINDOW_WIDTH} pixels "
                        "wide (default 0: 4 at 64x64, 2 at 128x128)")
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
    g.add_argument("--adaptive", action=argparse.BooleanOptionalAction, default=d.adaptive,
                   help="per-pixel bandwidth selection (sharper, about 3x the filter time; default off)")
    g.add_argument("--exposure", type=float, default=1.0)
    g.add_argument("--threads", type=int, default=1,
                   help="torch threads for the filter, 0 = torch's default (default 1: the images are small)")
    g.add_argument("--paused", action="store_true", help="start with playback paused")
    g.add_argument("--headless", action="store_true", help="EGL headless window (no display needed)")
    g.add_argument("--frames", type=int, default=0, help="stop after N frames (0 = run until closed)")
    g.add_argument("--screenshot", default=None, help="save the final window image to this PNG")
    g.add_argument("--stats", default=None,
                   help="write iterations per second and median ms per stage (trace, filter, display) to this "
                        "JSON file at the end")
    g.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=True,
                   help="trace the next iteration while this one is filtered (default on; --no-overlap traces "
                        "in turn, for comparison)")


def validate_args(args) -> None:
    """Bad option values -> ValueError naming the option and what was expected."""
    for name in ("width", "height"):
        if not 8 <= getattr(args, name) <= 4096:
            raise ValueError(f"--{name}: expected 8..4096 pixels, got {getattr(args, name)}")
    if not 0 <= args.scale <= 16:
        raise ValueError(f"--scale: expected 1..16, or 0 for the largest that fits, got {args.scale}")
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
                 temporal_mode=args.temporal_mode, adaptive=args.adaptive)


def image_size_argv(argv: list[str]) -> list[str]:
    """``--size WxH`` (or ``--size=WxH``) -> ``--width W --height H``; the rest of ``argv`` unchanged."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        if a == "--size" or a.startswith("--size="):
            value = a.split("=", 1)[1] if "=" in a else (argv[i + 1] if i + 1 < len(argv) else "")
            i += 1 if "=" in a else 2
            w, _, h = value.lower().partition("x")
            if not (w.isdigit() and h.isdigit()):
                raise ValueError(f"--size: expected WIDTHxHEIGHT in pixels, e.g. 128x128, got {value!r}")
            out += ["--width", w, "--height", h]
            continue
        out.append(a)
        i += 1
    return out


def create_app(argv: list[str]) -> DemoApp:
    """Parse ``argv`` (demo + moderngl-window options), open the window (headless if asked), build the app."""
    argv = image_size_argv(list(argv))
    pre = argparse.ArgumentParser(add_help=False)
    add_demo_arguments(pre)
    args, _ = pre.parse_known_args(argv)
    validate_args(args)
    if args.scale == 0:  # resolved once here: the window's size and the app's layout both read --scale
        args.scale = Layout.fitting_scale(args.width)
        argv += ["--scale", str(args.scale)]
    extra = []
    window_flag = any(a in ("-wnd", "--window") or a.startswith("--window=") for a in argv)
    asks_help = any(a in ("-h", "--help") for a in argv)  # moderngl-window prints the help and exits
    if not (args.headless or window_flag or asks_help) and not (os.environ.get("DISPLAY") or
                                                               os.environ.get("WAYLAND_DISPLAY")):
        raise ValueError("no display (DISPLAY is not set): use --headless, or run under xvfb-run")
    if args.headless:
        extra += ["--window", "headless", "--backend", "egl"]
    w, h = Layout(args.width, args.height, scale=args.scale).window_size
    extra += ["--size", f"{w}x{h}"]
    return moderngl_window.create_window_config_instance(DemoApp, args=list(argv) + extra)


def run(argv: list[str]) -> DemoApp:
    """Run the demo until the window closes or ``--frames`` frames were drawn; save ``--screenshot`` and
    ``--stats``."""
    app = create_app(argv)
    args = app.argv
    window, timer = app.wnd, app.timer
    timer.start()
    try:
        while not window.is_closing:
            current, delta = timer.next_frame()
            window.use()  # the app clears the window itself, inside its display time
            window.render(current, delta)
            if args.frames and app.frames_drawn >= args.frames:
                if args.screenshot:
                    app.screenshot(args.screenshot)
                break
            if not window.is_closing:
                window.swap_buffers()
        if args.stats:
            app.write_stats(args.stats)
    finally:
        timer.stop()
        app.on_close()
        window.destroy()
    return app
