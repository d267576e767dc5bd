"""The ``denoise`` command: other renderers' EXR frames (ours, Mitsuba's, Blender's) in, denoised
EXR frames out, all or nothing."""
from __future__ import annotations

import os
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Iterable, Iterator, Mapping, Sequence

import numpy as np
import torch

from torchmanifold._checks import check_int
from torchmanifold._threads import InOrder
from torchmanifold.io.files import prepare_out, staged_dir
from torchmanifold.io.frames import RenderFrame, read_render_frame, write_color
from torchmanifold.pipeline.denoise import (DenoiseSettings, FrameState, adapt_to_features,
                                            denoise_window_states, prepare_frames, radiance_sigma_at,
                                            spatial_sigma)
from torchmanifold.pipeline.footprint import footprint_width
from torchmanifold.pipeline.selection import ClipCache
from torchmanifold.pipeline.sliding import SlidingFrames
from torchmanifold.timewindow import index_window

__all__ = ["denoise_files", "clip_summary", "denoised_frames", "denoise_window", "prepared_window",
           "filter_window", "ClipWindow", "OUTPUT_LAYOUTS"]

#: the ``denoise`` command's filter, where it differs from :class:`DenoiseSettings`' defaults: the frames
#: within +-2 join in space-time (brought to each query's pixels, ``align_frames``). All frames from 1 / 4 spp
#: against +-1: the validation set +0.11 / +0.11 dB, its clips at 256x256 +0.12 / +0.12 (Mitsuba) and +0.10 /
#: +0.11 (Cycles), the probes +0.13 / +0.14, no clip below -0.01; +-3 the set +0.03 / +0.03 more. The frame
#: step of a 12-frame 256x256 clip takes 1.0-1.16 times as long (two threads)
#: (``benchmarks/validation/findings.md``)
COMMAND_FILTER = {"temporal_radius": 2}
#: ``"input"``: colour written back under the channels it was read from (Blender: ``<layer>.Combined``);
#: ``"plain"``: ``R, G, B``
OUTPUT_LAYOUTS = ("input", "plain")
#: what each frame's record counts, summed over the clip in the summary
FRAME_STATS = ("nonfinite_color", "nonfinite_features", "firefly_energy_removed", "noisy_sky_frames",
               "kept_flat_frames", "infinite_as_no_hit")


def clip_summary(records: Iterable[Mapping], settings: DenoiseSettings,
                 samples_per_pixel: float | None) -> dict:
    """What a clip's summary says of its frames: the non-finite counts and sky frames of the frames'
    records (:data:`FRAME_STATS`; a record of an earlier version without one of them counts 0)
    summed in frame order, the mean share of firefly energy removed, and the samples per pixel with the
    bandwidth and footprint they set. The one-process and the sharded command both report it."""
    total, n = dict.fromkeys(FRAME_STATS, 0), 0
    for rec in records:
        n += 1
        for k in FRAME_STATS:
            total[k] += rec.get(k, 0)
    return {"nonfinite_samples": total["nonfinite_color"] + total["nonfinite_features"],
            "nonfinite_color": total["nonfinite_color"], "nonfinite_features": total["nonfinite_features"],
            "firefly_energy_removed": total["firefly_energy_removed"] / max(n, 1),
            "noisy_sky_frames": total["noisy_sky_frames"], "kept_flat_frames": total["kept_flat_frames"],
            "infinite_as_no_hit": total["infinite_as_no_hit"],
            "samples_per_pixel": samples_per_pixel,
            "sigma_s": spatial_sigma(settings, samples_per_pixel),
            "footprint_sigma": footprint_width(settings, samples_per_pixel),
            "radiance_sigma": radiance_sigma_at(settings, samples_per_pixel)}


def _check_inputs(inputs: Sequence, out, output_layout: str) -> tuple[list[Path], Path]:
    inputs = [Path(p) for p in inputs]
    if not inputs:
        raise ValueError("inputs: expected at least one EXR frame")
    if output_layout not in OUTPUT_LAYOUTS:
        raise ValueError(f"output_layout must be one of {OUTPUT_LAYOUTS}, got {output_layout!r}")
    if len({p.name for p in inputs}) != len(inputs):
        raise ValueError("inputs: two frames share a file name; outputs are written under the input names")
    for p in inputs:
        if not p.is_file():
            raise FileNotFoundError(f"EXR file not found: {p}")
    outp = Path(out)
    if any(p.resolve().parent == outp.resolve() for p in inputs):
        raise ValueError(f"--out {outp} holds input frames; choose another folder")
    return inputs, outp


def _same_as_first(frame: RenderFrame, first: RenderFrame) -> None:
    """Every frame of a clip must have the first one's size, layout and features."""
    for what, a, b in (("frame size", frame.size, first.size), ("layout", frame.layout, first.layout),
                       ("view layer", frame.layer, first.layer)):
        if a != b:
            raise ValueError(f"{frame.path}: {what} {a} differs from {first.path} ({b})")


def clip_samples_per_pixel(first: RenderFrame, samples_per_pixel: int | None) -> int | None:
    """A clip's sample count: the caller's (a positive int), else the first frame's (its header's, or the
    count its features show: :attr:`~torchmanifold.io.frames.RenderFrame.samples_per_pixel`)."""
    if samples_per_pixel is None:
        return first.samples_per_pixel
    return check_int("samples_per_pixel", samples_per_pixel, min=1)


class ClipWindow:
    """The frames of a clip's files, read as a moving time window needs them and released behind it, with
    what the denoiser derives from each frame alone (prepared once, released with the frame; see
    :class:`~torchmanifold.pipeline.sliding.SlidingFrames`).

    Reading frame k starts reading frame k + 1 on a background thread (OpenEXR releases the GIL), so the
    next window's file is read while this one is filtered. A context manager: leaving it ends that thread.

    Args:
        inputs: the frame files, in order.
        first: the first frame, already read (it fixes size, layout, layer and feature channels).
        color_channels: as :func:`~torchmanifold.io.frames.read_render_frame`.
        samples_per_pixel: the frames' sample count (``None``: the first frame's, its header's or the count
            its features show, see :attr:`~torchmanifold.io.frames.RenderFrame.samples_per_pixel`).
        pool: where frames are prepared (:meth:`~torchmanifold._threads.InOrder.ahead`), or ``None``: on the
            calling thread.
    """

    def __init__(self, inputs: Sequence[Path], first: RenderFrame, color_channels: Sequence[str] | None,
                 samples_per_pixel: int | None = None, pool: InOrder | None = None):
        self.inputs, self.first, self.color_channels = list(inputs), first, color_channels
        self.samples_per_pixel = clip_samples_per_pixel(first, samples_per_pixel)
        self.feature_names = first.feature_names
        self.notes = list(first.notes)
        self._window = SlidingFrames(self._read, self._prepare, {0: first})
        self._settings: DenoiseSettings | None = None
        self.candidates = ClipCache()  # each query's candidates, lent to its neighbours, and the flows
        self._reader = ThreadPoolExecutor(1, thread_name_prefix="exr-read")
        self._ahead: tuple[int, Future] | None = None
        self._pool = pool or InOrder(1, 1)  # one worker: each frame prepared at once, here

    def __enter__(self) -> "ClipWindow":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End the read-ahead thread (a frame it is reading is read to the end and dropped)."""
        self._ahead = None
        self._reader.shutdown(wait=True, cancel_futures=True)

    def __len__(self) -> int:
        return len(self.inputs)

    @property
    def reads(self) -> int:
        """Frames served so far (each is read once: windows only move on)."""
        return self._window.served

    def _read_file(self, k: int) -> RenderFrame:
        return read_render_frame(self.inputs[k], self.color_channels, self.feature_names, self.first.layer)

    def _read(self, k: int) -> RenderFrame:
        ahead, self._ahead = self._ahead, None
        fr = ahead[1].result() if ahead is not None and ahead[0] == k else self._read_file(k)
        if k + 1 < len(self.inputs):
            self._ahead = (k + 1, self._reader.submit(self._read_file, k + 1))
        _same_as_first(fr, self.first)
        self.notes += [n for n in fr.notes if n not in self.notes]
        return fr

    def _prepare(self, k: int, fr: RenderFrame) -> Future:
        return self._pool.ahead(self._prepare_frame, fr, self._settings)

    def _prepare_frame(self, fr: RenderFrame, settings: DenoiseSettings) -> FrameState:
        em = None if fr.emission is None else torch.from_numpy(fr.emission)[None]
        features = torch.from_numpy(fr.stack(self.feature_names))[None]
        return prepare_frames(torch.from_numpy(fr.color)[None], features, self.feature_names, em, settings,
                              samples_per_pixel=self.samples_per_pixel)

    def frames(self, ids: Sequence[int]) -> list[RenderFrame]:
        """The frames ``ids`` (increasing); frames before ``ids[0]`` are dropped."""
        return self._window.frames(ids)

    def prepared(self, ids: Sequence[int], settings: DenoiseSettings) -> list[Future]:
        """The frames ``ids`` (increasing) through :func:`~torchmanifold.pipeline.denoise.prepare_frames`,
        each prepared once for ``settings``: futures of their states (done ones without a pool)."""
        if settings != self._settings:
            self._window.forget_prepared()
            self._settings, self.candidates = settings, ClipCache()
        # a query's window starts past the earlier queries that lent it evidence
        self.candidates.release_before(ids[0])
        return self._window.prepared(ids)


def denoise_window(clip: ClipWindow, t: int, settings: DenoiseSettings) -> tuple[np.ndarray, dict, RenderFrame]:
    """Output frame ``t`` of ``clip`` from the frames of its time window alone (so the one-process,
    streaming and sharded runs give the same bytes).

    Returns:
        ``(3, H, W)`` float32 colour, the frame's stats (its own non-finite samples, the firefly
        energy removed), and the frame as read (its layout is the output's).
    """
    window, frame = prepared_window(clip, t, settings)
    return (*filter_window(*window), frame)


def prepared_window(clip: ClipWindow, t: int, settings: DenoiseSettings) -> tuple[tuple, RenderFrame]:
    """:func:`denoise_window`'s first part, on the thread that reads the clip (windows in order): frame
    ``t``'s window, its frames prepared or being prepared, as the arguments of :func:`filter_window`, and
    the frame as read."""
    r = settings.window_radius
    ids = list(index_window(len(clip), t, r))
    states = clip.prepared(ids, settings)
    return (states, settings, ids, t, clip.candidates), clip.frames(ids)[ids.index(t)]


def filter_window(states: Sequence[Future], settings: DenoiseSettings, ids: list[int],
                  t: int, candidates: ClipCache | None = None) -> tuple[np.ndarray, dict]:
    """:func:`denoise_window`'s second part, on any thread: the window's filter at frame ``t``, ``(3, H, W)``
    float32, and the frame's stats; ``candidates``: the clip's, which its neighbouring windows share."""
    y = denoise_window_states(states, settings, ids, t, cache=candidates)[0]
    y = y.to(torch.float32)[0].numpy()
    stats = states[ids.index(t)].result().stats()
    return y, {k: stats[k] for k in FRAME_STATS}


def denoised_frames(clip: ClipWindow, settings: DenoiseSettings,
                    pool: InOrder) -> Iterator[tuple[int, np.ndarray, dict, RenderFrame]]:
    """Every frame of ``clip`` denoised, in frame order: ``(t, (3, H, W) float32 colour, the frame's stats,
    the frame as read)``.

    Windows are formed here in order (each frame read and prepared once); frames are prepared (``clip``
    made with ``pool``) and windows filtered side by side on ``pool``'s workers, which share the torch
    threads, one each: the Python around a frame's ops does not scale inside one call, and across frames
    it overlaps with the other's ops (:class:`~torchmanifold._threads.InOrder`)."""
    read: dict[int, RenderFrame] = {}  # frames submitted, as read
    for t in range(len(clip)):
        window, read[t] = prepared_window(clip, t, settings)
        for k, (y, rec) in pool.submit(t, filter_window, *window):
            yield k, y, rec, read.pop(k)
    for k, (y, rec) in pool.drain():
        yield k, y, rec, read.pop(k)


def denoise_files(inputs: Sequence[str | os.PathLike], out, settings: DenoiseSettings | None = None,
                  color_channels: Sequence[str] | None = None, feature_channels: Sequence[str] | None = None,
                  overwrite: bool = False, progress: bool = True, layer: str | None = None,
                  output_layout: str = "input", samples_per_pixel: int | None = None) -> dict:
    """Denoise a sequence of multi-channel EXR frames (one file per frame, in frame order).

    Frames are read by :func:`~torchmanifold.io.frames.read_render_frame` (our tracer's, Mitsuba's and
    Blender's layouts, detected per file) as the time window needs them and released behind it, so
    memory is bounded by the window (times the torch threads: each thread filters one frame's window, so
    that many windows are held at once). Outputs are staged and moved into ``out`` only when every frame
    succeeded: a bad frame leaves ``out`` empty.

    Args:
        inputs: the frame files, in order.
        out: output folder (new or empty unless ``overwrite``; it must not hold any input).
        settings: :class:`DenoiseSettings` (default: the command's, ``DenoiseSettings(**COMMAND_FILTER)``).
        color_channels: the three colour channels to denoise (``None``: ``R, G, B`` or Blender's
            ``<layer>.Combined.R/G/B``).
        feature_channels: features to read, by any name the feature table knows or a file channel
            name; ``None`` = the first frame's known features (all frames must have them). Our
            tracer's ``emission.R/G/B``, when present, is kept out of the filter.
        overwrite: reuse a non-empty ``out``.
        progress: tqdm progress bar over frames.
        layer: Blender view layer (only needed when a file has several).
        output_layout: ``"input"`` (colour under the channels it came from; Blender files keep
            ``<layer>.Combined.R/G/B`` and the input's ``A``) or ``"plain"`` (``R, G, B``).
        samples_per_pixel: the frames' sample count, for a renderer whose header does not record it
            (``None``: the first frame's, its header's or the count its features show; it sets the bandwidth
            and the footprint width, see :func:`~torchmanifold.pipeline.denoise.footprint_width`).

    Returns:
        ``{"frames": n, "size": [H, W], "layout": "flat" | "blender", "layer": ..., "feature_channels":
        [canonical names], "sources": {name: first frame's channel}, "notes": [...], "nonfinite_samples": n,
        "nonfinite_color": n, "nonfinite_features": n, "firefly_energy_removed": x, "noisy_sky_frames": n
        (frames whose pixels of depth 0 were filtered as noise, a scene in fog), "kept_flat_frames": n
        (frames whose flat pixels, no albedo beside pixels with one, kept their samples, their colour no
        noise: a picture on a black emitter), "infinite_as_no_hit": n (depth and position values that were
        infinite, read as a ray that left the scene), "samples_per_pixel":
        n or None (the first frame's header), "sigma_s": s (the spatial sigma used), "footprint_sigma": s (the
        footprint width used), "seconds_per_frame": s, "outputs": [...]}``; ``notes`` lists what the reader
        changed or found missing (deduplicated).

    Raises:
        FileNotFoundError, ValueError: missing/unreadable file, missing channel or pass, size mismatch,
            empty feature (named by file, layer and channel).
    """
    from tqdm.auto import tqdm

    inputs, outp = _check_inputs(inputs, out, output_layout)
    settings = (settings or DenoiseSettings(**COMMAND_FILTER)).check()
    # the first frame fixes the features; fail on it before creating anything
    first = read_render_frame(inputs[0], color_channels, feature_channels, layer)
    fnames = first.feature_names
    settings, adapted = adapt_to_features(settings, fnames)
    spp = clip_samples_per_pixel(first, samples_per_pixel)
    outp = prepare_out(outp, overwrite)

    records = []
    t0 = time.perf_counter()
    writes: deque[Future] = deque()
    with staged_dir(outp) as stage, ThreadPoolExecutor(1, thread_name_prefix="exr-write") as writer, \
            InOrder(torch.get_num_threads(), len(inputs)) as pool, \
            ClipWindow(inputs, first, color_channels, spp, pool) as clip:
        for t, y, rec, frame in tqdm(denoised_frames(clip, settings, pool), total=len(inputs), desc="denoise",
                                     unit="frame", disable=not progress):
            records.append(rec)
            # written on a thread while later frames are filtered; a failed write raises before the staged
            # folder is moved into place
            writes.append(writer.submit(write_color, stage / inputs[t].name, y, frame, output_layout))
            if len(writes) > 1:
                writes.popleft().result()
        for w in writes:
            w.result()
    outputs = [str(outp / p.name) for p in inputs]
    n = len(inputs)
    return {"frames": n, "size": list(first.size), "layout": first.layout, "layer": first.layer,
            "feature_channels": fnames, "sources": {k: first.sources[k] for k in ["R", "G", "B", *fnames]},
            "notes": clip.notes + ([adapted] if adapted else []),
            **clip_summary(records, settings, clip.samples_per_pixel),
            "seconds_per_frame": (time.perf_counter() - t0) / n, "outputs": outputs}
