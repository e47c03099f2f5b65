"""PSNR and SSIM against plain independent computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.signal import convolve2d

from meshsplat.errors import MeshsplatError
from meshsplat.metrics import psnr, ssim
from meshsplat.metrics.ssim import gaussian_blur


def _ssim_reference(x: np.ndarray, y: np.ndarray) -> float:
    """Wang et al. SSIM, written plainly: 11x11 Gaussian (sigma 1.5), valid windows, channel mean."""
    r = np.arange(11) - 5.0
    g = np.exp(-(r**2) / (2 * 1.5**2))
    win = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for c in range(x.shape[2]):
        a, b = x[:, :, c], y[:, :, c]
        f = lambda z: convolve2d(z, win, mode="valid")  # noqa: E731  (symmetric window)
        ma, mb = f(a), f(b)
        va, vb, cov = f(a * a) - ma**2, f(b * b) - mb**2, f(a * b) - ma * mb
        s = ((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
        vals.append(s.mean())
    return float(np.mean(vals))


def test_psnr_known_value_and_batch():
    ref = torch.rand(2, 8, 9, 3) * 0.8
    img = ref + 0.1  # mse 0.01 -> 20 dB
    assert psnr(img, ref).item() == pytest.approx(20.0, abs=1e-4)
    img2 = ref.clone()
    img2[1] += 0.01  # 40 dB on the second image
    per = psnr(img2, ref, reduction="none")
    assert math.isinf(per[0].item()) and per[1].item() == pytest.approx(40.0, abs=1e-3)
    assert psnr(ref[0] + 0.1, ref[0]).item() == pytest.approx(20.0, abs=1e-4)  # [H,W,3]


def test_psnr_mask_restricts_error():
    ref = torch.zeros(10, 10, 3)
    img = ref.clone()
    img[:5] = 1.0  # error only in the top half
    mask = torch.zeros(10, 10, 1)
    mask[5:] = 1.0
    mask[0, 0] = 1.0  # one wrong pixel among 51 -> mse = 1/51
    assert psnr(img, ref, mask=mask).item() == pytest.approx(10 * math.log10(51), abs=1e-4)
    assert psnr(img, ref, mask=mask[..., 0]).item() == pytest.approx(10 * math.log10(51), abs=1e-4)
    with pytest.raises(MeshsplatError, match="mask"):
        psnr(img, ref, mask=torch.ones(4, 4))
    with pytest.raises(MeshsplatError, match="no pixel"):
        psnr(img, ref, mask=torch.zeros(10, 10))


def test_psnr_bad_inputs():
    with pytest.raises(MeshsplatError, match="ref"):
        psnr(torch.rand(4, 4, 3), torch.rand(4, 5, 3))
    with pytest.raises(MeshsplatError, match="img"):
        psnr(torch.rand(4, 3), torch.rand(4, 3))
    bad = torch.rand(4, 4, 3)
    bad[0, 0, 0] = float("nan")
    with pytest.raises(MeshsplatError, match="NaN"):
        psnr(bad, torch.rand(4, 4, 3))


def test_ssim_matches_plain_reference():
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 32, 40, 3, generator=g, dtype=torch.float64)
    y = (x * 0.7 + 0.3 * torch.rand(2, 32, 40, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    per = ssim(x, y, reduction="none")
    for i in range(2):
        assert per[i].item() == pytest.approx(_ssim_reference(x[i].numpy(), y[i].numpy()), abs=1e-10)
    assert ssim(x, y).item() == pytest.approx(per.mean().item())


def test_ssim_properties():
    x = torch.rand(24, 24, 3)
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-6)
    assert ssim(x, x, padding="same").item() == pytest.approx(1.0, abs=1e-6)
    noisy = [ssim(x, (x + s * torch.randn_like(x)).clamp(0, 1)).item() for s in (0.01, 0.05, 0.2)]
    assert noisy[0] > noisy[1] > noisy[2]
    y = torch.rand(24, 24, 3)
    assert ssim(x, y).item() == pytest.approx(ssim(y, x).item(), abs=1e-6)
    with pytest.raises(MeshsplatError, match="at least 11x11"):
        ssim(torch.rand(8, 8, 3), torch.rand(8, 8, 3))
    with pytest.raises(MeshsplatError, match="padding"):
        ssim(x, x, padding="reflect")


def test_subject_metrics_score_only_the_subject():
    from meshsplat.metrics.subject import subject_box, subject_metrics

    gen = torch.Generator().manual_seed(0)
    gt = torch.ones(64, 48, 3)
    mask = torch.zeros(64, 48, 1)
    mask[20:40, 10:30] = 1.0
    gt[20:40, 10:30] = torch.rand(20, 20, 3, generator=gen)
    img = gt.clone()
    img[20:40, 10:30] += 0.1 * torch.randn(20, 20, 3, generator=gen)
    img = img.clamp(0, 1)
    m = subject_metrics(img, gt, mask)
    inside = float(((img - gt) ** 2)[20:40, 10:30].mean())
    assert abs(m["psnr_mask"] - (-10 * math.log10(inside))) < 1e-4
    full = float(psnr(img, gt))
    assert full > m["psnr_mask"] + 5  # the easy background inflates the full-image figure
    assert m["psnr_crop"] < full and m["ssim_mask"] < 1.0
    assert m["mask_fraction"] == pytest.approx(400 / (64 * 48))
    y0, y1, x0, x1 = subject_box(mask)
    assert y0 <= 20 and y1 >= 40 and x0 <= 10 and x1 >= 30 and (y1 - y0) < 64
    # an error outside the mask does not change the subject metrics
    img2 = img.clone()
    img2[:5] = 0.0
    assert subject_metrics(img2, gt, mask)["psnr_mask"] == pytest.approx(m["psnr_mask"])
    assert subject_metrics(img, gt, torch.zeros(64, 48, 1))["psnr_mask"] is None


def test_gaussian_blur_keeps_a_constant_inside_and_its_mass():
    x = torch.zeros(41, 41, 2)
    x[20, 20] = torch.tensor([1.0, 3.0])
    y = gaussian_blur(x, 2.0)
    assert y.shape == x.shape
    assert torch.allclose(y.sum(dim=(0, 1)), torch.tensor([1.0, 3.0]), atol=1e-5)  # a point's mass stays
    assert torch.allclose(y[20], y[:, 20])  # isotropic
    assert y[20, 20, 0] > y[20, 22, 0] > y[20, 26, 0] > 0 and y[20, 27, 0] == 0  # radius ceil(3 sigma) = 6
    flat = gaussian_blur(torch.full((30, 30, 1), 0.5), 1.0)
    assert torch.allclose(flat[3:-3, 3:-3], torch.tensor(0.5))  # zero outside: only the border darkens
    assert flat[0, 0, 0] < 0.5
