"""The compositing kernels with pixels in SIMD lanes (``numba_lanes``) against the scalar ones they replace by
default, their inlined ``exp``, the switch, and the vector code they compile to.

Both kernels also run every parity test against the torch backend (test_render_numba.py is parametrized over
them).
"""

from __future__ import annotations

import os
import platform

import numpy as np
import pytest
import torch

from _render_kit import random_scene
from meshsplat.errors import MeshsplatError
from meshsplat.render import rasterize
from meshsplat.render.backends import numba_available
from meshsplat.render.backends import numba_cpu as nc
from meshsplat.render.backends import numba_lanes as nl

numba = pytest.importorskip("numba")
pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is switched off (MESHSPLAT_NO_NUMBA=1)")


def _geometry(scene):
    """The binned entries of a scene (one call's no-grad state), as the compositing kernels take them."""
    k = nc._kernels()
    s = scene
    proj = nc.project_numba(
        (k.project, k.project_backward), s["means"], s["quats"], s["scales"], s["opacities"],
        s["viewmats"], s["Ks"], s["width"], s["height"], 0.01, 1e10,
    )  # fmt: skip
    colors = s["colors"]
    geo = nc._Geometry(proj, s["means"].shape[0], colors.dim() == 2, s["width"], s["height"], nc.TILE_SIZE)
    geo.bin(s["opacities"], colors)
    return k, geo, s["backgrounds"].contiguous().numpy()


@pytest.mark.parametrize("n_colors", [1, 4])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lanes_match_the_scalar_kernels(dtype, n_colors):
    """Same contribution lists (list position after each pixel's last splat), image and final T to rounding, every
    per-intersection gradient row to 1e-5 (float32) / 1e-12 (float64) of its column's largest entry; fewer and
    more colour channels than the 3 the lane loop sums itself."""
    scene = random_scene(n=400, seed=8, dtype=dtype, width=83, height=57)
    g = torch.Generator().manual_seed(3)
    scene["colors"] = torch.rand(3, 400, n_colors, generator=g, dtype=dtype)
    scene["backgrounds"] = torch.rand(3, n_colors, generator=g, dtype=dtype)
    k, geo, bg = _geometry(scene)
    out_s, tf_s, nc_s = k.forward(*geo.args(bg))
    out_l, tf_l, nc_l, alpha_l = k.forward_lanes(*geo.args(bg))
    rng = np.random.default_rng(0)
    n_pix = tf_s.shape[0]
    g_col = rng.standard_normal((n_pix, n_colors)).astype(out_s.dtype)
    g_alpha = rng.standard_normal(n_pix).astype(out_s.dtype)
    rows_s = k.backward(*geo.args(bg), g_col, g_alpha, tf_s, nc_s)
    rows_l = k.backward_lanes(*geo.args(bg), g_col, g_alpha, tf_s, nc_s)
    tol = 1e-6 if dtype == torch.float32 else 1e-13
    assert (tf_s < 1e-3).any() and int(nc_s.max()) > 5  # saturated pixels: the transmittance stop is exercised
    np.testing.assert_array_equal(nc_l, nc_s)
    np.testing.assert_allclose(out_l, out_s, atol=tol, rtol=0)
    np.testing.assert_allclose(tf_l, tf_s, atol=tol, rtol=0)
    np.testing.assert_allclose(alpha_l, 1.0 - tf_s, atol=tol, rtol=0)
    scale = np.abs(rows_s).max(0)
    assert (scale > 0).all()
    err = (np.abs(rows_l - rows_s).max(0) / scale).max()
    assert err < (1e-5 if dtype == torch.float32 else 1e-12), err


def test_inlined_exp_is_within_two_ulp():
    """The float32 polynomial ``exp(-x)`` of the lane loops against float64 ``exp``, over the range alpha uses."""
    nl.compile_kernels(numba)
    exp_neg = nl._exp_neg
    f = numba.njit(lambda a: np.array([exp_neg(v) for v in a], np.float32))
    x = np.concatenate([np.linspace(0, 20, 200_001), [87.0, 100.0, 1e30]]).astype(np.float32)
    got = f(x).astype(np.float64)
    ref = np.exp(-x.astype(np.float64))
    rel = np.abs(got[:-3] - ref[:-3]) / ref[:-3]
    assert float(rel.max()) < 2 * 2.0**-24  # two half-ulps; glibc's expf: one
    assert (got[-3:] >= 0).all() and (got[-3:] < 1e-37).all()  # far tails: tiny, not negative, no NaN


def test_switch_picks_the_kernel(monkeypatch):
    scene = random_scene(seed=0, dtype=torch.float32)
    monkeypatch.delenv(nc.KERNEL_ENV, raising=False)
    assert rasterize(**scene, backend="numba").meta["kernel"] == "lanes"
    monkeypatch.setenv(nc.KERNEL_ENV, "scalar")
    assert rasterize(**scene, backend="numba").meta["kernel"] == "scalar"
    monkeypatch.setenv(nc.KERNEL_ENV, "avx9")
    with pytest.raises(MeshsplatError, match="MESHSPLAT_RASTER_KERNEL"):
        rasterize(**scene, backend="numba")


def _host_features() -> list[str]:
    import llvmlite.binding as ll

    return ll.get_host_cpu_features().flatten().split(",")


x86_avx2 = pytest.mark.skipif(
    platform.machine() not in ("x86_64", "AMD64") or "+avx2" not in _host_features(),
    reason="checks x86-64 vector registers on a host with AVX2",
)


@x86_avx2
def test_lane_loops_compile_to_vector_code(monkeypatch):
    """On an x86-64 host with AVX2 the float32 lane loops are packed 256-bit (ymm) code: LLVM's own choice where the
    host has AVX-512 (a Zen 4 host), forced where it has AVX2 alone (LLVM picks 4 lanes, xmm, there: a Zen 3
    host). (The scalar kernel's code has none of it.)"""
    monkeypatch.delenv(nl.VECTOR_WIDTH_ENV, raising=False)
    assert nl.lane_vector_width() == (0 if "+avx512f" in _host_features() else 8)
    scene = random_scene(n=60, seed=1, dtype=torch.float32)
    _, geo, bg = _geometry(scene)
    report = nl.vector_report(geo.args(bg))
    assert report["ymm"] + report["zmm"] >= 30, report


def test_arm64_compiles_the_lane_loops_four_wide(monkeypatch):
    """The width rule on arm64 (checked on any host): 4 lanes, one NEON register, whatever numba's target CPU; an
    explicit ``MESHSPLAT_LANE_VECTOR_WIDTH`` still wins."""
    monkeypatch.delenv(nl.VECTOR_WIDTH_ENV, raising=False)
    for machine in ("arm64", "aarch64"):
        monkeypatch.setattr(platform, "machine", lambda m=machine: m)
        assert nl.lane_vector_width() == 4
    monkeypatch.setenv(nl.VECTOR_WIDTH_ENV, "8")
    assert nl.lane_vector_width() == 8


@pytest.mark.skipif(platform.machine() not in ("aarch64", "arm64"), reason="checks arm64 vector registers")
def test_lane_loops_compile_to_neon_on_arm64(monkeypatch):
    """On arm64 (Apple silicon, Graviton) the lane loops are compiled 4 lanes wide (NEON's 128 bits; LLVM's own
    choice leaves the forward's scalar) and are packed NEON (``v0.4s``) or SVE code, forward and backward. Run
    under qemu-aarch64 (bench/raster_cpu_lanes.md, arm64); no arm64 machine runs the suite."""
    monkeypatch.delenv(nl.VECTOR_WIDTH_ENV, raising=False)
    assert nl.lane_vector_width() == 4
    scene = random_scene(n=60, seed=1, dtype=torch.float32)
    k, geo, bg = _geometry(scene)
    out, t_final, n_contrib, _ = k.forward_lanes(*geo.args(bg))
    g_col, g_alpha = np.ones_like(out), np.ones(t_final.shape[0], out.dtype)
    forward = nl.vector_report(geo.args(bg))
    backward = nl.vector_report((*geo.args(bg), g_col, g_alpha, t_final, n_contrib), backward=True)
    assert forward["neon"] + forward["sve"] >= 30, forward
    assert backward["neon"] + backward["sve"] >= 30, backward


@x86_avx2
def test_the_forced_width_holds_only_while_the_lane_loops_compile(monkeypatch):
    """``MESHSPLAT_LANE_VECTOR_WIDTH=4`` compiles the lane loops on xmm; LLVM's option is reset after, so a loop
    compiled next gets LLVM's own (256-bit) choice again; numba compiling for another CPU gets LLVM's width; a
    width that is not 0/4/8/16 is refused in one line."""
    scene = random_scene(n=60, seed=1, dtype=torch.float32)
    _, geo, bg = _geometry(scene)  # (the kernels themselves compiled before the variable is set)
    monkeypatch.setenv(nl.VECTOR_WIDTH_ENV, "4")
    report = nl.vector_report(geo.args(bg))
    assert report["xmm"] >= 30 and report["ymm"] + report["zmm"] < report["xmm"] / 4, report

    def axpy(a, x, y):
        for i in range(x.shape[0]):
            y[i] = a * x[i] + y[i]

    fn = numba.njit(cache=False)(axpy)
    fn(np.float32(2.0), np.ones(64, np.float32), np.ones(64, np.float32))
    assert "%ymm" in "\n".join(fn.inspect_asm().values()) or "%zmm" in "\n".join(fn.inspect_asm().values())
    monkeypatch.delenv(nl.VECTOR_WIDTH_ENV)
    monkeypatch.setattr(numba.config, "CPU_NAME", "x86-64")  # numba told to compile for another CPU: LLVM's width
    assert nl.lane_vector_width() == 0
    monkeypatch.setenv(nl.VECTOR_WIDTH_ENV, "6")
    with pytest.raises(MeshsplatError, match="MESHSPLAT_LANE_VECTOR_WIDTH='6' is not one of 0, 4, 8, 16"):
        nl.lane_vector_width()


def _allocates_in_a_loop(x):  # a loop LLVM cannot vectorize (a call inside)
    t = 0.0
    for i in range(x.shape[0]):
        a = np.empty(3)
        a[0] = x[i]
        t += a[0]
    return t


@x86_avx2
def test_llvm_remarks_of_a_forced_width_stay_off_stderr(capfd):
    """At a forced width LLVM prints a remark on stderr for each loop it leaves scalar (31 lines for the first
    two-thread render): they are dropped while the lane kernels compile, and anything else written to stderr
    then still comes out."""
    import llvmlite.binding as ll

    ll.set_option("", "-force-vector-width=8")  # the bare option, as a control: the remark is printed
    try:
        numba.njit(cache=False)(_allocates_in_a_loop)(np.ones(4))
    finally:
        ll.set_option("", "-force-vector-width=0")
    assert "loop not vectorized" in capfd.readouterr().err
    with nl._compiling_at(8):
        numba.njit(cache=False)(_allocates_in_a_loop)(np.ones(4))
        os.write(2, b"a line of its own\n")
    err = capfd.readouterr().err
    assert "loop not vectorized" not in err and "a line of its own" in err, err


@x86_avx2
def test_the_vector_width_changes_the_code_not_the_numbers():
    """The lane loops compiled 4 and 8 lanes wide give the same image, transmittance, contribution lists and
    gradient rows, bit for bit: every lane is a pixel of its own, and an entry's lanes are summed in a fixed
    order outside the vector code (no fastmath: LLVM may not reassociate)."""
    scene = random_scene(n=400, seed=8, dtype=torch.float32, width=83, height=57)
    _, geo, bg = _geometry(scene)
    args = geo.args(bg)
    rng = np.random.default_rng(0)
    results = []
    for width in (4, 8):
        with nl._compiling_at(width):
            fwd = numba.njit(cache=False, nogil=True, error_model="numpy")(nl._forward_lanes)
            bwd = numba.njit(cache=False, nogil=True, error_model="numpy")(nl._backward_lanes)
            out = nl._outputs(args[2], args[4], args[5], args[8], args[9])
            fwd(*args, *out, 0, args[3].shape[0])
            colors, tf, last, _ = out
            g_col = rng.standard_normal(colors.shape).astype(colors.dtype)
            g_alpha = rng.standard_normal(tf.shape[0]).astype(colors.dtype)
            rows = nl.grad_rows(args[1], args[2])
            bwd(*args, g_col, g_alpha, tf, last, rows, 0, args[3].shape[0])
        rng = np.random.default_rng(0)
        results.append((*out, rows))
    assert np.abs(results[0][-1]).max() > 0
    for a, b in zip(*results, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_radix_depth_order_matches_torch_stable_argsort(dtype):
    """The entry order (camera, then depth, ties by Gaussian index) from the radix sort of the depths' bits is
    torch's stable argsort's, with ties, -0 beside +0, negative depths and empty cameras."""
    k = nc._kernels()
    g = torch.Generator().manual_seed(0)
    for n in (0, 1, 7, 3000):
        depths = torch.rand(3, n, generator=g, dtype=dtype) * 5 + 0.01
        if n > 10:
            depths[:, : n // 3] = depths[:, n // 3 : 2 * (n // 3)]  # ties
            depths[0, 5], depths[0, 6], depths[1, 3] = -0.0, 0.0, -1.5
        visible = torch.rand(3, n, generator=g) < 0.7
        visible[2] = False
        key = torch.where(visible, depths, torch.full_like(depths, float("inf")))
        order = torch.argsort(key, dim=1, stable=True)
        want = (order + torch.arange(3)[:, None] * n)[visible.gather(1, order)].numpy()
        d = depths.numpy()
        got = k.depth_order(nc._depth_keys(d), visible.numpy(), 8 * d.itemsize)
        np.testing.assert_array_equal(got, want)


def test_kernels_are_bit_identical_for_any_thread_count():
    """The projection and compositing kernels run over ranges of Gaussians / tiles on a pool of threads
    (``run_ranges``); each item is computed alone, so 1, 2 and 3 threads give the same bits."""
    scene = random_scene(n=500, seed=5, dtype=torch.float32, width=90, height=61)
    before = torch.get_num_threads()
    results = []
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            k, geo, bg = _geometry(scene)
            s = scene
            arrs = [s[x].contiguous().numpy() for x in ("means", "quats", "scales", "opacities")]
            cams = [s[x].double().contiguous().numpy() for x in ("viewmats", "Ks")]
            proj = k.project(*arrs, *cams, float(s["width"]), float(s["height"]), 0.01, 1e10)
            rng = np.random.default_rng(1)
            v = [rng.standard_normal(x.shape) for x in proj[:3]]
            proj_bwd = k.project_backward(*arrs[:3], *cams, float(s["width"]), float(s["height"]), proj[4], *v)
            fwd = k.forward_lanes(*geo.args(bg))
            g_col = rng.standard_normal(fwd[0].shape).astype(np.float32)
            g_alpha = rng.standard_normal(fwd[1].shape[0]).astype(np.float32)
            rows = k.backward_lanes(*geo.args(bg), g_col, g_alpha, fwd[1], fwd[2])
            rows_scalar = k.backward(*geo.args(bg), g_col, g_alpha, fwd[1], fwd[2])
            # the tile order depends on the thread count; the images and the rows of each intersection do not
            results.append((*proj, *proj_bwd, *fwd, rows, rows_scalar))
    finally:
        torch.set_num_threads(before)
    for other in results[1:]:
        for a, b in zip(results[0], other, strict=True):
            np.testing.assert_array_equal(a, b)
