"""GL side of the demo: window layout and the panel renderer.

The engine's estimates of every row (clip frames and tracked in-between times) travel to the GPU as
one RGB float texture array, written once per iteration straight from the engine's state (no
per-panel CPU work); the reference is uploaded once per progression. Tone mapping, the blend between
rows for a shown in-between time and the error heat map all happen in the fragment shader, at image
resolution into a small framebuffer that one more draw magnifies into the window.
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

#: The default zoom keeps the window this wide at most: it fits a 1366-pixel laptop screen, and on
#: llvmpipe the display's cost is its window pixels (magnify, clear, text).
MAX_WINDOW_WIDTH = 1280


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

    @staticmethod
    def fitting_scale(image_width: int, n_panels: int = 4, max_width: int = MAX_WINDOW_WIDTH) -> int:
        """The largest panel zoom whose window is at most ``max_width`` pixels wide (at least 1)."""
        scale = 1
        while Layout(image_width, 1, scale + 1, n_panels).window_size[0] <= max_width:
            scale += 1
        return scale

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

        def stage(*defines: str) -> str:
            lines = ["#version 330", *(f"#define {d}" for d in (f"N_PANELS {n_panels}", *defines))]
            return "\n".join(lines) + "\n" + source

        # per mode, a program that reads one row (a clip frame shown) and one that blends two (a time
        # between frames): the second texel fetch is a sixth of pass 1's time on llvmpipe
        self.programs = [[ctx.program(vertex_shader=stage("VERTEX_SHADER"),
                                      fragment_shader=stage("FRAGMENT_SHADER", f"MODE {mode}", f"BLEND {b}"))
                          for b in (0, 1)]
                         for mode in (MODE_IMAGE, MODE_DISPLAY, MODE_HEAT)]
        self.magnify = ctx.program(vertex_shader=stage("VERTEX_SHADER", "MAGNIFY"),
                                   fragment_shader=stage("FRAGMENT_SHADER", "MAGNIFY"))
        quad = np.array([0, 0, 1, 0, 0, 1, 1, 1], dtype="f4")
        self.vbo = ctx.buffer(quad.tobytes())
        self.vaos = [[ctx.vertex_array(p, [(self.vbo, "2f", "in_pos")]) for p in pair]
                     for pair in self.programs]
        # two triangles per panel: (clip-space x, y, u, v) per vertex, rewritten when the viewports change
        self.magnify_vbo = ctx.buffer(reserve=n_panels * 6 * 4 * 4, dynamic=True)
        self.magnify_vao = ctx.vertex_array(self.magnify, [(self.magnify_vbo, "2f 2f", "in_pos", "in_uv")])
        self._magnify_key = None
        self.estimates = None  # RGB float layers (rows * 3 estimates), HDR: tone mapped in the shader
        self.rows = 0
        self.reference = self._planes(1)  # placeholder until a reference arrives
        self.view = ctx.texture((image_width, image_height), 3, dtype="f4")
        self.small = ctx.texture((image_width * n_panels, image_height), 4)
        self.small_fbo = ctx.framebuffer(color_attachments=[self.small])
        for tex in (self.view, self.small):
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            tex.repeat_x = tex.repeat_y = False
        for prog in (p for pair in self.programs for p in pair):
            for name, value in (("u_estimates", 0), ("u_reference", 1), ("u_view", 2), ("u_heat_gain", 5.0)):
                if name in prog:  # the compiler drops what a mode does not use
                    prog[name] = value
        self.magnify["u_small"] = 3
        self.has_reference = False
        self.uploads = 0  # texture writes of estimates so far (one per iteration)

    def _planes(self, layers: int) -> moderngl.TextureArray:
        w, h = self.image_size
        tex = self.ctx.texture_array((w, h, layers), 3, dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return tex

    def upload_estimates(self, planes: torch.Tensor) -> None:
        """One write per iteration: ``planes`` is float32 ``(rows, len(SLOTS), H, W, 3)`` (RGB texels)."""
        w, h = self.image_size
        if planes.dim() != 5 or tuple(planes.shape[1:]) != (len(SLOTS), h, w, 3) or \
                planes.dtype != torch.float32:
            raise ValueError(f"estimates: expected float32 (rows, {len(SLOTS)}, {h}, {w}, 3), got "
                             f"{planes.dtype} {tuple(planes.shape)}")
        rows = planes.shape[0]
        if self.estimates is None or rows != self.rows:
            if self.estimates is not None:
                self.estimates.release()
            self.estimates, self.rows = self._planes(rows * len(SLOTS)), rows
        self.estimates.write(planes.contiguous().numpy())  # RGB texels: one fetch each
        self.uploads += 1

    def upload_reference(self, frames: torch.Tensor | None) -> None:
        """Reference frames ``(T, 3, H, W)`` for the heat map (once per run), or None (no heat map)."""
        self.has_reference = frames is not None
        if frames is not None:
            w, h = self.image_size
            if frames.dim() != 4 or tuple(frames.shape[1:]) != (3, h, w):
                raise ValueError(f"reference: expected (T, 3, {h}, {w}), got {tuple(frames.shape)}")
            self.reference.release()
            self.reference = self._planes(frames.shape[0])
            self.reference.write(frames.float().permute(0, 2, 3, 1).contiguous().numpy())

    def upload_view(self, image: torch.Tensor) -> None:
        """A display-ready ``(3, H, W)`` image in [0, 1] (a feature buffer) for :data:`MODE_DISPLAY`."""
        self.view.write(image.permute(1, 2, 0).float().contiguous().numpy())

    def draw_panels(self, panels, rows: tuple[int, int], blend: float, ref_frame: int | None,
                    exposure: float) -> None:
        """Pass 1: ``panels`` = [(mode, estimate index)] left to right, at image resolution; one draw per run
        of adjacent panels of one mode. A panel of mode None, or a heat map with no reference at this time,
        is black."""
        if self.estimates is None:
            return
        if len(panels) != self.n_panels:
            raise ValueError(f"panels: expected {self.n_panels} (mode, estimate) pairs, got {len(panels)}")
        no_heat = ref_frame is None or not self.has_reference
        modes = [None if mode == MODE_HEAT and no_heat else mode for mode, _ in panels]
        w, h = self.image_size
        self.small_fbo.use()
        self.estimates.use(0)
        self.reference.use(1)
        self.view.use(2)
        values = {"u_rows": rows, "u_blend": float(blend), "u_exposure": float(exposure),
                  "u_ref_frame": -1 if ref_frame is None else int(ref_frame),
                  "u_estimate": [int(estimate) for _, estimate in panels]}
        blends = int(rows[0] != rows[1] and blend > 0)
        start = 0
        for end in range(1, len(modes) + 1):
            if end < len(modes) and modes[end] == modes[start]:
                continue
            viewport = (start * w, 0, (end - start) * w, h)
            if modes[start] is None:
                self.small_fbo.clear(0.0, 0.0, 0.0, 1.0, viewport=viewport)
            else:
                prog = self.programs[modes[start]][blends]
                for name, value in values.items():
                    if name in prog:
                        prog[name] = value
                self.small_fbo.viewport = viewport
                self.vaos[modes[start]][blends].render(moderngl.TRIANGLE_STRIP)
            start = end

    def draw_magnified(self, fbo, viewports, buffer_size: tuple[int, int]) -> None:
        """Pass 2, one draw: panel ``i`` of pass 1 into ``viewports[i]`` of ``fbo`` (nearest); ``fbo`` is
        ``buffer_size`` pixels."""
        if len(viewports) != self.n_panels:
            raise ValueError(f"viewports: expected {self.n_panels}, got {len(viewports)}")
        key = (tuple(map(tuple, viewports)), tuple(buffer_size))
        if key != self._magnify_key:
            self._magnify_key = key
            self.magnify_vbo.write(magnify_vertices(viewports, buffer_size, self.n_panels).tobytes())
        fbo.use()
        self.ctx.viewport = (0, 0, *buffer_size)
        self.small.use(3)
        self.magnify_vao.render(moderngl.TRIANGLES)

    def release(self) -> None:
        for obj in (*(v for pair in self.vaos for v in pair), self.magnify_vao, self.vbo, self.magnify_vbo,
                    *(p for pair in self.programs for p in pair), self.magnify,
                    self.estimates, self.reference, self.view, self.small_fbo, self.small):
            if obj is not None:
                obj.release()


def magnify_vertices(viewports, buffer_size: tuple[int, int], n_panels: int) -> np.ndarray:
    """Two triangles per panel, ``(n_panels * 6, 4)`` float32 rows of (clip x, clip y, u, v): panel ``i``
    of the small image (columns ``[i / n, (i + 1) / n)`` of its texture) over ``viewports[i]`` = (x, y, w, h)
    in framebuffer pixels, GL origin."""
    corners = np.array([(0, 0), (1, 0), (0, 1), (0, 1), (1, 0), (1, 1)], np.float32)
    out = np.empty((len(viewports), 6, 4), np.float32)
    size = np.asarray(buffer_size, np.float32)
    for i, (x, y, w, h) in enumerate(viewports):
        out[i, :, :2] = (np.array([x, y], np.float32) + corners * (w, h)) / size * 2.0 - 1.0
        out[i, :, 2] = (i + corners[:, 0]) / n_panels
        out[i, :, 3] = corners[:, 1]
    return out.reshape(-1, 4)
