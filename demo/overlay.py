"""The 2D layer of the demo, drawn on the GPU: panel labels, stats, the PSNR plot, the clip bar, help.

Glyphs of PIL's default font are rendered once into an atlas texture; a frame's text, boxes and lines
are then a few small arrays of quads and line segments (a string's quads are cached, so a line that
did not change costs a lookup), drawn with two draw calls. Nothing is rasterised on the CPU per frame,
so the numbers can change every iteration at no cost. The layer comes in two parts: a backdrop of what
changes with the settings alone (:func:`draw_backdrop`, drawn into a cached framebuffer that each frame
copies into the window in place of a clear) and what changes every iteration or frame (:func:`draw_live`).
"""
from __future__ import annotations

import math
from functools import lru_cache

import moderngl
import numpy as np
from PIL import Image, ImageDraw, ImageFont

#: Line colours of the three methods in the plot (and their labels).
CURVE_COLOURS = {"raw": (170, 170, 170), "gaussian": (90, 160, 255), "ours": (255, 150, 40)}
TEXT = (235, 235, 235, 255)
DIM = (150, 150, 150, 255)
#: The window's background (its clear colour); boxes are outlines on it.
BACKGROUND = (15, 15, 18, 255)
AXIS = (120, 120, 130, 255)
SIZES = (11, 12, 13)
PLOT_TITLE = "PSNR (dB, clamped sRGB) vs iteration"
FIRST, LAST = 32, 127  # printable ASCII; other characters draw as "?"


@lru_cache(maxsize=8)
def font(size: int = 13) -> ImageFont.FreeTypeFont:
    return ImageFont.load_default(size=size)


class GlyphAtlas:
    """Every printable ASCII glyph of :data:`SIZES` in one alpha image, plus an opaque cell for boxes.

    Attributes:
        image: ``(H, W)`` uint8 alpha.
        cells: ``cells[size]`` is ``(96, 4)`` float32 ``(u0, v0, u1, v1)``: each character's ink box in
            the atlas, in pixels.
        ink: ``ink[size]`` is ``(96, 4)`` float32 ``(x, y, w, h)``: that box relative to the character's
            origin (its top-left at the pen position); empty for a space.
        advance: ``advance[size]`` is ``(96,)`` pen advance in pixels (PIL's ``getlength``).
        cell_size: ``cell_size[size]`` = (w, h) of every cell of that size.
        glyph_quads: ``glyph_quads[size]`` is ``(96, 8)`` float32: ``ink`` then ``cells``, each character's
            quad with its pen at 0; ``has_ink[size]`` ``(96,)`` bool: whether it draws anything.
        solid: (u0, v0, u1, v1) of an opaque patch.
    """

    def __init__(self):
        chars = [chr(c) for c in range(FIRST, LAST)]
        self.cells, self.ink, self.advance, self.cell_size = {}, {}, {}, {}
        self.glyph_quads, self.has_ink = {}, {}
        rows, y = [], 4  # the first 4 pixel rows hold the solid patch
        for size in SIZES:
            f = font(size)
            cw = max(max(f.getbbox(c)[2] for c in chars), 1) + 1
            ch = max(f.getbbox(c)[3] for c in chars) + 1
            self.cell_size[size] = (cw, ch)
            self.advance[size] = np.array([f.getlength(c) for c in chars], np.float32)
            per_row = 32
            alpha = np.zeros((ch * -(-len(chars) // per_row), cw * per_row), np.uint8)
            cells = np.zeros((len(chars), 4), np.float32)
            ink = np.zeros((len(chars), 4), np.float32)
            for i, c in enumerate(chars):
                # each glyph drawn alone, so no neighbour's overhang lands in its cell
                glyph = Image.new("L", (cw, ch), 0)
                ImageDraw.Draw(glyph).text((0, 0), c, font=f, fill=255)
                glyph = np.asarray(glyph)
                cx, cy = (i % per_row) * cw, (i // per_row) * ch
                alpha[cy:cy + ch, cx:cx + cw] = glyph
                # a glyph's quad covers its ink only: on llvmpipe the overlay costs the pixels it blends
                cols, lines = np.nonzero(glyph.any(0))[0], np.nonzero(glyph.any(1))[0]
                if len(cols):
                    x0, x1, y0, y1 = cols[0], cols[-1] + 1, lines[0], lines[-1] + 1
                    ink[i] = (x0, y0, x1 - x0, y1 - y0)
                    cells[i] = (cx + x0, y + cy + y0, cx + x1, y + cy + y1)
            self.cells[size], self.ink[size] = cells, ink
            # per character, its quad at the pen position (ink box, then atlas box) and whether it has ink
            self.glyph_quads[size] = np.concatenate([ink, cells], 1)
            self.has_ink[size] = (ink[:, 2] > 0) & (ink[:, 3] > 0)
            rows.append(alpha)
            y += alpha.shape[0]
        width = max(r.shape[1] for r in rows)
        self.image = np.zeros((y, width), np.uint8)
        self.image[:4, :4] = 255
        yy = 4
        for r in rows:
            self.image[yy:yy + r.shape[0], :r.shape[1]] = r
            yy += r.shape[0]
        self.solid = (1.0, 1.0, 3.0, 3.0)

    def layout(self, text: str, size: int, max_width: float | None = None) -> tuple[np.ndarray, float]:
        """Quads ``(n, 8)`` = (x, y, w, h, u0, v0, u1, v1) of ``text`` with its origin at (0, 0), and its
        width; characters that would end beyond ``max_width`` are cut."""
        return _layout(self, text, size, max_width)


#: Latin-1 code -> glyph index (characters outside printable ASCII draw as "?").
_GLYPH_OF = np.full(256, ord("?") - FIRST, np.intp)
_GLYPH_OF[FIRST:LAST] = np.arange(LAST - FIRST)


@lru_cache(maxsize=4096)
def _layout(atlas: GlyphAtlas, text: str, size: int, max_width: float | None) -> tuple[np.ndarray, float]:
    # a few whole-array steps: the stats lines are new strings every iteration
    idx = _GLYPH_OF[np.frombuffer(text.encode("latin-1", "replace"), np.uint8)]
    pen = np.zeros(len(idx) + 1, np.float32)
    np.cumsum(atlas.advance[size][idx], out=pen[1:])
    keep = len(idx) if max_width is None else int(np.searchsorted(pen[1:], max_width, side="right"))
    inked = atlas.has_ink[size][idx[:keep]]  # spaces draw nothing
    quads = atlas.glyph_quads[size][idx[:keep][inked]]
    quads[:, 0] += np.round(pen[:keep][inked])
    quads.setflags(write=False)
    return quads, float(pen[keep])


@lru_cache(maxsize=64)
def _rgba(fill: tuple) -> np.ndarray:
    """An 8-bit colour as float32 in [0, 1]."""
    return np.asarray(fill, np.float32) / 255.0


@lru_cache(maxsize=4096)
def _placed_text(atlas: GlyphAtlas, x: int, y: int, text: str, size: int, fill: tuple,
                 max_width: float | None) -> tuple[np.ndarray, float]:
    """(quads ``(n, 12)`` of ``text`` at (x, y) in ``fill``, width): most strings repeat every frame."""
    quads, width = atlas.layout(text, size, max_width)
    out = np.empty((len(quads), 12), np.float32)
    out[:, :8] = quads
    out[:, :2] += np.array((x, y), np.float32)
    out[:, 8:] = _rgba(fill)
    out.setflags(write=False)
    return out, width


class Canvas:
    """A frame's 2D layer as arrays: coloured quads (text and boxes) and coloured line segments.

    Coordinates are window pixels, top-left origin. Nothing is drawn until :meth:`OverlayRenderer.draw`.
    """

    def __init__(self, atlas: GlyphAtlas):
        self.atlas = atlas
        self._quads: list[np.ndarray] = []
        self._lines: list[np.ndarray] = []

    def text(self, xy, text: str, size: int = 12, fill=TEXT, max_width: float | None = None) -> float:
        """Draw ``text`` with its top-left at ``xy``; returns its width in pixels."""
        quads, width = _placed_text(self.atlas, round(xy[0]), round(xy[1]), text, size, tuple(fill), max_width)
        if len(quads):
            self._quads.append(quads)
        return width

    def extend(self, other: "Canvas") -> None:
        """Add everything drawn on ``other`` (e.g. a cached part)."""
        self._quads += other._quads
        self._lines += other._lines

    def rect(self, x, y, w, h, fill) -> None:
        self._quads.append(np.array([[x, y, w, h, *self.atlas.solid, *_rgba(tuple(fill))]], np.float32))

    def box(self, x, y, w, h, fill=None, outline=(80, 80, 90, 255)) -> None:
        """A box outline, filled with ``fill`` when given (quads draw in order, so what is drawn after it
        lies on top). The overlay's boxes are unfilled, on the window's background: on llvmpipe a filled
        box cost more than all the text."""
        if fill is not None:
            self.rect(x, y, w, h, fill)
        self.polyline([(x, y), (x + w, y), (x + w, y + h), (x, y + h), (x, y)], outline)

    def polyline(self, points, colour, thickness: int = 1) -> None:
        """Segments between consecutive ``points`` ((n, 2) pixels), ``thickness`` pixels thick downwards
        (core GL has no wide lines: each pixel row is a copy one pixel lower)."""
        p = np.asarray(points, np.float32).reshape(-1, 2)
        if len(p) < 2:
            return
        seg = np.empty((thickness, len(p) - 1, 2, 6), np.float32)
        seg[:, :, 0, :2], seg[:, :, 1, :2] = p[:-1], p[1:]
        seg[:, :, :, 1] += np.arange(thickness, dtype=np.float32)[:, None, None]
        seg[..., 2:] = _rgba(tuple(colour))
        self._lines.append(seg.reshape(-1, 6))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(quads ``(n, 12)``, line vertices ``(m, 6)``) float32."""
        q = np.concatenate(self._quads) if self._quads else np.zeros((0, 12), np.float32)
        ln = np.concatenate(self._lines) if self._lines else np.zeros((0, 6), np.float32)
        return q, ln


_QUAD_VS = """#version 330
uniform vec2 u_window;
uniform vec2 u_atlas;
in vec2 in_corner;
in vec4 in_rect;    // x, y, w, h (window pixels, top-left origin)
in vec4 in_uv;      // atlas pixels
in vec4 in_colour;
out vec2 uv;
out vec4 colour;
void main() {
    vec2 p = in_rect.xy + in_corner * in_rect.zw;
    uv = mix(in_uv.xy, in_uv.zw, in_corner) / u_atlas;
    colour = in_colour;
    gl_Position = vec4(p.x / u_window.x * 2.0 - 1.0, 1.0 - p.y / u_window.y * 2.0, 0.0, 1.0);
}
"""
_QUAD_FS = """#version 330
uniform sampler2D u_glyphs;
in vec2 uv;
in vec4 colour;
out vec4 frag;
void main() { frag = vec4(colour.rgb, colour.a * texture(u_glyphs, uv).r); }
"""
_LINE_VS = """#version 330
uniform vec2 u_window;
in vec2 in_pos;
in vec4 in_colour;
out vec4 colour;
void main() {
    colour = in_colour;
    vec2 p = in_pos + 0.5;  // pixel centres: integer coordinates name pixels
    gl_Position = vec4(p.x / u_window.x * 2.0 - 1.0, 1.0 - p.y / u_window.y * 2.0, 0.0, 1.0);
}
"""
_LINE_FS = """#version 330
in vec4 colour;
out vec4 frag;
void main() { frag = colour; }
"""


class OverlayRenderer:
    """Draws a :class:`Canvas` over the window: one instanced quad call, one line call (alpha blended).

    Filled boxes are quads of that call too.
    """

    def __init__(self, ctx: moderngl.Context, atlas: GlyphAtlas | None = None):
        self.ctx = ctx
        self.atlas = atlas or GlyphAtlas()
        h, w = self.atlas.image.shape
        self.glyphs = ctx.texture((w, h), 1, self.atlas.image.tobytes())
        self.glyphs.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.quad_prog = ctx.program(vertex_shader=_QUAD_VS, fragment_shader=_QUAD_FS)
        self.line_prog = ctx.program(vertex_shader=_LINE_VS, fragment_shader=_LINE_FS)
        self.quad_prog["u_atlas"] = (float(w), float(h))
        self.quad_prog["u_glyphs"] = 4
        self.corners = ctx.buffer(np.array([0, 0, 1, 0, 0, 1, 1, 1], "f4").tobytes())
        self.quads = ctx.buffer(reserve=12 * 4 * 1024, dynamic=True)
        self.lines = ctx.buffer(reserve=6 * 4 * 4096, dynamic=True)
        self._vaos()
        self._backdrop = self._backdrop_texture = self._backdrop_key = None

    def _vaos(self) -> None:
        self.quad_vao = self.ctx.vertex_array(self.quad_prog, [
            (self.corners, "2f", "in_corner"),
            (self.quads, "4f 4f 4f/i", "in_rect", "in_uv", "in_colour"),
        ])
        self.line_vao = self.ctx.vertex_array(self.line_prog, [(self.lines, "2f 4f", "in_pos", "in_colour")])

    def _fit(self, buf: moderngl.Buffer, data: np.ndarray) -> bool:
        if data.nbytes <= buf.size:
            return False
        buf.orphan(max(data.nbytes, 2 * buf.size))
        return True

    def draw(self, canvas: Canvas, window_size: tuple[int, int], viewport) -> None:
        quads, lines = canvas.arrays()
        grown = self._fit(self.quads, quads) | self._fit(self.lines, lines)
        if grown:
            self._vaos()
        self.ctx.viewport = viewport
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
        size = tuple(float(v) for v in window_size)
        if len(quads):
            self.quads.write(quads)
            self.glyphs.use(4)
            self.quad_prog["u_window"] = size
            self.quad_vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=len(quads))
        if len(lines):
            self.lines.write(lines)
            self.line_prog["u_window"] = size
            self.line_vao.render(moderngl.LINES, vertices=len(lines))
        self.ctx.disable(moderngl.BLEND)

    def draw_backdrop(self, fbo: moderngl.Framebuffer, key, build, window_size: tuple[int, int]) -> None:
        """Fill ``fbo`` with the backdrop: the background colour and the overlay's rarely changing part,
        ``build()`` (a :class:`Canvas`, see :func:`draw_backdrop`), drawn into a cached framebuffer of
        ``fbo``'s size when ``key`` (everything ``build`` reads) changes, and copied into ``fbo`` each
        frame. The copy costs what the window's clear did; the text it holds is not built or drawn again."""
        if self._backdrop is None or self._backdrop.size != fbo.size:
            if self._backdrop is not None:
                self._backdrop.release()
                self._backdrop_texture.release()
            self._backdrop_texture = self.ctx.texture(fbo.size, 4)
            self._backdrop = self.ctx.framebuffer(color_attachments=[self._backdrop_texture])
            self._backdrop_key = None
        if key != self._backdrop_key:
            self._backdrop.use()
            self._backdrop.clear(*(c / 255.0 for c in BACKGROUND))
            self.draw(build(), window_size, (0, 0, *fbo.size))
            self._backdrop_key = key
        self.ctx.copy_framebuffer(fbo, self._backdrop)
        fbo.use()

    def release(self) -> None:
        for obj in (self.quad_vao, self.line_vao, self.quads, self.lines, self.corners, self.quad_prog,
                    self.line_prog, self.glyphs, self._backdrop, self._backdrop_texture):
            if obj is not None:
                obj.release()


class CurveArrays:
    """Growing curves (name -> [(iteration, value), ...], appended to) as arrays of their finite points.

    A call returns name -> ``(2, n)`` float64 (iterations, values) and converts only the points appended
    since the last call (a curve replaced by a new list, as on a restart, starts again): the plot's Python
    per frame does not grow with the run.
    """

    def __init__(self):
        self._state: dict[str, tuple[list, int, np.ndarray, int]] = {}

    def __call__(self, curves: dict[str, list[tuple[int, float]]]) -> dict[str, np.ndarray]:
        out = {}
        for name, curve in curves.items():
            source, seen, buf, n = self._state.get(name, (None, 0, np.empty((2, 0)), 0))
            if source is not curve or len(curve) < seen:
                seen, n = 0, 0
            new = [p for p in curve[seen:] if math.isfinite(p[1])]
            if new:
                if n + len(new) > buf.shape[1]:
                    grown = np.empty((2, max(2 * buf.shape[1], n + len(new), 64)))
                    grown[:, :n] = buf[:, :n]
                    buf = grown
                buf[:, n:n + len(new)] = np.asarray(new, np.float64).T
                n += len(new)
            self._state[name] = (curve, len(curve), buf, n)
            out[name] = buf[:, :n]
        return out


def plot_axes(curves: dict[str, np.ndarray]) -> tuple[int, float, float] | None:
    """The plot's axis ranges ``(max iteration, lo, hi)`` for ``curves`` (:class:`CurveArrays`' output), or
    None when there is no point.

    The x axis ends at a power of two and the y axis at whole dB beyond the values, so the ranges (and the
    cached frame drawn from them) change log2 times, not every iteration."""
    points = [c for c in curves.values() if c.shape[1]]
    if not points:
        return None
    last = max(float(c[0].max()) for c in points)
    max_it = 1 << (max(2, int(last)) - 1).bit_length()
    lo, hi = min(float(c[1].min()) for c in points), max(float(c[1].max()) for c in points)
    return max_it, float(math.floor(lo - 0.5)), float(math.ceil(hi + 0.5))


def draw_curves(canvas: Canvas, rect, curves: dict[str, np.ndarray],
                axes: tuple[int, float, float] | None) -> None:
    """The PSNR plot's curves inside ``rect`` = (x, y, w, h), log x (the frame is :func:`plot_frame`'s):
    ``curves`` is :class:`CurveArrays`' output, ``axes`` :func:`plot_axes`'; two pixels thick, with their
    legend (a curve of one point is a dot). A curve keeps its last point in each pixel column: on the log x
    axis late iterations share columns, and the segments drawn stay bounded by the plot's width however
    long the run (on llvmpipe each segment costs its own setup)."""
    if axes is None:
        return
    x0, y0, w, h = rect
    to_px = _plot_mapping(rect, *axes)
    legend_x = x0 + 46
    for name, (its, vals) in curves.items():
        colour = CURVE_COLOURS.get(name, (255, 255, 255)) + (255,)
        if len(its) >= 2:
            pts = to_px(its, vals)
            column = np.floor(pts[:, 0])
            canvas.polyline(pts[np.append(column[1:] != column[:-1], True)], colour, thickness=2)
        elif len(its):
            px, py = to_px(its[0], vals[0])
            canvas.rect(px - 2, py - 2, 4, 4, colour)
        label = f"{name} {vals[-1]:.1f}" if len(vals) else name
        legend_x += canvas.text((legend_x, y0 + 24), label, 11, colour) + 12


def _plot_mapping(rect, max_it: int, lo: float, hi: float):
    x0, y0, w, h = rect
    left, top, right, bottom = x0 + 40, y0 + 22, x0 + w - 8, y0 + h - 20

    def to_px(it, val):
        # log x so the fast early gains and the slow tail are both readable
        fx = np.log1p(np.asarray(it, np.float64) - 1) / np.log1p(max_it - 1)
        return np.stack([left + fx * (right - left), bottom - (np.asarray(val) - lo) / (hi - lo) * (bottom - top)], -1)
    return to_px


@lru_cache(maxsize=64)
def plot_frame(atlas: GlyphAtlas, rect, title: str, axes: tuple[int, float, float] | None) -> Canvas:
    """The plot's box, title, axes and ticks (or a note that there is no curve): they change only when
    the axis ranges do."""
    canvas = Canvas(atlas)
    x0, y0, w, h = rect
    canvas.box(x0, y0, w, h)
    canvas.text((x0 + 6, y0 + 3), title, 12, TEXT, w - 10)
    left, top, right, bottom = x0 + 40, y0 + 22, x0 + w - 8, y0 + h - 20
    if axes is None:
        canvas.text((left, top + 10), "no reference: no error curve", 12, DIM)
        return canvas
    max_it, lo, hi = axes
    to_px = _plot_mapping(rect, max_it, lo, hi)
    canvas.polyline([(left, top), (left, bottom), (right, bottom)], AXIS)
    for val in np.linspace(lo, hi, 4):
        _, py = to_px(1, val)
        canvas.polyline([(left - 3, py), (left, py)], AXIS)
        canvas.text((x0 + 4, py - 6), f"{val:.0f}", 11, DIM)
    for it in sorted({1, max_it} | {2**k for k in range(1, 12) if 2**k < max_it}):
        px, _ = to_px(it, lo)
        canvas.polyline([(px, bottom), (px, bottom + 3)], AXIS)
        canvas.text((px - 4, bottom + 4), str(it), 11, DIM)
    return canvas


def draw_backdrop(
    canvas: Canvas,
    labels: list[tuple[tuple[int, int], str, int]],
    plot_rect: tuple[int, int, int, int],
    axes: tuple[int, float, float] | None,
    text_rect: tuple[int, int, int, int],
    text_lines: list[str | None],
    timeline: tuple[list[float], tuple[int, int, int]] | None = None,
) -> Canvas:
    """The part of the overlay that changes rarely into ``canvas``: it is drawn once into the cached backdrop
    (:meth:`OverlayRenderer.draw_backdrop`), the live part (:func:`draw_live`) over it every frame.

    Args:
        labels: ((x, y), text, max width) panel titles.
        plot_rect, axes: the plot's place and axis ranges (:func:`plot_axes`): its frame.
        text_rect, text_lines: the stats block; the lines given (not None) are drawn here (the first line
            is highlighted).
        timeline: (frame times, (x0, x1, y)): the clip bar with a tick per frame, without its marker.
    """
    for (x, y), text, max_width in labels:
        canvas.text((x + 2, y + 3), text, 13, TEXT, max_width - 4)
    canvas.extend(plot_frame(canvas.atlas, tuple(plot_rect), PLOT_TITLE, axes))
    canvas.box(*text_rect)
    _text_block(canvas, text_rect, text_lines)
    if timeline is not None and len(timeline[0]) > 1:
        times, (x0, x1, y) = timeline
        canvas.rect(x0, y - 1, x1 - x0, 2, AXIS)
        for t in times:
            x = _timeline_x(times, (x0, x1), t)
            canvas.polyline([(x, y - 4), (x, y + 4)], (170, 170, 180, 255))
        canvas.text((x0 - 12, y + 4), f"{times[0]:g}", 11, DIM)
        canvas.text((x1 - 4, y + 4), f"{times[-1]:g}", 11, DIM)
    return canvas


def draw_live(
    canvas: Canvas,
    size: tuple[int, int],
    plot_rect: tuple[int, int, int, int],
    curves: dict[str, np.ndarray],
    axes: tuple[int, float, float] | None,
    text_rect: tuple[int, int, int, int],
    text_lines: list[str | None],
    help_lines: list[str] | None = None,
    timeline: tuple[list[float], float, tuple[int, int, int]] | None = None,
) -> Canvas:
    """The part of the overlay that changes every iteration or frame into ``canvas`` (drawn over the
    backdrop of :func:`draw_backdrop`).

    Args:
        size: window size (width, height).
        plot_rect, curves, axes: the plot's curves (:class:`CurveArrays`' output) and legend
            (:func:`draw_curves`).
        text_rect, text_lines: the stats lines given (not None) here.
        help_lines: when given, a translucent help screen over everything.
        timeline: (frame times, shown time, (x0, x1, y)): the clip bar's marker at the shown time.
    """
    width, height = size
    draw_curves(canvas, plot_rect, curves, axes)
    _text_block(canvas, text_rect, text_lines)
    if timeline is not None and len(timeline[0]) > 1:
        times, shown, (x0, x1, y) = timeline
        mx = _timeline_x(times, (x0, x1), shown)
        for k in range(6):  # a small downward triangle
            canvas.rect(mx - 5 + k, y - 9 + k, 11 - 2 * k, 1, (255, 210, 120, 255))
    if help_lines:
        canvas.rect(0, 0, width, height, (0, 0, 0, 200))
        columns = 2 if len(help_lines) > (height - 20) // 16 else 1
        per_col = -(-len(help_lines) // columns)
        for i, line in enumerate(help_lines):
            col, row = divmod(i, per_col)
            canvas.text((16 + col * width // 2, 10 + 16 * row), line, 13, TEXT)
    return canvas


def _text_block(canvas: Canvas, text_rect, lines: list[str | None]) -> None:
    """Line ``i`` of the stats block at its row, the first highlighted; None lines are left out."""
    tx, ty, tw, th = text_rect
    for i, line in enumerate(lines):
        if line is not None:
            canvas.text((tx + 6, ty + 4 + 15 * i), line, 12, TEXT if i else (255, 210, 120, 255), tw - 10)


def _timeline_x(times: list[float], span: tuple[int, int], t: float) -> float:
    x0, x1 = span
    return x0 + (t - times[0]) / (times[-1] - times[0]) * (x1 - x0)
