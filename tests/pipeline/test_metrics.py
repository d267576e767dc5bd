import math

import numpy as np
import pytest
import torch

from torchmanifold import metrics as M


def _srgb_np(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


def test_psnr_matches_numpy_formula():
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(2, 3, 16, 16, generator=g) * 1.5
    img = ref + 0.05 * torch.randn(2, 3, 16, 16, generator=g)
    per = [10 * math.log10(1 / np.mean((_srgb_np(a) - _srgb_np(b)) ** 2)) for a, b in zip(img.numpy(), ref.numpy())]
    assert M.psnr(img, ref) == pytest.approx(np.mean(per), abs=1e-3)
    assert M.psnr(img[0], ref[0]) == pytest.approx(per[0], abs=1e-3)
    lin = 10 * math.log10(float(ref.max()) ** 2 / float(((img - ref) ** 2).mean()))
    assert M.psnr_linear(img, ref) == pytest.approx(lin, abs=1e-3)
    rel = float(((img - ref) ** 2 / (ref**2 + 1e-2)).mean())
    assert M.relmse(img, ref) == pytest.approx(rel, rel=1e-5)


def test_temporal_psnr_matches_numpy_formula_and_sees_flicker():
    """The PSNR of the frame-to-frame changes against a numpy loop; a fixed error from frame to frame costs
    nothing, the same error's size flickering in sign costs as much as its doubled change."""
    g = torch.Generator().manual_seed(1)
    ref = torch.rand(4, 3, 12, 10, generator=g)
    out = ref + 0.05 * torch.randn(4, 3, 12, 10, generator=g)
    s, r = _srgb_np(out.numpy()), _srgb_np(ref.numpy())
    per = [np.mean(((s[t] - s[t - 1]) - (r[t] - r[t - 1])) ** 2) for t in range(1, 4)]
    assert M.temporal_psnr(out, ref) == pytest.approx(10 * math.log10(1 / np.mean(per)), abs=1e-4)
    assert M.temporal_psnr(out, ref, reduction="none").tolist() == pytest.approx(
        [10 * math.log10(1 / p) for p in per], abs=1e-4)
    base = torch.full((3, 3, 8, 8), 0.25)
    steady = base + 0.1  # the same error in every frame
    flicker = base + 0.1 * torch.tensor([1.0, -1.0, 1.0]).view(3, 1, 1, 1)
    assert M.temporal_psnr(steady, base) > 150
    assert M.temporal_psnr(flicker, base) < M.psnr(flicker, base) - 3
    with pytest.raises(ValueError, match="at least 2 frames"):
        M.temporal_psnr(base[:1], base[:1])


def test_identical_and_masked():
    ref = torch.rand(1, 3, 24, 24)
    assert M.ssim(ref, ref) == pytest.approx(1.0, abs=1e-5)
    assert M.relmse(ref, ref) == 0
    noisy = ref.clone()
    noisy[..., :12] += 0.2
    mask = torch.zeros(24, 24)
    mask[:, 12:] = 1
    assert M.psnr(noisy, ref, mask=mask) > 100  # the error lies outside the mask
    assert M.psnr(noisy, ref) < 30


def test_flip_orders_errors():
    ref = torch.rand(1, 3, 32, 32) * 0.8
    small, big = ref + 0.01, ref + 0.2
    assert M.flip(ref, ref) < 1e-6
    assert M.flip(small, ref) < M.flip(big, ref)


def test_flip_is_a_dependency(monkeypatch):
    """FLIP is in requirements.txt: present, flip_available() is True; missing, every FLIP call raises."""
    import sys

    assert M.flip_available() is True
    assert "flip" in M.evaluate(torch.rand(3, 16, 16), torch.rand(3, 16, 16))
    monkeypatch.setitem(sys.modules, "flip_evaluator", None)  # import now raises ImportError
    for call in (M.flip_available, lambda: M.flip(torch.rand(3, 8, 8), torch.rand(3, 8, 8)),
                 lambda: M.evaluate(torch.rand(3, 8, 8), torch.rand(3, 8, 8))):
        with pytest.raises(ImportError, match="flip_evaluator"):
            call()


def test_errors_name_argument():
    with pytest.raises(ValueError, match="same shape"):
        M.psnr(torch.rand(3, 8, 8), torch.rand(3, 8, 9))
    with pytest.raises(TypeError, match="img"):
        M.psnr(np.zeros((3, 8, 8)), torch.rand(3, 8, 8))
    with pytest.raises(ValueError, match="reduction"):
        M.psnr(torch.rand(3, 8, 8), torch.rand(3, 8, 8), reduction="sum")
