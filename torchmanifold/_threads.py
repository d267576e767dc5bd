"""Torch intra-op thread counts for a block or a function, and the cores a job takes (:func:`set_threads`):
one place for the library and the demo.

The pipeline is thousands of small elementwise torch ops around a few C++ ops. With OpenMP workers that
sleep between parallel regions (``import torchmanifold`` sets ``OMP_WAIT_POLICY=PASSIVE``, see
``torchmanifold/__init__.py``), every small op on two threads paid more to wake a worker than it saved:
the denoiser's frame step took 20 ms longer on 2 threads than on 1 in such glue, and a ``render``
iteration (128x96 frames) was no faster on 2 threads than on 1 (``benchmarks/bench_threads.py``). So a
pipeline entry point runs :func:`serial` and the C++ ops it calls run :func:`call_parallel`, with the threads
the caller had. Elementwise results do not depend on the thread count, and the ops give the same bits
for any count, so nothing changes but the time.
"""
from __future__ import annotations

import contextlib
import functools
import os
import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

import torch

_caller = threading.local()  # .threads: the count a serial() entry point took away, inside it
#: llvmpipe's rasterizer threads as the user's environment set them (None: not set); theirs wins
_USER_LLVMPIPE_THREADS = os.environ.get("LP_NUM_THREADS")


def set_threads(n: int) -> None:
    """Give this process ``n`` cores: torch's intra-op threads and the threads Mesa's llvmpipe renders the
    path tracer with (``LP_NUM_THREADS``, unless the user set it). llvmpipe reads it when the first GL
    context is made, so call this before creating a tracer. By default llvmpipe takes every core whatever
    torch's count: a one-thread ``render`` then traced on two cores, and two jobs of one thread each shared
    both cores' rasterizers."""
    torch.set_num_threads(n)
    if _USER_LLVMPIPE_THREADS is None:
        os.environ["LP_NUM_THREADS"] = str(int(n))


@contextlib.contextmanager
def torch_threads(n: int | None):
    """Run the block with ``n`` torch intra-op threads (None = unchanged), then restore the count."""
    if n is None:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def serial(fn):
    """Run ``fn`` on the calling thread alone; the :func:`call_parallel` calls inside it get the caller's
    threads."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        n = torch.get_num_threads()
        if n == 1:
            return fn(*args, **kwargs)
        before = getattr(_caller, "threads", None)
        _caller.threads = n
        try:
            with torch_threads(1):
                return fn(*args, **kwargs)
        finally:
            _caller.threads = before
    return run


def caller_threads() -> int:
    """The torch threads of the :func:`serial` entry point around this call (the current count outside
    one)."""
    return getattr(_caller, "threads", None) or torch.get_num_threads()


def call_parallel(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` (a C++ op, which scales) with the threads of the :func:`serial` entry point
    around it, if any."""
    if torch.compiler.is_compiling():  # a traced graph has no thread count to set
        return fn(*args, **kwargs)
    n = getattr(_caller, "threads", None)
    if n is None or n == torch.get_num_threads():
        return fn(*args, **kwargs)
    with torch_threads(n):
        return fn(*args, **kwargs)


def parallel(fn):
    """Decorator form of :func:`call_parallel`."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        return call_parallel(fn, *args, **kwargs)
    return run


class InOrder:
    """Independent calls run side by side on worker threads that share ``threads`` torch threads between
    them, at most one per worker ahead of the caller (what a call holds stays bounded), with the results
    handed back in submission order (so anything summed from them sums in one order for any thread
    count). With one worker (one thread, or one call) each call runs at once on the calling thread.

    Use as a context manager::

        with InOrder(threads, calls) as pool:
            for item in items:
                for key, result in pool.submit(key, fn, *args):
                    ...  # the results now due, in order
            for key, result in pool.drain():
                ...
    """

    def __init__(self, threads: int, calls: int):
        self.workers = max(1, min(int(threads), int(calls)))
        self.threads_each = max(1, int(threads) // self.workers)
        self._pool = None
        self._pending: deque = deque()

    def __enter__(self) -> "InOrder":
        if self.workers > 1:
            self._pool = ThreadPoolExecutor(self.workers)
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def submit(self, key, fn, *args) -> list:
        """Queue ``fn(*args)``; returns the ``(key, result)`` pairs due now (oldest first)."""
        if self._pool is None:
            return [(key, fn(*args))]
        self._pending.append((key, self._pool.submit(_with_threads, self.threads_each, fn, *args)))
        done = []
        while len(self._pending) > self.workers:
            k, fut = self._pending.popleft()
            done.append((k, fut.result()))
        return done

    def ahead(self, fn, *args) -> Future:
        """Start ``fn(*args)`` on a worker, outside the ordered results, for later calls to wait on (the
        caller bounds how many are held); with one worker it runs at once. Workers take calls first come,
        first served, so a call submitted after the ones it waits on never waits on a call still queued."""
        if self._pool is None:
            done: Future = Future()
            try:
                done.set_result(fn(*args))
            except Exception as e:  # raised where the result is taken, as from a worker
                done.set_exception(e)
            return done
        return self._pool.submit(_with_threads, self.threads_each, fn, *args)

    def drain(self) -> list:
        """Every result still due, in order."""
        done = [(k, fut.result()) for k, fut in self._pending]
        self._pending.clear()
        return done


def _with_threads(n: int, fn, *args):
    with torch_threads(n):
        return fn(*args)
