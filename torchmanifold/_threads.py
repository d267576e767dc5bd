"""Torch intra-op thread counts for a block or a function: one place for the library and the demo."""
from __future__ import annotations

import contextlib
import functools

import torch


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
    """Run ``fn`` on the calling thread alone. For a chain of elementwise passes over one frame: on a
    shared CPU each parallel region costs more to wake its threads than it saves (the denoiser's frame
    step took 20 ms longer on 2 threads than on 1 in such glue, `benchmarks/bench_pipeline.py`).
    Elementwise results do not depend on the thread count, so the bits stay the same."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        if torch.get_num_threads() == 1:
            return fn(*args, **kwargs)
        with torch_threads(1):
            return fn(*args, **kwargs)
    return run
