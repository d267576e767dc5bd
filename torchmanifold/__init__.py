"""torchmanifold: adaptive-manifold filtering for progressive Monte Carlo video rendering.

The filter op lives in :mod:`torchmanifold.ops`, the path tracer in :mod:`torchmanifold.render`,
the progressive pipeline in :mod:`torchmanifold.pipeline`, EXR/video I/O in :mod:`torchmanifold.io`.
"""
import os

# OpenMP workers sleep as soon as a parallel region ends instead of spinning: with two torch threads on two
# busy cores the spinning made a render iteration 10x slower (19 s instead of 2 s) and the frame step 4x
# slower (benchmarks/bench_threads.py). libgomp reads this once, when torch loads it: effective when
# torchmanifold is imported before torch (as the CLI does); a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from torchmanifold._extension import build_info  # noqa: E402
from torchmanifold.ops import (
    AdaptiveManifoldFilter,
    TemporalAdaptiveManifoldFilter,
    adaptive_manifold_filter,
    bilateral_brute_force,
    temporal_adaptive_manifold_filter,
)

__version__ = "0.1.0"
__all__ = [
    "AdaptiveManifoldFilter",
    "TemporalAdaptiveManifoldFilter",
    "adaptive_manifold_filter",
    "bilateral_brute_force",
    "build_info",
    "temporal_adaptive_manifold_filter",
]
