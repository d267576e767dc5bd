"""The main job (``torchmanifold render``) and the ``denoise`` command, as Python functions.

:func:`render_job` renders a clip progressively, filters it every iteration, measures raw / Gaussian /
ours against a converged reference and writes EXR + PNG frames, MP4s, ``metrics.json`` and a chart.
:func:`denoise_files` denoises other renderers' multi-channel EXR frames into ``--out``.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from torchmanifold import metrics as M
from torchmanifold.pipeline.denoise import DenoiseSettings, denoise_frames
from torchmanifold.pipeline.progressive import ProgressiveRenderer

__all__ = ["prepare_out", "render_job", "denoise_files", "moving_mask", "spp_to_match", "write_chart",
           "RENDER_DEFAULTS"]

#: defaults of the render job: about two minutes on a shared 2-core CPU (reference ~75 s, 16 iterations ~25 s)
RENDER_DEFAULTS = dict(frames=8, iterations=16, width=128, height=96, reference_spp=256, seed=0)

METHODS = ("raw", "gaussian", "ours")


def prepare_out(out, overwrite: bool) -> Path:
    """Create the output folder; an existing non-empty one is reused only with ``overwrite``."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a directory")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"--out {out} exists and is not empty; pass --overwrite to reuse it")
    out.mkdir(parents=True, exist_ok=True)
    return out


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _write_png(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    tmp = path.with_name(path.stem + ".tmp.png")
    iio.imwrite(tmp, img)
    os.replace(tmp, path)


def moving_mask(object_id: torch.Tensor, moving_ids: Sequence[int], dilate: int = 2) -> torch.Tensor:
    """``(T, H, W)`` object ids -> ``(T, 1, H, W)`` float mask of pixels within ``dilate`` px of a moving
    object in this frame or a neighbouring one (where temporal accumulation would leave ghosts)."""
    if not moving_ids:
        return torch.zeros(object_id.shape[0], 1, *object_id.shape[1:])
    m = torch.isin(object_id.long(), torch.tensor(list(moving_ids))).float()[:, None]
    both = m.clone()
    both[1:] = torch.maximum(both[1:], m[:-1])
    both[:-1] = torch.maximum(both[:-1], m[1:])
    if dilate > 0:
        both = torch.nn.functional.max_pool2d(both, 2 * dilate + 1, 1, dilate)
    return both


def spp_to_match(raw_mse: Sequence[float], target_mse: float) -> float:
    """Samples per pixel plain path tracing needs to reach ``target_mse``, from its measured curve
    ``raw_mse[n-1]`` at n spp: interpolated where reached, else extrapolated with MSE ~ 1/spp from the
    last point."""
    for n, m in enumerate(raw_mse, start=1):
        if m <= target_mse:
            if n == 1:
                return 1.0
            m0 = raw_mse[n - 2]  # log-log interpolation between n-1 and n
            s = (math.log(m0) - math.log(target_mse)) / max(math.log(m0) - math.log(m), 1e-12)
            return float((n - 1) * (n / (n - 1)) ** s)
    n = len(raw_mse)
    return float(n * raw_mse[-1] / max(target_mse, 1e-30))


def write_chart(path: Path, rows: list[dict], title: str = "") -> None:
    """PNG chart: PSNR against iteration and against wall time for raw / Gaussian / ours."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    it = [r["iteration"] for r in rows]
    for m, style in zip(METHODS, ("-o", "-s", "-^")):
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
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)


def _evaluate(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None, with_flip: bool) -> dict:
    out = {"psnr": M.psnr(img, ref), "psnr_linear": M.psnr_linear(img, ref), "relmse": M.relmse(img, ref),
           "ssim": M.ssim(img, ref),
           "mse_srgb": float(((M.linear_to_srgb(img) - M.linear_to_srgb(ref)) ** 2).mean())}
    if with_flip and M.flip_available():
        out["flip"] = M.flip(img, ref)
    if mask is not None and float(mask.sum()) > 0:
        out["psnr_moving"] = M.psnr(img, ref, mask=mask)
        out["relmse_moving"] = M.relmse(img, ref, mask=mask)
    return out


def render_job(out, scene=None, frames: int = RENDER_DEFAULTS["frames"],
               iterations: int = RENDER_DEFAULTS["iterations"], width: int = RENDER_DEFAULTS["width"],
               height: int = RENDER_DEFAULTS["height"], seed: int = RENDER_DEFAULTS["seed"],
               reference_spp: int = RENDER_DEFAULTS["reference_spp"], overwrite: bool = False,
               settings: DenoiseSettings | None = None, alpha: float | None = None, inbetween: int = 0,
               fps: float = 8.0, flip_every: int = 0, progress: bool = True) -> dict:
    """Render, filter and measure a clip progressively; write everything under ``out``.

    Args:
        out: output folder (must be new or empty unless ``overwrite``).
        scene: a :class:`~torchmanifold.render.Scene`, a scene file path, or ``None`` for the built-in scene.
        frames, iterations, width, height, seed: the clip and the number of progressive iterations.
        reference_spp: samples per pixel of the converged reference (0 = no reference, no metrics).
        settings: filter settings (default: +-1 frame in ``"spacetime"`` mode: no ghosts behind moving objects).
        alpha: bandwidth schedule's ``a`` (default :data:`~torchmanifold.pipeline.schedule.DEFAULT_ALPHA`).
        inbetween: extra frames output between each pair of rendered frames (interpolated in time).
        fps: frame rate of the MP4s.
        flip_every: compute FLIP every this many iterations (and always at the last); 0 = last only.
        progress: show tqdm progress bars.

    Returns:
        The dict written to ``metrics.json``.
    """
    from tqdm.auto import tqdm

    from torchmanifold.io.exr import write_exr
    from torchmanifold.io.video import to_uint8_srgb, write_mp4
    from torchmanifold.pipeline.schedule import DEFAULT_ALPHA
    from torchmanifold.render import EXR_CHANNELS, PathTracer, default_scene, load_scene
    from torchmanifold.render.scene import Scene

    for name, v, lo in (("frames", frames, 1), ("iterations", iterations, 1), ("width", width, 8),
                        ("height", height, 8), ("reference_spp", reference_spp, 0), ("inbetween", inbetween, 0),
                        ("seed", seed, 0)):
        if not isinstance(v, int) or isinstance(v, bool) or v < lo:
            raise ValueError(f"{name} must be an int >= {lo}, got {v!r}")
    alpha = DEFAULT_ALPHA if alpha is None else alpha
    if scene is None:
        scene_obj, scene_name = default_scene(), "built-in Cornell box"
    elif isinstance(scene, Scene):
        scene_obj, scene_name = scene, scene.source
    else:
        scene_obj, scene_name = load_scene(scene), str(scene)
    out = prepare_out(out, overwrite)
    settings = settings or DenoiseSettings(temporal_radius=1, mode="spacetime")

    tracer = PathTracer(scene_obj, width, height)
    times = [float(t) for t in range(frames)]
    step = 1.0 / (inbetween + 1)
    query = [t + k * step for t in times[:-1] for k in range(inbetween + 1)] + [times[-1]]
    moving_ids = [k for k, o in enumerate(scene_obj.objects) if len(o.motion) > 1]

    t0 = time.perf_counter()
    ref = mask = None
    if reference_spp > 0:
        chunk = 32
        acc = None
        bar = tqdm(total=reference_spp, desc="reference", unit="spp", disable=not progress)
        done = 0
        while done < reference_spp:
            n = min(chunk, reference_spp - done)
            r = tracer.render(times=query, spp=n, seed=seed + 7919, sample_offset=done)
            acc = r.color.double() * n if acc is None else acc + r.color.double() * n
            if mask is None:
                mask = moving_mask(r.object_id, moving_ids)
            done += n
            bar.update(n)
        bar.close()
        ref = (acc / reference_spp).float()
    ref_seconds = time.perf_counter() - t0

    bar = tqdm(total=iterations * len(query), desc="iterations x frames", unit="frame", disable=not progress)
    pr = ProgressiveRenderer(tracer, times, query, settings=settings, alpha=alpha, seed=seed,
                             progress=bar.update)
    rows = []
    clock = {"raw": 0.0, "gaussian": 0.0, "ours": 0.0}
    raw_mse = []
    for i in range(1, iterations + 1):
        st = pr.step()
        # raw costs only the rendering; the Gaussian baseline adds a blur (timed here); ours everything
        tg = time.perf_counter()
        from torchmanifold.pipeline.progressive import gaussian_baseline
        gaussian_baseline(st.raw, 1.0)
        g_s = time.perf_counter() - tg
        clock["raw"] += st.render_seconds
        clock["gaussian"] += st.render_seconds + g_s
        clock["ours"] += st.seconds
        row = {"iteration": i, "sigma_s": st.sigma_s, "stats": st.stats}
        if ref is not None:
            with_flip = i == iterations or (flip_every > 0 and i % flip_every == 0)
            for m, img in (("raw", st.raw), ("gaussian", st.gaussian), ("ours", st.ours)):
                row[m] = _evaluate(img, ref, mask, with_flip)
                row[m]["seconds"] = clock[m]
            raw_mse.append(row["raw"]["mse_srgb"])
            bar.set_postfix(ours=f"{row['ours']['psnr']:.2f}dB", raw=f"{row['raw']['psnr']:.2f}dB")
        else:
            for m in METHODS:
                row[m] = {"seconds": clock[m]}
        rows.append(row)
    bar.close()
    final = pr.history[-1]

    # frames of the final iteration: EXR (ours + baselines + the last sample's features) and PNG
    last = tracer.render(times=query, spp=1, seed=seed, sample_offset=iterations - 1)
    (out / "frames").mkdir(exist_ok=True)
    (out / "png").mkdir(exist_ok=True)
    for q in range(len(query)):
        ch = {}
        for c, n in enumerate("RGB"):
            ch[n] = final.ours[q, c].numpy()
            ch[f"raw.{n}"] = final.raw[q, c].numpy()
            ch[f"gaussian.{n}"] = final.gaussian[q, c].numpy()
            if ref is not None:
                ch[f"reference.{n}"] = ref[q, c].numpy()
        for k, name in enumerate(last.feature_names):
            ch[EXR_CHANNELS[name]] = last.features[q, k].numpy()
        write_exr(out / "frames" / f"frame_{q:04d}.exr", ch, half=[EXR_CHANNELS[n] for n in last.feature_names])
        _write_png(out / "png" / f"frame_{q:04d}.png", to_uint8_srgb(final.ours[q]))
    write_mp4(out / "clip.mp4", final.ours, fps=fps)
    panels = [final.raw, final.gaussian, final.ours] + ([ref] if ref is not None else [])
    write_mp4(out / "compare.mp4", torch.cat(panels, dim=3), fps=fps)

    summary = {
        "scene": scene_name, "frames": frames, "query_times": query, "iterations": iterations,
        "width": width, "height": height, "seed": seed, "reference_spp": reference_spp,
        "reference_seconds": ref_seconds, "alpha": alpha,
        "settings": {k: (str(v) if isinstance(v, torch.dtype) else v) for k, v in settings.__dict__.items()},
        "gaussian_sigma": pr.gaussian_sigma, "moving_object_ids": moving_ids,
        "memory_frames": pr.memory_frames, "threads": torch.get_num_threads(),
        "per_iteration": rows,
    }
    if ref is not None:
        summary["final"] = {m: rows[-1][m] for m in METHODS}
        summary["spp_plain_to_match_ours_final"] = spp_to_match(raw_mse, rows[-1]["ours"]["mse_srgb"])
        write_chart(out / "chart.png", rows, f"{scene_name}: {width}x{height}, {len(query)} frames")
    _atomic_text(out / "metrics.json", json.dumps(summary, indent=1, default=float))
    return summary


def _read_frame(path: Path, color_channels: Sequence[str], feature_channels: Sequence[str] | None):
    from torchmanifold.io.exr import read_exr

    chans = read_exr(path)  # FileNotFoundError / ValueError name the file
    missing = [c for c in color_channels if c not in chans]
    if missing:
        raise ValueError(f"{path}: colour channel(s) {missing} not found; the file has {sorted(chans)}")
    if feature_channels is None:
        from torchmanifold.pipeline.denoise import GROUP_SIGMAS, feature_group

        feature_channels = [n for n in chans if n not in color_channels and feature_group(n) in GROUP_SIGMAS]
        order = ["albedo", "N", "P", "Z", "D", "S"]
        feature_channels = sorted(feature_channels, key=lambda n: (order.index(feature_group(n)), n))
    else:
        missing = [c for c in feature_channels if c not in chans]
        if missing:
            raise ValueError(f"{path}: feature channel(s) {missing} not found; the file has {sorted(chans)}")
    color = torch.from_numpy(np.stack([chans[c] for c in color_channels]))
    h, w = color.shape[1:]
    feats = (torch.from_numpy(np.stack([chans[c] for c in feature_channels])) if feature_channels
             else torch.zeros(0, h, w))
    # emitted radiance at the first hit (our tracer writes it): kept apart from the filter
    em_names = ("emission.R", "emission.G", "emission.B")
    emission = torch.from_numpy(np.stack([chans[c] for c in em_names])) if all(c in chans for c in em_names) else None
    return color, feats, list(feature_channels), emission


def denoise_files(inputs: Sequence[str | os.PathLike], out, settings: DenoiseSettings | None = None,
                  color_channels: Sequence[str] = ("R", "G", "B"), feature_channels: Sequence[str] | None = None,
                  overwrite: bool = False, progress: bool = True) -> dict:
    """Denoise a sequence of multi-channel EXR frames (one file per frame, in frame order).

    Frames are read as the time window needs them and released behind it, so memory is bounded by the
    window. Each output is ``out/<input name>`` with the filtered ``R, G, B`` (float32).

    Args:
        inputs: the frame files, in order.
        out: output folder (new or empty unless ``overwrite``; it must not hold any input).
        settings: :class:`DenoiseSettings` (default: ``DenoiseSettings(temporal_radius=1)``).
        color_channels: the three colour channels to denoise.
        feature_channels: guide/albedo channels; ``None`` picks the known ones each file has
            (``albedo.*``, ``N.*``, ``P.*``, ``Z``, ...); all frames must have the same. Channels
            ``emission.R/G/B`` (our tracer's EXRs), when present, are kept out of the filter.
        overwrite: reuse a non-empty ``out``.
        progress: tqdm progress bar over frames.

    Returns:
        ``{"frames": n, "feature_channels": [...], "nonfinite_samples": n, "firefly_energy_removed": x,
        "seconds_per_frame": s, "outputs": [...]}``.

    Raises:
        FileNotFoundError, ValueError: missing/unreadable file, missing channel, size mismatch (named).
    """
    from tqdm.auto import tqdm

    from torchmanifold.io.exr import write_exr

    inputs = [Path(p) for p in inputs]
    if not inputs:
        raise ValueError("inputs: expected at least one EXR frame")
    if len(color_channels) != 3:
        raise ValueError(f"color_channels must name 3 channels, got {list(color_channels)}")
    if len({p.name for p in inputs}) != len(inputs):
        raise ValueError("inputs: two frames share a file name; outputs are written under the input names")
    for p in inputs:
        if not p.is_file():
            raise FileNotFoundError(f"EXR file not found: {p}")
    settings = (settings or DenoiseSettings(temporal_radius=1)).check()
    outp = Path(out)
    if any(p.resolve().parent == outp.resolve() for p in inputs):
        raise ValueError(f"--out {outp} holds input frames; choose another folder")
    # read every header first: fail before writing anything
    first = _read_frame(inputs[0], color_channels, feature_channels)
    fnames = first[2]
    size = tuple(first[0].shape[1:])
    outp = prepare_out(outp, overwrite)

    r = settings.temporal_radius
    cache: dict[int, tuple] = {0: first}
    outputs, stats_sum = [], {"nonfinite_color": 0, "nonfinite_features": 0, "firefly_energy_removed": 0.0}
    t0 = time.perf_counter()
    partial = outp / ".partial"  # frames land here; renamed into place only when all succeeded
    if partial.exists():
        shutil.rmtree(partial)
    partial.mkdir()
    try:
        for t in tqdm(range(len(inputs)), desc="denoise", unit="frame", disable=not progress):
            ids = list(range(max(0, t - r), min(len(inputs), t + r + 1)))
            for k in ids:
                if k not in cache:
                    fr = _read_frame(inputs[k], color_channels, fnames)
                    if tuple(fr[0].shape[1:]) != size:
                        raise ValueError(f"{inputs[k]}: frame size {tuple(fr[0].shape[1:])} differs from "
                                         f"{inputs[0]} ({size})")
                    cache[k] = fr
            for k in [k for k in cache if k < ids[0]]:
                del cache[k]
            color = torch.stack([cache[k][0] for k in ids])
            feats = torch.stack([cache[k][1] for k in ids])
            ems = [cache[k][3] for k in ids]
            emission = torch.stack(ems) if all(e is not None for e in ems) else None
            y, st = denoise_frames(color, feats, fnames, emission, settings=settings, frame_times=ids,
                                   query_times=[t], return_stats=True)
            own = ids.index(t)  # count the frame's own samples once
            stats_sum["nonfinite_color"] += int((~torch.isfinite(color[own])).sum())
            stats_sum["nonfinite_features"] += int((~torch.isfinite(feats[own])).sum())
            stats_sum["firefly_energy_removed"] += st.get("firefly_energy_removed", 0.0)
            yn = y[0].numpy()
            write_exr(partial / inputs[t].name, {c: yn[k] for k, c in enumerate(color_channels)})
        for p in inputs:
            os.replace(partial / p.name, outp / p.name)
            outputs.append(str(outp / p.name))
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    n = len(inputs)
    return {"frames": n, "size": list(size), "feature_channels": fnames,
            "nonfinite_samples": stats_sum["nonfinite_color"] + stats_sum["nonfinite_features"],
            "nonfinite_color": stats_sum["nonfinite_color"], "nonfinite_features": stats_sum["nonfinite_features"],
            "firefly_energy_removed": stats_sum["firefly_energy_removed"] / n,
            "seconds_per_frame": (time.perf_counter() - t0) / n, "outputs": outputs}
