"""Fast torch rasterizer vs the brute-force dense reference, gradcheck, and gsplat parity (GPU)."""

from __future__ import annotations

import pytest
import torch

from _render_kit import PARAMS, _gradcheck_scene, _loss, _with_grad, random_scene
from meshsplat.render import rasterize
from meshsplat.render.backends._dense_reference import rasterize_dense


@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_backward_match_dense_float64(render_mode, seed):
    scene = random_scene(seed=seed)
    fast_in, ref_in = _with_grad(scene), _with_grad(scene)
    out = rasterize(**fast_in, render_mode=render_mode, backend="torch")
    ref_c, ref_a = rasterize_dense(**ref_in, render_mode=render_mode)
    assert out.meta["n_pairs"] > 0
    torch.testing.assert_close(out.colors, ref_c, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.alphas, ref_a, atol=1e-9, rtol=1e-9)
    assert float(out.alphas.detach().max()) > 1 - 1e-3  # the opaque stack saturates some pixels
    _loss(out.colors, out.alphas).backward()
    _loss(ref_c, ref_a).backward()
    for k in PARAMS + ("backgrounds",):
        torch.testing.assert_close(fast_in[k].grad, ref_in[k].grad, atol=1e-8, rtol=1e-7, msg=k)


def test_forward_backward_match_dense_float32():
    scene = random_scene(seed=3, dtype=torch.float32)
    fast_in, ref_in = _with_grad(scene), _with_grad(scene)
    out = rasterize(**fast_in, backend="torch")
    ref_c, ref_a = rasterize_dense(**ref_in)
    # float32: a pair sitting on the 1/255 or 1e-4 threshold may flip; allow rare small outliers.
    diff = (out.colors - ref_c).detach().abs()
    assert float(diff.mean()) < 1e-5 and float((diff > 1e-4).float().mean()) < 0.01
    _loss(out.colors, out.alphas).backward()
    _loss(ref_c, ref_a).backward()
    for k in PARAMS:
        a, b = fast_in[k].grad, ref_in[k].grad
        assert float((a - b).norm() / b.norm()) < 2e-3, k


def test_small_pair_budget_gives_same_result():
    scene = random_scene(seed=4)
    a_in, b_in = _with_grad(scene), _with_grad(scene)
    a = rasterize(**a_in, backend="torch")
    # many bands, some rows alone; only the first bands saved, the rest recomputed in backward
    b = rasterize(**b_in, backend="torch", pair_budget=50, saved_pair_limit=300)
    torch.testing.assert_close(a.colors, b.colors, atol=1e-12, rtol=0)
    _loss(a.colors, a.alphas).backward()
    _loss(b.colors, b.alphas).backward()
    for k in PARAMS:
        torch.testing.assert_close(a_in[k].grad, b_in[k].grad, atol=1e-10, rtol=1e-9)


def test_custom_backward_matches_autograd_mode():
    scene = random_scene(seed=5)
    a_in, b_in = _with_grad(scene), _with_grad(scene)
    a = rasterize(**a_in, backend="torch", grad_mode="custom")
    b = rasterize(**b_in, backend="torch", grad_mode="autograd")
    torch.testing.assert_close(a.colors, b.colors, atol=1e-12, rtol=0)
    _loss(a.colors, a.alphas).backward()
    _loss(b.colors, b.alphas).backward()
    for k in PARAMS + ("backgrounds",):
        torch.testing.assert_close(a_in[k].grad, b_in[k].grad, atol=1e-9, rtol=1e-8)
    torch.testing.assert_close(a.meta["means2d"].grad, b.meta["means2d"].grad, atol=1e-9, rtol=1e-8)


@pytest.mark.gradcheck
@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
def test_gradcheck_torch_backend(render_mode):
    means, quats, scales, opac, colors, viewmats, K, bg = _gradcheck_scene()

    def f(means, quats, scales, opac, colors, bg):
        out = rasterize(
            means,
            quats,
            scales,
            opac,
            colors,
            viewmats,
            K,
            16,
            12,
            backgrounds=bg,
            render_mode=render_mode,
            backend="torch",
        )
        return out.colors, out.alphas

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors, bg))
    # fast_mode checks v^T J u for random u, v: the full Jacobian needs ~1.5k backward calls
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
    assert torch.autograd.gradcheck(lambda *a: f(*a)[0][:, 4:8, 6:10], inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.gpu
def test_gsplat_backend_matches_torch_backend():
    pytest.importorskip("gsplat")
    scene = random_scene(seed=6, dtype=torch.float32, width=64, height=48)
    cpu_in = _with_grad(scene)
    gpu_in = {
        k: (v.detach().cuda().requires_grad_(v.requires_grad) if isinstance(v, torch.Tensor) else v)
        for k, v in cpu_in.items()
    }
    a = rasterize(**cpu_in, backend="torch")
    b = rasterize(**gpu_in, backend="gsplat")
    assert b.meta["backend"] == "gsplat"
    diff = (a.colors - b.colors.cpu()).detach().abs()
    assert float(diff.mean()) < 1e-4 and float((diff > 1e-2).float().mean()) < 0.01
    assert int((a.meta["radii"] - b.meta["radii"].cpu()).abs().max()) <= 1  # ceil of float32 values
    torch.testing.assert_close(a.meta["depths"], b.meta["depths"].cpu(), atol=1e-5, rtol=1e-5)
    _loss(a.colors, a.alphas).backward()
    _loss(b.colors.cpu(), b.alphas.cpu()).backward()
    for k in PARAMS:
        ga, gb = cpu_in[k].grad, gpu_in[k].grad.cpu()
        assert float((ga - gb).norm() / ga.norm().clamp_min(1e-12)) < 1e-2, k
    m2a, m2b = a.meta["means2d"].grad, b.meta["means2d"].grad.cpu()
    assert float((m2a - m2b).norm() / m2a.norm()) < 1e-2


def test_clamped_alpha_passes_no_gradient_like_gsplat(monkeypatch):
    """opacity * exp(-sigma) > 0.999 clamps alpha; gsplat then drops that pair's gradients."""
    from meshsplat.render.backends import torch_ref

    clamped = []
    real = torch_ref._band_forward

    def spy(*args):
        out = real(*args)
        clamped.append(int(out[2][7].sum()))
        return out

    monkeypatch.setattr(torch_ref, "_band_forward", spy)
    scene = random_scene(seed=7)
    scene["opacities"] = torch.full_like(scene["opacities"], 1.0)
    scene["scales"] = scene["scales"] * 10.0  # wide splats: several pixels near their centres
    a_in, b_in, r_in = _with_grad(scene), _with_grad(scene), _with_grad(scene)
    a = rasterize(**a_in, backend="torch")
    assert sum(clamped) >= 5
    b = rasterize(**b_in, backend="torch", grad_mode="autograd")
    ref_c, ref_a = rasterize_dense(**r_in)
    torch.testing.assert_close(a.colors, ref_c, atol=1e-9, rtol=1e-9)
    for out in (a, b):
        _loss(out.colors, out.alphas).backward()
    _loss(ref_c, ref_a).backward()
    for k in PARAMS:
        torch.testing.assert_close(a_in[k].grad, b_in[k].grad, atol=1e-8, rtol=1e-7, msg=k)
        torch.testing.assert_close(a_in[k].grad, r_in[k].grad, atol=1e-8, rtol=1e-7, msg=k)
