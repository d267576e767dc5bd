"""torchmanifold: adaptive-manifold filtering for progressive Monte Carlo video rendering.

The filter op lives in :mod:`torchmanifold.ops`, the path tracer in :mod:`torchmanifold.render`,
the progressive pipeline in :mod:`torchmanifold.pipeline`, EXR/video I/O in :mod:`torchmanifold.io`.
"""
from torchmanifold._extension import build_info
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
