"""Long clips on many machines: contiguous frame chunks with a halo, run by Ray workers.

A chunk *owns* a contiguous run of output frames (it writes them) and *reads* a halo of neighbour
frames around them that it never writes: the frames the filter needs to get the owned frames exactly
as the one-process path does. Sharded output is bitwise identical to :func:`~torchmanifold.pipeline.
denoise_files.denoise_files` and :func:`~torchmanifold.pipeline.render_job.render_job` because every owned frame is computed
from the same inputs by the same code:

- ``denoise``: output frame ``t`` is :func:`~torchmanifold.pipeline.denoise.denoise_frames` of the
  frames ``t - r .. t + r`` (``r = DenoiseSettings.window_radius``: the filter's, the albedo's and the
  evidence-lending neighbours' windows) at query ``t``; the halo is ``r`` frames per side.
- ``render``: iteration ``i`` filters query ``q`` from the samples of the frames in its time window and its
  evidence-lending neighbours' (``r = DenoiseSettings.query_radius``) and,
  as the firefly pilot, the running estimates of those frames after iteration ``i - 1``, which depend on
  *their* windows. So the frames that reach an owned frame after ``N`` iterations form a cone: ``N r``
  frames per side at iteration 1, one radius fewer each iteration (:func:`render_cone`).

One Ray actor per worker core runs chunks one after another (the next chunk goes to the first one
free) and keeps its imports, GL context and compiled tracer across chunks. Each worker writes its own
frames atomically (temporary name, then rename), so a retried chunk rewrites the same bytes and nobody
ever sees half a frame. The driver keeps a manifest of finished frames (``shards-manifest.json`` in the
output folder, rewritten atomically as frames finish); a re-run of the same job skips the frames listed
there.

Ray is imported only by the functions that run a job (``--engine ray``); planning needs nothing.

Fault injection for tests: when the environment variable ``TORCHMANIFOLD_SHARDS_KILL_FILE`` names an
existing file, the first worker that has written a frame with more of its chunk still to do claims the
file (renames it) and exits at once, the way a crashed or preempted worker would.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import pickle
import socket
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import torch

from torchmanifold._threads import set_threads
from torchmanifold.pipeline.denoise import DenoiseSettings, adapt_to_features, denoise_frames
from torchmanifold.timewindow import frame_at, index_window, window

__all__ = ["Chunk", "plan_chunks", "denoise_halo", "render_cone", "traced_frames", "connect",
           "shard_denoise", "shard_render", "MANIFEST", "RAY_VERSION"]

#: the name of the manifest of finished frames, in the output folder
MANIFEST = "shards-manifest.json"
#: the Ray release the project is tested with (requirements.txt)
RAY_VERSION = "2.60.0"
#: seconds to wait for a cluster address to answer before giving up (a live head answers in milliseconds)
CONNECT_TIMEOUT_S = 5.0
#: Ray retries of a chunk whose worker died (an application error is never retried: it would fail again)
MAX_RETRIES = 3
#: seconds the other chunks get to finish when one fails for good, before their workers are stopped
GRACE_S = 10.0
_KILL_ENV = "TORCHMANIFOLD_SHARDS_KILL_FILE"


# -- planning -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Chunk:
    """One task of a sharded job.

    Attributes:
        index: position in the plan.
        owned: the output indices (frames or query times) it writes, contiguous and increasing.
        lo, hi: the input frames it reads or traces, ``lo .. hi`` inclusive (owned frames + halo).
    """

    index: int
    owned: tuple[int, ...]
    lo: int
    hi: int


def _check_chunk(chunk) -> int:
    if not isinstance(chunk, int) or isinstance(chunk, bool) or chunk < 1:
        raise ValueError(f"chunk must be an integer >= 1 (frames per task), got {chunk!r}")
    return chunk


def plan_chunks(todo: Sequence[int], chunk: int, reads) -> list[Chunk]:
    """Split the output indices still to do into contiguous chunks of at most ``chunk``.

    A gap in ``todo`` (frames finished by an earlier run) ends a chunk, so no task rewrites a finished
    frame.

    Args:
        todo: output indices to produce, increasing.
        chunk: most outputs per chunk (>= 1).
        reads: ``callable(owned) -> (lo, hi)``: the input frames a chunk owning ``owned`` reads.

    Returns:
        The chunks in order.
    """
    _check_chunk(chunk)
    runs: list[list[int]] = []
    for q in todo:
        if runs and q == runs[-1][-1] + 1 and len(runs[-1]) < chunk:
            runs[-1].append(q)
        else:
            runs.append([q])
    return [Chunk(k, tuple(run), *reads(run)) for k, run in enumerate(runs)]


def denoise_halo(n: int, r: int):
    """``reads`` of :func:`plan_chunks` for ``denoise``: owned frames ``a..b`` read ``a-r .. b+r``."""
    return lambda owned: (index_window(n, owned[0], r)[0], index_window(n, owned[-1], r)[-1])


def render_cone(times: Sequence[float], query: Sequence[float], owned: Sequence[int], radius: int,
                iterations: int) -> tuple[list[list[int]], int, int]:
    """The query times a chunk must keep at every iteration so its owned ones come out exact.

    At iteration ``i`` a query needs the samples of the frames in its window and, as firefly pilot,
    the estimates after ``i - 1`` of those frames (frame times are query times). Going back from the
    last iteration, the needed set grows by the windows' frames each iteration.

    Args:
        times: ``(T,)`` frame times of the clip; query: ``(Q,)`` its output times (all frame times among them).
        owned: indices into ``query`` the chunk writes.
        radius: the frames on each side a query reads (``DenoiseSettings.query_radius``); iterations: ``N``.

    Returns:
        ``(keep, lo, hi)``: ``keep[i-1]`` = sorted query indices the chunk's engine must hold during
        iteration ``i`` (never growing), and the frames ``lo..hi`` it may trace.
    """
    frame_q = [frame_at(query, t) for t in times]
    if any(q is None for q in frame_q):
        raise ValueError("query must contain every frame time")
    need = [set(owned)]  # need[m] = queries exact after iteration N - m
    for _ in range(iterations - 1):
        prev = set(need[-1])
        for q in need[-1]:
            prev.update(frame_q[k] for k in window(times, query[q], radius))
        need.append(prev)
    need.reverse()  # need[i-1]: queries exact after iteration i
    # during iteration i the pilots (exact after i-1) must still be held: keep need[i-2] (need[0] at i = 1)
    keep = [sorted(need[max(i - 2, 0)]) for i in range(1, iterations + 1)]
    frames = {k for q in keep[0] for k in window(times, query[q], radius)}
    return keep, min(frames), max(frames)


def traced_frames(times: Sequence[float], query: Sequence[float], keep: Sequence[Sequence[int]],
                  radius: int) -> int:
    """Frame renders of a chunk's engine over all iterations: the union of its queries' windows, per
    iteration (what :class:`~torchmanifold.pipeline.progressive.ProgressiveRenderer` renders)."""
    return sum(len({k for q in ks for k in window(times, query[q], radius)}) for ks in keep)


# -- Ray ------------------------------------------------------------------------------------------------
def _import_ray():
    try:
        import ray
    except ImportError:
        raise ImportError(f"--engine ray needs the Python package 'ray', which is not installed; install it "
                          f"with `pip install ray=={RAY_VERSION}` (or `pip install -r requirements.txt`)") from None
    return ray


def _probe(address: str) -> None:
    """Fail within :data:`CONNECT_TIMEOUT_S` when nothing listens at ``host:port`` (``ray.init`` itself
    would retry for a minute)."""
    hostport = address.split("://", 1)[-1]
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise ValueError(f"--address must be HOST:PORT (e.g. 10.0.0.5:6379) or ray://HOST:PORT, "
                         f"got {address!r}")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        raise ConnectionError(f"--address {address}: no Ray cluster answers there ({exc}); start one with "
                              f"`ray start --head` on that machine, or leave --address out for a local "
                              f"cluster") from None


def connect(address: str | None = None) -> tuple[object, bool]:
    """Join a Ray cluster: an already initialised one, the one at ``address`` (``HOST:PORT``,
    ``ray://HOST:PORT`` or ``auto``), or a new local one (all cores).

    Returns:
        ``(ray module, started)``: ``started`` says this call initialised Ray (the caller shuts it down).

    Raises:
        ImportError: Ray is not installed (the message says how to install it).
        ConnectionError: nothing answers at ``address`` within :data:`CONNECT_TIMEOUT_S` seconds.
    """
    ray = _import_ray()
    if ray.is_initialized():
        return ray, False
    if address not in (None, "auto"):
        _probe(address)
    kw = dict(include_dashboard=False, log_to_driver=False) if address is None else {}
    ray.init(address=address, configure_logging=False, **kw)
    return ray, True


def _events_class():
    """The Ray actor body the workers report to and the driver drains (progress bar, manifest).

    Defined in a function so cloudpickle ships it by value: the actor's process then never imports
    this module (and torch), which costs seconds per process on a busy machine."""

    class Events:
        def __init__(self):
            self.events: list = []
            self.done: dict = {}

        def start(self, chunk: int, worker: str) -> list:
            self.events.append(("start", chunk, worker))
            return sorted(self.done)

        def frame(self, chunk: int, index: int, record: dict) -> None:
            self.done[index] = record
            self.events.append(("frame", chunk, index, record))

        def progress(self, chunk: int, n: int) -> None:
            self.events.append(("progress", chunk, n))

        def drain(self) -> list:
            out, self.events = self.events, []
            return out

        def reset(self) -> None:
            self.events, self.done = [], {}

    return Events


_EVENTS: dict[str, object] = {}  # Ray job id -> the events actor of this driver


def _events_actor(ray):
    """One events actor per driver, reset for each job: an actor takes a worker process of its own, and
    a new one per job would take a warm worker from the pool and make the tasks start a cold one."""
    job = ray.get_runtime_context().get_job_id()
    if job not in _EVENTS:
        _EVENTS.clear()
        _EVENTS[job] = ray.remote(num_cpus=0)(_events_class()).remote()
    ray.get(_EVENTS[job].reset.remote())
    return _EVENTS[job]


def _worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _maybe_die(more_to_do: bool) -> None:
    flag = os.environ.get(_KILL_ENV)
    if not flag or not more_to_do:
        return
    try:
        os.rename(flag, f"{flag}.claimed-{os.getpid()}")  # atomic: exactly one worker claims it
    except OSError:
        return
    os._exit(1)


def _run_chunk(kind: str, job: dict, chunk: Chunk, events) -> dict:
    """On a worker: produce the owned frames of ``chunk`` not yet reported done, reporting each one."""
    import ray

    set_threads(job["threads"])
    worker = _worker_id()
    done = set(ray.get(events.start.remote(chunk.index, worker)))
    t0 = time.perf_counter()
    todo = [q for q in chunk.owned if q not in done]
    body = _denoise_chunk if kind == "denoise" else _render_chunk
    written = 0
    counts = {}
    for q, files, record in body(job, chunk, todo, events, counts):
        record.update(worker=worker, files={f: {"bytes": (Path(job["out"]) / f).stat().st_size,
                                                 "sha256": _sha256(Path(job["out"]) / f)} for f in files})
        ray.get(events.frame.remote(chunk.index, q, record))  # synchronous: reported => written
        written += 1
        _maybe_die(written < len(todo))
    return {"chunk": chunk.index, "worker": worker, "frames": written, "seconds": time.perf_counter() - t0,
            **counts}


# -- denoise --------------------------------------------------------------------------------------------
def _denoise_chunk(job, chunk: Chunk, todo, events, counts):
    from torchmanifold.io.frames import read_render_frame, write_color
    from torchmanifold.pipeline.denoise_files import ClipWindow, denoise_window

    inputs = [Path(p) for p in job["inputs"]]
    first = read_render_frame(inputs[0], job["color"], job["feature_channels"], job["layer"])
    with ClipWindow(inputs, first, job["color"], job["samples_per_pixel"]) as clip:
        for t in todo:
            y, record, frame = denoise_window(clip, t, job["settings"])
            write_color(Path(job["out"]) / inputs[t].name, y, frame, job["output_layout"])
            events.progress.remote(chunk.index, 1)
            yield t, [inputs[t].name], record
            counts["frames_read"] = clip.reads


# -- render ---------------------------------------------------------------------------------------------
_TRACERS: dict[str, object] = {}  # per worker process: the warm GL context and compiled tracer


def _tracer(scene, width: int, height: int):
    from torchmanifold.render import PathTracer

    key = hashlib.sha256(pickle.dumps((scene, width, height))).hexdigest()
    if key not in _TRACERS:
        for old in _TRACERS.values():
            old.release()
        _TRACERS.clear()  # one scene at a time: a GL context per scene would pile up
        _TRACERS[key] = PathTracer(scene, width, height)
    return _TRACERS[key]


def _render_chunk(job, chunk: Chunk, todo, events, counts):
    from torchmanifold.pipeline.progressive import ProgressiveRenderer
    from torchmanifold.pipeline.render_job import render_reference, write_frame

    if not todo:
        return
    out = Path(job["out"])
    tracer = _tracer(job["scene"], job["width"], job["height"])
    times, query, n_it, seed = job["times"], job["query"], job["iterations"], job["seed"]
    settings = job["settings"]
    keep, lo, hi = render_cone(times, query, chunk.owned, settings.query_radius, n_it)
    traced = [0]

    def count(k, res):
        traced[0] += 1

    pr = ProgressiveRenderer(tracer, times[lo:hi + 1], [query[q] for q in keep[0]], settings=settings,
                             alpha=job["alpha"], seed=seed, on_render=count, scheme=job["scheme"])
    held = list(keep[0])
    for i in range(1, n_it + 1):
        for q in sorted(set(held) - set(keep[i - 1])):
            pr.untrack(query[q])
        held = keep[i - 1]
        state = pr.step()
        pr.history.clear()  # the chunk keeps only the running sums
        events.progress.remote(chunk.index, len(chunk.owned))
    counts["frames_traced"] = traced[0]
    owned_t = [query[q] for q in todo]
    rows = [frame_at(state.query_times, t) for t in owned_t]
    ref = None
    if job["reference_spp"] > 0:
        ref, _ = render_reference(tracer, owned_t, job["reference_spp"], seed)
    last = tracer.render(times=owned_t, spp=1, seed=seed, sample_offset=n_it - 1)
    for j, (q, row) in enumerate(zip(todo, rows)):
        files = write_frame(out, q, state.ours[row], state.raw[row], state.gaussian[row],
                            None if ref is None else ref[j], last.features[j], last.feature_names)
        yield q, files, {}


def _jsonable(settings: DenoiseSettings) -> dict:
    return {k: (str(v) if isinstance(v, torch.dtype) else v) for k, v in settings.__dict__.items()}


def _open_out(out, overwrite: bool, job_key: dict, n_outputs: int) -> tuple[Path, dict]:
    """The output folder and the manifest to resume from (empty when starting afresh)."""
    from torchmanifold.io.files import prepare_out

    out = Path(out).resolve()
    mpath = out / MANIFEST
    digest = hashlib.sha256(json.dumps(job_key, sort_keys=True, default=str).encode()).hexdigest()
    if mpath.is_file():
        try:
            m = json.loads(mpath.read_text())
        except ValueError:
            m = {}
        if m.get("job_sha256") == digest:
            return out, m  # the same job: resume
        if not overwrite:
            raise FileExistsError(f"--out {out} holds the manifest of another job ({mpath}); pass --overwrite "
                                  f"to start this one there")
        mpath.unlink()
    out = prepare_out(out, overwrite)
    return out, {"job_sha256": digest, "job": job_key, "outputs": n_outputs, "done": {}}


def _save_manifest(out: Path, m: dict) -> None:
    tmp = out / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(m, indent=1, sort_keys=True))
    os.replace(tmp, out / MANIFEST)


def _finished(out: Path, m: dict) -> set[int]:
    """Outputs the manifest lists whose files are all there with the recorded size."""
    ok = set()
    for key, rec in m["done"].items():
        files = rec["files"].items()
        if all((out / f).is_file() and (out / f).stat().st_size == v["bytes"] for f, v in files):
            ok.add(int(key))
    return ok


class _ChunkWorker:
    """Ray actor body: one per worker core, alive across chunks and jobs of a driver, so the imports, the
    GL context and the compiled tracer are paid once per process (Ray's task workers come and go)."""

    def run(self, kind: str, job: dict, chunk: Chunk, events) -> dict:
        return _run_chunk(kind, job, chunk, events)


_POOLS: dict[str, list] = {}  # Ray job id -> the chunk workers of this driver


def _pool(ray) -> list:
    job = ray.get_runtime_context().get_job_id()
    if job not in _POOLS:
        _POOLS.clear()
        n = max(1, int(ray.cluster_resources().get("CPU", 1)))
        # a worker that dies is restarted and its chunk run again (an application error is not retried)
        cls = ray.remote(num_cpus=1, max_restarts=MAX_RETRIES, max_task_retries=MAX_RETRIES)(_ChunkWorker)
        _POOLS[job] = [cls.remote() for _ in range(n)]
    return _POOLS[job]


def _drive(kind: str, job: dict, chunks: list[Chunk], manifest: dict, progress_total: int, progress: bool,
           desc: str) -> dict:
    """Run the chunks on the cluster's workers (the next chunk goes to the first worker free); keep the
    manifest and the bar up to date; return the summary."""
    import ray
    from tqdm.auto import tqdm

    out = Path(job["out"])
    events = _events_actor(ray)
    workers_ = _pool(ray)
    t0 = time.perf_counter()
    job_ref = ray.put(job)
    queue = list(chunks)
    inflight: dict = {}
    for w in workers_:
        if queue:
            inflight[w.run.remote(kind, job_ref, queue.pop(0), events)] = w
    bar = tqdm(total=progress_total, desc=desc, unit="frame" if kind == "denoise" else "frame-it",
               disable=not progress)
    starts: dict[int, int] = {}
    results: list[dict] = []
    reports = [0]

    def pump():
        for ev in ray.get(events.drain.remote()):
            if ev[0] == "start":
                starts[ev[1]] = starts.get(ev[1], 0) + 1
            elif ev[0] == "frame":
                manifest["done"][str(ev[2])] = ev[3]
                reports[0] += 1
            else:
                bar.update(ev[2])
        _save_manifest(out, manifest)

    try:
        while inflight:
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.25)
            for ref in ready:
                w = inflight.pop(ref)
                try:
                    results.append(ray.get(ref))
                except ray.exceptions.RayError as exc:
                    # no new chunks; the running ones get a moment to finish (their frames reach the
                    # manifest), then their workers are stopped
                    if inflight:
                        ray.wait(list(inflight), num_returns=len(inflight), timeout=GRACE_S)
                    pump()
                    for a in workers_:
                        ray.kill(a)
                    _POOLS.clear()
                    cause = getattr(exc, "cause", None)
                    if isinstance(exc, ray.exceptions.RayTaskError) and isinstance(cause, Exception):
                        raise cause from None  # the worker's own error (e.g. the unreadable file, named)
                    raise RuntimeError(f"a chunk failed after {MAX_RETRIES} retries: {exc}") from None
                if queue:
                    inflight[w.run.remote(kind, job_ref, queue.pop(0), events)] = w
            pump()
    finally:
        bar.close()
        for tmp in list(out.rglob("*.tmp")) + list(out.rglob("*.tmp.png")):  # left by a killed worker
            tmp.unlink(missing_ok=True)
    seconds = time.perf_counter() - t0
    workers: dict[str, dict] = {}
    for r in results:
        w = workers.setdefault(r["worker"], {"chunks": 0, "frames": 0, "seconds": 0.0})
        w["chunks"] += 1
        w["frames"] += r["frames"]
        w["seconds"] += r["seconds"]
    for w in workers.values():
        w["frames_per_second"] = w["frames"] / w["seconds"] if w["seconds"] > 0 else 0.0
    written = sum(r["frames"] for r in results)
    summary = {"engine": "ray", "chunks": len(chunks), "written": written, "seconds": seconds,
               "frames_per_second": written / seconds if seconds > 0 else 0.0,
               "retries": sum(max(0, s - 1) for s in starts.values()), "reports": reports[0],
               "workers": workers}
    for k in ("frames_read", "frames_traced"):
        if any(k in r for r in results):
            summary[k] = sum(r.get(k, 0) for r in results)
    return summary


def shard_denoise(inputs: Sequence[str | os.PathLike], out, settings: DenoiseSettings | None = None,
                  color_channels: Sequence[str] | None = None, feature_channels: Sequence[str] | None = None,
                  overwrite: bool = False, progress: bool = True, chunk: int | None = None,
                  address: str | None = None, threads: int = 1, layer: str | None = None,
                  output_layout: str = "input", samples_per_pixel: int | None = None) -> dict:
    """:func:`~torchmanifold.pipeline.denoise_files.denoise_files` on a Ray cluster, in chunks of frames.

    The outputs are the same files with the same bytes; each is written by the worker that computes
    it. A re-run into the same ``out`` skips the frames the manifest lists.

    Args:
        inputs, out, settings, color_channels, feature_channels, overwrite, progress, samples_per_pixel: as
            :func:`~torchmanifold.pipeline.denoise_files.denoise_files` (paths must be visible to every worker).
        chunk: frames a task writes (default: ``8 * max(r, 1)`` frames, at most an even share per worker).
        address: Ray cluster (``HOST:PORT``); ``None`` = the running one or a new local one.
        threads: torch threads per worker (the one-process path's ``--threads``).

    Returns:
        The keys of :func:`~torchmanifold.pipeline.denoise_files.denoise_files` (``frames``, ``size``,
        ``feature_channels``, non-finite counts, ``firefly_energy_removed``, ``noisy_sky_frames`` and
        ``kept_flat_frames`` (0 for frames a manifest of an earlier version lists), ``seconds_per_frame``,
        ``outputs``) over all frames of the clip, and ``"shards"``: ``chunks``, ``written`` (this run),
        ``reports`` (frame writes reported, retries included), ``skipped`` (finished before),
        ``seconds``, ``frames_per_second``, ``retries``, ``frames_read``
        (owned + halo), and per worker ``frames``, ``seconds``, ``frames_per_second``.

    Raises:
        FileNotFoundError, ValueError: as ``denoise_files``, and a bad ``chunk``; an unreadable frame stops
            the job with that file's error (finished frames stay, listed in the manifest).
        ImportError: Ray is not installed. ConnectionError: nothing answers at ``address``.
    """
    from torchmanifold.io.frames import read_render_frame
    from torchmanifold.pipeline.denoise_files import _check_inputs, clip_samples_per_pixel, clip_summary

    if chunk is not None:
        _check_chunk(chunk)
    inputs, _ = _check_inputs(inputs, out, output_layout)
    inputs = [p.resolve() for p in inputs]
    settings = (settings or DenoiseSettings(temporal_radius=1)).check()
    first = read_render_frame(inputs[0], color_channels, feature_channels, layer)
    settings = adapt_to_features(settings, first.feature_names)[0]
    spp = clip_samples_per_pixel(first, samples_per_pixel)
    ray, started = connect(address)  # before anything is written: a dead address writes nothing
    try:
        n, r = len(inputs), settings.window_radius
        key = {"kind": "denoise", "inputs": [str(p) for p in inputs], "settings": _jsonable(settings),
               "color": color_channels and list(color_channels), "features": first.feature_names,
               "layer": first.layer, "output_layout": output_layout, "samples_per_pixel": spp}
        outp, manifest = _open_out(out, overwrite, key, n)
        finished = _finished(outp, manifest)
        manifest["done"] = {k: v for k, v in manifest["done"].items() if int(k) in finished}
        _save_manifest(outp, manifest)
        workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        size = chunk or max(1, min(8 * max(r, 1), math.ceil(n / workers)))
        chunks = plan_chunks([t for t in range(n) if t not in finished], size, denoise_halo(n, r))
        job = {"inputs": [str(p) for p in inputs], "out": str(outp), "settings": settings,
               "color": color_channels and list(color_channels), "feature_channels": first.feature_names,
               "layer": first.layer, "output_layout": output_layout, "size": list(first.size),
               "threads": threads, "samples_per_pixel": spp}
        shards = _drive("denoise", job, chunks, manifest, n - len(finished), progress, "denoise")
    finally:
        if started:
            ray.shutdown()
    shards.update(chunk=size, halo=r, skipped=len(finished))
    recs = [manifest["done"][str(t)] for t in range(n)]  # every frame is listed now, summed in frame order
    return {"frames": n, "size": list(first.size), "feature_channels": first.feature_names,
            **clip_summary(recs, settings, spp),
            "seconds_per_frame": shards["seconds"] / max(shards["written"], 1),
            "outputs": [str(outp / p.name) for p in inputs], "shards": shards}


def shard_render(out, scene=None, frames: int = 8, iterations: int = 16, width: int = 128, height: int = 96,
                 seed: int = 0, reference_spp: int = 0, overwrite: bool = False,
                 settings: DenoiseSettings | None = None, alpha: float | None = None, inbetween: int = 0,
                 progress: bool = True, chunk: int | None = None, address: str | None = None,
                 threads: int = 1, scheme: str = "accumulate") -> dict:
    """The frames of :func:`~torchmanifold.pipeline.render_job.render_job` rendered on a Ray cluster in chunks.

    Every chunk runs the progressive loop (:class:`~torchmanifold.pipeline.progressive.ProgressiveRenderer`)
    over its owned output times and the cone of neighbours they depend on (:func:`render_cone`), and
    writes ``frames/frame_QQQQ.exr`` and ``png/frame_QQQQ.png`` of its owned times: the same bytes as
    ``render_job``. The clip-wide parts of ``render_job`` (metrics against the reference over the whole
    clip per iteration, MP4s, chart) need every frame in one place and are not made here.

    Args:
        out, scene, frames, iterations, width, height, seed, reference_spp, overwrite, settings, alpha,
            inbetween, progress: as :func:`~torchmanifold.pipeline.render_job.render_job` (``reference_spp`` > 0
            adds the ``reference.R/G/B`` channels, rendered by the chunk for its own frames).
        chunk: output times a task writes (default: an even share per worker).
        address, threads: as :func:`shard_denoise`.

    Returns:
        ``{"frames", "outputs", "iterations", ..., "shards": {...}}`` where ``shards`` also has
        ``frames_traced`` (frame renders of all chunks of this run) and ``frames_traced_one_process``
        (``iterations * frames``, what the one-process loop renders).

    Raises:
        ValueError: bad arguments (named). ImportError, ConnectionError: as :func:`shard_denoise`.
    """
    from torchmanifold.pipeline.progressive import PROGRESSIVE_FILTER
    from torchmanifold.pipeline.render_job import _check_job_ints, _resolve_scene, render_query_times
    from torchmanifold.pipeline.schedule import DEFAULT_ALPHA

    if chunk is not None:
        _check_chunk(chunk)
    _check_job_ints(frames=frames, iterations=iterations, width=width, height=height,
                    reference_spp=reference_spp, inbetween=inbetween, seed=seed)
    alpha = DEFAULT_ALPHA if alpha is None else alpha
    scene_obj, _ = _resolve_scene(scene)
    settings = (settings or DenoiseSettings(**PROGRESSIVE_FILTER)).check()
    times, query = render_query_times(frames, inbetween)
    ray, started = connect(address)
    try:
        scene_sha = hashlib.sha256(pickle.dumps(scene_obj)).hexdigest()
        key = {"kind": "render", "scene": scene_sha, "frames": frames,
               "iterations": iterations, "width": width, "height": height, "seed": seed,
               "reference_spp": reference_spp, "settings": _jsonable(settings), "alpha": alpha, "scheme": scheme,
               "inbetween": inbetween}
        outp, manifest = _open_out(out, overwrite, key, len(query))
        finished = _finished(outp, manifest)
        manifest["done"] = {k: v for k, v in manifest["done"].items() if int(k) in finished}
        _save_manifest(outp, manifest)
        workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        size = chunk or max(1, math.ceil(len(query) / workers))
        r = settings.query_radius

        def reads(owned):
            return render_cone(times, query, owned, r, iterations)[1:]

        chunks = plan_chunks([q for q in range(len(query)) if q not in finished], size, reads)
        job = {"out": str(outp), "scene": scene_obj, "width": width, "height": height, "times": times,
               "query": query, "iterations": iterations, "seed": seed, "reference_spp": reference_spp,
               "settings": settings, "alpha": alpha, "threads": threads, "scheme": scheme}
        todo = len(query) - len(finished)
        shards = _drive("render", job, chunks, manifest, todo * iterations, progress, "render")
    finally:
        if started:
            ray.shutdown()
    shards.update(chunk=size, skipped=len(finished), frames_traced_one_process=iterations * frames)
    return {"frames": frames, "query_times": query, "iterations": iterations, "width": width, "height": height,
            "seed": seed, "reference_spp": reference_spp, "alpha": alpha, "settings": _jsonable(settings),
            "outputs": [str(outp / f) for q in range(len(query))
                        for f in (f"frames/frame_{q:04d}.exr", f"png/frame_{q:04d}.png")],
            "shards": shards}
