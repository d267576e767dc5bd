"""GL side of the demo: window layout and the panel renderer.

The engine's estimates of every row (clip frames and tracked in-between times) travel to the GPU as
one float texture array, written once per iteration straight from the engine's state (no per-panel
CPU work); the reference is uploaded once per progression. Tone mapping, the blend between rows for a
shown in-between time and the error heat map all happen in the fragment shader, at image resolution
into a small framebuffer that is then magnified into the window.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np
import torch

SHADER_PATH = Path(__file__).with_name("shaders") / "panel.glsl"

#: Panel slots (estimates) in the uploaded texture array, left to right.
SLOTS = ("raw", "gaussian", "ours")

MODE_IMAGE, MODE_DISPLAY, MODE_HEAT = 0, 1, 2


@dataclass(frozen=True)
class Layout:
    """Pixel layout of the window: a row of panels, a label strip above them, a plot and text below.

    Coordinates are top-left based ``(x, y, w, h)`` in window pixels; :meth:`gl_viewport` converts
    them for GL, whose origin is bottom-left.
    """

    image_width: int
    image_height: int
    scale: int = 2
    n_panels: int = 4
    label_height: int = 22
    bottom_height: int = 210
    gap: int = 4

    @property
    def panel_size(self) -> tuple[int, int]:
        return self.image_width * self.scale, self.image_height * self.scale

    @property
    def window_size(self) -> tuple[int, int]:
        pw, ph = self.panel_size
        width = self.n_panels * pw + (self.n_panels + 1) * self.gap
        # The bottom strip holds the plot and the text; keep it wide enough to be legible.
        width = max(width, 720)
        return width, self.label_height + ph + self.gap + self.bottom_height

    def panel_rect(self, index: int) -> tuple[int, int, int, int]:
        pw, ph = self.panel_size
        return self.gap + index * (pw + self.gap), self.label_height, pw, ph

    def plot_rect(self) -> tuple[int, int, int, int]:
        width, height = self.window_size
        top = self.label_height + self.panel_size[1] + self.gap
        return self.gap, top, min(360, width // 2) - self.gap, height - top - self.gap

    def text_rect(self) -> tuple[int, int, int, int]:
        width, height = self.window_size
        px, top, pw, ph = self.plot_rect()
        left = px + pw + 2 * self.gap
        return left, top, width - left - self.gap, ph

    def timeline_span(self) -> tuple[int, int, int]:
        """(x0, x1, y) of the clip bar drawn at the bottom of the stats block."""
        tx, ty, tw, th = self.text_rect()
        return tx + 16, tx + tw - 16, ty + th - 18

    def uv_rect(self, rect: tuple[int, int, int, int]) -> tuple[float, float, float, float]:
        """Window rect -> (u, v, du, dv) of the window-sized overlay texture (v from the top)."""
        width, height = self.window_size
        x, y, w, h = rect
        return x / width, y / height, w / width, h / height

    def gl_viewport(self, rect: tuple[int, int, int, int], buffer_size: tuple[int, int]) -> tuple[int, int, int, int]:
        """Top-left window rect -> GL viewport in framebuffer pixels (handles HiDPI buffers)."""
        width, height = self.window_size
        sx, sy = buffer_size[0] / width, buffer_size[1] / height
        x, y, w, h = rect
        return (round(x * sx), round((height - y - h) * sy), round(w * sx), round(h * sy))


class PanelRenderer:
    """Draws the panels into the current framebuffer.

    Args:
        ctx: the window's moderngl context.
        image_width, image_height: size of one image, in pixels.
        n_panels: panels in the row (the estimates, then the heat map).
    """

    def __init__(self, ctx: moderngl.Context, image_width: int, image_height: int, n_panels: int = 4):
        self.ctx = ctx
        self.image_size = (image_width, image_height)
        self.n_panels = n_panels
        source = SHADER_PATH.read_text()
        vs = "#version 330\n#define VERTEX_SHADER\n" + source
        self.programs = [ctx.program(vertex_shader=vs, fragment_shader=f"#version 330\n#define FRAGMENT_SHADER\n"
                                     f"#define MODE {mode}\n" + source) for mode in (MODE_IMAGE, MODE_DISPLAY, MODE_HEAT)]
        self.magnify = ctx.program(vertex_shader=vs, fragment_shader="#version 330\n#define FRAGMENT_SHADER\n"
                                   "#define MAGNIFY\n" + source)
        quad = np.array([0, 0, 1, 0, 0, 1, 1, 1], dtype="f4")
        self.vbo = ctx.buffer(quad.tobytes())
        self.vaos = [ctx.vertex_array(p, [(self.vbo, "2f", "in_pos")]) for p in self.programs]
        self.magnify_vao = ctx.vertex_array(self.magnify, [(self.vbo, "2f", "in_pos")])
        self.estimates = None  # float planes (rows * 3 estimates * 3 channels), HDR: tone mapped in the shader
        self.rows = 0
        self.reference = self._planes(3)  # placeholder until a reference arrives
        self.view = ctx.texture((image_width, image_height), 3, dtype="f4")
        self.small = ctx.texture((image_width * n_panels, image_height), 4)
        self.small_fbo = ctx.framebuffer(color_attachments=[self.small])
        for tex in (self.view, self.small):
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            tex.repeat_x = tex.repeat_y = False
        for prog in self.programs:
            for name, value in (("u_estimates", 0), ("u_reference", 1), ("u_view", 2), ("u_heat_gain", 5.0)):
                if name in prog:  # the compiler drops what a mode does not use
                    prog[name] = value
        self.magnify["u_small"] = 3
        self.has_reference = False
        self.uploads = 0  # texture writes of estimates so far (one per iteration)

    def _planes(self, layers: int) -> moderngl.TextureArray:
        w, h = self.image_size
        tex = self.ctx.texture_array((w, h, layers), 1, dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return tex

    def upload_estimates(self, planes: torch.Tensor) -> None:
        """One write per iteration: ``planes`` is float32 ``(rows, len(SLOTS), 3, H, W)``."""
        w, h = self.image_size
        if planes.dim() != 5 or tuple(planes.shape[1:]) != (len(SLOTS), 3, h, w) or planes.dtype != torch.float32:
            raise ValueError(f"estimates: expected float32 (rows, {len(SLOTS)}, 3, {h}, {w}), got "
                             f"{planes.dtype} {tuple(planes.shape)}")
        rows = planes.shape[0]
        if self.estimates is None or rows != self.rows:
            if self.estimates is not None:
                self.estimates.release()
            self.estimates, self.rows = self._planes(rows * len(SLOTS) * 3), rows
        self.estimates.write(planes.contiguous().numpy())
        self.uploads += 1

    def upload_reference(self, frames: torch.Tensor | None) -> None:
        """Reference frames ``(T, 3, H, W)`` for the heat map (once per run), or None (no heat map)."""
        self.has_reference = frames is not None
        if frames is not None:
            w, h = self.image_size
            if frames.dim() != 4 or tuple(frames.shape[1:]) != (3, h, w):
                raise ValueError(f"reference: expected (T, 3, {h}, {w}), got {tuple(frames.shape)}")
            self.reference.release()
            self.reference = self._planes(frames.shape[0] * 3)
            self.reference.write(frames.float().contiguous().numpy())

    def upload_view(self, image: torch.Tensor) -> None:
        """A display-ready ``(3, H, W)`` image in [0, 1] (a feature buffer) for :data:`MODE_DISPLAY`."""
        self.view.write(image.permute(1, 2, 0).float().contiguous().numpy())

    def draw_panels(self, panels, rows: tuple[int, int], blend: float, ref_frame: int | None,
                    exposure: float) -> None:
        """Pass 1: ``panels`` = [(mode, estimate index)] left to right, at image resolution."""
        if self.estimates is None:
            return
        w, h = self.image_size
        self.small_fbo.use()
        self.small_fbo.clear(0.0, 0.0, 0.0, 1.0)
        self.estimates.use(0)
        self.reference.use(1)
        self.view.use(2)
        values = {"u_rows": rows, "u_blend": float(blend), "u_exposure": float(exposure),
                  "u_ref_frame": -1 if ref_frame is None else int(ref_frame)}
        for i, (mode, estimate) in enumerate(panels):
            if mode is None or (mode == MODE_HEAT and (ref_frame is None or not self.has_reference)):
                continue  # left black: no reference at this time
            self.small_fbo.viewport = (i * w, 0, w, h)
            prog = self.programs[mode]
            for name, value in dict(values, u_estimate=estimate).items():
                if name in prog:
                    prog[name] = value
            self.vaos[mode].render(moderngl.TRIANGLE_STRIP)

    def draw_magnified(self, fbo, viewports) -> None:
        """Pass 2: panel ``i`` of pass 1 into ``viewports[i]`` of ``fbo`` (nearest)."""
        fbo.use()
        self.small.use(3)
        n = self.n_panels
        for i, viewport in enumerate(viewports):
            self.ctx.viewport = viewport
            self.magnify["u_sub"] = (i / n, 0.0, 1.0 / n, 1.0)
            self.magnify_vao.render(moderngl.TRIANGLE_STRIP)

    def release(self) -> None:
        for obj in (*self.vaos, self.magnify_vao, self.vbo, *self.programs, self.magnify, self.estimates, self.reference, self.view, self.small_fbo,
                    self.small):
            if obj is not None:
                obj.release()
