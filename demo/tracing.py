"""The tracer in its own process: the next iteration of the whole clip renders while this one filters.

The progressive engine keeps calling ``render(times=[t], spp=1, seed, sample_offset=i)`` one frame at a
time; the first such call of iteration ``i`` renders all clip frames of sample ``i`` in one dispatch and
queues sample ``i + 1``, so the tracer renders iteration ``i + 1`` while the caller filters iteration ``i``.
The tracer's RNG is keyed on (pixel, sample index, frame time, seed), so a frame cut out of the clip's
render is the frame rendered alone: the images are the same as without the look-ahead, bit for bit.

Why a process and not a thread: moderngl keeps the GIL through every call, and llvmpipe runs a compute
dispatch to the end inside ``glDispatchCompute`` (a 128x128x3 dispatch held the GIL for 600-700 ms,
measured on the 2-core VM), so a tracer thread stops the filter's Python between torch ops; measured, a
thread made the iteration slower, not faster. The child process has its own GIL and its own GL context;
a frame set comes back through a pipe (about 5 MB at 128x128x3, a few ms). A thread in this process only
waits on that pipe (waiting releases the GIL) and keeps the order of the jobs.
"""
from __future__ import annotations

import dataclasses
import multiprocessing
import queue
import threading
import time
from concurrent.futures import Future
from typing import Sequence

import numpy as np
import torch


@dataclasses.dataclass(frozen=True)
class TracerSpec:
    """What the tracer process builds: ``PathTracer(scene, width, height)`` (picklable)."""

    scene: object
    width: int
    height: int

    def __call__(self, ctx):
        from torchmanifold.render import PathTracer

        return PathTracer(self.scene, width=self.width, height=self.height, ctx=ctx)


def _serve(conn, make_tracer) -> None:
    """The tracer process: build the tracer, then answer render requests until told to stop."""
    torch.set_num_threads(1)  # it only wraps the read-back arrays
    try:
        from torchmanifold.render import create_context

        tracer = make_tracer(create_context())
    except BaseException as exc:  # noqa: BLE001  (re-raised in the parent)
        conn.send(("error", exc))
        return
    conn.send(("ready", (tracer.width, tracer.height, list(tracer.feature_names))))
    while True:
        kwargs = conn.recv()
        if kwargs is None:
            break
        try:
            t0 = time.perf_counter()
            res = tracer.render(**kwargs)
            fields = {f.name: getattr(res, f.name) for f in dataclasses.fields(res)}
            fields = {k: (v.numpy() if isinstance(v, torch.Tensor) else v) for k, v in fields.items()}
            conn.send(("ok", (fields, time.perf_counter() - t0)))
        except BaseException as exc:  # noqa: BLE001
            conn.send(("error", exc))
    tracer.release()
    conn.close()


class TracerProcess:
    """A ``PathTracer`` living in a child process, with one iteration of look-ahead over a clip.

    Args:
        make_tracer: picklable ``callable(ctx) -> PathTracer`` (e.g. :class:`TracerSpec`), called in the
            child with its GL context (``torchmanifold.render.create_context()``).
        clip_times: the frame times the engine renders every iteration; a ``spp=1`` render of one of
            them is served from (and triggers) the look-ahead.
        prefetch: render the next iteration ahead (False: every call renders on demand, in the worker).

    Attributes:
        width, height, feature_names: those of the tracer.
        trace_seconds: wall time the tracer spent in the last whole-clip render (the trace stage; 0 without
            look-ahead, where the engine's wait is the whole trace).
        wait_seconds: time callers spent blocked on renders since :meth:`take_wait` last reset it.
    """

    def __init__(self, make_tracer, clip_times: Sequence[float], prefetch: bool = True):
        self.clip_times = [float(t) for t in clip_times]
        if not self.clip_times:
            raise ValueError("clip_times: expected at least one frame time")
        self.prefetch = bool(prefetch)
        self._jobs: queue.Queue = queue.Queue()
        self._clip: dict[tuple[int, int], Future] = {}  # (seed, sample_offset) -> whole-clip RenderResult
        self._lock = threading.Lock()
        self.trace_seconds = 0.0
        self.wait_seconds = 0.0
        ready: Future = Future()
        # spawn, not fork: the parent holds GL contexts and thread pools a fork would copy half of
        mp = multiprocessing.get_context("spawn")
        self._conn, child = mp.Pipe()
        self._process = mp.Process(target=_serve, args=(child, make_tracer), name="demo-tracer", daemon=True)
        self._process.start()
        child.close()
        kind, payload = self._conn.recv()
        if kind == "error":
            self._process.join()
            raise payload  # the child's error (no GL driver, bad scene, ...)
        self.width, self.height, self.feature_names = payload
        self._thread = threading.Thread(target=self._work, name="demo-tracer-jobs", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------- worker side
    def _work(self) -> None:
        from torchmanifold.render.frames import RenderResult

        while True:
            job = self._jobs.get()
            if job is None:
                break
            fut, kwargs, clip = job
            if not fut.set_running_or_notify_cancel():
                continue
            self._conn.send(kwargs)
            kind, payload = self._conn.recv()  # waiting here releases the GIL: the filter runs meanwhile
            if kind == "error":
                fut.set_exception(payload)
                continue
            fields, seconds = payload
            if clip:
                self.trace_seconds = seconds
            fut.set_result(RenderResult(**{k: (torch.from_numpy(v) if isinstance(v, np.ndarray) else v)
                                           for k, v in fields.items()}))

    def _submit(self, clip: bool = False, **kwargs) -> Future:
        fut: Future = Future()
        self._jobs.put((fut, kwargs, clip))
        return fut

    def _clip_future(self, seed: int, offset: int) -> Future:
        key = (seed, offset)
        with self._lock:
            fut = self._clip.get(key)
            if fut is None:
                fut = self._clip[key] = self._submit(clip=True, times=self.clip_times, spp=1, seed=seed,
                                                     sample_offset=offset)
            return fut

    # ------------------------------------------------------------------------------- caller side
    def render(self, times, spp: int = 1, seed: int = 0, sample_offset: int = 0, **kwargs):
        """``PathTracer.render`` (same arguments, same result), run in the worker thread."""
        t0 = time.perf_counter()
        try:
            times_l = [float(t) for t in times]
            if self.prefetch and spp == 1 and not kwargs and len(times_l) == 1 and times_l[0] in self.clip_times:
                fut = self._clip_future(seed, sample_offset)
                with self._lock:
                    for key in [k for k in self._clip if k not in ((seed, sample_offset), (seed, sample_offset + 1))]:
                        self._clip.pop(key).cancel()  # other samples (earlier, or before a restart) are done with
                # the next iteration renders while this one is filtered
                self._clip_future(seed, sample_offset + 1)
                k = self.clip_times.index(times_l[0])
                return _frame(fut.result(), k)
            return self._submit(times=times, spp=spp, seed=seed, sample_offset=sample_offset, **kwargs).result()
        finally:
            self.wait_seconds += time.perf_counter() - t0

    def take_wait(self) -> float:
        """Seconds callers waited on renders since the last call (the trace time not hidden)."""
        w, self.wait_seconds = self.wait_seconds, 0.0
        return w

    def drop_lookahead(self) -> None:
        """Forget the rendered-ahead samples (after a restart they would be the wrong ones)."""
        with self._lock:
            for fut in self._clip.values():
                fut.cancel()
            self._clip.clear()

    def close(self) -> None:
        """Stop the job thread and the tracer process (which releases its tracer)."""
        if self._thread.is_alive():
            self.drop_lookahead()
            self._jobs.put(None)
            self._thread.join()
            self._conn.send(None)
            self._process.join(timeout=60)
            self._conn.close()


def _frame(res, k: int):
    """Frame ``k`` of a whole-clip ``RenderResult`` as a one-frame result (views, no copies)."""
    cut = {f.name: getattr(res, f.name)[k:k + 1] for f in dataclasses.fields(res)
           if isinstance(getattr(res, f.name), torch.Tensor)}
    return dataclasses.replace(res, **cut)
