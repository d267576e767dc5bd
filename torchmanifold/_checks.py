"""Argument checks shared by every entry point (ops, pipeline, CLI, demo): one rule, one message style.

Rules, everywhere:

- a value of the wrong kind (a string where a number is expected, a float where an int is, a list
  where a tensor is) raises :class:`TypeError`;
- a value of the right kind that is out of range (negative sigma, NaN, a height of 0, an unknown
  choice, a tensor of the wrong rank, size, dtype or device) raises :class:`ValueError`;
- every message reads ``"<name> must be <what was expected>, got <what came>"``, where ``name`` is the
  argument as the caller knows it (``"sigma_s"``, ``"guide_sigmas[2]"``, ``"--tree-height"``).

Which check for what:

- numbers: :func:`check_positive` (sigmas, scales), :func:`check_nonnegative`, :func:`check_number` (any
  interval, open or closed ends), :func:`check_int` (``min`` / ``max``), :func:`check_tree_height`
  (``[1, MAX_TREE_HEIGHT]``, ``None`` = automatic where allowed);
- choices: :func:`check_choice` (modes, backends, firefly treatments);
- sequences: :func:`check_numbers` (times, ...), :func:`check_sigmas` (one positive sigma per channel; a
  ``{name: sigma}`` mapping checks each value with ``check_positive(f"guide_sigmas[{name!r}]", v)``);
- tensors: :func:`check_tensor` (rank, dtype), :func:`check_values_and_guide` (a filter's image pair),
  :func:`check_same_dtype_device`.

``bool`` is not accepted as a number (``True`` is an ``int`` in Python, almost never meant as one).
Messages are built only on failure. Each check returns the value normalised (``float``, ``int``, a
float64 tensor) so callers write ``sigma_s = check_positive("sigma_s", sigma_s)``.

Example:
    >>> check_positive("sigma_s", 8)
    8.0
    >>> check_tree_height(3)
    3
    >>> check_choice("mode", "window", ("window", "spacetime"))
    'window'
"""
from __future__ import annotations

import math
import numbers
from typing import Any, Iterable, Sequence

import torch
from torch import Tensor

__all__ = [
    "MAX_TREE_HEIGHT",
    "check_choice",
    "check_int",
    "check_nonnegative",
    "check_number",
    "check_numbers",
    "check_positive",
    "check_same_dtype_device",
    "check_sigmas",
    "check_tensor",
    "check_tree_height",
    "check_values_and_guide",
]

#: Largest manifold tree height, the same bound as ``kMaxTreeHeight`` in
#: ``csrc/ops/adaptive_manifold_common.h``. The C++ kernel labels every pixel with the heap id of its
#: cluster as an ``int32``: nodes at depth ``d`` have ids in ``[2^d, 2^(d+1))``, so a tree of height H
#: writes labels below ``2^H``; H <= 30 keeps them clear of the sign bit with one bit to spare.
#: (Memory is not the limit: empty clusters are pruned, so a level has at most one node per pixel.)
MAX_TREE_HEIGHT = 30


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _interval(low, high, low_open: bool, high_open: bool) -> str:
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {low:g}"
    if high is not None:
        return f"{'<' if high_open else '<='} {high:g}"
    return ""


def check_number(name: str, value: Any, *, low: float | None = None, high: float | None = None,
                 low_open: bool = False, high_open: bool = False) -> float:
    """A finite real number (or a one-element tensor) within ``[low, high]``; returns it as ``float``.

    ``low_open`` / ``high_open`` exclude the bound. Raises TypeError for a non-number, ValueError for a
    non-finite or out-of-range one.
    """
    bounds = _interval(low, high, low_open, high_open)
    expected = f"a finite number {bounds}".rstrip()
    if isinstance(value, Tensor):
        if value.numel() != 1 or value.is_complex() or value.dtype == torch.bool:
            raise TypeError(f"{name} must be {expected} (or a one-element real tensor), got a tensor of "
                            f"shape {tuple(value.shape)} and dtype {value.dtype}")
        value = value.item()
    if not _is_real(value):
        raise TypeError(f"{name} must be {expected}, got {type(value).__name__}")
    x = float(value)
    ok = math.isfinite(x)
    if ok and low is not None:
        ok = x > low if low_open else x >= low
    if ok and high is not None:
        ok = x < high if high_open else x <= high
    if not ok:
        raise ValueError(f"{name} must be {expected}, got {value!r}")
    return x


def check_positive(name: str, value: Any) -> float:
    """A finite number > 0 (a sigma, a scale); returns it as ``float``."""
    return check_number(name, value, low=0.0, low_open=True)


def check_nonnegative(name: str, value: Any) -> float:
    """A finite number >= 0; returns it as ``float``."""
    return check_number(name, value, low=0.0)


def check_int(name: str, value: Any, *, min: int | None = None, max: int | None = None) -> int:  # noqa: A002
    """An ``int`` (not ``bool``, not ``2.0``) within ``[min, max]``; returns it as ``int``."""
    expected = f"an int {_interval(min, max, False, False)}".rstrip()
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be {expected}, got {type(value).__name__}")
    if (min is not None and value < min) or (max is not None and value > max):
        raise ValueError(f"{name} must be {expected}, got {value!r}")
    return int(value)


def check_tree_height(value: Any, *, name: str = "tree_height", allow_none: bool = False) -> int | None:
    """A manifold tree height: an int in ``[1, MAX_TREE_HEIGHT]`` (``None`` passes when ``allow_none``,
    meaning "choose automatically")."""
    if value is None and allow_none:
        return None
    return check_int(name, value, min=1, max=MAX_TREE_HEIGHT)


def check_tree_heights(value: Any, k: int, *, name: str = "tree_height") -> list[int]:
    """One tree height for ``k`` bandwidths, or one per bandwidth (an int, or a sequence of 1 or ``k`` as the
    ops take it), as ``k`` checked heights."""
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        if len(value) not in (1, k):
            raise ValueError(f"{name}: one height or one per sigma ({k}), got {len(value)}")
        heights = [check_tree_height(h, name=f"{name}[{j}]") for j, h in enumerate(value)]
        return heights * k if len(heights) == 1 else heights
    return [check_tree_height(value, name=name)] * k


def check_choice(name: str, value: Any, choices: Iterable[Any]) -> Any:
    """One of ``choices``; TypeError when it is not even of their type (e.g. not a string)."""
    choices = tuple(choices)
    kinds = tuple({type(c) for c in choices})
    if not isinstance(value, kinds):
        raise TypeError(f"{name} must be one of {choices}, got {type(value).__name__}")
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")
    return value


def check_numbers(name: str, values: Any, *, n: int | None = None, positive: bool = False,
                  allow_scalar: bool = False) -> Tensor:
    """A non-empty sequence or 1-D tensor of finite numbers (``n`` of them when given, all > 0 when
    ``positive``); returns them as a float64 tensor ``(n,)`` (on the CPU for a sequence, on the
    tensor's device for a tensor).

    ``allow_scalar``: a single number counts as a sequence of one. Tensor values are checked only in
    eager mode (under ``torch.compile`` a data-dependent check would break the graph).
    """
    what = "a sequence of" + (f" {n}" if n is not None else "") + (" positive" if positive else "") + \
        " finite numbers or a 1-D tensor"
    if allow_scalar and _is_real(values):
        values = [values]
    if isinstance(values, Tensor):
        if values.dim() != 1 or values.is_complex() or values.dtype == torch.bool:
            raise ValueError(f"{name} must be {what}, got a tensor of shape {tuple(values.shape)} and "
                             f"dtype {values.dtype}")
        if values.numel() == 0 or (n is not None and values.numel() != n):
            raise ValueError(f"{name} must be {what}, got {values.numel()}")
        t = values.detach().to(torch.float64)
        # a data-dependent check would break a torch.compile graph: eager only
        if not torch.compiler.is_compiling() and not (bool(torch.isfinite(t).all()) and
                                                      (not positive or bool((t > 0).all()))):
            raise ValueError(f"{name} must be {what}, got {t.tolist()}")
        return t
    if not isinstance(values, Sequence) or isinstance(values, (str, bytes)):
        raise TypeError(f"{name} must be {what}, got {type(values).__name__}")
    for i, x in enumerate(values):
        if not _is_real(x):
            raise TypeError(f"{name} must be {what}, got {type(x).__name__} at index {i}")
    xs = [float(x) for x in values]
    if not xs or (n is not None and len(xs) != n):
        raise ValueError(f"{name} must be {what}, got {len(xs)}")
    if not all(math.isfinite(x) and (x > 0 or not positive) for x in xs):
        raise ValueError(f"{name} must be {what}, got {xs}")
    return torch.tensor(xs, dtype=torch.float64)


def check_sigmas(name: str, sigmas: Any, n: int) -> Tensor:
    """``n`` positive finite sigmas (a sequence or a ``(n,)`` tensor), e.g. one range sigma per guide
    channel; returns them as a float64 tensor ``(n,)`` (see :func:`check_numbers`)."""
    return check_numbers(name, sigmas, n=n, positive=True)


def check_tensor(name: str, x: Any, *, dims: int | Sequence[int], layout: str | None = None,
                 dtypes: Sequence[torch.dtype] | None = None, min_sizes: bool = False) -> Tensor:
    """A :class:`torch.Tensor` with a rank in ``dims`` (and a dtype in ``dtypes`` when given).

    Args:
        name: the argument's name in messages.
        x: the value to check.
        dims: allowed ranks, e.g. ``(3, 4)``.
        layout: how the expected shape reads in messages, e.g. ``"(B, C, H, W) or (C, H, W)"``.
        dtypes: allowed dtypes (a wrong dtype is a TypeError, like a wrong kind of value).
        min_sizes: also require every dimension >= 1 (no empty images).
    """
    dims = (dims,) if isinstance(dims, int) else tuple(dims)
    shape = layout or " or ".join(f"{d}-D" for d in dims)
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {shape}, got {type(x).__name__}")
    if x.dim() not in dims:
        raise ValueError(f"{name} must be {shape}, got shape {tuple(x.shape)}")
    if min_sizes and min(x.shape, default=1) < 1:
        raise ValueError(f"{name} must be {shape} with every size >= 1, got shape {tuple(x.shape)}")
    if dtypes is not None and x.dtype not in dtypes:
        names = ", ".join(str(d).replace("torch.", "") for d in dtypes)
        raise TypeError(f"{name} must have dtype {names}, got {x.dtype}")
    return x


def check_values_and_guide(values: Any, guide: Any, *, dtypes: Sequence[torch.dtype] | None = None) -> bool:
    """A filter's image pair: ``values`` ``(B, C, H, W)`` or ``(C, H, W)`` (dtype in ``dtypes`` when given) and
    ``guide`` of the same rank, ``(B, D, H, W)`` or ``(D, H, W)``, sharing B, H, W, with H, W, D >= 1.
    Returns whether they are batched (4-D)."""
    check_tensor("values", values, dims=(3, 4), layout="(B, C, H, W) or (C, H, W)", dtypes=dtypes)
    batched = values.dim() == 4
    check_tensor("guide", guide, dims=values.dim(), layout="(B, D, H, W)" if batched else "(D, H, W)")
    if values.shape[-2:] != guide.shape[-2:] or (batched and values.shape[0] != guide.shape[0]):
        raise ValueError(f"guide must share batch size and H, W with values {tuple(values.shape)}, "
                         f"got {tuple(guide.shape)}")
    if values.shape[-2] < 1 or values.shape[-1] < 1 or guide.shape[-3] < 1:
        raise ValueError(f"values and guide must have H, W and the guide channels D >= 1, got values "
                         f"{tuple(values.shape)}, guide {tuple(guide.shape)}")
    return batched


def check_same_dtype_device(name: str, x: Tensor, ref_name: str, ref: Tensor) -> None:
    """``x`` has the dtype and the device of ``ref`` (ValueError naming both otherwise)."""
    if x.dtype != ref.dtype:
        raise ValueError(f"{name} must have the dtype of {ref_name} ({ref.dtype}), got {x.dtype}")
    if x.device != ref.device:
        raise ValueError(f"{name} must be on the device of {ref_name} ({ref.device}), got {x.device}")
