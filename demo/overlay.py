"""The 2D layer of the demo: panel labels, stats, the error-vs-iteration plot and the help screen.

Drawn with PIL into one RGBA image the size of the window (no imgui needed, works headless), then
uploaded as a texture and blended over the panels.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont

#: Line colours of the three methods in the plot (and their labels).
CURVE_COLOURS = {"raw": (170, 170, 170), "gaussian": (90, 160, 255), "ours": (255, 150, 40)}
TEXT = (235, 235, 235, 255)
DIM = (150, 150, 150, 255)


@lru_cache(maxsize=8)
def font(size: int = 13) -> ImageFont.ImageFont:
    return ImageFont.load_default(size=size)


@lru_cache(maxsize=1024)
def _text_patch(text: str, size: int, fill: tuple, max_width: int | None) -> Image.Image:
    """``text`` rendered once into its own RGBA patch, cut to ``max_width`` (rendering text with
    FreeType costs ~1 ms a string on a slow CPU; most strings repeat from frame to frame)."""
    f = font(size)
    while max_width is not None and len(text) > 1 and f.getbbox(text)[2] > max_width:
        text = text[:-1]
    left, top, right, bottom = f.getbbox(text or " ")
    patch = Image.new("RGBA", (max(1, right), max(1, bottom)), (0, 0, 0, 0))
    ImageDraw.Draw(patch).text((0, 0), text, font=f, fill=fill)
    return patch


def put_text(img: Image.Image, xy, text: str, size: int = 12, fill=TEXT, max_width: int | None = None) -> int:
    """Blend cached ``text`` into ``img`` at ``xy``; returns the text's width in pixels."""
    patch = _text_patch(text, size, tuple(fill), max_width)
    x, y = int(round(xy[0])), int(round(xy[1]))
    if 0 <= x < img.width and 0 <= y < img.height:
        img.alpha_composite(patch.crop((0, 0, min(patch.width, img.width - x), min(patch.height, img.height - y))),
                            dest=(x, y))
    return patch.width


def draw_plot(
    img: Image.Image,
    rect: tuple[int, int, int, int],
    curves: dict[str, list[tuple[int, float]]],
    title: str = "PSNR (dB, clamped sRGB) vs iteration",
) -> None:
    """Line plot of ``curves`` (name -> [(iteration, value), ...]) inside ``rect`` = (x, y, w, h)."""
    x0, y0, w, h = rect
    draw = ImageDraw.Draw(img)
    draw.rectangle((x0, y0, x0 + w, y0 + h), fill=(20, 20, 24, 235), outline=(80, 80, 90, 255))
    put_text(img, (x0 + 6, y0 + 3), title, 12, TEXT, w - 10)
    pts = [p for c in curves.values() for p in c if np.isfinite(p[1])]
    left, top, right, bottom = x0 + 40, y0 + 22, x0 + w - 8, y0 + h - 20
    if not pts:
        put_text(img, (left, top + 10), "no reference: no error curve", 12, DIM)
        return
    max_it = max(2, max(p[0] for p in pts))
    lo, hi = min(p[1] for p in pts), max(p[1] for p in pts)
    lo, hi = np.floor(lo - 0.5), np.ceil(hi + 0.5)

    def to_px(it: float, val: float) -> tuple[float, float]:
        # log x so the fast early gains and the slow tail are both readable
        fx = np.log1p(it - 1) / np.log1p(max_it - 1) if max_it > 1 else 0.0
        return left + fx * (right - left), bottom - (val - lo) / (hi - lo) * (bottom - top)

    draw.line((left, top, left, bottom, right, bottom), fill=(120, 120, 130, 255))
    for val in np.linspace(lo, hi, 4):
        _, py = to_px(1, val)
        draw.line((left - 3, py, left, py), fill=(120, 120, 130, 255))
        put_text(img, (x0 + 4, py - 6), f"{val:.0f}", 11, DIM)
    for it in sorted({1, max_it} | {2**k for k in range(1, 12) if 2**k < max_it}):
        px, _ = to_px(it, lo)
        draw.line((px, bottom, px, bottom + 3), fill=(120, 120, 130, 255))
        put_text(img, (px - 4, bottom + 4), str(it), 11, DIM)
    legend_x = left + 6
    for name, curve in curves.items():
        colour = CURVE_COLOURS.get(name, (255, 255, 255))
        good = [p for p in curve if np.isfinite(p[1])]
        if len(good) >= 2:
            draw.line([to_px(*p) for p in good], fill=colour + (255,), width=2)
        elif good:
            px, py = to_px(*good[0])
            draw.ellipse((px - 2, py - 2, px + 2, py + 2), fill=colour + (255,))
        label = f"{name} {good[-1][1]:.1f}" if good else name
        legend_x += put_text(img, (legend_x, top + 2), label, 11, colour + (255,)) + 12


def render_overlay(
    size: tuple[int, int],
    labels: list[tuple[tuple[int, int], str, int]],
    plot_rect: tuple[int, int, int, int],
    curves: dict[str, list[tuple[int, float]]],
    text_rect: tuple[int, int, int, int],
    text_lines: list[str],
    help_lines: list[str] | None = None,
    timeline: tuple[list[float], float, tuple[int, int, int]] | None = None,
) -> np.ndarray:
    """The whole overlay as an RGBA8 array ``(H, W, 4)``, top row first.

    Args:
        size: window size (width, height).
        labels: ((x, y), text, max width) panel titles.
        plot_rect, curves: where and what to plot (see :func:`draw_plot`).
        text_rect, text_lines: the stats block.
        help_lines: when given, a translucent help screen over everything.
        timeline: (frame times, shown time, (x0, x1, y)): a clip bar with a marker at the shown time.
    """
    width, height = size
    img = Image.new("RGBA", (width, height), (0, 0, 0, 0))
    draw = ImageDraw.Draw(img)
    for (x, y), text, max_width in labels:
        put_text(img, (x + 2, y + 3), text, 13, TEXT, max_width - 4)
    draw_plot(img, plot_rect, curves)
    tx, ty, tw, th = text_rect
    draw.rectangle((tx, ty, tx + tw, ty + th), fill=(20, 20, 24, 235), outline=(80, 80, 90, 255))
    for i, line in enumerate(text_lines):
        put_text(img, (tx + 6, ty + 4 + 15 * i), line, 12, TEXT if i else (255, 210, 120, 255), tw - 10)
    if timeline is not None and len(timeline[0]) > 1:
        times, shown, (x0, x1, y) = timeline
        span = times[-1] - times[0]
        to_x = lambda t: x0 + (t - times[0]) / span * (x1 - x0)  # noqa: E731
        draw.line((x0, y, x1, y), fill=(120, 120, 130, 255), width=2)
        for t in times:
            draw.line((to_x(t), y - 4, to_x(t), y + 4), fill=(170, 170, 180, 255))
        mx = to_x(shown)
        draw.polygon([(mx - 5, y - 9), (mx + 5, y - 9), (mx, y - 2)], fill=(255, 210, 120, 255))
        put_text(img, (x0 - 12, y + 4), f"{times[0]:g}", 11, DIM)
        put_text(img, (x1 - 4, y + 4), f"{times[-1]:g}", 11, DIM)
    if help_lines:
        draw.rectangle((0, 0, width, height), fill=(0, 0, 0, 200))
        columns = 2 if len(help_lines) > (height - 20) // 16 else 1
        per_col = -(-len(help_lines) // columns)
        for i, line in enumerate(help_lines):
            col, row = divmod(i, per_col)
            put_text(img, (16 + col * width // 2, 10 + 16 * row), line, 13, TEXT)
    return np.asarray(img, dtype=np.uint8)
