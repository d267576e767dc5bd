"""The main job (``torchmanifold render``): render a clip progressively, filter it every iteration,
measure raw / Gaussian / ours against a converged reference, and write EXR + PNG frames, MP4s,
``metrics.json`` and a chart."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Sequence

import torch

from torchmanifold import metrics as M
from torchmanifold.io.files import prepare_out, write_text
from torchmanifold.pipeline.charts import write_chart
from torchmanifold.pipeline.convergence import spp_to_match
from torchmanifold.pipeline.denoise import DenoiseSettings
from torchmanifold.pipeline.progressive import PROGRESSIVE_FILTER, ProgressiveRenderer, gaussian_baseline

__all__ = ["render_job", "moving_mask", "RENDER_DEFAULTS", "METHODS"]

#: defaults of the render job: about a minute on the shared 2-core CPU (65 s at load ~1: reference 14 s,
#: 16 iterations 40 s, videos and files the rest)
RENDER_DEFAULTS = dict(frames=8, iterations=16, width=256, height=256, reference_spp=256, seed=0)

METHODS = ("raw", "gaussian", "ours")

#: the reference's seed is the job's plus this prime, so its samples share none with the iterations'
REFERENCE_SEED_OFFSET = 7919
#: samples per reference render call (bounds one call's time; the sum is the same for any chunking)
REFERENCE_CHUNK_SPP = 32


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


def _evaluate(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None, with_flip: bool) -> dict:
    out = {"psnr": M.psnr(img, ref), "psnr_linear": M.psnr_linear(img, ref), "relmse": M.relmse(img, ref),
           "ssim": M.ssim(img, ref),
           "mse_srgb": float(((M.linear_to_srgb(img) - M.linear_to_srgb(ref)) ** 2).mean())}
    if with_flip:
        out["flip"] = M.flip(img, ref)
    if mask is not None and float(mask.sum()) > 0:
        out["psnr_moving"] = M.psnr(img, ref, mask=mask)
        out["relmse_moving"] = M.relmse(img, ref, mask=mask)
    return out


def _check_job_ints(**values) -> None:
    lows = dict(frames=1, iterations=1, width=8, height=8, reference_spp=0, inbetween=0, seed=0)
    for name, v in values.items():
        lo = lows[name]
        if not isinstance(v, int) or isinstance(v, bool) or v < lo:
            raise ValueError(f"{name} must be an int >= {lo}, got {v!r}")


def _resolve_scene(scene):
    """``(Scene, name for people)`` of a Scene, a scene file path or ``None`` (the built-in scene)."""
    from torchmanifold.render import Scene, default_scene, load_scene

    if scene is None:
        return default_scene(), "built-in Cornell box"
    if isinstance(scene, Scene):
        return scene, scene.source
    return load_scene(scene), str(scene)


def render_query_times(frames: int, inbetween: int) -> tuple[list[float], list[float]]:
    """The frame times ``0 .. frames-1`` and the output (query) times: ``inbetween`` extra times between
    each pair of frames."""
    times = [float(t) for t in range(frames)]
    step = 1.0 / (inbetween + 1)
    return times, [t + k * step for t in times[:-1] for k in range(inbetween + 1)] + [times[-1]]


def render_reference(tracer, query: Sequence[float], spp: int, seed: int, progress: bool = False):
    """The converged reference ``(Q, 3, H, W)`` at the query times: ``spp`` samples drawn in chunks
    of :data:`REFERENCE_CHUNK_SPP` with the job's seed + :data:`REFERENCE_SEED_OFFSET`, summed in
    float64 in one order (any sharding of the query times gives the same bytes). Also returns the
    object ids of the first chunk ``(Q, H, W)``."""
    from tqdm.auto import tqdm

    acc = object_id = None
    bar = tqdm(total=spp, desc="reference", unit="spp", disable=not progress)
    done = 0
    while done < spp:
        n = min(REFERENCE_CHUNK_SPP, spp - done)
        r = tracer.render(times=list(query), spp=n, seed=seed + REFERENCE_SEED_OFFSET, sample_offset=done)
        acc = r.color.double() * n if acc is None else acc + r.color.double() * n
        if object_id is None:
            object_id = r.object_id
        done += n
        bar.update(n)
    bar.close()
    return (acc / spp).float(), object_id


def write_frame(out: Path, q: int, ours, raw, gaussian, ref, features, feature_names) -> list[str]:
    """One output frame: ``frames/frame_q.exr`` (ours as R,G,B, the baselines, the reference and the
    last sample's features) and ``png/frame_q.png`` (ours); each ``(3, H, W)`` / ``(D, H, W)``.
    Returns the two paths relative to ``out``."""
    from torchmanifold import features as feature_table
    from torchmanifold.io.exr import write_exr
    from torchmanifold.io.png import write_png
    from torchmanifold.io.video import to_uint8_srgb

    ch = {}
    for c, n in enumerate("RGB"):
        ch[n] = ours[c].numpy()
        ch[f"raw.{n}"] = raw[c].numpy()
        ch[f"gaussian.{n}"] = gaussian[c].numpy()
        if ref is not None:
            ch[f"reference.{n}"] = ref[c].numpy()
    feats = {feature_table.canonical_name(n): features[k].numpy() for k, n in enumerate(feature_names)}
    exr, png = f"frames/frame_{q:04d}.exr", f"png/frame_{q:04d}.png"
    write_exr(out / exr, {**ch, **feats}, half=[c for c in feats if feature_table.is_half(c)])
    write_png(out / png, to_uint8_srgb(ours))
    return [exr, png]


def _iterate(pr: ProgressiveRenderer, iterations: int, ref, mask, flip_every: int, bar) -> tuple[list, list]:
    """Run the progressive iterations; one row of timings (and errors, with a reference) per iteration,
    and plain path tracing's sRGB MSE curve."""
    rows, raw_mse = [], []
    clock = {m: 0.0 for m in METHODS}
    for i in range(1, iterations + 1):
        st = pr.step()
        # raw costs only the rendering; the Gaussian baseline adds a blur (timed here); ours everything
        tg = time.perf_counter()
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
    return rows, raw_mse


def _write_frames(out: Path, tracer, final, ref, query: list[float], iterations: int, seed: int,
                  fps: float) -> None:
    """Frames of the final iteration (:func:`write_frame`) and the MP4s."""
    from torchmanifold.io.video import write_mp4

    last = tracer.render(times=query, spp=1, seed=seed, sample_offset=iterations - 1)
    for q in range(len(query)):
        write_frame(out, q, final.ours[q], final.raw[q], final.gaussian[q], None if ref is None else ref[q],
                    last.features[q], last.feature_names)
    write_mp4(out / "clip.mp4", final.ours, fps=fps)
    panels = [final.raw, final.gaussian, final.ours] + ([ref] if ref is not None else [])
    write_mp4(out / "compare.mp4", torch.cat(panels, dim=3), fps=fps)


def render_job(out, scene=None, frames: int = RENDER_DEFAULTS["frames"],
               iterations: int = RENDER_DEFAULTS["iterations"], width: int = RENDER_DEFAULTS["width"],
               height: int = RENDER_DEFAULTS["height"], seed: int = RENDER_DEFAULTS["seed"],
               reference_spp: int = RENDER_DEFAULTS["reference_spp"], overwrite: bool = False,
               settings: DenoiseSettings | None = None, alpha: float | None = None, inbetween: int = 0,
               fps: float = 8.0, flip_every: int = 0, progress: bool = True, scheme: str = "accumulate") -> dict:
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
        scheme: how iterations combine (see :class:`~torchmanifold.pipeline.progressive.ProgressiveRenderer`).

    Returns:
        The dict written to ``metrics.json``.
    """
    from tqdm.auto import tqdm

    from torchmanifold.pipeline.schedule import DEFAULT_ALPHA
    from torchmanifold.render import PathTracer

    _check_job_ints(frames=frames, iterations=iterations, width=width, height=height,
                    reference_spp=reference_spp, inbetween=inbetween, seed=seed)
    alpha = DEFAULT_ALPHA if alpha is None else alpha
    scene_obj, scene_name = _resolve_scene(scene)
    out = prepare_out(out, overwrite)
    settings = settings or DenoiseSettings(**PROGRESSIVE_FILTER)

    tracer = PathTracer(scene_obj, width, height)
    times, query = render_query_times(frames, inbetween)
    moving_ids = scene_obj.moving_objects()

    t0 = time.perf_counter()
    ref = mask = None
    if reference_spp > 0:
        ref, object_id = render_reference(tracer, query, reference_spp, seed, progress)
        mask = moving_mask(object_id, moving_ids)
    ref_seconds = time.perf_counter() - t0

    bar = tqdm(total=iterations * len(query), desc="iterations x frames", unit="frame", disable=not progress)
    pr = ProgressiveRenderer(tracer, times, query, settings=settings, alpha=alpha, seed=seed, scheme=scheme,
                             progress=bar.update)
    rows, raw_mse = _iterate(pr, iterations, ref, mask, flip_every, bar)
    bar.close()
    _write_frames(out, tracer, pr.history[-1], ref, query, iterations, seed, fps)

    summary = {
        "scene": scene_name, "frames": frames, "query_times": query, "iterations": iterations,
        "width": width, "height": height, "seed": seed, "reference_spp": reference_spp,
        "reference_seconds": ref_seconds, "alpha": alpha, "scheme": scheme,
        "settings": {k: (str(v) if isinstance(v, torch.dtype) else v) for k, v in settings.__dict__.items()},
        "gaussian_sigma": pr.gaussian_sigma, "moving_object_ids": moving_ids,
        "memory_frames": pr.memory_frames, "threads": torch.get_num_threads(),
        "per_iteration": rows,
    }
    if ref is not None:
        summary["final"] = {m: rows[-1][m] for m in METHODS}
        summary["spp_plain_to_match_ours_final"] = spp_to_match(raw_mse, rows[-1]["ours"]["mse_srgb"])
        write_chart(out / "chart.png", rows, f"{scene_name}: {width}x{height}, {len(query)} frames", METHODS)
    write_text(out / "metrics.json", json.dumps(summary, indent=1, default=float))
    return summary
