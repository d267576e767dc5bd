"""Benchmarks live outside ``testpaths``: ``pytest benchmarks`` (or a file) collects ``bench_*.py`` here.

``--quick`` shrinks every benchmark to a smoke run (small sizes, few frames; what CI may run). Timings are
recorded, never asserted.
"""
import os
import sys
from pathlib import Path

# Threads for every library, fixed before torch loads and recorded in the results. Default 1: on a shared,
# oversubscribed machine a 2-thread parallel region waits for a descheduled thread at every barrier (kornia
# gaussian_blur2d 64x64 measured 1 ms or 60-200 ms depending on the neighbours' load); one thread stays comparable.
THREADS = int(os.environ.setdefault("TORCHMANIFOLD_BENCH_THREADS", "1"))
os.environ["OMP_NUM_THREADS"] = str(THREADS)

import pytest

_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:  # bench files import baselines.py / harness.py beside them
    sys.path.insert(0, _HERE)


def pytest_configure(config):
    import cv2
    import torch

    torch.set_num_threads(THREADS)
    cv2.setNumThreads(THREADS)


def pytest_addoption(parser):
    parser.addoption("--quick", action="store_true", default=False,
                     help="smoke-run the benchmarks at tiny sizes (no numbers worth quoting)")


def pytest_collect_file(file_path, parent):
    if file_path.suffix == ".py" and file_path.name.startswith("bench_") and file_path.parent == Path(_HERE):
        if parent.session.isinitpath(file_path):
            return None  # named on the command line: pytest collects it already
        return pytest.Module.from_parent(parent, path=file_path)
    return None


@pytest.fixture(scope="session")
def quick(request) -> bool:
    return bool(request.config.getoption("--quick"))
