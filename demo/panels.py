"""GL side of the demo: window layout and the panel renderer.

The images of one displayed frame (raw average, Gaussian-filtered, ours) travel to the GPU as one
packed float texture, written once per frame; the reference is uploaded once per progression and the
error heat map is computed from both in the fragment shader.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

SHADER_PATH = Path(__file__).with_name("shaders") / "panel.glsl"

#: Panel slots in the packed image texture, left to right.
SLOTS = ("raw", "gaussian", "ours")

MODE_IMAGE, MODE_DISPLAY, MODE_HEAT, MODE_OVERLAY = 0, 1, 2, 3


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
    """Draws the panels and the overlay into the current framebuffer.

    Args:
        ctx: the window's moderngl context (the tracer renders in the same one).
        image_width, image_height: size of one image (one slot), in pixels.
    """

    def __init__(self, ctx: moderngl.Context, image_width: int, image_height: int):
        self.ctx = ctx
        self.image_size = (image_width, image_height)
        source = SHADER_PATH.read_text()
        self.program = ctx.program(
            vertex_shader="#version 330\n#define VERTEX_SHADER\n" + source,
            fragment_shader="#version 330\n#define FRAGMENT_SHADER\n" + source,
        )
        quad = np.array([0, 0, 1, 0, 0, 1, 1, 1], dtype="f4")
        self.vbo = ctx.buffer(quad.tobytes())
        self.vao = ctx.vertex_array(self.program, [(self.vbo, "2f", "in_pos")])
        # Float textures keep HDR radiance; tone mapping happens in the shader.
        self.images = ctx.texture((image_width * len(SLOTS), image_height), 3, dtype="f4")
        self.reference = ctx.texture((image_width, image_height), 3, dtype="f4")
        self.reference.write(np.zeros((image_height, image_width, 3), "f4").tobytes())
        for tex in (self.images, self.reference):
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            tex.repeat_x = tex.repeat_y = False
        self.overlay = None
        self.program["u_image"] = 0
        self.program["u_reference"] = 1
        self.program["u_overlay"] = 2
        self.program["u_exposure"] = 1.0
        self.program["u_heat_gain"] = 5.0
        self.has_reference = False

    def upload_images(self, packed: np.ndarray) -> None:
        """One write per frame: ``packed`` is float32 ``(H, len(SLOTS) * W, 3)``, top row first."""
        w, h = self.image_size
        expected = (h, w * len(SLOTS), 3)
        if packed.shape != expected or packed.dtype != np.float32:
            raise ValueError(f"packed images: expected float32 {expected}, got {packed.dtype} {packed.shape}")
        self.images.write(np.ascontiguousarray(packed))

    def upload_reference(self, image: np.ndarray | None) -> None:
        """Reference frame ``(H, W, 3)`` float32 for the heat map, or None to hide the heat map."""
        self.has_reference = image is not None
        if image is not None:
            self.reference.write(np.ascontiguousarray(image, dtype=np.float32))

    def upload_overlay(self, rgba: np.ndarray) -> None:
        """RGBA8 ``(H, W, 4)`` layer drawn over the whole window."""
        h, w = rgba.shape[:2]
        if self.overlay is None or self.overlay.size != (w, h):
            if self.overlay is not None:
                self.overlay.release()
            self.overlay = self.ctx.texture((w, h), 4, dtype="f1")
            self.overlay.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.overlay.write(np.ascontiguousarray(rgba))

    def draw_panel(self, viewport, slot: int, mode: int, exposure: float = 1.0) -> None:
        self.ctx.viewport = viewport
        self.images.use(0)
        self.reference.use(1)
        self.program["u_slot"] = (float(slot), float(len(SLOTS)))
        self.program["u_mode"] = mode
        self.program["u_exposure"] = exposure
        self.vao.render(moderngl.TRIANGLE_STRIP)

    def draw_overlay(self, viewport, uv_rect=(0.0, 0.0, 1.0, 1.0)) -> None:
        """Blend the overlay's ``uv_rect`` (u, v, du, dv; v from the top) into ``viewport``."""
        if self.overlay is None:
            return
        self.ctx.viewport = viewport
        self.overlay.use(2)
        self.program["u_mode"] = MODE_OVERLAY
        self.program["u_sub"] = tuple(float(x) for x in uv_rect)
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
        self.vao.render(moderngl.TRIANGLE_STRIP)
        self.ctx.disable(moderngl.BLEND)

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.program, self.images, self.reference, self.overlay):
            if obj is not None:
                obj.release()
