"""The adaptive-manifold filter op: public functions and modules, the pure-PyTorch reference and oracle.

- :func:`adaptive_manifold_filter` / :class:`AdaptiveManifoldFilter`: the spatial filter (B, C, H, W).
- :func:`temporal_adaptive_manifold_filter` / :class:`TemporalAdaptiveManifoldFilter`: a window of
  frames (B, T, C, H, W) filtered at query times, by a Gaussian time window or jointly in space-time.
- :func:`adaptive_manifold_torch`: the pure-PyTorch implementation (any device; the C++ kernel matches it).
- :func:`bilateral_brute_force`: the exact O(N^2) filter used as the test oracle.
"""
from torchmanifold.ops._reference import adaptive_manifold_torch
from torchmanifold.ops.adaptive_manifold import (
    AdaptiveManifoldFilter,
    adaptive_manifold_filter,
    automatic_tree_height,
    has_kernel,
)
from torchmanifold.ops.reference import bilateral_brute_force
from torchmanifold.ops.temporal import (
    TemporalAdaptiveManifoldFilter,
    spacetime_adaptive_manifold_torch,
    temporal_adaptive_manifold_filter,
    time_weights,
)

__all__ = [
    "AdaptiveManifoldFilter",
    "adaptive_manifold_filter",
    "adaptive_manifold_torch",
    "automatic_tree_height",
    "bilateral_brute_force",
    "has_kernel",
    "spacetime_adaptive_manifold_torch",
    "temporal_adaptive_manifold_filter",
    "TemporalAdaptiveManifoldFilter",
    "time_weights",
]
