"""A simple bounding-volume hierarchy over triangles, flattened for a GLSL storage buffer.

Median split on the longest centroid axis, leaves of at most ``leaf_size`` triangles. Nodes are in
depth-first order: an interior node's left child is the next node, its right child index is stored, and so
is its split axis, so that a traversal can visit the child nearer the ray first (the left child holds the
lower centroids). That is all a shader needs for a stack traversal; meshes in our scenes are small.
"""
from __future__ import annotations

import numpy as np


def build_bvh(triangles: np.ndarray, leaf_size: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Build a BVH over triangles.

    Args:
        triangles: ``(M, 3, 3)`` float vertices of M triangles.
        leaf_size: the most triangles in a leaf.

    Returns:
        ``(nodes, order)``: ``nodes`` is a structured list as an ``(N, 8)`` float64 array with rows
        ``(min x, min y, min z, first_or_right, max x, max y, max z, count)`` where ``count > 0``
        marks a leaf holding triangles ``order[first:first+count]`` and ``count = -1 - axis < 0`` an
        interior node split along ``axis`` whose children are ``row + 1`` (lower centroids) and
        ``first_or_right``; ``order`` is the triangle permutation the leaves index into.
    """
    tris = np.asarray(triangles, dtype=np.float64)
    if tris.ndim != 3 or tris.shape[1:] != (3, 3) or len(tris) == 0:
        raise ValueError(f"build_bvh: triangles must be a non-empty (M, 3, 3) array, got {tris.shape}")
    lo_t, hi_t = tris.min(axis=1), tris.max(axis=1)
    cent = tris.mean(axis=1)
    order = np.arange(len(tris))
    nodes: list[list[float]] = []

    # explicit stack instead of recursion: (start, end, parent row to patch with the right child)
    stack = [(0, len(tris), -1)]
    while stack:
        start, end, patch = stack.pop()
        row = len(nodes)
        if patch >= 0:
            nodes[patch][3] = row
        idx = order[start:end]
        lo, hi = lo_t[idx].min(axis=0), hi_t[idx].max(axis=0)
        n = end - start
        if n <= leaf_size:
            nodes.append([*lo, start, *hi, n])
            continue
        c = cent[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        order[start:end] = idx[np.argsort(c[:, axis], kind="stable")]
        mid = start + n // 2
        nodes.append([*lo, -1, *hi, -1 - axis])
        # left child must come right after this node: push right first so left is popped first
        stack.append((mid, end, row))
        stack.append((start, mid, -1))
    return np.asarray(nodes, dtype=np.float64), order
