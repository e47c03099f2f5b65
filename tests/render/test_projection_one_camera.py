"""The one-camera projection kernels (vector code over Gaussians, ``numba_projection._project_one_kernel`` and its
backward) against the general kernel (cameras in a loop, scalar) and the torch projection."""

from __future__ import annotations

import platform
import re

import numpy as np
import pytest
import torch

from _render_kit import random_scene
from meshsplat.render.backends import numba_available

pytestmark = pytest.mark.skipif(not numba_available(), reason="needs numba")

NEAR, FAR = 0.01, 1e10


def _kernels():
    from meshsplat.render.backends.numba_cpu import _kernels as kernels

    k = kernels()
    return k.project, k.project_backward


def _hard_scene(dtype: torch.dtype, n: int = 300, seed: int = 3) -> dict:
    """``random_scene`` (three cameras: outside, oblique, inside the cloud) plus Gaussians on every branch: behind
    the camera, at its plane, far to the side (the field-of-view clamp), below the opacity threshold, zero, NaN
    and infinite quaternions, infinite and huge scales, a NaN mean."""
    s = random_scene(n=n, seed=seed, dtype=dtype, width=61, height=47)
    means, quats, scales, opac = (s[k].clone() for k in ("means", "quats", "scales", "opacities"))
    means[10] = torch.tensor([0.0, 0.0, -3.0])  # at camera 0's centre
    means[11] = torch.tensor([0.0, 0.0, -4.0])  # behind camera 0
    means[12] = torch.tensor([40.0, 3.0, 0.0])  # far outside the field of view (clamped)
    means[13] = torch.tensor([0.0, -25.0, 1.0])
    opac[14] = 0.5 / 255.0  # below the threshold
    opac[15] = 1.0 / 255.0  # at it
    quats[16] = 0.0
    quats[17, 1] = float("nan")
    quats[18, 2] = float("inf")
    scales[19, 0] = float("inf")
    scales[20] = 50.0  # larger than the image
    means[21, 1] = float("nan")
    scales[22] = 1e-9  # a point: the dilation alone
    means[23] = torch.tensor([0.0, 0.0, -2.985])  # just past camera 0's near plane, huge: radii past int32
    scales[23] = 1e7
    s.update(means=means, quats=quats, scales=scales, opacities=opac)
    return s


def _arrays(s: dict) -> tuple[np.ndarray, ...]:
    return tuple(s[k].contiguous().numpy() for k in ("means", "quats", "scales", "opacities"))


def _cams(s: dict, cams: list[int]) -> tuple[np.ndarray, np.ndarray]:
    return s["viewmats"][cams].double().contiguous().numpy(), s["Ks"][cams].double().contiguous().numpy()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cam", [0, 1, 2])
def test_one_camera_gives_the_general_kernels_bits(dtype, cam):
    """Forward outputs and backward gradients bit for bit those of the general kernel (the same camera beside
    another), for every branch: culled, clamped, non-finite. The upstream gradients are random everywhere: what a
    camera does not see must get none of them."""
    project, backward = _kernels()
    s = _hard_scene(dtype)
    arrs = _arrays(s)
    w, h = float(s["width"]), float(s["height"])
    vm1, k1 = _cams(s, [cam])
    vm2, k2 = _cams(s, [cam, (cam + 1) % 3])
    one = project(*arrs, vm1, k1, w, h, NEAR, FAR)
    two = project(*arrs, vm2, k2, w, h, NEAR, FAR)
    assert one[4].sum() > 20 and (~one[4]).sum() > 20  # both kinds present
    assert cam != 0 or one[3][0, 23].max() == 2147483647  # capped, not wrapped
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a[0], b[0])
    n = arrs[0].shape[0]
    rng = np.random.default_rng(cam)
    grads = [rng.standard_normal(shape).astype(arrs[0].dtype) for shape in ((1, n, 2), (1, n, 3), (1, n))]
    g_one = backward(arrs[0], arrs[1], arrs[2], vm1, k1, w, h, one[4], *grads)

    def beside(x: np.ndarray, fill: float | bool) -> np.ndarray:  # camera 2 of the pair: sees nothing
        return np.concatenate([x, np.full_like(x, fill)])

    g_two = backward(arrs[0], arrs[1], arrs[2], vm2, k2, w, h, beside(one[4], False), *(beside(g, 0.0) for g in grads))
    for a, b in zip(g_one, g_two, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.isfinite(g_one[0][:10]).all() and np.abs(g_one[0]).max() > 0


def test_one_camera_matches_the_torch_projection():
    """Against ``project_gaussians`` (torch) on one camera, float32: the same visibility and radii, values and
    gradients to rounding."""
    from meshsplat.render.backends.numba_projection import project_numba
    from meshsplat.render.projection import project_gaussians

    s = random_scene(n=500, seed=5, dtype=torch.float32, width=80, height=64)
    args = {k: s[k].clone().requires_grad_(True) for k in ("means", "quats", "scales")}
    outs = []
    for fn in (lambda *a: project_numba(_kernels(), *a), project_gaussians):
        p = fn(args["means"], args["quats"], args["scales"], s["opacities"], s["viewmats"][:1], s["Ks"][:1],
               s["width"], s["height"], NEAR, FAR)  # fmt: skip
        g = torch.Generator().manual_seed(1)
        loss = sum((t * torch.randn(t.shape, generator=g)).sum() for t in (p.means2d, p.conics, p.depths))
        grads = torch.autograd.grad(loss, list(args.values()))
        outs.append((p, grads))
    (pn, gn), (pt, gt) = outs
    assert torch.equal(pn.visible, pt.visible) and int(pn.visible.sum()) > 100
    assert torch.equal(pn.radii, pt.radii)
    for a, b in ((pn.means2d, pt.means2d), (pn.conics, pt.conics), (pn.depths, pt.depths)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    for a, b in zip(gn, gt, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()))


@pytest.mark.gradcheck
def test_gradcheck_one_camera():
    from meshsplat.render.backends.numba_projection import project_numba

    s = random_scene(n=12, seed=2, dtype=torch.float64, width=40, height=30)
    vm, ks = s["viewmats"][:1], s["Ks"][:1]
    assert int(project_numba(_kernels(), s["means"], s["quats"], s["scales"], s["opacities"], vm, ks, 40, 30,
                             NEAR, FAR).visible.sum()) >= 6  # fmt: skip

    def f(means, quats, scales):
        p = project_numba(_kernels(), means, quats, scales, s["opacities"], vm, ks, 40, 30, NEAR, FAR)
        return p.means2d, p.conics, p.depths

    inputs = tuple(s[k].clone().requires_grad_(True) for k in ("means", "quats", "scales"))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def _host_features() -> str:
    import llvmlite.binding as ll

    return ll.get_host_cpu_features().flatten()


def _one_camera_asm() -> list[str]:
    """The generated code of uncached copies of the one-camera forward and backward, compiled with the options the
    kernels get on this host (``projection_llvm_options``) and run once on a small scene."""
    import numba

    from meshsplat._numba import llvm_options
    from meshsplat.render.backends import numba_projection as P

    _kernels()  # the helpers bound
    s = _hard_scene(torch.float32, n=40)
    flat = [a.reshape(-1) for a in _arrays(s)]
    vm, ks = _cams(s, [0])
    n = flat[3].shape[0]
    cam = P._camera_vector(vm, ks, 61.0, 47.0)
    outs = (np.zeros(2 * n, np.float32), np.zeros(3 * n, np.float32), np.zeros(n, np.float32),
            np.zeros(2 * n, np.int32), np.zeros(n, np.bool_))  # fmt: skip
    grads = (np.zeros(2 * n, np.float32), np.zeros(3 * n, np.float32), np.zeros(n, np.float32))
    g_out = (np.zeros(3 * n, np.float32), np.zeros(4 * n, np.float32), np.zeros(3 * n, np.float32))
    with llvm_options(P.projection_llvm_options()):
        fwd = numba.njit(cache=False, nogil=True, error_model="numpy")(P._project_one_kernel)
        bwd = numba.njit(cache=False, nogil=True, error_model="numpy")(P._project_one_backward_kernel)
        fwd(*flat, cam, 61.0, 47.0, NEAR, FAR, *outs, 0, n)
        bwd(*flat[:3], cam, outs[4], *grads, *g_out, 0, n)
    return ["\n".join(dispatcher.inspect_asm().values()) for dispatcher in (fwd, bwd)]


@pytest.mark.skipif(
    platform.machine() not in ("x86_64", "AMD64") or "+avx2" not in _host_features(),
    reason="checks x86-64 vector registers on a host with AVX2",
)
def test_one_camera_kernels_compile_to_vector_code():
    """The Gaussians' loop is packed 256-bit float64 code (``v...pd`` on ``ymm``), forward and backward; LLVM's
    cost model alone leaves it scalar on a Zen 3 host, so this fails if the options are lost."""
    for asm in _one_camera_asm():
        packed = re.findall(r"^\s*v(?:add|sub|mul|div|min|max|sqrt)pd\s+([^\n]*)", asm, re.M)
        assert sum("%ymm" in ops or "%zmm" in ops for ops in packed) >= 50, len(packed)


def test_arm64_compiles_the_projection_two_float64_wide(monkeypatch):
    """The width rule on arm64 (checked on any host): 2 float64 lanes, one NEON register, whatever numba's target
    CPU (LLVM leaves the loop scalar there by itself)."""
    from meshsplat.render.backends import numba_projection as P

    for machine in ("arm64", "aarch64"):
        monkeypatch.setattr(platform, "machine", lambda m=machine: m)
        assert P.projection_llvm_options()["force-vector-width"] == 2


@pytest.mark.skipif(platform.machine() not in ("aarch64", "arm64"), reason="checks arm64 vector registers")
def test_one_camera_kernels_compile_to_neon_on_arm64():
    """On arm64 the Gaussians' loop is packed float64 NEON code (``f...`` on ``v0.2d``), forward and backward. Run
    under qemu-aarch64 (bench/raster_cpu_lanes.md, arm64); no arm64 machine runs the suite."""
    for asm in _one_camera_asm():
        assert len(re.findall(r"^\s*f[a-z]+\s+v\d+\.2d", asm, re.M)) >= 50


def test_one_camera_kernels_write_every_element():
    """The one-camera wrappers hand the kernels uninitialised outputs (``np.empty``): run on outputs full of a
    sentinel, the kernels give what the wrappers return, element for element."""
    from meshsplat.render.backends import numba_projection as P

    project, backward = _kernels()
    s = _hard_scene(torch.float32, n=200)
    arrs = _arrays(s)
    vm, ks = _cams(s, [0])
    w, h = float(s["width"]), float(s["height"])
    expected = project(*arrs, vm, ks, w, h, NEAR, FAR)
    n = arrs[0].shape[0]
    cam = P._camera_vector(vm, ks, w, h)
    flat = [a.reshape(-1) for a in arrs]
    outs = [np.full(o.size, 7, o.dtype) for o in expected]
    P._project_one_serial(*flat, cam, w, h, NEAR, FAR, *outs, 0, n)
    for got, want in zip(outs, expected, strict=True):
        np.testing.assert_array_equal(got, want.reshape(-1))
    rng = np.random.default_rng(4)
    grads = [rng.standard_normal(shape).astype(np.float32) for shape in ((1, n, 2), (1, n, 3), (1, n))]
    want_g = backward(arrs[0], arrs[1], arrs[2], vm, ks, w, h, expected[4], *grads)
    got_g = [np.full(g.size, 7, g.dtype) for g in want_g]
    P._project_one_backward_serial(*flat[:3], cam, expected[4].reshape(-1), *(g.reshape(-1) for g in grads), *got_g,
                                   0, n)  # fmt: skip
    for got, want in zip(got_g, want_g, strict=True):
        np.testing.assert_array_equal(got, want.reshape(-1))
