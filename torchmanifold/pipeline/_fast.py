"""Fused C++ kernels of the denoiser's frame step, and when each may run.

:mod:`torchmanifold.pipeline.denoise` keeps every stage in PyTorch: that code is the reference and the
path on other devices and dtypes. A stage calls :func:`enabled` with its tensors and, when it holds,
the ``torchmanifold::_<stage>`` op (``csrc/ops/denoise_steps.cpp``, CPU kernels in
``csrc/ops/cpu/denoise_steps_kernel.cpp``), which mirrors the stage's float operations and agrees with
it to float rounding, with the same bytes for any thread count.

Use :func:`reference` to run the PyTorch stages instead (tests compare the two; benchmarks time both).
"""
from __future__ import annotations

import contextlib
import math
import threading

import torch
from torch import Tensor

from torchmanifold._threads import call_parallel, parallel

__all__ = ["enabled", "reference", "normalise_guard", "normalise_guard_bounds", "window_bounds",
           "footprint_average", "kuwahara3", "cv_blend", "cv_residuals", "quantiles", "cv_halves", "cv_split",
           "sanitize", "normalised_blur", "box_mean", "same_pixel", "footprint_samples", "edge_directions",
           "along_edges", "least_offset_cost", "median_offset_costs"]

_FLOATS = (torch.float32, torch.float64)
_state = threading.local()
#: largest workspace kept between calls, in elements (64 MB of float32: a 1 MP frame's stack)
_MAX_WORKSPACE = 1 << 24
_HAVE_OPS: bool | None = None


def _have_ops() -> bool:
    try:
        return hasattr(torch.ops.torchmanifold, "_cv_blend")
    except (AttributeError, RuntimeError):  # pragma: no cover - no extension
        return False


def enabled(*tensors: Tensor) -> bool:
    """True when the fused kernels may run on ``tensors``: the ops are built, every tensor is a CPU
    float32/float64 tensor of one dtype that needs no gradient (the kernels have no backward), and
    :func:`reference` is not active."""
    global _HAVE_OPS
    if getattr(_state, "reference", False):
        return False
    if _HAVE_OPS is None:  # first call: torchmanifold._C is loaded by then (torchmanifold/__init__)
        _HAVE_OPS = _have_ops()
    if not _HAVE_OPS:
        return False
    dt = tensors[0].dtype
    return dt in _FLOATS and all(t.device.type == "cpu" and t.dtype == dt and not t.requires_grad for t in tensors)


@contextlib.contextmanager
def reference():
    """Within this block (this thread) the denoiser runs its pure-PyTorch stages."""
    old = getattr(_state, "reference", False)
    _state.reference = True
    try:
        yield
    finally:
        _state.reference = old


@parallel
def normalise_guard(num: Tensor, den: Tensor, values: Tensor, mask: Tensor, radius: int) -> Tensor:
    """``_Filter.normalise`` at frame queries: num ``(N, C, H, W)``, den ``(N, 1, H, W)``, values
    ``(N, C, H, W)``, mask ``(N, 1, H, W)`` -> ``(N, C, H, W)``; ``radius`` 0 skips the guard."""
    return torch.ops.torchmanifold._normalise_guard(num, den, values, mask, int(radius))


@parallel
def normalise_guard_bounds(num: Tensor, den: Tensor, fallback: Tensor, hi: Tensor, nlo: Tensor,
                           radius: int) -> Tensor:
    """``_Filter.normalise`` where a query mixes a window: num, fallback (the masked values at the
    queries), hi and nlo (``_Filter.window_bounds``) ``(N, C, H, W)``, den ``(N, 1, H, W)`` ->
    ``(N, C, H, W)``; ``radius`` 0 skips the guard."""
    return torch.ops.torchmanifold._normalise_guard_bounds(num, den, fallback, hi, nlo, int(radius))


@parallel
def window_bounds(values: Tensor, mask: Tensor, starts: list[int],
                  lengths: list[int]) -> tuple[Tensor, Tensor]:
    """``_Filter.window_bounds`` where each query's frames are consecutive: values ``(T, C, H, W)``, mask
    ``(T, 1, H, W)``, each query's first frame and frame count -> hi and nlo ``(Q, C, H, W)``."""
    return torch.ops.torchmanifold._window_bounds(values, mask, [int(s) for s in starts],
                                                  [int(n) for n in lengths])


@parallel
def footprint_average(x: Tensor, k: Tensor, sigma: float, range_sigma: float,
                      unseen_border: float = 0.0) -> Tensor:
    """``denoise._footprint_average`` after its tone-mapping knee: x ``(T, 3, H, W)`` (clamped at 0), k
    ``(T, 1, 1, 1)`` -> ``(T, 3, H, W)``."""
    return torch.ops.torchmanifold._footprint_average(x, k.reshape(-1), float(sigma), float(range_sigma),
                                                      float(unseen_border))


@parallel
def edge_directions(x: Tensor, k: Tensor, tensor_sigma: float, power: float) -> Tensor:
    """``footprint._edge_directions`` after its knee: x ``(T, 3, H, W)``, k ``(T, 1, 1, 1)`` ->
    ``(T, 3, H, W)``, each pixel's coherence to ``power`` and its edge direction ``(tx, ty)``."""
    return torch.ops.torchmanifold._edge_directions(x, k.reshape(-1), float(tensor_sigma), float(power))


@parallel
def along_edges(x: Tensor, k: Tensor, sigma: Tensor, directions: Tensor, range_sigma: float) -> Tensor:
    """``footprint._along_edges`` after the knees of M images sharing one set of directions: x ``(M, T, 3, H,
    W)``, k ``(M, T, 1, 1, 1)``, sigma ``(M, T, 1, H, W)``, directions ``(T, 3, H, W)``
    (:func:`edge_directions`) -> ``(M, T, 3, H, W)``."""
    return torch.ops.torchmanifold._along_edges(x, k.reshape(x.shape[:2]), sigma, directions,
                                                float(range_sigma))


@parallel
def kuwahara3(x: Tensor) -> Tensor:
    """``denoise._log_radiance``'s 3x3 Kuwahara filter: ``(N, C, H, W)`` -> ``(N, C, H, W)``."""
    return torch.ops.torchmanifold._kuwahara3(x)


def cv_blend(preds: list[Tensor], fulls: list[Tensor], e: Tensor, weight: Tensor, mask: Tensor,
             blur_sigma: float, softness: float, error_cut: float, others: Tensor | None = None,
             other_weights: Tensor | None = None) -> Tensor:
    """The end of ``denoise._select_bandwidth`` at frame queries: K predictions and outputs
    ``(T, 3, H, W)`` each, e ``(T, 3, H, W)``, weight and mask ``(T, 1, H, W)`` -> ``(T, 3, H, W)``; with the
    neighbouring queries' residual planes ``others`` ``(J, K + 1, T, H, W)`` (:func:`cv_residuals`) pooled in
    under ``other_weights`` ``(J, T, H, W)``."""
    return call_parallel(torch.ops.torchmanifold._cv_blend, torch.stack(preds), torch.stack(fulls), e, weight,
                         mask, float(blur_sigma), float(softness), float(error_cut), others, other_weights)


@parallel
def cv_residuals(preds: list[Tensor], e: Tensor, weight: Tensor, mask: Tensor) -> Tensor:
    """A query's residual planes for its neighbours' blends: K predictions ``(T, 3, H, W)``, e ``(T, 3, H,
    W)``, weight and mask ``(T, 1, H, W)`` -> ``(K + 1, T, H, W)``."""
    return torch.ops.torchmanifold._cv_residuals(torch.stack(preds), e, weight, mask)


@parallel
def quantiles(v: Tensor, q: list[float]) -> Tensor:
    """``torch.quantile(v.double(), q, dim=1)`` (linear) by selection: v ``(R, N)`` -> ``(len(q), R)``
    float64, the same bits."""
    return torch.ops.torchmanifold._quantiles(v, [float(x) for x in q]).t()


@parallel
def cv_halves(e: Tensor, mask: Tensor) -> Tensor:
    """``_select_bandwidth``'s op input: per checkerboard half ``[e * m, m]``, ``m = mask * half``:
    e ``(T, 3, H, W)``, mask ``(T, 1, H, W)`` -> ``(T, 8, H, W)``."""
    shape = (e.shape[0], 8, *e.shape[2:])
    if math.prod(shape) > _MAX_WORKSPACE:
        return torch.ops.torchmanifold._cv_halves(e, mask)
    # one workspace per thread, reused by every bandwidth and frame: the op reads it and returns a new
    # tensor, so the stack is dead by the next call
    buf = getattr(_state, "halves", None)
    if buf is None or buf.shape != shape or buf.dtype != e.dtype:
        buf = _state.halves = torch.empty(shape, dtype=e.dtype)
    torch.ops.torchmanifold._cv_halves_out(e, mask, buf)
    return buf


@parallel
def cv_split(y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The op's output on :func:`cv_halves` ``(T, 8, H, W)`` -> the other half's prediction ``(T, 3, H, W)``
    (NaN where the other half has no weight), and the halves' sums num ``(T, 3, H, W)`` and den
    ``(T, 1, H, W)``."""
    return torch.ops.torchmanifold._cv_split(y)


@parallel
def sanitize(c: Tensor, f: Tensor) -> tuple[Tensor, Tensor, Tensor, dict]:
    """``denoise._sanitize``'s finite check: c ``(T, C, H, W)``, f ``(T, D, H, W)`` -> c and f with non-finite
    values 0, the mask ``(T, 1, H, W)`` and the stats dict (same keys and counts)."""
    c, f, mask, n = torch.ops.torchmanifold._sanitize(c, f)
    n = n.tolist()
    return c, f, mask, {"nonfinite_color": n[0], "nonfinite_features": n[1], "masked_pixels": n[2]}


@parallel
def normalised_blur(x: Tensor, weight: Tensor, sigma: float) -> Tensor:
    """``denoise._normalised_blur`` (``sigma > 0``): x ``(T, C, H, W)``, weight ``(T, 1, H, W)`` ->
    ``(T, C, H, W)``."""
    return torch.ops.torchmanifold._normalised_blur(x, weight, float(sigma))


@parallel
def box_mean(x: Tensor, radius: int) -> Tensor:
    """``footprint._box_mean``: the mean of ``(..., H, W)`` over the ``(2 radius + 1)^2`` box around each
    pixel, the border replicated."""
    return torch.ops.torchmanifold._box_mean(x, int(radius))


@parallel
def same_pixel(p: Tensor, others: Tensor, same: float, still: float, radius: int) -> Tensor:
    """``denoise._same_pixel``: positions p ``(3, H, W)`` against others ``(K, 3, H, W)`` -> bool
    ``(K, 1, H, W)``."""
    return torch.ops.torchmanifold._same_pixel(p, others, float(same), float(still), int(radius))


@parallel
def footprint_samples(p: Tensor, others: Tensor, albedo: Tensor, valid: Tensor, search: Tensor,
                      radius: int) -> tuple[Tensor, Tensor]:
    """``denoise._footprint_samples``: positions p ``(3, H, W)``, others and their albedo ``(K, 3, H, W)``,
    valid ``(K, H, W)``, search bool ``(K, H, W)`` -> albedo sums ``(K, 3, H, W)`` and counts
    ``(K, 1, H, W)``."""
    return torch.ops.torchmanifold._footprint_samples(p, others, albedo, valid, search, int(radius))


@parallel
def least_offset_cost(to: Tensor, source: Tensor, dy: Tensor, dx: Tensor, offsets: list[tuple[int, int]],
                      radius: int) -> tuple[Tensor, Tensor, Tensor]:
    """``align._least_cost``: matched features to, source ``(C, H, W)``, offsets dy, dx int64 ``(H, W)`` ->
    the offset dy, dx and pooled cost ``(H, W)`` of least cost among ``(dy, dx) + offsets``."""
    flat = [int(v) for o in offsets for v in o]
    return torch.ops.torchmanifold._least_offset_cost(to, source, dy, dx, flat, int(radius))


@parallel
def median_offset_costs(to: Tensor, source: Tensor, ys: Tensor, xs: Tensor,
                        offsets: list[tuple[int, int]], keep: int = 0) -> Tensor:
    """``align._median_costs``: matched features to, source ``(C, H, W)``, grid pixels ys, xs int64
    ``(N,)`` -> ``(O,)``; ``keep``: as there."""
    flat = [int(v) for o in offsets for v in o]
    return torch.ops.torchmanifold._median_offset_costs(to, source, ys, xs, flat, int(keep))


def _register_fakes() -> None:
    """Shapes and dtypes of the private ops for fake tensors (``torch.compile``, ``opcheck``); each matches
    its CPU kernel's outputs."""
    lib = "torchmanifold::"

    @torch.library.register_fake(lib + "_normalise_guard")
    def _(num, den, values, mask, radius):
        return torch.empty_like(num, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_normalise_guard_bounds")
    def _(num, den, fallback, hi, nlo, radius):
        return torch.empty_like(num, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_window_bounds")
    def _(values, mask, starts, lengths):
        shape = (len(starts), *values.shape[1:])
        return values.new_empty(shape), values.new_empty(shape)

    @torch.library.register_fake(lib + "_box_mean")
    def _(x, radius):
        return torch.empty_like(x, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_footprint_average")
    def _(x, k, sigma, range_sigma, unseen_border=0.0):
        return torch.empty_like(x, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_edge_directions")
    def _(x, k, tensor_sigma, power):
        return torch.empty_like(x, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_along_edges")
    def _(x, k, sigma, directions, range_sigma):
        return torch.empty_like(x, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_kuwahara3")
    def _(x):
        return torch.empty_like(x, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_cv_blend")
    def _(preds, fulls, e, weight, mask, blur_sigma, softness, error_cut, others=None, other_weights=None):
        return torch.empty_like(e, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_cv_residuals")
    def _(preds, e, weight, mask):
        return e.new_empty((preds.shape[0] + 1, e.shape[0], *e.shape[2:]))

    @torch.library.register_fake(lib + "_quantiles")
    def _(v, q):
        return v.new_empty((v.shape[0], len(q)), dtype=torch.float64)

    @torch.library.register_fake(lib + "_cv_halves")
    def _(e, mask):
        return e.new_empty((e.shape[0], 8, *e.shape[2:]))

    @torch.library.register_fake(lib + "_cv_halves_out")
    def _(e, mask, out):
        return None

    @torch.library.register_fake(lib + "_cv_split")
    def _(y):
        T, H, W = y.shape[0], y.shape[2], y.shape[3]
        return y.new_empty((T, 3, H, W)), y.new_empty((T, 3, H, W)), y.new_empty((T, 1, H, W))

    @torch.library.register_fake(lib + "_sanitize")
    def _(c, f):
        return (torch.empty_like(c, memory_format=torch.contiguous_format),
                torch.empty_like(f, memory_format=torch.contiguous_format),
                c.new_empty((c.shape[0], 1, *c.shape[2:])), c.new_empty((3,), dtype=torch.int64))

    @torch.library.register_fake(lib + "_normalised_blur")
    def _(x, weight, sigma):
        return torch.empty_like(x, memory_format=torch.contiguous_format)

    @torch.library.register_fake(lib + "_same_pixel")
    def _(p, others, same, still, radius):
        return others.new_empty((others.shape[0], 1, *others.shape[2:]), dtype=torch.bool)

    @torch.library.register_fake(lib + "_least_offset_cost")
    def _(to, source, dy, dx, offsets, radius):
        return torch.empty_like(dy), torch.empty_like(dx), to.new_empty(to.shape[1:])

    @torch.library.register_fake(lib + "_median_offset_costs")
    def _(to, source, ys, xs, offsets, keep=0):
        return to.new_empty((len(offsets) // 2,))

    @torch.library.register_fake(lib + "_footprint_samples")
    def _(p, others, albedo, valid, search, radius):
        return others.new_empty(others.shape), others.new_empty((others.shape[0], 1, *others.shape[2:]))


if _have_ops():
    _register_fakes()
