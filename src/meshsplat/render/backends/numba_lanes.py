"""Compositing kernels with the 16 pixels of a 4x4 block in SIMD lanes (numba), forward and backward.

Same inputs, outputs and conventions as the scalar kernels of ``numba_cpu`` (which stay the reference and
the fallback: ``MESHSPLAT_RASTER_KERNEL=scalar``), a different shape: a 16x16 tile is 4x4 blocks of 4x4 pixels,
and for each entry of a tile's list and each block of its footprint box (the binning's rows and columns) inside
the tile, the block's 16 pixels are evaluated together in fixed-length loops (``for lane in range(16)``) that LLVM
turns into vector code; branches are masks and selects (lanes outside the entry's rows masked), there is no
per-row span pass (the ``alpha >= 1/255`` test is the footprint: the span is only its closed form plus 0.05 px
of slack, and opacities are at most 1, where the torch backend's ``tau`` clamp never binds). Transmittance,
colour sums and the per-pixel terms are in the input dtype (float32 in training); alpha is returned as the sum
of the weights (exact near 0, where ``1 - T`` in float32 is not). An entry's gradient is summed per lane over its
blocks, then the 16 lanes in float64 in a fixed order: results are bit-identical for any thread count.

Blocks instead of tile rows (issue 47): an entry of 3 x 4 pixels (500k Gaussians at 512²) touched 4 rows of 16
lanes, about 2.6 blocks; one of 4.7 x 7 (50k) 7 rows, about 4.8 blocks. Same images, bit for bit, on the
benchmark scenes (the lanes a row left out lay outside the footprint box); forward 1.6x at 500k, 1.25x at 50k.

Per tile: a tile without entries is the background straight away (more than half the tiles of a 512² avatar
image), the per-tile arrays are allocated once per range of tiles, and the forward asks every 16th entry whether
the whole tile is done (a count of finished pixels per block cost 10% of the forward).

``exp`` is inlined as a polynomial for float32 (Cephes' ``expf``: range reduction by ``ln 2``, degree-6
polynomial, ``2^n`` put into the exponent bits; within 8.1e-8 relative of ``exp`` on [0, 20], glibc's
``expf``: 6e-8), since a call to libm stops LLVM from vectorizing the loop; float64 calls ``math.exp``.

Generated code (numba 0.68.1 / LLVM 20 on a Zen 4 host with AVX-512, ``vector_report``): the float32 lane
loops compile to packed 256-bit code, each 16-pixel block as two ``ymm`` halves (``vmulps``/``vaddps``,
``vcmpleps`` into ``k`` masks and masked moves as selects, ``vrndscaleps``/``vcvttps2dq``/``vpslld`` for the
exp), fully unrolled, with the aliasing checks hoisted out of the block loop; LLVM prefers 256-bit vectors on this
CPU and numba exposes no per-function switch to 512. On a host with AVX2 but no AVX-512 (a Zen 3 host, the same
versions) LLVM's cost model vectorizes the same loops 4 lanes wide, on 128-bit ``xmm`` registers; there the lane
kernels are compiled with LLVM's ``-force-vector-width=8`` (:func:`lane_vector_width`), set only while they
compile and reset after (``ymm``; bench/raster_cpu_lanes.md). On arm64 (numba 0.68.1 / LLVM 20, the code
compiled under qemu-aarch64 for Apple M1, Neoverse V1 and a generic target) LLVM vectorizes the backward's lane
loops on NEON but leaves the forward's scalar (2-5 packed instructions); forced to 4 lanes (one 128-bit ``v``
register) the forward has 61 and the backward 143 (bench/raster_cpu_lanes.md, arm64). The scalar kernels' pixel
loops have no packed arithmetic.
"""

from __future__ import annotations

import math
import os
from contextlib import AbstractContextManager
from functools import lru_cache, partial
from typing import Any

import numpy as np

from meshsplat._numba import (
    float_from_bits,
    host_is_arm64,
    llvm_options,
    njit_driver,
    njit_serial,
    run_ranges_compiling_in,
)
from meshsplat.errors import MeshsplatError
from meshsplat.render._constants import PIXEL_CENTER, TRANSMITTANCE_MIN

__all__ = ["LANES", "compile_kernels", "grad_rows", "vector_report", "lane_vector_width", "VECTOR_WIDTH_ENV"]

LANES = 16  # pixels per block (4x4) = the tile size of numba_cpu (a tile: 4x4 blocks)
# columns of an entry's record (numba_cpu's binning writes them, in the input dtype): the projection's values
# exactly, the footprint's first and last pixel row and column, then the colours
_MX, _MY, _CA, _CB, _CC, _OP, _Y0, _Y1, _X0, _X1, _COL = range(11)

_ULANES = np.uint64(LANES)  # lane loops run over unsigned indices: no negative-index wraparound to vectorize
# Per-tile state: one flat array of [block, field, lane], so that LLVM sees the fields of a block at constant
# distances (no run-time aliasing checks per block). Forward fields: T (negative once done), w, alpha (the sum of
# the weights: near 0 it is exact where ``1 - T`` in float32 is not; RGB+ED divides by it), colour sums.
_F_T, _F_W, _F_A, _F_ACC = 0, 1, 2, 3
# Backward fields: T, later splats' sum, <g, c>, w, dL/dcolour of the pixel.
_B_T, _B_LATER, _B_CG, _B_W, _B_GP = 0, 1, 2, 3, 4


VECTOR_WIDTH_ENV = "MESHSPLAT_LANE_VECTOR_WIDTH"  # 0: LLVM's own choice; 4, 8, 16: forced (unset: the host's)


def lane_vector_width() -> int:
    """The vector width (float32 elements) LLVM is told to use for the lane loops: 8 on an x86-64 host with AVX2
    and without AVX-512, where its cost model picks 4 (``xmm``) and 8 (``ymm``) measured 26% faster forward; 4 on
    arm64 (NEON's 128 bits, on every arm64 CPU), where its cost model leaves the forward's lane loops scalar (code
    seen under qemu-aarch64 for Apple M1, Neoverse V1 and generic targets; on x86-64 the same loops unvectorized
    ran 3.4x slower than at 4 lanes); 0 (LLVM's choice) elsewhere, including AVX-512 hosts, where it already
    picks 8, and where numba compiles for another x86-64 CPU than the host (``NUMBA_CPU_NAME``/
    ``NUMBA_CPU_FEATURES``). ``MESHSPLAT_LANE_VECTOR_WIDTH`` overrides it (0, 4, 8 or 16; read when the kernels
    first compile in a process); the kernels are then compiled without numba's disk cache, whose entries do not
    record the width."""
    override = _width_override()
    if override is not None:
        return override
    if host_is_arm64():
        return 4
    import numba
    from llvmlite import binding as llvm

    config: Any = numba.config  # (its settings are set at import: no attributes for mypy)
    if config.CPU_NAME or config.CPU_FEATURES:  # a target of the user's choosing: LLVM's width for it
        return 0
    features = llvm.get_host_cpu_features()
    return 8 if features.get("avx2", False) and not features.get("avx512f", False) else 0


def _width_override() -> int | None:
    """``MESHSPLAT_LANE_VECTOR_WIDTH`` as a width, ``None`` when unset; any other value than 0/4/8/16 is refused."""
    value = os.environ.get(VECTOR_WIDTH_ENV, "").strip()
    if not value:
        return None
    if value not in ("0", "4", "8", "16"):
        raise MeshsplatError(f"{VECTOR_WIDTH_ENV}={value!r} is not one of 0, 4, 8, 16 (or unset)")
    return int(value)


def _compiling_at(width: int) -> AbstractContextManager[None]:
    """Numba compilations inside run with LLVM's ``-force-vector-width=width`` (0: nothing changes; see
    ``_numba.llvm_options``)."""
    return llvm_options({"force-vector-width": width} if width else {})


def _exp_neg(x):  # pragma: no cover - replaced by an overload when compiled
    """``exp(-x)`` (compiled: a polynomial for float32, ``math.exp`` for float64)."""
    return math.exp(-x)


def _forward_lanes(
    tile_ptr, isect, rec, order, bg, xs, ys, consts, width, height, tile, tiles_x, tiles_y,
    out, t_final, n_contrib, alphas, lo, hi,
):  # pragma: no cover - compiled  # fmt: skip
    """As ``numba_cpu._forward_kernel``, for the tiles ``order[lo:hi]``: into colors ``out`` [P,D] (dtype), final
    T [P] float64, list position after the last splat [P] int32, and alpha [P] (dtype, the sum of the weights);
    per tile, the blocks of each entry's footprint box inside the tile, 16 pixels at a time."""
    to_dt = xs.dtype.type
    half, a_max, a_thr = consts[0], consts[1], consts[2]
    one, zero, t_min = to_dt(1.0), to_dt(0.0), to_dt(TRANSMITTANCE_MIN)
    d_out = rec.shape[1] - _COL
    d_pad = max(d_out, 3)  # the first 3 colours are summed in the lane loop itself
    nf = _F_ACC + d_pad
    n_pix_cam = width * height
    per_cam = tiles_x * tiles_y
    st = np.empty(LANES * nf * LANES, xs.dtype)  # per tile: [block, field, lane]
    last = np.empty(LANES * LANES, np.int32)  # [block, lane]
    pxb, pyb = np.empty(4 * LANES, xs.dtype), np.empty(4 * LANES, xs.dtype)
    col = np.zeros(d_pad, xs.dtype)
    for i in range(lo, hi):
        t = order[i]
        c = t // per_cam
        tx0 = (t % tiles_x) * LANES
        ty0 = ((t % per_cam) // tiles_x) * LANES
        tw = min(width, tx0 + LANES) - tx0
        th = min(height, ty0 + LANES) - ty0
        if tile_ptr[t] == tile_ptr[t + 1]:  # no entry: the background (as below with nothing composited)
            for r in range(th):
                for x in range(tw):
                    p = c * n_pix_cam + (ty0 + r) * width + tx0 + x
                    for d in range(d_out):
                        out[p, d] = zero + one * bg[c, d]
                    t_final[p] = 1.0
                    n_contrib[p] = 0
                    alphas[p] = zero
            continue
        st[:] = zero
        last[:] = 0
        _block_grid(tx0, ty0, pxb, pyb)
        for q in range(LANES):
            for lane in range(LANES):  # pixels past the image start done
                inside = 4 * (q & 3) + (lane & 3) < tw and 4 * (q >> 2) + (lane >> 2) < th
                st[(q * nf + _F_T) * LANES + lane] = one if inside else -one
        s0 = tile_ptr[t]
        unf = np.uint64(nf)
        for k in range(s0, tile_ptr[t + 1]):
            if (k - s0) & 15 == 15 and _tile_done(st, nf):  # every 16th entry (a count per block cost 10%)
                break
            e = isect[k]
            ra, rb, y_lo, y_hi, xa, xb, mxe, mye, ca, cb, cc, ope = _entry(rec, e, tx0, ty0, tw, th, col, d_out, xs)
            c0, c1, c2 = col[0], col[1], col[2]
            step = np.int32(k - s0 + 1)
            for by in range(ra >> 2, (rb >> 2) + 1):  # the blocks of the entry's box in the tile
                pyo = np.uint64(by * LANES)
                for bx in range(xa >> 2, (xb >> 2) + 1):
                    pxo = np.uint64(bx * LANES)
                    uq = np.uint64(by * 4 + bx)
                    b = uq * unf * _ULANES  # the block's T; its other fields at constant distances
                    bl = uq * _ULANES
                    for lane in range(_ULANES):  # vectorized: one pixel per lane
                        dx = mxe - pxb[pxo + lane]
                        py = pyb[pyo + lane]
                        dy = mye - py
                        sigma = half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                        alpha = min(ope * _exp_neg(sigma), a_max)
                        tq = st[b + lane]
                        t_next = tq * (one - alpha)
                        live = (py >= y_lo) & (py <= y_hi) & (sigma >= zero) & (alpha >= a_thr) & (tq > zero)
                        stop = live & (t_next <= t_min)
                        hit = live & (not stop)
                        wv = alpha * tq if hit else zero
                        st[b + lane] = t_next if hit else (-tq if stop else tq)
                        st[b + np.uint64(_F_W * LANES) + lane] = wv
                        st[b + np.uint64(_F_A * LANES) + lane] += wv
                        st[b + np.uint64(_F_ACC * LANES) + lane] += wv * c0
                        st[b + np.uint64((_F_ACC + 1) * LANES) + lane] += wv * c1
                        st[b + np.uint64((_F_ACC + 2) * LANES) + lane] += wv * c2
                        last[bl + lane] = step if hit else last[bl + lane]
                    for d in range(3, d_out):
                        cd = col[d]
                        bd = b + np.uint64((_F_ACC + d) * LANES)
                        for lane in range(_ULANES):
                            st[bd + lane] += st[b + np.uint64(_F_W * LANES) + lane] * cd
        for r in range(th):
            for x in range(tw):
                p = c * n_pix_cam + (ty0 + r) * width + tx0 + x
                sb = _block(r, x) * nf * LANES + _lane(r, x)
                tf = abs(st[sb + _F_T * LANES])
                for d in range(d_out):
                    out[p, d] = st[sb + (_F_ACC + d) * LANES] + tf * bg[c, d]
                t_final[p] = np.float64(tf)
                n_contrib[p] = last[_block(r, x) * LANES + _lane(r, x)]
                alphas[p] = st[sb + _F_A * LANES]


def _backward_lanes(
    tile_ptr,
    isect,
    rec,
    order,
    bg,
    xs,
    ys,
    consts,
    width,
    height,
    tile,
    tiles_x,
    tiles_y,
    g_col,
    g_alpha,
    t_final,
    n_contrib,
    grad,
    lo,
    hi,
):  # pragma: no cover - compiled
    """As ``numba_cpu._backward_kernel``, for the tiles ``order[lo:hi]``: into the per-intersection gradient rows
    ``grad`` [I, 6+D] float64 (mx, my, a, b, c, opacity, colours), walking each tile's list back to front, 16
    pixels of a block at a time."""
    to_dt = xs.dtype.type
    half, a_max, a_thr = consts[0], consts[1], consts[2]
    one, zero = to_dt(1.0), to_dt(0.0)
    d_out = rec.shape[1] - _COL
    d_pad = max(d_out, 3)  # the first 3 colours are handled in the lane loop itself
    nf = _B_GP + d_pad
    n_pix_cam = width * height
    per_cam = tiles_x * tiles_y
    n_g = 6 + d_out
    st = np.empty(LANES * nf * LANES, xs.dtype)  # per tile: [block, field, lane]
    last = np.empty(LANES * LANES, np.int32)  # [block, lane]; 0 past the image: no lane there is ever live
    pxb, pyb = np.empty(4 * LANES, xs.dtype), np.empty(4 * LANES, xs.dtype)
    col = np.zeros(d_pad, xs.dtype)
    # an entry's sums per lane: v dx, v dy, v dx dx, v dx dy, v dy dy (v: dL/dsigma), dL/dopacity, colours
    gl = np.empty((6 + d_pad) * LANES, xs.dtype)
    sums = np.empty(6 + d_pad, np.float64)
    for i in range(lo, hi):
        t = order[i]
        c = t // per_cam
        tx0 = (t % tiles_x) * LANES
        ty0 = ((t % per_cam) // tiles_x) * LANES
        tw = min(width, tx0 + LANES) - tx0
        th = min(height, ty0 + LANES) - ty0
        if tile_ptr[t] == tile_ptr[t + 1]:  # no entry: nothing to take back
            continue
        st[:] = zero
        last[:] = 0
        _block_grid(tx0, ty0, pxb, pyb)
        max_last = 0
        for r in range(th):
            for x in range(tw):
                p = c * n_pix_cam + (ty0 + r) * width + tx0 + x
                b = _block(r, x) * nf * LANES + _lane(r, x)
                tf = t_final[p]
                ex = -np.float64(g_alpha[p]) * tf
                for d in range(d_out):
                    st[b + (_B_GP + d) * LANES] = g_col[p, d]
                    ex += tf * np.float64(bg[c, d]) * np.float64(g_col[p, d])
                st[b + _B_T * LANES] = to_dt(tf)
                st[b + _B_LATER * LANES] = to_dt(ex)
                last[_block(r, x) * LANES + _lane(r, x)] = n_contrib[p]
                max_last = max(max_last, n_contrib[p])
        s0 = tile_ptr[t]
        unf = np.uint64(nf)
        for k in range(s0 + max_last - 1, s0 - 1, -1):
            e = isect[k]
            ra, rb, y_lo, y_hi, xa, xb, mxe, mye, ca, cb, cc, ope = _entry(rec, e, tx0, ty0, tw, th, col, d_out, xs)
            c0, c1, c2 = col[0], col[1], col[2]
            gl[:] = zero
            kk = np.int32(k - s0)
            for by in range(ra >> 2, (rb >> 2) + 1):  # the blocks of the entry's box in the tile
                pyo = np.uint64(by * LANES)
                for bx in range(xa >> 2, (xb >> 2) + 1):
                    pxo = np.uint64(bx * LANES)
                    uq = np.uint64(by * 4 + bx)
                    b = uq * unf * _ULANES  # the block's T; its other fields at constant distances
                    bl = uq * _ULANES
                    for d in range(3, d_out):  # colours past the third: their share of <g, c> first
                        cd = col[d]
                        bd = b + np.uint64((_B_GP + d) * LANES)
                        for lane in range(_ULANES):
                            st[b + np.uint64(_B_CG * LANES) + lane] += st[bd + lane] * cd
                    for lane in range(_ULANES):  # vectorized: one pixel per lane
                        dx = mxe - pxb[pxo + lane]
                        py = pyb[pyo + lane]
                        dy = mye - py
                        sigma = half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                        vis = _exp_neg(sigma)
                        raw = ope * vis
                        alpha = min(raw, a_max)
                        live = (py >= y_lo) & (py <= y_hi) & (kk < last[bl + lane]) & (sigma >= zero) & (alpha >= a_thr)
                        g0 = st[b + np.uint64(_B_GP * LANES) + lane]
                        g1 = st[b + np.uint64((_B_GP + 1) * LANES) + lane]
                        g2 = st[b + np.uint64((_B_GP + 2) * LANES) + lane]
                        cg = g0 * c0 + g1 * c1 + g2 * c2 + st[b + np.uint64(_B_CG * LANES) + lane]
                        st[b + np.uint64(_B_CG * LANES) + lane] = zero
                        one_m = one - alpha
                        tq = st[b + lane]
                        tr = tq / one_m  # T before this splat
                        wl = alpha * tr
                        lat = st[b + np.uint64(_B_LATER * LANES) + lane]
                        v_alpha = tr * cg - lat / one_m
                        grads = live & (raw <= a_max)  # through the 0.999 clamp no gradient passes (as gsplat)
                        vs = -alpha * v_alpha if grads else zero
                        vdx = vs * dx
                        gl[lane] += vdx
                        gl[LANES + lane] += vs * dy
                        gl[2 * LANES + lane] += vdx * dx
                        gl[3 * LANES + lane] += vdx * dy
                        gl[4 * LANES + lane] += vs * dy * dy
                        gl[5 * LANES + lane] += vis * v_alpha if grads else zero
                        w = wl if live else zero
                        gl[6 * LANES + lane] += g0 * w
                        gl[7 * LANES + lane] += g1 * w
                        gl[8 * LANES + lane] += g2 * w
                        st[b + np.uint64(_B_W * LANES) + lane] = w
                        st[b + lane] = tr if live else tq
                        st[b + np.uint64(_B_LATER * LANES) + lane] = lat + w * cg
                    for d in range(3, d_out):
                        bd = b + np.uint64((_B_GP + d) * LANES)
                        gd = np.uint64((6 + d) * LANES)
                        for lane in range(_ULANES):
                            gl[gd + lane] += st[bd + lane] * st[b + np.uint64(_B_W * LANES) + lane]
            for j in range(6 + d_pad):  # the lanes summed in a fixed order, in float64
                sums[j] = 0.0
                for lane in range(LANES):
                    sums[j] += np.float64(gl[j * LANES + lane])
            a64, b64, c64 = np.float64(rec[e, _CA]), np.float64(rec[e, _CB]), np.float64(rec[e, _CC])
            grad[k, 0] = a64 * sums[0] + b64 * sums[1]  # d sigma / d mean = conic @ (dx, dy)
            grad[k, 1] = b64 * sums[0] + c64 * sums[1]
            grad[k, 2] = 0.5 * sums[2]
            grad[k, 3] = sums[3]
            grad[k, 4] = 0.5 * sums[4]
            for j in range(5, n_g):
                grad[k, j] = sums[j]


def _tile_done_py(st, nf):  # pragma: no cover - compiled
    """Whether every pixel of a tile's forward state is done (its T negative)."""
    m = st[_F_T * LANES]
    for q in range(LANES):
        for lane in range(LANES):
            m = max(m, st[(q * nf + _F_T) * LANES + lane])
    return m <= 0


def _block_py(r, x):  # pragma: no cover - compiled
    """The block ``[16]`` of a tile's pixel (row r, column x): 4x4 blocks of 4x4 pixels, row-major."""
    return (r >> 2) * 4 + (x >> 2)


def _lane_py(r, x):  # pragma: no cover - compiled
    """The lane ``[16]`` of a tile's pixel (row r, column x) in its block, row-major."""
    return (r & 3) * 4 + (x & 3)


def _block_grid_py(tx0, ty0, pxb, pyb):  # pragma: no cover - compiled
    """Into ``pxb``/``pyb`` ``[4*16]``: the pixel centres x and y per block column / row of the tile at (tx0, ty0), 16
    lanes each, in their dtype, as the scalar kernels' ``xs``/``ys`` (``arange + 0.5``; rows past the image go on)."""
    to_dt = pxb.dtype.type
    for bb in range(4):
        for lane in range(LANES):
            pxb[bb * LANES + lane] = to_dt(tx0 + 4 * bb + (lane & 3)) + to_dt(PIXEL_CENTER)
            pyb[bb * LANES + lane] = to_dt(ty0 + 4 * bb + (lane >> 2)) + to_dt(PIXEL_CENTER)


def _entry_py(rec, e, tx0, ty0, tw, th, col, d_out, xs):  # pragma: no cover - compiled
    """Entry ``e``'s record in the input dtype (``xs``), clipped to the tile at (tx0, ty0) of ``tw`` x ``th``: its
    first and last row and column in the tile, the first and last row's pixel centre, mean, conic, opacity; its
    ``d_out`` colours into ``col``."""
    to_dt = xs.dtype.type
    ra, rb = max(int(rec[e, _Y0]), ty0) - ty0, min(int(rec[e, _Y1]), ty0 + th - 1) - ty0
    y_lo, y_hi = to_dt(ty0 + ra) + to_dt(PIXEL_CENTER), to_dt(ty0 + rb) + to_dt(PIXEL_CENTER)
    xa, xb = max(int(rec[e, _X0]), tx0) - tx0, min(int(rec[e, _X1]), tx0 + tw - 1) - tx0
    for d in range(d_out):
        col[d] = to_dt(rec[e, _COL + d])
    mxe, mye = to_dt(rec[e, _MX]), to_dt(rec[e, _MY])
    ca, cb, cc, ope = to_dt(rec[e, _CA]), to_dt(rec[e, _CB]), to_dt(rec[e, _CC]), to_dt(rec[e, _OP])
    return ra, rb, y_lo, y_hi, xa, xb, mxe, mye, ca, cb, cc, ope


_block: Any = _block_py
_tile_done: Any = _tile_done_py
_lane: Any = _lane_py
_block_grid: Any = _block_grid_py
_entry: Any = _entry_py


def _exp_neg_f32(x):  # pragma: no cover - compiled
    """``exp(-x)`` for float32 ``x`` (Cephes ``expf``), vectorizable: no calls, no branches."""
    v = min(max(-x, np.float32(-87.0)), np.float32(0.0))  # x >= 0 where it counts (sigma); 2^n stays normal
    n = np.floor(v * np.float32(1.44269504088896341) + np.float32(0.5))
    r = v - n * np.float32(0.693359375) + n * np.float32(2.12194440e-4)
    p = np.float32(1.9875691500e-4)
    p = p * r + np.float32(1.3981999507e-3)
    p = p * r + np.float32(8.3334519073e-3)
    p = p * r + np.float32(4.1665795894e-2)
    p = p * r + np.float32(1.6666665459e-1)
    p = p * r + np.float32(5.0000001201e-1)
    p = p * r * r + r + np.float32(1.0)
    return p * _f32_from_bits((np.int32(n) + np.int32(127)) << np.int32(23))


def _f32_from_bits_py(i):  # pragma: no cover - replaced by an intrinsic when compiled
    return np.array([i], np.int32).view(np.float32)[0]


_f32_from_bits: Any = _f32_from_bits_py


# Plain Python until compile_kernels() rebinds them: numba's prange, and the compiled serial kernels the parallel
# drivers below call.
_prange: Any = range
_forward_serial: Any = None
_backward_serial: Any = None


def _forward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_forward_lanes`` over the tile ranges ``bounds [R+1]`` in numba's parallel loop (``run_ranges``'s driver)."""
    for j in _prange(bounds.shape[0] - 1):
        _forward_serial(*args, bounds[j], bounds[j + 1])


def _backward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_backward_lanes`` over the tile ranges ``bounds [R+1]`` in numba's parallel loop."""
    for j in _prange(bounds.shape[0] - 1):
        _backward_serial(*args, bounds[j], bounds[j + 1])


def grad_rows(isect: np.ndarray, rec: np.ndarray) -> np.ndarray:
    """The backward's output, zeroed: a gradient row ``[I, 6+D]`` float64 per intersection (both kernels')."""
    return np.zeros((isect.shape[0], 6 + rec.shape[1] - _COL), np.float64)


def _outputs(rec, bg, xs, width, height) -> tuple[np.ndarray, ...]:
    """The forward's outputs, before any tile: colours [P,D] 0, T [P] 1, list positions [P] 0, alpha [P] 0."""
    n_pix = bg.shape[0] * width * height
    return (np.zeros((n_pix, rec.shape[1] - _COL), bg.dtype), np.ones(n_pix, np.float64),
            np.zeros(n_pix, np.int32), np.zeros(n_pix, xs.dtype))  # fmt: skip


@lru_cache(maxsize=1)
def compile_kernels(numba: Any) -> tuple[Any, Any]:
    """The forward and backward: serial lane kernels (``njit_serial``, cached on disk) over ranges of tiles, run
    by ``run_ranges`` on torch's thread count, with the arguments and results of ``numba_cpu``'s scalar kernels;
    registers the float32 ``exp`` once."""
    global _tile_done, _f32_from_bits, _prange, _forward_serial, _backward_serial, _block, _lane, _block_grid, _entry
    from numba.core import types
    from numba.extending import overload

    _f32_from_bits = float_from_bits()[0]
    exp_f32 = numba.njit(inline="always")(_exp_neg_f32)
    _entry = numba.njit(inline="always")(_entry_py)  # per entry, beside the lane loops: no call

    @overload(_exp_neg, inline="always")
    def _exp_neg_overload(x):
        if x == types.float32:
            return lambda x: exp_f32(x)
        return lambda x: math.exp(-x)

    vector_width = lane_vector_width()
    cache = _width_override() is None  # an override compiles afresh (see lane_vector_width)
    at_width = partial(_compiling_at, vector_width)  # what every compilation of these runs inside
    helper = njit_serial(numba, cache=cache, compile_context=at_width)
    _block, _lane, _block_grid = helper(_block_py), helper(_lane_py), helper(_block_grid_py)
    _tile_done = helper(_tile_done_py)
    fwd, bwd = helper(_forward_lanes), helper(_backward_lanes)
    _prange, _forward_serial, _backward_serial = numba.prange, fwd, bwd
    par = njit_driver(numba, cache=cache, compile_context=at_width)
    fwd_par, bwd_par = par(_forward_ranges), par(_backward_ranges)
    # The first call of each kind compiles (or loads from the disk cache) at the lane width; the key is what makes
    # numba specialize: the float type, and serial or parallel (run_ranges). A specialization outside these
    # compiles at LLVM's own width: the same results, maybe slower.
    seen: set[tuple[Any, ...]] = set()

    def _run(kernel, driver, n, key, *args):
        run_ranges_compiling_in(at_width, seen, key, kernel, driver, n, *args)

    def forward(tile_ptr, isect, rec, order, bg, xs, ys, consts, width, height, tile, tiles_x, tiles_y):
        out = _outputs(rec, bg, xs, width, height)
        args = (tile_ptr, isect, rec, order, bg, xs, ys, consts, width, height, tile, tiles_x, tiles_y)
        _run(fwd, fwd_par, order.shape[0], ("fwd", rec.dtype, xs.dtype), *args, *out)
        return out

    def backward(*args):
        grad = grad_rows(args[1], args[2])
        _run(bwd, bwd_par, args[3].shape[0], ("bwd", args[2].dtype, args[5].dtype), *args, grad)
        return grad

    return forward, backward


def vector_report(args: tuple[Any, ...], backward: bool = False, width: int | None = None) -> dict[str, int]:
    """How wide LLVM made the lane loops on this host: an uncached copy of the forward (or backward) kernel is
    compiled for ``args`` (as the forward and backward of :func:`compile_kernels` take them) and run once over
    every tile, and its generated code (``inspect_asm``) searched for packed floating-point arithmetic, counted by
    register: on x86-64 (``v...ps``/``v...pd``) ``zmm`` 512-bit, ``ymm`` 256-bit, ``xmm`` 128-bit (scalar
    ``ss``/``sd`` code uses ``xmm`` too, but is not counted); on arm64 ``neon`` (``f...`` on ``v0.4s``/``v0.2d``:
    128-bit) and ``sve`` (on ``z0.s``/``z0.d``). ``width``: LLVM's vector width to compile at (1: no vector code;
    default :func:`lane_vector_width`). Imports numba; takes seconds."""
    import re

    import numba

    compile_kernels(numba)
    fn = numba.njit(cache=False, nogil=True, error_model="numpy")(_backward_lanes if backward else _forward_lanes)
    if backward:
        outs: tuple[np.ndarray, ...] = (grad_rows(args[1], args[2]),)
    else:
        outs = _outputs(args[2], args[4], args[5], args[8], args[9])
    with _compiling_at(lane_vector_width() if width is None else width):
        fn(*args, *outs, 0, args[3].shape[0])
    asm = "\n".join(fn.inspect_asm().values())
    packed = re.findall(
        r"^\s*v(?:add|sub|mul|div|min|max|cmp[a-z]*|rndscale|round|blendm|fmadd[0-9]*)p[sd]\s+([^\n]*)", asm, re.M
    )
    report = {reg: sum(f"%{reg}" in ops for ops in packed) for reg in ("zmm", "ymm", "xmm")}
    arm = re.findall(r"^\s*(?:f[a-z]+|[su]cvtf)\s+(?:(v)\d+\.(?:4s|2d)|(z)\d+\.[sd])", asm, re.M)
    report.update(neon=sum(v == "v" for v, _ in arm), sve=sum(z == "z" for _, z in arm))
    return report
