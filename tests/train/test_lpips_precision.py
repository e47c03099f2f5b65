"""LPIPS with its backbone in bfloat16 (``loss.lpips_precision``): close to float32, and chosen as documented."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

import meshsplat.metrics.lpips_net as lp_mod
from meshsplat.errors import MeshsplatError
from meshsplat.metrics.lpips_net import get_lpips, lpips_available, lpips_compute_dtype
from meshsplat.train.config import TrainConfig
from meshsplat.train.losses import PerceptualLoss, make_perceptual_loss

pytestmark = pytest.mark.skipif(not lpips_available("alex"), reason="LPIPS weights not found")


def _pair(seed: int = 0, h: int = 96, w: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth image [H, W, 3] and a noisy copy of it, in [0, 1] (a render and its ground truth)."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(1, 3, h // 8, w // 8, generator=g)
    gt = F.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
    render = (gt + 0.05 * torch.randn(gt.shape, generator=g)).clamp(0, 1)
    return render.contiguous(), gt.contiguous()


def _loss_and_grad(precision: str, render: torch.Tensor, gt: torch.Tensor) -> tuple[float, torch.Tensor]:
    x = render.clone().requires_grad_(True)
    loss = make_perceptual_loss("alex", precision=precision)(x, gt)
    loss.backward()
    assert x.grad is not None
    return loss.item(), x.grad


@pytest.mark.parametrize("seed", [0, 1])
def test_bfloat16_backbone_close_to_float32(seed):
    render, gt = _pair(seed)
    l32, g32 = _loss_and_grad("float32", render, gt)
    l16, g16 = _loss_and_grad("bfloat16", render, gt)
    assert l16 == pytest.approx(l32, rel=5e-3)
    cos = F.cosine_similarity(g16.flatten(), g32.flatten(), dim=0)
    assert cos > 0.98
    assert (g16.norm() / g32.norm()).item() == pytest.approx(1.0, abs=0.03)
    # the rounding is real: bfloat16 is not float32 under another name
    assert l16 != l32


def test_bfloat16_keeps_the_distance_float32_and_the_model_untouched():
    model = get_lpips("alex")
    w0 = model.convs[0].weight.clone()
    render, gt = _pair()
    x = render.permute(2, 0, 1)[None]
    y = gt.permute(2, 0, 1)[None]
    d16 = model(x, y, torch.bfloat16)
    assert d16.dtype == torch.float32
    taps = model.features(model._scaled(x), torch.bfloat16)
    assert all(t.dtype == torch.float32 for t in taps)
    assert torch.equal(model.convs[0].weight, w0) and model.convs[0].weight.dtype == torch.float32
    # identical inputs: zero distance in either dtype
    assert float(model(x, x, torch.bfloat16)) == pytest.approx(0.0, abs=1e-6)
    # the float32 path is the one without compute_dtype, bit for bit
    assert torch.equal(model(x, y), model(x, y, torch.float32))


def test_auto_is_bfloat16_only_on_a_cpu_with_native_bf16(monkeypatch):
    monkeypatch.setattr(lp_mod, "native_bf16", lambda: True)
    assert lpips_compute_dtype("auto", "cpu") == torch.bfloat16
    assert lpips_compute_dtype("auto", "cuda") is None  # GPUs keep float32
    monkeypatch.setattr(lp_mod, "native_bf16", lambda: False)
    assert lpips_compute_dtype("auto", "cpu") is None
    assert lpips_compute_dtype("bfloat16", "cpu") == torch.bfloat16  # asked for by name: always
    assert lpips_compute_dtype("float32", "cpu") is None


def test_native_bf16_survives_missing_probes(monkeypatch):
    for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported"):
        monkeypatch.delattr(torch.cpu, name, raising=False)
    lp_mod.native_bf16.cache_clear()
    try:
        assert lp_mod.native_bf16() is False
    finally:
        lp_mod.native_bf16.cache_clear()  # the real answer again for later tests


def test_unknown_precision_refused_in_one_line():
    with pytest.raises(MeshsplatError, match="float32, bfloat16, auto"):
        PerceptualLoss("alex", "float16")
    cfg = TrainConfig()
    cfg.loss.lpips_precision = "half"
    with pytest.raises(MeshsplatError, match=r"loss\.lpips_precision"):
        cfg.validate()
    assert repr(make_perceptual_loss("alex", precision="auto")).endswith("precision='auto')")
