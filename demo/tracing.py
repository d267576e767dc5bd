"""The tracer on its own thread: the next iteration of the whole clip renders while this one filters.

A GL context is current in one thread at a time, so :class:`TracerThread` makes its own headless
context and :class:`~torchmanifold.render.PathTracer` in a worker thread and runs every render there.
The progressive engine keeps calling ``render(times=[t], spp=1, seed, sample_offset=i)`` one frame at a
time; the first such call of iteration ``i`` renders all clip frames of sample ``i`` in one dispatch and
queues sample ``i + 1``, so the worker traces iteration ``i + 1`` while the caller filters iteration ``i``
(torch and the GL driver release the GIL). The tracer's RNG is keyed on (pixel, sample index, frame
time, seed), so a frame cut out of the clip's render is the frame rendered alone: the images are the
same as without the thread, bit for bit.
"""
from __future__ import annotations

import dataclasses
import queue
import threading
import time
from concurrent.futures import Future
from typing import Callable, Sequence

import torch


class TracerThread:
    """A ``PathTracer`` living in a worker thread, with one iteration of look-ahead over a clip.

    Args:
        make_tracer: ``callable(ctx) -> PathTracer``, called in the worker with the worker's own GL
            context (``torchmanifold.render.create_context(new=True)``).
        clip_times: the frame times the engine renders every iteration; a ``spp=1`` render of one of
            them is served from (and triggers) the look-ahead.
        prefetch: render the next iteration ahead (False: every call renders on demand, in the worker).

    Attributes:
        width, height, feature_names: those of the tracer.
        trace_seconds: wall time the worker spent in the last whole-clip render (the trace stage).
        wait_seconds: time callers spent blocked on renders since :meth:`take_wait` last reset it.
    """

    def __init__(self, make_tracer: Callable, clip_times: Sequence[float], prefetch: bool = True):
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
        self._thread = threading.Thread(target=self._work, args=(make_tracer, ready), name="demo-tracer",
                                        daemon=True)
        self._thread.start()
        tracer = ready.result()  # re-raises the worker's error (no GL driver, bad scene, ...)
        self.width, self.height = tracer.width, tracer.height
        self.feature_names = list(tracer.feature_names)

    # ------------------------------------------------------------------------------- worker side
    def _work(self, make_tracer, ready: Future) -> None:
        from torchmanifold.render import create_context

        try:
            tracer = make_tracer(create_context(new=True))
        except BaseException as exc:  # noqa: BLE001  (handed to the constructor's thread)
            ready.set_exception(exc)
            return
        ready.set_result(tracer)
        torch.set_num_threads(1)  # the worker only reads back and wraps arrays
        while True:
            job = self._jobs.get()
            if job is None:
                break
            fut, kwargs, clip = job
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                t0 = time.perf_counter()
                res = tracer.render(**kwargs)
                if clip:
                    self.trace_seconds = time.perf_counter() - t0
                fut.set_result(res)
            except BaseException as exc:  # noqa: BLE001
                fut.set_exception(exc)
        tracer.release()
        tracer.ctx.release()  # the context was made here and dies here

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
        """Stop the worker (its tracer and GL context are released in its own thread)."""
        if self._thread.is_alive():
            self.drop_lookahead()
            self._jobs.put(None)
            self._thread.join()


def _frame(res, k: int):
    """Frame ``k`` of a whole-clip ``RenderResult`` as a one-frame result (views, no copies)."""
    cut = {f.name: getattr(res, f.name)[k:k + 1] for f in dataclasses.fields(res)
           if isinstance(getattr(res, f.name), torch.Tensor)}
    return dataclasses.replace(res, **cut)
