"""Image error metrics against a reference: PSNR (clamped sRGB and linear), relMSE, SSIM, FLIP, and the
temporal PSNR of a clip's frame-to-frame changes.

All functions take ``(B, 3, H, W)`` or ``(3, H, W)`` linear-radiance tensors and return the mean over
the batch as a Python float (``reduction="none"`` gives one value per image). The clamped-sRGB PSNR is
the score used throughout the project (see ``shared/data/README.md``): clip to [0, 1], apply the sRGB
transfer curve, PSNR with peak 1.
"""
from __future__ import annotations

import torch

from torchmanifold._checks import check_choice, check_tensor

__all__ = ["linear_to_srgb", "psnr", "psnr_linear", "relmse", "ssim", "flip", "flip_available", "temporal_psnr",
           "evaluate"]


def _as_batch(x: torch.Tensor, name: str) -> torch.Tensor:
    check_tensor(name, x, dims=(3, 4), layout="(B, C, H, W) or (C, H, W)")
    if x.dim() == 3:
        x = x.unsqueeze(0)
    return x.to(torch.float64) if x.dtype == torch.float64 else x.float()


def _pair(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None = None):
    img, ref = _as_batch(img, "img"), _as_batch(ref, "ref")
    if img.shape != ref.shape:
        raise ValueError(f"ref must have the same shape as img {tuple(img.shape)}, got {tuple(ref.shape)}")
    if mask is not None:
        check_tensor("mask", mask, dims=(2, 3, 4), layout="(B, 1, H, W), (1, H, W) or (H, W)")
        mask = _as_batch(mask if mask.dim() != 2 else mask[None], "mask")
        if mask.shape[-2:] != img.shape[-2:]:
            raise ValueError(f"mask must have the H, W of img {tuple(img.shape[-2:])}, got {tuple(mask.shape[-2:])}")
        mask = mask.expand(img.shape[0], 1, *img.shape[-2:]).to(img.dtype)
    return img, ref, mask


def _reduce(per_image: torch.Tensor, reduction: str):
    if check_choice("reduction", reduction, ("mean", "none")) == "mean":
        return float(per_image.mean())
    return per_image


def _masked_mean(err: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean over (C,H,W) per image, inside ``mask`` (B,1,H,W) when given."""
    if mask is None:
        return err.flatten(1).mean(1)
    num = (err * mask).flatten(1).sum(1)
    den = (mask.expand_as(err)).flatten(1).sum(1).clamp_min(1e-12)
    return num / den


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Clamp linear radiance to [0, 1] and apply the sRGB transfer curve (same shape)."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308).pow(1.0 / 2.4) - 0.055)


def _psnr_from_mse(mse: torch.Tensor, peak: float) -> torch.Tensor:
    return 10.0 * torch.log10(peak**2 / mse.clamp_min(1e-20))


def psnr(img, ref, mask=None, reduction: str = "mean"):
    """PSNR in dB on clamped sRGB (peak 1), the project's headline score.

    Args:
        img: ``(B,3,H,W)`` or ``(3,H,W)`` linear radiance.
        ref: reference, same shape.
        mask: optional ``(B,1,H,W)``/``(H,W)`` weights; the error is averaged inside it only.
        reduction: ``"mean"`` over the batch (float) or ``"none"`` (``(B,)`` tensor).
    """
    img, ref, mask = _pair(img, ref, mask)
    mse = _masked_mean((linear_to_srgb(img) - linear_to_srgb(ref)) ** 2, mask)
    return _reduce(_psnr_from_mse(mse, 1.0), reduction)


def temporal_psnr(frames, ref, reduction: str = "mean"):
    """PSNR in dB (clamped sRGB, peak 1) of a clip's frame-to-frame changes against the reference's: each
    change ``x_t - x_(t-1)`` minus the reference's ``r_t - r_(t-1)``. Flicker (a change the reference does
    not have: noise or a bandwidth that jumps between frames) and lag (a change missing) count; an error
    that stays put from frame to frame does not. Noise in the reference adds the same to every method's
    error.

    Args:
        frames: ``(T, 3, H, W)`` linear radiance of consecutive frames, ``T >= 2``.
        ref: the reference frames, same shape.
        reduction: ``"mean"`` of the squared errors over the ``T - 1`` changes, then PSNR (float), or
            ``"none"``: the PSNR of each change (``(T - 1,)`` tensor).
    """
    x, r, _ = _pair(frames, ref)
    if x.shape[0] < 2:
        raise ValueError(f"frames must hold at least 2 frames (T, 3, H, W), got {tuple(frames.shape)}")
    sx, sr = linear_to_srgb(x), linear_to_srgb(r)
    mse = (((sx[1:] - sx[:-1]) - (sr[1:] - sr[:-1])) ** 2).flatten(1).mean(1)
    if check_choice("reduction", reduction, ("mean", "none")) == "mean":
        return float(_psnr_from_mse(mse.mean(), 1.0))
    return _psnr_from_mse(mse, 1.0)


def psnr_linear(img, ref, mask=None, peak: float | None = None, reduction: str = "mean"):
    """PSNR in dB on linear values; the peak is the reference's maximum unless given."""
    img, ref, mask = _pair(img, ref, mask)
    mse = _masked_mean((img - ref) ** 2, mask)
    p = float(ref.max()) if peak is None else float(peak)
    return _reduce(_psnr_from_mse(mse, max(p, 1e-12)), reduction)


def relmse(img, ref, mask=None, eps: float = 1e-2, reduction: str = "mean"):
    """Relative MSE on linear values: mean of (img-ref)^2 / (ref^2 + eps), lower is better."""
    img, ref, mask = _pair(img, ref, mask)
    return _reduce(_masked_mean((img - ref) ** 2 / (ref**2 + eps), mask), reduction)


def ssim(img, ref, window_size: int = 11, reduction: str = "mean"):
    """SSIM on clamped sRGB via :func:`kornia.metrics.ssim` (1 is identical)."""
    import kornia

    img, ref, _ = _pair(img, ref)
    s = kornia.metrics.ssim(linear_to_srgb(img).float(), linear_to_srgb(ref).float(), window_size)
    return _reduce(s.flatten(1).mean(1), reduction)


def _flip_evaluator():
    """The ``flip_evaluator`` module (NVIDIA FLIP), a listed dependency: its absence is an error."""
    try:
        import flip_evaluator
    except ImportError as exc:
        raise ImportError("FLIP needs the flip_evaluator package (requirements.txt: flip-evaluator); "
                          f"it failed to import: {exc}") from exc
    return flip_evaluator


def flip_available() -> bool:
    """True: FLIP is a dependency. Raises ImportError (with the import's own error) when it cannot be
    imported, so that no caller silently drops the metric. Kept for callers that still ask."""
    _flip_evaluator()
    return True


def flip(img, ref, reduction: str = "mean"):
    """Mean LDR-FLIP error (0 is identical, lower is better) on clamped sRGB images.

    Uses the ``flip_evaluator`` package (ImportError when it is missing).
    """
    img, ref, _ = _pair(img, ref)
    flip_evaluator = _flip_evaluator()

    a = linear_to_srgb(img).float().permute(0, 2, 3, 1).cpu().numpy()
    b = linear_to_srgb(ref).float().permute(0, 2, 3, 1).cpu().numpy()
    vals = []
    for x, r in zip(a, b):
        _, mean_err, _ = flip_evaluator.evaluate(r.copy(), x.copy(), "LDR", inputsRGB=True, applyMagma=False)
        vals.append(float(mean_err))
    return _reduce(torch.tensor(vals, dtype=torch.float64), reduction)


def evaluate(img, ref, mask=None, with_flip: bool = True) -> dict:
    """All metrics at once: ``{"psnr", "psnr_linear", "relmse", "ssim", "flip"[, "psnr_masked", "relmse_masked"]}``."""
    out = {
        "psnr": psnr(img, ref),
        "psnr_linear": psnr_linear(img, ref),
        "relmse": relmse(img, ref),
        "ssim": ssim(img, ref),
    }
    if with_flip:
        out["flip"] = flip(img, ref)
    if mask is not None and float(mask.sum()) > 0:
        out["psnr_masked"] = psnr(img, ref, mask=mask)
        out["relmse_masked"] = relmse(img, ref, mask=mask)
    return out
