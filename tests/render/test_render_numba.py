"""The compiled CPU backend (numba) against the torch backend, gradcheck, determinism.

numba is in the ``dev`` extra, so these run in CI; without numba, or with it switched off
(``MESHSPLAT_NO_NUMBA=1``), they are skipped here and the fallback (``auto`` -> torch) is tested in
test_render_api.py.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from _render_kit import PARAMS, _gradcheck_scene, _loss, _with_grad, random_scene
from meshsplat.render import api as render_api
from meshsplat.render import rasterize
from meshsplat.render.backends import numba_available
from meshsplat.render.backends.numba_cpu import KERNEL_ENV, KERNELS

numba = pytest.importorskip("numba")
pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is switched off (MESHSPLAT_NO_NUMBA=1)")

GRAD_NAMES = PARAMS + ("backgrounds",)


@pytest.fixture(params=KERNELS, autouse=True)
def kernel(request, monkeypatch):
    """Every test here runs with both compositing kernels: pixels in SIMD lanes (the default) and the scalar one."""
    monkeypatch.setenv(KERNEL_ENV, request.param)
    return request.param


def _run(scene, backend, render_mode="RGB", seed=1):
    inputs = _with_grad({k: v for k, v in scene.items() if v is not None})
    out = rasterize(**inputs, render_mode=render_mode, backend=backend)
    _loss(out.colors, out.alphas, seed=seed).backward()
    grads = {k: inputs[k].grad for k in GRAD_NAMES if k in inputs}
    grads["means2d"] = out.meta["means2d"].grad
    return out, grads


def _assert_parity(scene, render_mode="RGB", img_tol=1e-5, grad_rtol=1e-4, proj_exact=True):
    """Images to img_tol (the depth channel of RGB+ED relative to its size), every gradient to grad_rtol of
    its largest entry; projection outputs to rounding (``proj_exact=False``: checked by the caller)."""
    a, ga = _run(scene, "torch", render_mode)
    b, gb = _run(scene, "numba", render_mode)
    assert b.meta["backend"] == "numba"
    assert b.meta["kernel"] == (os.environ.get(KERNEL_ENV) or "lanes")
    ca, cb = a.colors.detach(), b.colors.detach()
    scale = torch.ones(ca.shape[-1], dtype=ca.dtype)
    if render_mode == "RGB+ED":
        scale[-1] = ca[..., -1].abs().max().clamp_min(1.0)
    torch.testing.assert_close(cb / scale, ca / scale, atol=img_tol, rtol=0)
    torch.testing.assert_close(b.alphas.detach(), a.alphas.detach(), atol=img_tol, rtol=0)
    for key in ("radii", "visible"):
        torch.testing.assert_close(b.meta[key], a.meta[key], atol=0, rtol=0)
    for key in ("depths", "conics", "means2d") if proj_exact else ():  # float64 inside vs torch's float32
        ref = a.meta[key].detach()
        tol = 1e-6 if ref.dtype == torch.float32 else 1e-13
        torch.testing.assert_close(b.meta[key].detach(), ref, atol=tol * float(ref.abs().max()), rtol=tol)
    for k, g in ga.items():
        assert gb[k] is not None, k
        err = float((gb[k] - g).abs().max() / g.abs().max().clamp_min(1e-30))
        assert err < grad_rtol, f"{k}: max error {err:.2e} of the largest gradient"
    return a, b


@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_torch_backend_float32(render_mode, seed):
    """The parity scenes: opaque stack (T < 1e-4), 3 cameras incl. one inside the cloud (behind-camera and
    off-screen splats), backgrounds per camera; images to 1e-5, gradients to 1e-4."""
    _, b = _assert_parity(random_scene(seed=seed, dtype=torch.float32), render_mode)
    assert float(b.alphas.detach().max()) > 1 - 1e-3  # saturated pixels exercise the transmittance stop


def test_matches_torch_backend_float64_tightly():
    scene = random_scene(seed=3, dtype=torch.float64)
    _assert_parity(scene, img_tol=1e-12, grad_rtol=1e-10)


def test_many_tiles_odd_sizes_and_per_camera_colors():
    """More Gaussians than the parity scenes, images that are not a multiple of the 16 px tile, colors [C,N,D]."""
    scene = random_scene(n=400, seed=8, dtype=torch.float32, width=83, height=57)
    g = torch.Generator().manual_seed(3)
    scene["colors"] = torch.rand(3, 400, 3, generator=g)
    _assert_parity(scene)


def test_saturated_alpha_clamp_and_degenerate_splats():
    """alpha clamped at 0.999 (no gradient through the clamp), needle and point-like Gaussians, unnormalised
    quaternions, a near plane that culls part of the cloud, no backgrounds."""
    scene = random_scene(seed=7, dtype=torch.float32)  # as test_clamped_alpha_passes_no_gradient_like_gsplat
    scene["opacities"] = torch.full_like(scene["opacities"], 1.0)
    scene["scales"] = scene["scales"] * 10.0
    scene["scales"][10:14, :2] = 1e-6  # needles
    scene["scales"][14:18] = 1e-7  # points: the 0.3 px^2 dilation alone
    scene["quats"][18:22] *= 1e3
    scene["backgrounds"] = None
    _assert_parity(scene, proj_exact=False)
    # needle conics cancel catastrophically in float32 (det of a near rank-1 covariance); the compiled projection
    # works in float64 inside, so it is checked against the torch projection run in float64
    ref = rasterize(**{k: v.double() if isinstance(v, torch.Tensor) else v for k, v in scene.items()}, backend="torch")
    out = rasterize(**scene, backend="numba")
    for key in ("depths", "conics", "means2d"):
        want = ref.meta[key].detach()
        torch.testing.assert_close(
            out.meta[key].detach().double(), want, atol=1e-6 * float(want.abs().max()), rtol=1e-6
        )
    near = dict(scene, backgrounds=random_scene(seed=7, dtype=torch.float32)["backgrounds"])
    a = rasterize(**near, near_plane=2.5, backend="numba")
    b = rasterize(**{k: v.double() if isinstance(v, torch.Tensor) else v for k, v in near.items()}, near_plane=2.5)
    assert 0 < int(a.meta["visible"].sum()) < int(rasterize(**near, backend="numba").meta["visible"].sum())
    # the stop before T <= 1e-4 is a step: a rounding-level change of alpha can drop a whole splat at a pixel
    # where T * (1 - alpha) sits on the threshold (3 of 6912 pixels here); every other pixel agrees to 1e-5
    err = (a.colors.double() - b.colors).abs().amax(-1)
    assert int((err > 1e-5).sum()) <= 4 and float(err.max()) < 1e-3


def test_nothing_visible_gives_background_and_zero_gradients():
    scene = random_scene(seed=0, dtype=torch.float32)
    scene["means"] = scene["means"] * 0.1 + torch.tensor([0.0, 0.0, -50.0])  # behind every camera
    out, grads = _run(scene, "numba")
    assert not bool(out.meta["visible"].any())
    C, H, W = 3, scene["height"], scene["width"]
    expected = scene["backgrounds"][:, None, None, :].expand(C, H, W, 3)
    torch.testing.assert_close(out.colors.detach(), expected, atol=0, rtol=0)
    assert float(out.alphas.detach().abs().max()) == 0.0
    assert float(grads["means"].abs().max()) == 0.0 and float(grads["backgrounds"].abs().max()) > 0


@pytest.mark.gradcheck
@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
def test_gradcheck_numba_backend(render_mode):
    means, quats, scales, opac, colors, viewmats, K, bg = _gradcheck_scene()

    def f(means, quats, scales, opac, colors, bg):
        out = rasterize(
            means, quats, scales, opac, colors, viewmats, K, 16, 12, backgrounds=bg, render_mode=render_mode,
            backend="numba",
        )  # fmt: skip
        return out.colors, out.alphas

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors, bg))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
    assert torch.autograd.gradcheck(lambda *a: f(*a)[0][:, 4:8, 6:10], inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_deterministic_for_a_fixed_thread_count():
    """Gradient rows belong to (tile, Gaussian) intersections and are summed in a fixed order: repeated runs
    with the same thread count (1, and 2 where numba has more than one) are bit-identical. Runs with other
    thread counts agree to rounding only (torch's projection may block its sums differently)."""
    scene = random_scene(n=300, seed=9, dtype=torch.float32, width=70, height=50)
    before = torch.get_num_threads()
    counts = [1] + ([2] if numba.config.NUMBA_NUM_THREADS > 1 else [])
    try:
        for n in counts:
            torch.set_num_threads(n)
            (ref, ref_g), (out, grads) = _run(scene, "numba"), _run(scene, "numba")
            assert torch.equal(out.colors, ref.colors) and torch.equal(out.alphas, ref.alphas), n
            for k, g in ref_g.items():
                assert torch.equal(grads[k], g), (n, k)
    finally:
        torch.set_num_threads(before)


def test_auto_picks_numba_for_cpu_tensors(monkeypatch):
    monkeypatch.delenv("MESHSPLAT_NO_NUMBA", raising=False)
    scene = random_scene(seed=0, dtype=torch.float32)
    assert rasterize(**scene).meta["backend"] == "numba"
    assert render_api._pick_backend("auto", torch.device("cpu"), torch.float64) == "numba"


def test_torch_keeps_its_thread_count():
    """numba's OpenMP layer shares the runtime with torch: a render must not change torch's thread count."""
    scene = random_scene(n=50, seed=3, dtype=torch.float32, width=32, height=24)
    before = torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            _run(scene, "numba")
            assert torch.get_num_threads() == n
    finally:
        torch.set_num_threads(before)


def test_camera_gradients_use_torch_projection():
    """viewmats/Ks that require grad (pose refinement) get their gradient: the numba backend then projects with
    torch's autograd projection and still composites with its kernels; every gradient matches the torch backend."""
    scene = random_scene(seed=4, dtype=torch.float32)
    got = {}
    for backend in ("torch", "numba"):
        inputs = _with_grad({k: v for k, v in scene.items() if v is not None})
        inputs["viewmats"] = inputs["viewmats"].clone().requires_grad_(True)
        out = rasterize(**inputs, backend=backend)
        _loss(out.colors, out.alphas, seed=2).backward()
        got[backend] = {k: inputs[k].grad for k in GRAD_NAMES + ("viewmats",)}
    for k, g in got["torch"].items():
        err = float((got["numba"][k] - g).abs().max() / g.abs().max().clamp_min(1e-30))
        assert err < 1e-4, f"{k}: {err:.2e}"
    assert float(got["numba"]["viewmats"].abs().max()) > 0


def test_run_ranges_covers_every_item_once():
    """``run_ranges``: one call over ``[0, n)`` on one thread, and on more the driver's ranges tile ``[0, n)``
    exactly (contiguous, in order, about 4 per thread), for several thread counts and sizes."""
    from meshsplat._numba import run_ranges

    def mark(hits, lo, hi):
        hits[lo:hi] += 1

    def driver(bounds, hits):  # what the compiled drivers do, in plain Python
        assert bounds[0] == 0 and (np.diff(bounds) > 0).all()
        for j in range(bounds.shape[0] - 1):
            mark(hits, bounds[j], bounds[j + 1])

    before = torch.get_num_threads()
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            for n in (0, 1, 2, 7, 1000):
                hits = np.zeros(n, np.int64)
                run_ranges(mark, driver, n, hits)
                assert (hits == 1).all(), (threads, n)
            assert torch.get_num_threads() == threads
    finally:
        torch.set_num_threads(before)
