"""The render job's chart: error against iteration and against wall time, one line per method."""
from __future__ import annotations

import os
from typing import Sequence

from torchmanifold.io.files import atomic_path

__all__ = ["write_chart"]


def write_chart(path: str | os.PathLike, rows: list[dict], title: str = "",
                methods: Sequence[str] = ("raw", "gaussian", "ours")) -> None:
    """PNG chart: PSNR against iteration and against cumulative wall time.

    Args:
        path: the PNG file.
        rows: one dict per iteration: ``{"iteration": i, <method>: {"psnr": dB, "seconds": s}, ...}``.
        title: the figure's title.
        methods: the methods to draw (keys of each row).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    it = [r["iteration"] for r in rows]
    for m, style in zip(methods, ("-o", "-s", "-^", "-v", "-d")):
        ps = [r[m]["psnr"] for r in rows]
        axes[0].plot(it, ps, style, ms=3, label=m)
        axes[1].plot([r[m]["seconds"] for r in rows], ps, style, ms=3, label=m)
    axes[0].set_xscale("log", base=2)
    axes[0].set_xlabel("iteration (samples per pixel per frame)")
    axes[1].set_xscale("log")
    axes[1].set_xlabel("cumulative wall time (s), render + filter")
    for ax in axes:
        ax.set_ylabel("PSNR (dB, clamped sRGB)")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
