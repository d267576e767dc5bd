"""Adaptive-manifold filtering of a window of frames, output at query times.

Two modes, both with Gaussian weights in time tau_t = exp(-(t - q)^2 / 2 sigma_t^2) (sigma_t = 1 frame
by default):

- ``"window"``: average the frames' values and guides with tau at each query time q (per pixel, over
  the finite samples), then run the spatial filter on the averages (the C++ op when available).
  Cheap (one spatial filter per query) and right for a static camera and scene, where frames at the same
  pixel see the same surface: it is the paper's accumulation of neighbour frames. A moving object
  leaves a ghost: the averaged values and guides at its old position mix object and background,
  and the spatial filter keeps the mix.
- ``"spacetime"``: joint space-time filtering. Time is one more dimension of the Gaussian kernel,
  centred on the query: every sample (x_j, t, f^_tj) contributes to query pixel i with weight
  exp(-|x_i - x_j|^2/2 sigma_s^2 - |f^_i(q) - f^_tj|^2/2 sigma_r^2 - (t - q)^2/2 sigma_t^2).
  The manifolds are built from the query frame's guide f^(q) (linear interpolation of the guides of the
  frames bracketing q), samples of every frame splat onto them with their own guide's weight times
  tau_t, the splats of all frames are summed (the time-weighted combination), blurred once and sliced
  into the query frame. A sample whose guide no longer matches the query frame's content at that
  place (an object that moved away, a disocclusion) lands on no nearby manifold and does not smear.
  Use it when things move (camera or objects); it costs T splats per query. It runs as the C++ op
  ``torchmanifold::spacetime_adaptive_manifold`` where that has a kernel for the device (CPU), else in
  pure PyTorch (:func:`spacetime_torch`, the reference the kernel matches).

With T = 1 and the query at the frame, ``"spacetime"`` is exactly the spatial filter.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from torchmanifold._checks import (check_choice, check_int, check_numbers, check_positive, check_same_dtype_device,
                                   check_tensor, check_tree_heights)
from torchmanifold._threads import call_parallel
from torchmanifold.ops._reference import (
    GRAM_BAND,
    _domain_transform,
    _dominant_direction,
    downsample,
    downsample_factor,
    gram_band_stride,
    normalise,
    recursive_lowpass,
    root_manifold,
    upsample,
    value_offsets,
)
from torchmanifold.ops.adaptive_manifold import (
    _DISPATCH_KEYS,
    _constant_when_compiled,
    _FilterSettings,
    _check_settings,
    _has_kernel_for,
    _working_inputs,
    adaptive_manifold_filter,
    automatic_tree_height,
)
from torchmanifold.timewindow import interpolate, time_weights

__all__ = ["temporal_adaptive_manifold_filter", "TemporalAdaptiveManifoldFilter", "spacetime_adaptive_manifold_torch",
           "spacetime_torch"]

MODES = ("window", "spacetime")


def spacetime_adaptive_manifold_torch(values: Tensor, guide: Tensor, weights: Tensor, query_guide: Tensor,
                                      sigma_s: float, sigma_r: float, tree_height: int, power_iterations: int,
                                      adjust_outliers: bool) -> Tensor:
    """Joint space-time adaptive-manifold filter into one query frame (pure PyTorch).

    Follows the numbered steps of :mod:`torchmanifold.ops._reference` with the manifolds built from
    ``query_guide`` and every frame splatting with its own guide's weight times its time weight.

    Args:
        values: (B, T, C, H, W) frames' values.
        guide: (B, T, D, H, W) frames' guides (scaled).
        weights: (T,) non-negative time weights of the frames for this query.
        query_guide: (B, D, H, W) guide of the query frame; the manifolds follow it.
        sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers: as the spatial filter.

    Returns:
        (B, C, H, W), dtype of ``values``.
    """
    out_dtype = values.dtype
    wd = torch.float64 if values.dtype == torch.float64 else torch.float32
    dev = values.device
    f = values.to(wd)
    g = guide.detach().to(wd)
    gq = query_guide.detach().to(wd)
    tau = weights.detach().to(dev, wd)
    B, T, C, H, W = f.shape
    Dg = g.shape[2]
    fmax = torch.finfo(wd).max
    inv_r2 = min(1.0 / (sigma_r * sigma_r), fmax) if sigma_r * sigma_r > 0 else fmax
    df = downsample_factor(sigma_s, sigma_r)
    s_low, r_low = sigma_s / df, sigma_r / math.sqrt(2.0)
    zero = torch.zeros((), dtype=wd, device=dev)

    fin_v = torch.isfinite(f)
    fin_g = torch.isfinite(g)
    ms = (fin_g.all(2) & fin_v.all(2)).to(wd) * tau[None, :, None, None]  # (B,T,H,W) splat weight
    f_s = torch.where(fin_v, f, zero)
    g0 = torch.where(fin_g, g, zero)
    fin_q = torch.isfinite(gq)
    mq = fin_q.all(1)
    q0 = torch.where(fin_q, gq, zero)

    # exact constants: one reference per image and channel over every splatting sample
    with torch.no_grad():
        sel = (ms > 0).unsqueeze(2)
        lo = torch.where(sel, f_s, math.inf).amin((1, 3, 4))
        hi = torch.where(sel, f_s, -math.inf).amax((1, 3, 4))
        c = value_offsets(lo, hi)[:, :, None, None]  # (B,C,1,1)
    fp = (f_s - c.unsqueeze(1)) * (ms > 0).to(wd).unsqueeze(2)
    # fallback where nothing slices: the time-weighted average of the finite samples at the pixel,
    # taken about c so that constant values come back exactly
    wv = fin_v.to(wd) * tau[None, :, None, None, None]
    wsum = wv.sum(1)
    fb = torch.where(wsum > 0, c + (wv * (f_s - c.unsqueeze(1))).sum(1) / torch.where(wsum > 0, wsum, 1.0), zero)
    has_sample = (wsum > 0).all(1)  # (B,H,W)

    eta_low, eta_full, gs = root_manifold(q0, mq, sigma_s, df)

    S = torch.zeros((B, C, H, W), dtype=wd, device=dev)
    S0 = torch.zeros((B, 1, H, W), dtype=wd, device=dev)
    min_d = torch.full((B, H, W), math.inf, dtype=wd, device=dev)
    eta_low, eta_full = eta_low.unsqueeze(0), eta_full.unsqueeze(0)
    alive = torch.ones((1, B), dtype=torch.bool, device=dev)
    label = torch.zeros((B, H, W), dtype=torch.long, device=dev)
    frames = [t for t in range(T) if float(tau[t]) > 0]

    for level in range(tree_height):
        n = eta_low.shape[0]
        aw = alive.to(wd)[:, :, None, None]
        resid = gs.unsqueeze(0) - eta_full
        dist = torch.linalg.vecdot(resid, resid, dim=2)
        w_raw = torch.exp(dist * -inv_r2)
        w = w_raw * aw
        min_d = torch.minimum(min_d, torch.where(alive[:, :, None, None], dist, math.inf).amin(0))
        low = None
        for t in frames:  # every frame splats with its own guide onto the query frame's manifolds
            rt_ = g0[:, t].unsqueeze(0) - eta_full
            ws = torch.exp(torch.linalg.vecdot(rt_, rt_, dim=2) * -inv_r2) * aw * ms[:, t].unsqueeze(0)
            part = torch.cat([downsample(ws.unsqueeze(2) * fp[:, t].unsqueeze(0), df),
                              downsample(ws.unsqueeze(2), df)], 2)
            low = part if low is None else low + part
        if low is None:
            break
        blurred = _domain_transform(low, eta_low, s_low, r_low)
        sliced = (w.unsqueeze(2) * upsample(blurred, df, (H, W))).sum(0)
        S = S + sliced[:, :C]
        S0 = S0 + sliced[:, C:]
        if level == tree_height - 1:
            break
        onehot = label.unsqueeze(0) == torch.arange(n, device=dev)[:, None, None, None]
        ohf = (onehot & mq.unsqueeze(0) & alive[:, :, None, None]).to(wd)
        r = resid.mul_(ohf.unsqueeze(2))
        scale = torch.linalg.vector_norm(r, ord=math.inf, dim=(2, 3, 4), keepdim=True)
        r = r.div_(torch.where(scale > 0, scale, 1.0)).flatten(3)
        # M over every s-th band of rows, as the spatial filter's step 8
        bands = torch.arange(H, device=dev) // GRAM_BAND % gram_band_stride(H, W) == 0
        rows = r.unflatten(3, (H, W))[..., bands, :].flatten(3)
        v = _dominant_direction(rows @ rows.transpose(-1, -2), power_iterations)
        positive = (v.unsqueeze(2) @ r).reshape(n, B, H, W) >= 0
        theta = (1.0 - w_raw) * ohf
        pos = positive.to(wd)
        t_children = torch.stack([theta * (1.0 - pos), theta * pos], 1).flatten(0, 1)
        alive = alive.repeat_interleave(2, 0) & (t_children.sum((2, 3)) > 0)
        acc = recursive_lowpass(
            torch.cat([downsample(t_children.unsqueeze(2) * gs.unsqueeze(0), df),
                       downsample(t_children.unsqueeze(2), df)], 2), s_low)
        num, den = acc[:, :, :Dg], acc[:, :, Dg:]
        eta_low = torch.where(den > 0, num / torch.where(den > 0, den, 1.0), eta_low.repeat_interleave(2, 0))
        eta_full = upsample(eta_low, df, (H, W))
        label = 2 * label + torch.gather(positive, 0, label.unsqueeze(0)).squeeze(0).long()

    return normalise(S, S0, c, fb, min_d, has_sample, inv_r2, adjust_outliers).to(out_dtype)


def spacetime_torch(values: Tensor, guide: Tensor, weights: Tensor, query_guide: Tensor, sigma_s: float,
                    sigma_r: float, tree_height: int, power_iterations: int, adjust_outliers: bool) -> Tensor:
    """Pure-PyTorch implementation of the op ``torchmanifold::spacetime_adaptive_manifold``: every query.

    Args:
        values: (B, T, C, H, W) frames' values.
        guide: (B, T, D, H, W) frames' guides (scaled).
        weights: (Q, T) time weights of the frames for every query.
        query_guide: (B, Q, D, H, W) every query frame's guide.
        sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers: as the spatial filter.

    Returns:
        (B, Q, C, H, W), dtype of ``values``.
    """
    outs = [spacetime_adaptive_manifold_torch(values, guide, weights[q], query_guide[:, q], sigma_s, sigma_r,
                                              tree_height, power_iterations, adjust_outliers)
            for q in range(weights.shape[0])]
    if not outs:
        B, _, C, H, W = values.shape
        return values.new_empty((B, 0, C, H, W))
    return torch.stack(outs, 1)


@_constant_when_compiled
def _has_spacetime_kernel_for(device_type: str) -> bool:
    return (_has_kernel_for(device_type) and hasattr(torch.ops.torchmanifold, "spacetime_adaptive_manifold")
            and torch._C._dispatch_has_kernel_for_dispatch_key("torchmanifold::spacetime_adaptive_manifold",
                                                               _DISPATCH_KEYS[device_type]))


def _window_inputs(values: Tensor, guide: Tensor, ft: Tensor, qt: Tensor, sigma_r: float, sigma_t: float,
                    guide_sigmas) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`~torchmanifold.ops.adaptive_manifold._working_inputs` of the window, and the time weights
    ``(Q, T)`` in the same dtype."""
    v, g = _working_inputs(values, guide, sigma_r, guide_sigmas)
    return v, g, time_weights(ft, qt, sigma_t).to(v.device, v.dtype)


def _query_guides(g: Tensor, ft: Tensor, qt: Tensor) -> Tensor:
    """Every query's guide ``(B, Q, D, H, W)``: linear between the frames that bracket it."""
    return torch.stack([interpolate(g, ft, q, dim=1) for q in qt.tolist()], 1)


def _spacetime_bandwidths(values: Tensor, guide: Tensor, frame_times, query_times, sigmas_s: Sequence[float],
                          sigma_r: float, sigma_t: float, tree_height: int | Sequence[int],
                          guide_sigmas: Sequence[float] | Tensor | None = None,
                          power_iterations: int = 32) -> Tensor:
    """:func:`temporal_adaptive_manifold_filter` in ``"spacetime"`` mode at every spatial sigma of
    ``sigmas_s``, with ``tree_height`` for all or one height per sigma: ``(K, B, Q, C, H, W)``, each slice
    the bits of that call. With the CPU kernel and no gradient it is one op call whose images share the
    threads (``_spacetime_adaptive_manifold_bandwidths``); otherwise one call each."""
    heights = check_tree_heights(tree_height, len(sigmas_s))
    if not (values.dim() == 5 and values.device.type == "cpu" and _has_spacetime_kernel_for("cpu")
            and values.numel() and not (torch.is_grad_enabled() and values.requires_grad)):
        return torch.stack([temporal_adaptive_manifold_filter(
            values, guide, frame_times, query_times, s, sigma_r, sigma_t, "spacetime", h,
            guide_sigmas=guide_sigmas, power_iterations=power_iterations) for s, h in zip(sigmas_s, heights)])
    check_same_dtype_device("guide", guide, "values", values)
    ft = check_numbers("frame_times", frame_times, n=values.shape[1]).cpu()
    qt = check_numbers("query_times", query_times, allow_scalar=True).cpu()
    sigma_r, sigma_t = check_positive("sigma_r", sigma_r), check_positive("sigma_t", sigma_t)
    power_iterations = check_int("power_iterations", power_iterations, min=0)
    sigmas = [check_positive(f"sigmas_s[{k}]", s) for k, s in enumerate(sigmas_s)]
    v, g, tw = _window_inputs(values, guide, ft, qt, sigma_r, sigma_t, guide_sigmas)
    gq = _query_guides(g, ft, qt)
    out = call_parallel(torch.ops.torchmanifold._spacetime_adaptive_manifold_bandwidths, v.contiguous(),
                        g.contiguous(), tw.contiguous(), gq.contiguous(), sigmas, sigma_r, heights,
                        power_iterations, False)
    return out.to(values.dtype)


def temporal_adaptive_manifold_filter(values: Tensor, guide: Tensor, frame_times, query_times, sigma_s: float,
                                      sigma_r: float, sigma_t: float = 1.0, mode: str = "window",
                                      tree_height: int | None = 2, *,
                                      guide_sigmas: Sequence[float] | Tensor | None = None,
                                      adjust_outliers: bool = False, power_iterations: int = 32,
                                      backend: str = "auto") -> Tensor:
    r"""Filter a window of frames at query times with Gaussian weights in time.

    See the module docstring for when to use ``"window"`` (static content, fast, the C++ op) or
    ``"spacetime"`` (moving content: no ghosts; T splats per query).

    Args:
        values: (B, T, C, H, W) frames' values.
        guide: (B, T, D, H, W) frames' guides, same dtype and device.
        frame_times: (T,) time of every frame (a sequence or tensor, any order).
        query_times: (Q,) times to output (a number, sequence or tensor); may fall between frames.
        sigma_s, sigma_r: spatial (pixels) and range (guide units) standard deviations.
        sigma_t: temporal standard deviation in the units of the times (> 0; default 1 frame).
        mode: ``"window"`` or ``"spacetime"``.
        tree_height, guide_sigmas, adjust_outliers, power_iterations: as
            :func:`~torchmanifold.ops.adaptive_manifold_filter` (keyword-only after ``tree_height``).
        backend: ``"auto"`` (the C++ op where it has a kernel for the device, else pure PyTorch),
            ``"cpp"`` or ``"torch"``; for ``"window"`` it picks the spatial filter's backend, for
            ``"spacetime"`` the space-time op's.

    Returns:
        (B, Q, C, H, W) filtered frames at the query times, dtype of ``values``.

    Raises:
        TypeError: a value of the wrong kind (non-tensors, non-number sigmas or times, a non-int height).
        ValueError: a value out of range (shapes, dtypes, devices, times, sigmas, height, mode, backend);
            see :mod:`torchmanifold._checks`.

    Example:
        >>> v, g = torch.rand(1, 3, 3, 16, 16), torch.rand(1, 3, 4, 16, 16)
        >>> temporal_adaptive_manifold_filter(v, g, [0, 1, 2], [1.0, 1.5], 4.0, 0.3).shape
        torch.Size([1, 2, 3, 16, 16])
    """
    check_tensor("values", values, dims=5, layout="(B, T, C, H, W)")
    check_tensor("guide", guide, dims=5, layout="(B, T, D, H, W)")
    if values.shape[:2] != guide.shape[:2] or values.shape[3:] != guide.shape[3:]:
        raise ValueError(f"guide must share B, T, H, W with values {tuple(values.shape)}, got {tuple(guide.shape)}")
    check_same_dtype_device("guide", guide, "values", values)
    ft = check_numbers("frame_times", frame_times, n=values.shape[1]).cpu()
    qt = check_numbers("query_times", query_times, allow_scalar=True).cpu()
    sigma_s, sigma_r, tree_height, power_iterations, backend = _check_settings(
        sigma_s, sigma_r, tree_height, power_iterations, backend)
    sigma_t = check_positive("sigma_t", sigma_t)
    mode = check_choice("mode", mode, MODES)
    if mode == "spacetime" and backend == "cpp" and not _has_spacetime_kernel_for(values.device.type):
        raise ValueError(f"backend='cpp' needs a kernel of torchmanifold::spacetime_adaptive_manifold for "
                         f"{values.device.type} tensors; none is registered (use backend='torch' or 'auto')")
    if tree_height is None:
        tree_height = automatic_tree_height(sigma_s, sigma_r)

    B, T, C, H, W = values.shape
    v, g, tw = _window_inputs(values, guide, ft, qt, sigma_r, sigma_t, guide_sigmas)
    work = v.dtype

    if mode == "window":
        fin_v, fin_g = torch.isfinite(v), torch.isfinite(g)
        tw6 = tw[None, :, :, None, None, None]
        wv = fin_v.to(work).unsqueeze(1) * tw6  # (B,Q,T,C,H,W): finite samples only
        wg = fin_g.to(work).unsqueeze(1) * tw6
        vz = torch.where(fin_v, v, 0.0).unsqueeze(1)
        gz = torch.where(fin_g, g, 0.0).unsqueeze(1)
        # no finite sample at a pixel -> NaN, which the spatial filter ignores (never spreads)
        va = (wv * vz).sum(2) / wv.sum(2)
        ga = (wg * gz).sum(2) / wg.sum(2)
        out = adaptive_manifold_filter(va.flatten(0, 1), ga.flatten(0, 1), sigma_s, sigma_r, tree_height,
                                       adjust_outliers=adjust_outliers, power_iterations=power_iterations,
                                       backend=backend)
        out = out.reshape(B, -1, C, H, W)
    else:
        gq = _query_guides(g, ft, qt)
        args = (sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers)
        if backend == "torch" or (backend == "auto" and not _has_spacetime_kernel_for(v.device.type)):
            out = spacetime_torch(v, g, tw, gq, *args)
        else:
            out = call_parallel(torch.ops.torchmanifold.spacetime_adaptive_manifold, v.contiguous(),
                                g.detach().contiguous(), tw.contiguous(), gq.detach().contiguous(), *args)
    return out.to(values.dtype)


class TemporalAdaptiveManifoldFilter(_FilterSettings):
    r"""Module form of :func:`temporal_adaptive_manifold_filter`; stores the hyper-parameters.

    Shape:
        - values: (B, T, C, H, W), guide: (B, T, D, H, W), frame_times: (T,), query_times: (Q,)
        - output: (B, Q, C, H, W)

    Example:
        >>> f = TemporalAdaptiveManifoldFilter(4.0, 0.3, mode="spacetime")
        >>> f(torch.rand(1, 3, 3, 16, 16), torch.rand(1, 3, 4, 16, 16), [0, 1, 2], [1]).shape
        torch.Size([1, 1, 3, 16, 16])
    """

    _REPR = ("sigma_s", "sigma_r", "sigma_t", "mode") + _FilterSettings._REPR[2:]

    def __init__(self, sigma_s: float, sigma_r: float, sigma_t: float = 1.0, mode: str = "window",
                 tree_height: int | None = 2, *, guide_sigmas: Sequence[float] | Tensor | None = None,
                 adjust_outliers: bool = False, power_iterations: int = 32, backend: str = "auto") -> None:
        super().__init__(sigma_s, sigma_r, tree_height, guide_sigmas, adjust_outliers, power_iterations, backend)
        self.sigma_t = check_positive("sigma_t", sigma_t)
        self.mode = check_choice("mode", mode, MODES)

    def forward(self, values: Tensor, guide: Tensor, frame_times, query_times) -> Tensor:
        return temporal_adaptive_manifold_filter(values, guide, frame_times, query_times, self.sigma_s,
                                                 self.sigma_r, self.sigma_t, self.mode, **self._settings())
