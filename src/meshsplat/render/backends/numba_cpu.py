"""Compiled CPU rasterizer (numba), forward and backward, with the torch backend's conventions.

Projection is compiled too (``numba_projection``, float64 inside; torch's autograd projection is
used instead when ``viewmats`` or ``Ks`` require grad). Entries are ordered by camera, then camera
``z``, ties by Gaussian index (one stable ``argsort``), and gathered inside the compositing
``autograd.Function``, whose backward scatters straight into the projection's outputs: no
``index_select`` nodes or pair tensors.

1. Binning: each entry's footprint box (the same closed-form ``alpha >= 1/255`` ellipse and
   0.05 px slack as the torch backend's row spans, float64) is cut into 16x16 tiles; tile lists
   are filled in entry order, so each tile's list is depth-ordered exactly as the torch backend.
   Each entry's values (projection outputs, footprint box, colours) go into one record in the input dtype
   (exact: the box is whole pixels; the scalar kernels' row-span terms are recomputed from it), and records
   are laid out by the first tile they touch: a tile's walk reads neighbouring records instead of
   six arrays at random (memory latency, not arithmetic, is much of what the walks wait on).
2. Forward, parallel over tiles (ranges of tiles on threads): every pixel walks its tile's list front to back
   (alpha evaluated in the input dtype with the torch backend's operation order and thresholds;
   transmittance in float64), stops before the splat that would take T to ``<= 1e-4``, and keeps
   its final T (float64) and the list position after its last contributing splat. An entry's row
   spans are computed in one pass before its pixels.
3. Backward, parallel over tiles: the standard reverse walk from that position (T recovered by
   division in float64, "later splats" sums carried along). Each (tile, entry) intersection owns
   a gradient row that only its tile writes; rows are summed into ``means2d``/``conics [C,N]``,
   opacities and colours in intersection order afterwards (serial). No atomics, no per-thread buffers:
   the result is bit-identical for any thread count and scheduling.

Steps 2 and 3 run by default with the 16 pixels of a 4x4 block in SIMD lanes (``numba_lanes``: the same
lists, thresholds and stop, transmittance in the input dtype, ``exp`` inlined as a polynomial for float32);
the scalar kernels here are the reference and the fallback, forced with ``MESHSPLAT_RASTER_KERNEL=scalar``.

The kernels are serial (numba's ``parallel=True`` took several times longer to compile); the projection and the
compositing kernels take a range of their items, and ``_numba.run_ranges`` runs contiguous ranges on a pool of
``torch.get_num_threads()`` Python threads (numba releases the GIL), so one setting drives both libraries. Tiles
are ordered as combs (every n-th tile to each of n threads), so each range holds tiles from the whole image: an
avatar's work is not spread evenly over the image's rows.

numba is imported lazily (first call); kernels are compiled with ``cache=True`` (on-disk cache next
to this file, or numba's user cache directory when that is read-only).
"""

from __future__ import annotations

import math
import os
from functools import lru_cache
from typing import Any, NamedTuple

import numpy as np
import torch

from meshsplat._numba import njit_driver, njit_serial, run_ranges
from meshsplat.errors import MeshsplatError
from meshsplat.render._constants import (
    ALPHA_MAX,
    ALPHA_THRESHOLD,
    MAX_EXTEND,
    PIXEL_CENTER,
    SPAN_MARGIN,
    TRANSMITTANCE_MIN,
)
from meshsplat.render.backends import numba_available, numba_lanes, numba_projection
from meshsplat.render.backends.numba_lanes import _CA, _CB, _CC, _COL, _MX, _MY, _OP, _X0, _X1, _Y0, _Y1
from meshsplat.render.backends.numba_projection import project_numba
from meshsplat.render.backends.torch_ref import render_output
from meshsplat.render.projection import Projection, project_gaussians
from meshsplat.render.types import RenderOutput

__all__ = ["rasterize_numba", "TILE_SIZE", "warm_up", "compositing_kernel", "KERNEL_ENV", "KERNELS"]

TILE_SIZE = numba_lanes.LANES  # a tile is 4x4 blocks of the lane kernels' 16 SIMD lanes
KERNEL_ENV = "MESHSPLAT_RASTER_KERNEL"  # "scalar": the scalar compositing kernels; "lanes" or unset: SIMD lanes
KERNELS = ("lanes", "scalar")
# The kernels below are plain Python until _kernels() wraps them with numba.njit; _spans and _tau_det are then
# rebound to the jitted helpers, which the kernels resolve when compiled.


def _tau_det_py(a, b, c, op):  # pragma: no cover - compiled
    """An entry's footprint terms (float64, the torch backend's): ``tau``, the ``sigma`` at which alpha falls to
    1/255 (clamped to [0, MAX_EXTEND² / 2]), and the conic's determinant ``a c - b²`` (at least 1e-300)."""
    tau = min(max(math.log(op / ALPHA_THRESHOLD), 0.0), 0.5 * MAX_EXTEND * MAX_EXTEND)
    return tau, max(a * c - b * b, 1e-300)


_tau_det: Any = _tau_det_py


def _bin_kernel(
    m2, con, op, col, flat, vis, shared_colors, n_gauss, n_cams, width, height, tile, tiles_x, tiles_y
):  # pragma: no cover - compiled
    """Entry records and tile lists, from the projection's ``means2d [C*N,2]``, ``conics [C*N,3]``, ``visible
    [C*N]``, ``opacities [N]`` and colours (``[N, D]`` when ``shared_colors``, else ``[C*N, D]``; input dtype), for
    the visible entries ``flat [M]`` (camera * N + Gaussian) in compositing order.

    Records are stored in the order of the first tile each entry touches, so that a tile's entries lie close
    together in memory (random reads are what a tile's walk waits on); ``isect`` holds these record ids.
    Returns ``rec [M, 10+D]`` in the input dtype (mx, my, a, b, c, opacity: the input values exactly; first and
    last pixel row, last < first: empty; first and last pixel column; colours), ``slot [C*N]`` (camera * N +
    Gaussian -> record id; visible ones only), ``tile_ptr [T+1]`` and ``isect [I]`` int32 record ids, in depth
    order within each tile.

    Serial passes, none of them arithmetic behind a random read, and random writes instead of random reads (a
    store does not stall the loop as a load does): each entry's position in depth order, then footprints in
    Gaussian order, their tile boxes written to that position, then first tiles and tile counts in depth order,
    then each entry's record id, then the records filled in Gaussian order (sequential reads), then the tile lists.
    """
    m = flat.shape[0]
    d_out = col.shape[1]
    per_cam = tiles_x * tiles_y
    slot = np.empty(vis.shape[0], np.int64)  # camera * N + Gaussian -> entry (visible ones), later -> record id
    for e in range(m):
        slot[flat[e]] = e
    foot = np.empty((vis.shape[0], 4), m2.dtype)  # first and last pixel row and column (whole numbers: exact)
    rect = np.empty((m, 4), np.int32)  # per entry: first and last tile column, row (last < first: none)
    for f in range(vis.shape[0]):  # Gaussian order: sequential reads, the boxes written in depth order
        if not vis[f]:
            continue
        mx, my = np.float64(m2[f, 0]), np.float64(m2[f, 1])
        a, b, c = np.float64(con[f, 0]), np.float64(con[f, 1]), np.float64(con[f, 2])
        tau, det = _tau_det(a, b, c, np.float64(op[f % n_gauss]))
        ry = math.sqrt(2.0 * tau * a / det)
        rx = math.sqrt(2.0 * tau * c / det)
        y0 = max(np.ceil(my - ry - PIXEL_CENTER - SPAN_MARGIN), 0.0)
        y1 = min(np.floor(my + ry - PIXEL_CENTER + SPAN_MARGIN), height - 1.0)
        x0 = max(np.ceil(mx - rx - PIXEL_CENTER - SPAN_MARGIN), 0.0)
        x1 = min(np.floor(mx + rx - PIXEL_CENTER + SPAN_MARGIN), width - 1.0)
        if not (y0 <= y1 and x0 <= x1):  # also false for NaN
            foot[f, 0], foot[f, 1], foot[f, 2], foot[f, 3] = 0.0, -1.0, 0.0, -1.0
            e = slot[f]
            rect[e, 0], rect[e, 1], rect[e, 2], rect[e, 3] = 0, -1, 0, -1
        else:
            foot[f, 0], foot[f, 1], foot[f, 2], foot[f, 3] = y0, y1, x0, x1
            e = slot[f]
            rect[e, 0], rect[e, 1] = int(x0) // tile, int(x1) // tile
            rect[e, 2], rect[e, 3] = int(y0) // tile, int(y1) // tile
    first = np.zeros(n_cams * per_cam + 1, np.int64)  # entries per first tile, then counting-sort offsets
    counts = np.zeros(n_cams * per_cam + 1, np.int64)  # intersections per tile, then tile_ptr
    for e in range(m):
        base = (flat[e] // n_gauss) * per_cam
        if rect[e, 1] < rect[e, 0]:
            first[1] += 1
            continue
        first[base + rect[e, 2] * tiles_x + rect[e, 0] + 1] += 1
        for ty in range(rect[e, 2], rect[e, 3] + 1):
            for tx in range(rect[e, 0], rect[e, 1] + 1):
                counts[base + ty * tiles_x + tx + 1] += 1
    for t in range(1, first.shape[0]):  # offsets (a loop: np.cumsum costs a second of compiling)
        first[t] += first[t - 1]
        counts[t] += counts[t - 1]
    rid = np.empty(m, np.int64)  # entry -> record id (stable counting sort by first tile)
    for e in range(m):
        f = flat[e]
        key = (f // n_gauss) * per_cam + rect[e, 2] * tiles_x + rect[e, 0] if rect[e, 1] >= rect[e, 0] else 0
        r = first[key]
        first[key] += 1
        rid[e], slot[f] = r, r
    rec = np.empty((m, _COL + d_out), m2.dtype)
    for f in range(vis.shape[0]):  # Gaussian order: sequential reads, random writes
        if not vis[f]:
            continue
        r = slot[f]
        g = f % n_gauss
        rec[r, _MX], rec[r, _MY] = m2[f, 0], m2[f, 1]
        rec[r, _CA], rec[r, _CB], rec[r, _CC], rec[r, _OP] = con[f, 0], con[f, 1], con[f, 2], op[g]
        rec[r, _Y0], rec[r, _Y1], rec[r, _X0], rec[r, _X1] = foot[f, 0], foot[f, 1], foot[f, 2], foot[f, 3]
        cr = g if shared_colors else f
        for d in range(d_out):
            rec[r, _COL + d] = col[cr, d]
    tile_ptr = counts
    cursor = np.empty(tile_ptr.shape[0] - 1, np.int64)
    for t in range(cursor.shape[0]):
        cursor[t] = tile_ptr[t]
    isect = np.empty(tile_ptr[tile_ptr.shape[0] - 1], np.int32)
    for e in range(m):  # entry order = depth order within each camera, hence within each tile
        base = (flat[e] // n_gauss) * per_cam
        for ty in range(rect[e, 2], rect[e, 3] + 1):
            for tx in range(rect[e, 0], rect[e, 1] + 1):
                t = base + ty * tiles_x + tx
                isect[cursor[t]] = rid[e]
                cursor[t] += 1
    return rec, slot, tile_ptr, isect


def _depth_order_kernel(keys, visible, nbits):  # pragma: no cover - compiled
    """The visible entries ``[M]`` (camera * N + Gaussian) in compositing order: camera, then ``keys [C,N]``
    (uint64, ordered as the depths), ties by Gaussian index. A stable LSD radix sort, 8 bits a pass over the
    low ``nbits`` bits, skipping passes where every key has the same digit (the exponent's high bits). Plain
    index loops over two ping-pong rows (no slices: they made this kernel the slowest to compile)."""
    n_cams, n = keys.shape[0], keys.shape[1]
    m = 0
    for c in range(n_cams):
        for i in range(n):
            m += visible[c, i]
    idx = np.empty((2, m), np.int64)
    kb = np.empty((2, m), np.uint64)
    hist = np.empty(257, np.int64)
    pos = 0
    for c in range(n_cams):
        cnt = 0
        for i in range(n):
            if visible[c, i]:
                idx[0, pos + cnt] = c * n + i
                kb[0, pos + cnt] = keys[c, i]
                cnt += 1
        cur = 0
        for shift in range(0, nbits, 8):
            sh = np.uint64(shift)
            for d in range(257):
                hist[d] = 0
            for j in range(cnt):
                hist[np.int64((kb[cur, pos + j] >> sh) & np.uint64(255)) + 1] += 1
            top = 0
            for d in range(1, 257):
                top = max(top, hist[d])
            if top == cnt:  # one digit for all: the pass would not move anything
                continue
            for d in range(256):
                hist[d + 1] += hist[d]
            nxt = 1 - cur
            for j in range(cnt):
                key = kb[cur, pos + j]
                d = np.int64((key >> sh) & np.uint64(255))
                o = pos + hist[d]
                idx[nxt, o] = idx[cur, pos + j]
                kb[nxt, o] = key
                hist[d] += 1
            cur = nxt
        if cur == 1:
            for j in range(cnt):
                idx[0, pos + j] = idx[1, pos + j]
        pos += cnt
    return idx[0].copy()


def _depth_keys(depths: np.ndarray) -> np.ndarray:
    """uint64 keys ``[C,N]`` whose unsigned order is the float order of ``depths`` (float32 or float64; -0 as +0)."""
    d = depths + depths.dtype.type(0.0)  # -0.0 -> +0.0: torch's sort treats them as equal
    if d.dtype == np.float32:
        b32 = d.view(np.int32)
        k32 = (b32 ^ ((b32 >> 31) & np.int32(0x7FFFFFFF))).view(np.uint32) ^ np.uint32(0x80000000)
        return k32.astype(np.uint64)
    b64 = d.view(np.int64)
    return (b64 ^ ((b64 >> 63) & np.int64(0x7FFFFFFFFFFFFFFF))).view(np.uint64) ^ np.uint64(1 << 63)


def _spans_py(rec, e, ya, yb, lo, hi, span):  # pragma: no cover - compiled
    """Columns ``span[y - ya] = (x0, x1)`` of rows ya..yb inside entry e's ``alpha >= 1/255`` ellipse, clipped
    to [lo, hi] (the torch backend's ``_row_spans`` arithmetic, float64; x1 < x0: empty). One pass over the
    rows before the pixels: the rows' square roots and divisions overlap instead of waiting on each other."""
    mx, my, a, b = np.float64(rec[e, _MX]), np.float64(rec[e, _MY]), np.float64(rec[e, _CA]), np.float64(rec[e, _CB])
    tau, det = _tau_det(a, b, np.float64(rec[e, _CC]), np.float64(rec[e, _OP]))
    two_a_tau = 2.0 * a * tau
    for y in range(ya, yb + 1):
        dy = my - (y + PIXEL_CENTER)
        disc = math.sqrt(max(two_a_tau - det * dy * dy, 0.0))
        dx_lo = (-b * dy - disc) / a
        dx_hi = (-b * dy + disc) / a
        x0 = np.ceil(mx - dx_hi - PIXEL_CENTER - SPAN_MARGIN)
        x1 = np.floor(mx - dx_lo - PIXEL_CENTER + SPAN_MARGIN)
        if not (x0 <= x1):  # also NaN
            span[y - ya, 0], span[y - ya, 1] = lo, lo - 1
        else:
            span[y - ya, 0] = int(min(max(x0, lo), hi + 1.0))
            span[y - ya, 1] = int(max(min(x1, hi), lo - 1.0))


_spans: Any = _spans_py


def _forward_kernel(
    tile_ptr, isect, rec, order, bg, xs, ys, consts, width, height, tile, tiles_x, tiles_y, out, t_final, n_contrib,
    lo, hi,
):  # pragma: no cover - compiled  # fmt: skip
    """Composite the pixels of the tiles ``order[lo:hi]`` into colors ``out`` [P,D] (dtype, zeroed), final T
    ``t_final`` [P] float64 (ones), list position after the last splat ``n_contrib`` [P] (zeros).

    Per tile (in ``order``), entries are walked front to back and each one visits only the pixels of its
    exact footprint rows; per-pixel state (T, colour sums, done) lives in tile buffers.
    """
    half, a_max, a_thr = consts[0], consts[1], consts[2]
    to_dt = xs.dtype.type  # the record keeps input-dtype values exactly; alpha is evaluated in that dtype
    d_out = rec.shape[1] - _COL
    n_pix_cam = width * height
    per_cam = tiles_x * tiles_y
    for i in range(lo, hi):
        t = order[i]
        c = t // per_cam
        tx0 = (t % tiles_x) * tile
        ty0 = ((t % per_cam) // tiles_x) * tile
        tw = min(width, tx0 + tile) - tx0
        th = min(height, ty0 + tile) - ty0
        trans = np.ones(tw * th, np.float64)
        acc = np.zeros((d_out, tw * th), np.float64)
        done = np.zeros(tw * th, np.bool_)
        last = np.zeros(tw * th, np.int32)
        span = np.empty((tile, 2), np.int64)
        col = np.empty(d_out, np.float64)
        n_done = 0
        s0 = tile_ptr[t]
        for k in range(s0, tile_ptr[t + 1]):
            if n_done == tw * th:
                break
            e = isect[k]
            ya, yb = max(int(rec[e, _Y0]), ty0), min(int(rec[e, _Y1]), ty0 + th - 1)
            _spans(rec, e, ya, yb, tx0, tx0 + tw - 1, span)
            mxe, mye = to_dt(rec[e, _MX]), to_dt(rec[e, _MY])
            ca, cb, cc, ope = to_dt(rec[e, _CA]), to_dt(rec[e, _CB]), to_dt(rec[e, _CC]), to_dt(rec[e, _OP])
            for d in range(d_out):
                col[d] = rec[e, _COL + d]
            step = np.int32(k - s0 + 1)
            for y in range(ya, yb + 1):
                dy = mye - ys[y]
                cdy = cc * dy * dy
                row = (y - ty0) * tw - tx0
                for x in range(span[y - ya, 0], span[y - ya, 1] + 1):
                    q = row + x
                    if done[q]:
                        continue
                    dx = mxe - xs[x]
                    sigma = half * (ca * dx * dx + cdy) + cb * dx * dy
                    if sigma < 0:
                        continue
                    alpha = min(ope * math.exp(-sigma), a_max)
                    if alpha < a_thr:
                        continue
                    a64 = np.float64(alpha)
                    tq = trans[q]
                    t_next = tq * (1.0 - a64)
                    if t_next <= TRANSMITTANCE_MIN:
                        done[q] = True
                        n_done += 1
                        continue
                    w = a64 * tq
                    for d in range(d_out):
                        acc[d, q] += w * col[d]
                    trans[q] = t_next
                    last[q] = step
        for q in range(tw * th):
            p = c * n_pix_cam + (ty0 + q // tw) * width + tx0 + q % tw
            for d in range(d_out):
                out[p, d] = acc[d, q] + trans[q] * bg[c, d]
            t_final[p] = trans[q]
            n_contrib[p] = last[q]


def _backward_kernel(
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
    """Per-intersection gradient rows ``grad`` [I, 6+D] float64 (zeroed): (mx, my, a, b, c, opacity, colors...),
    for the tiles ``order[lo:hi]``.

    Per tile, entries are walked back to front over the same footprint pixels; each pixel carries
    T (recovered by division, float64) and the sum of later splats' ``w_j <g, c_j>``.
    """
    half, a_max, a_thr = consts[0], consts[1], consts[2]
    to_dt = xs.dtype.type
    d_out = rec.shape[1] - _COL
    n_pix_cam = width * height
    per_cam = tiles_x * tiles_y
    for i in range(lo, hi):
        t = order[i]
        c = t // per_cam
        tx0 = (t % tiles_x) * tile
        ty0 = ((t % per_cam) // tiles_x) * tile
        tw = min(width, tx0 + tile) - tx0
        th = min(height, ty0 + tile) - ty0
        trans = np.empty(tw * th, np.float64)
        later = np.empty(tw * th, np.float64)  # extra terms + sum over later splats of w_j <g, c_j>
        gp = np.empty((d_out, tw * th), np.float64)
        last = np.empty(tw * th, np.int32)
        span = np.empty((tile, 2), np.int64)
        col = np.empty(d_out, np.float64)
        g_c = np.empty(d_out, np.float64)
        max_last = 0
        for q in range(tw * th):
            p = c * n_pix_cam + (ty0 + q // tw) * width + tx0 + q % tw
            tf = t_final[p]
            trans[q] = tf
            ex = -np.float64(g_alpha[p]) * tf
            for d in range(d_out):
                gp[d, q] = g_col[p, d]
                ex += tf * np.float64(bg[c, d]) * gp[d, q]
            later[q] = ex
            last[q] = n_contrib[p]
            max_last = max(max_last, n_contrib[p])
        s0 = tile_ptr[t]
        for k in range(s0 + max_last - 1, s0 - 1, -1):
            e = isect[k]
            ya, yb = max(int(rec[e, _Y0]), ty0), min(int(rec[e, _Y1]), ty0 + th - 1)
            _spans(rec, e, ya, yb, tx0, tx0 + tw - 1, span)
            mxe, mye = to_dt(rec[e, _MX]), to_dt(rec[e, _MY])
            ca, cb, cc, ope = to_dt(rec[e, _CA]), to_dt(rec[e, _CB]), to_dt(rec[e, _CC]), to_dt(rec[e, _OP])
            ca64, cb64, cc64 = np.float64(rec[e, _CA]), np.float64(rec[e, _CB]), np.float64(rec[e, _CC])
            for d in range(d_out):
                col[d] = rec[e, _COL + d]
                g_c[d] = 0.0
            g0 = g1 = g2 = g3 = g4 = g5 = 0.0
            kk = k - s0
            for y in range(ya, yb + 1):
                dy = mye - ys[y]
                cdy = cc * dy * dy
                fdy = np.float64(dy)
                row = (y - ty0) * tw - tx0
                for x in range(span[y - ya, 0], span[y - ya, 1] + 1):
                    q = row + x
                    if kk >= last[q]:
                        continue
                    dx = mxe - xs[x]
                    sigma = half * (ca * dx * dx + cdy) + cb * dx * dy
                    if sigma < 0:
                        continue
                    vis = math.exp(-sigma)
                    raw = ope * vis
                    alpha = min(raw, a_max)
                    if alpha < a_thr:
                        continue
                    a64 = np.float64(alpha)
                    one_m = 1.0 - a64
                    tr = trans[q] / one_m  # T before this splat
                    trans[q] = tr
                    w = a64 * tr
                    cg = 0.0
                    for d in range(d_out):
                        cg += gp[d, q] * col[d]
                        g_c[d] += gp[d, q] * w
                    if raw <= a_max:  # through the 0.999 clamp no gradient passes (as gsplat)
                        v_alpha = tr * cg - later[q] / one_m
                        v_sigma = -a64 * v_alpha
                        fdx = np.float64(dx)
                        g0 += v_sigma * (ca64 * fdx + cb64 * fdy)
                        g1 += v_sigma * (cb64 * fdx + cc64 * fdy)
                        g2 += 0.5 * v_sigma * fdx * fdx
                        g3 += v_sigma * fdx * fdy
                        g4 += 0.5 * v_sigma * fdy * fdy
                        g5 += np.float64(vis) * v_alpha
                    later[q] += w * cg
            grad[k, 0], grad[k, 1], grad[k, 2], grad[k, 3], grad[k, 4], grad[k, 5] = g0, g1, g2, g3, g4, g5
            for d in range(d_out):
                grad[k, 6 + d] = g_c[d]


def _scatter_kernel(isect, grad, slot, vis, m, shared_colors, n_gauss, n_cams, like):  # pragma: no cover - compiled
    """Sum intersection rows into the gradients of the projection's outputs, in intersection order (serial:
    deterministic): each record's rows first (one pass over the rows; a record's tiles are neighbours, so these
    sums stay in cache), then, in camera * N + Gaussian order (sequential writes), the record ``slot[f]`` of each
    visible ``f`` (``vis [C*N]``; ``m`` records). Returns means2d and conics [C*N, 2|3] in the dtype of ``like``
    (one record per row: rounded once, as before), opacities [N] and colours ([N, D] when ``shared_colors``, else
    [C*N, D]) float64 (summed over cameras in camera order, which is record order)."""
    n_g = grad.shape[1]
    d_out = n_g - 6
    acc = np.zeros((m, n_g), np.float64)
    for k in range(isect.shape[0]):
        r = isect[k]
        for j in range(n_g):
            acc[r, j] += grad[k, j]
    g_m2 = np.zeros((n_cams * n_gauss, 2), like.dtype)
    g_con = np.zeros((n_cams * n_gauss, 3), like.dtype)
    g_op = np.zeros(n_gauss, np.float64)
    g_col = np.zeros((n_gauss if shared_colors else n_cams * n_gauss, d_out), np.float64)
    for f in range(vis.shape[0]):
        if not vis[f]:
            continue
        r = slot[f]
        g_m2[f, 0], g_m2[f, 1] = acc[r, 0], acc[r, 1]
        g_con[f, 0], g_con[f, 1], g_con[f, 2] = acc[r, 2], acc[r, 3], acc[r, 4]
        g_op[f % n_gauss] += acc[r, 5]
        cr = f % n_gauss if shared_colors else f
        for d in range(d_out):
            g_col[cr, d] += acc[r, 6 + d]
    return g_m2, g_con, g_op, g_col


def _background_grad_kernel(t_final, g_out, n_cams):  # pragma: no cover - compiled
    """dL/dbackground ``[C, D]`` float64: per camera, its pixels' final T ``[P]`` (float64) times dL/dcolour ``[P, D]``,
    summed in pixel order (serial: deterministic)."""
    n_pix_cam = t_final.shape[0] // n_cams
    out = np.zeros((n_cams, g_out.shape[1]), np.float64)
    for c in range(n_cams):
        for p in range(c * n_pix_cam, (c + 1) * n_pix_cam):
            for d in range(g_out.shape[1]):
                out[c, d] += t_final[p] * np.float64(g_out[p, d])
    return out


# Plain Python until _kernels() rebinds them: numba's prange and the serial kernels the parallel drivers call.
_prange: Any = range
_forward_serial: Any = None
_backward_serial: Any = None


def _forward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_forward_kernel`` over the tile ranges ``bounds [R+1]`` in numba's parallel loop (``run_ranges``'s driver)."""
    for j in _prange(bounds.shape[0] - 1):
        _forward_serial(*args, bounds[j], bounds[j + 1])


def _backward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_backward_kernel`` over the tile ranges ``bounds [R+1]`` in numba's parallel loop."""
    for j in _prange(bounds.shape[0] - 1):
        _backward_serial(*args, bounds[j], bounds[j + 1])


class _Kernels(NamedTuple):
    bin: Any
    forward: Any
    backward: Any
    scatter: Any
    project: Any
    project_backward: Any
    forward_lanes: Any
    backward_lanes: Any
    depth_order: Any
    background_grad: Any


@lru_cache(maxsize=1)
def _kernels() -> _Kernels:
    """Import numba and wrap the kernels (compilation itself happens per dtype on first call). Serial kernels
    (``njit_serial``); the projection and the compositing ones take ranges, run by ``run_ranges`` on torch's
    thread count, and their wrappers here take and return what the kernels did before they took ranges."""
    global _spans, _tau_det, _prange, _forward_serial, _backward_serial
    try:
        import numba
    except Exception as exc:  # ImportError, or a broken llvmlite/numpy combination
        raise MeshsplatError(f"numba could not be imported ({exc}); use backend='torch'") from exc
    ser = njit_serial(numba)
    _tau_det = ser(_tau_det_py)
    _spans = ser(_spans_py)
    proj, proj_bwd = numba_projection.compile_kernels(numba)
    fwd_lanes, bwd_lanes = numba_lanes.compile_kernels(numba)
    fwd_k, bwd_k = ser(_forward_kernel), ser(_backward_kernel)
    _prange, _forward_serial, _backward_serial = numba.prange, fwd_k, bwd_k
    par = njit_driver(numba)
    fwd_par, bwd_par = par(_forward_ranges), par(_backward_ranges)

    def forward(tile_ptr, isect, rec, order, bg, xs, ys, consts, width, height, tile, tiles_x, tiles_y):
        n_pix = bg.shape[0] * width * height
        out = (np.zeros((n_pix, rec.shape[1] - _COL), bg.dtype), np.ones(n_pix), np.zeros(n_pix, np.int32))
        args = (tile_ptr, isect, rec, order, bg, xs, ys, consts, width, height, tile, tiles_x, tiles_y)
        run_ranges(fwd_k, fwd_par, order.shape[0], *args, *out)
        return out

    def backward(*args):
        grad = numba_lanes.grad_rows(args[1], args[2])
        run_ranges(bwd_k, bwd_par, args[3].shape[0], *args, grad)
        return grad

    return _Kernels(
        ser(_bin_kernel), forward, backward, ser(_scatter_kernel), proj, proj_bwd, fwd_lanes, bwd_lanes,
        ser(_depth_order_kernel), ser(_background_grad_kernel),
    )  # fmt: skip


def compositing_kernel() -> str:
    """Which compositing kernels a render uses now: ``"lanes"`` (the default: pixels in SIMD lanes) or ``"scalar"``
    (``MESHSPLAT_RASTER_KERNEL=scalar``, the reference). Read at every render."""
    value = os.environ.get(KERNEL_ENV, "").strip().lower() or "lanes"
    if value not in KERNELS:
        raise MeshsplatError(f"{KERNEL_ENV}={value!r} is not one of {', '.join(KERNELS)} (or unset)")
    return value


def _tile_order(n_tiles: int) -> np.ndarray:
    """Tiles in the order the kernels' ranges take them: every n-th tile, for each of torch's n threads in turn,
    so that each contiguous range (``run_ranges``) holds tiles spread over the whole image instead of one band of
    it (an avatar's busy rows are not evenly spread)."""
    n = max(1, torch.get_num_threads())
    return np.argsort(np.arange(n_tiles) % n, kind="stable")


class _Geometry:
    """No-grad per-call state shared by forward and backward: the visible entries in compositing order
    (camera, then depth, ties by Gaussian index), their records and tile lists (numpy arrays)."""

    def __init__(self, proj: Projection, n_gauss: int, shared_colors: bool, width: int, height: int, tile: int) -> None:
        dt = proj.means2d.dtype
        np_dt: type[np.floating[Any]] = np.float32 if dt == torch.float32 else np.float64
        n_cams = proj.visible.shape[0]
        self.width, self.height, self.n_cams, self.tile, self.n_gauss = width, height, n_cams, tile, n_gauss
        self.tiles_x = -(-width // tile)
        self.tiles_y = -(-height // tile)
        depths = proj.depths.detach().contiguous().numpy()
        visible = proj.visible.contiguous().numpy()
        # [M] entry -> camera * N + Gaussian: a radix sort of the depths' bits (torch's stable argsort's order)
        self.flat = _kernels().depth_order(_depth_keys(depths), visible, 8 * depths.itemsize)
        self.shared_colors = shared_colors
        self.visible = visible.reshape(-1)
        self.m2 = proj.means2d.detach().reshape(-1, 2).contiguous().numpy()
        self.con = proj.conics.detach().reshape(-1, 3).contiguous().numpy()
        # pixel centres in the input dtype, as torch_ref's ``arange(W, dtype) + 0.5``
        self.xs = torch.arange(width, dtype=dt).add_(PIXEL_CENTER).numpy()
        self.ys = torch.arange(height, dtype=dt).add_(PIXEL_CENTER).numpy()
        self.consts = np.array([0.5, ALPHA_MAX, ALPHA_THRESHOLD], dtype=np_dt)
        self.t_final: np.ndarray | None = None
        self.n_contrib: np.ndarray | None = None
        self.kernel = compositing_kernel()  # forward and backward use the same kind

    def bin(self, opacities: torch.Tensor, colors: torch.Tensor) -> None:
        """Entry records (footprints, the projection's values, colours ``[N,D]`` or ``[C,N,D]``) and tile lists."""
        op = opacities.detach().contiguous().numpy()
        col = colors.detach().reshape(-1, colors.shape[-1]).contiguous().numpy()
        self.rec, self.slot, self.tile_ptr, self.isect = _kernels().bin(
            self.m2, self.con, op, col, self.flat, self.visible, self.shared_colors, self.n_gauss, self.n_cams,
            self.width, self.height, self.tile, self.tiles_x, self.tiles_y,
        )  # fmt: skip

    def args(self, bg: np.ndarray) -> tuple[Any, ...]:
        order = _tile_order(self.n_cams * self.tiles_x * self.tiles_y)
        return (self.tile_ptr, self.isect, self.rec, order, bg, self.xs, self.ys, self.consts, self.width,
                self.height, self.tile, self.tiles_x, self.tiles_y)  # fmt: skip


def _bg_array(bg: torch.Tensor | None, n_cams: int, d: int, dtype: torch.dtype) -> np.ndarray:
    if bg is None:
        return np.zeros((n_cams, d), np.float32 if dtype == torch.float32 else np.float64)
    return bg.detach().contiguous().numpy()


class _Composite(torch.autograd.Function):
    """(means2d [C,N,2], conics [C,N,3], opacities [N], colors [N,D] or [C,N,D], bg [C,D]) -> image, alpha.

    Gathers the visible entries itself and scatters their gradients straight back to these inputs."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, bg, geo):
        C, H, W, D = geo.n_cams, geo.height, geo.width, colors.shape[-1]
        geo.bin(opacities, colors)
        bgv = _bg_array(bg, C, D, colors.dtype)
        k = _kernels()
        if geo.kernel == "lanes":  # alpha as the sum of the weights: exact near 0, where 1 - T is not in float32
            out, t_final, n_contrib, alpha_np = k.forward_lanes(*geo.args(bgv))
        else:
            out, t_final, n_contrib = k.forward(*geo.args(bgv))
            alpha_np = (1.0 - t_final).astype(out.dtype)
        geo.t_final, geo.n_contrib = t_final, n_contrib
        ctx.geo, ctx.has_bg, ctx.col_shape, ctx.dtype = geo, bg is not None, tuple(colors.shape), colors.dtype
        ctx.save_for_backward(bg if bg is not None else torch.empty(0))
        img = torch.from_numpy(out).reshape(C, H, W, D)
        alpha = torch.from_numpy(alpha_np).reshape(C, H, W, 1)
        return img, alpha

    @staticmethod
    def backward(ctx, g_out, g_alpha):
        (bg,) = ctx.saved_tensors
        bg = bg if ctx.has_bg else None
        geo, dtype = ctx.geo, ctx.dtype
        C, H, W, D = geo.n_cams, geo.height, geo.width, ctx.col_shape[-1]
        n_pix = C * H * W
        g_out = torch.zeros(n_pix, D, dtype=dtype) if g_out is None else g_out.reshape(n_pix, D)
        g_alpha = torch.zeros(n_pix, dtype=dtype) if g_alpha is None else g_alpha.reshape(n_pix)
        bgv = _bg_array(bg, C, D, dtype)
        k = _kernels()
        g_out_np = g_out.detach().contiguous().numpy()
        rows = (k.backward_lanes if geo.kernel == "lanes" else k.backward)(
            *geo.args(bgv), g_out_np, g_alpha.detach().contiguous().numpy(), geo.t_final, geo.n_contrib
        )
        g_m2, g_con, g_op, g_col = k.scatter(
            geo.isect, rows, geo.slot, geo.visible, geo.flat.shape[0], len(ctx.col_shape) == 2, geo.n_gauss, C, geo.xs
        )  # means2d, conics in the input dtype
        grad_bg = None
        if bg is not None and ctx.needs_input_grad[4]:
            grad_bg = torch.from_numpy(k.background_grad(geo.t_final, g_out_np, C)).to(dtype)
        n = geo.n_gauss
        return (
            torch.from_numpy(g_m2).reshape(C, n, 2),
            torch.from_numpy(g_con).reshape(C, n, 3),
            torch.from_numpy(g_op).to(dtype),
            torch.from_numpy(g_col).to(dtype).reshape(ctx.col_shape),
            grad_bg,
            None,
        )


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) the kernels for float32 and float64 now (the compositing
    kernels that :func:`compositing_kernel` picks)."""
    for dt in (torch.float32, torch.float64):
        means = torch.tensor([[0.0, 0.0, 2.0]], dtype=dt, requires_grad=True)
        out = rasterize_numba(
            means=means,
            quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dt),
            scales=torch.full((1, 3), 0.1, dtype=dt),
            opacities=torch.tensor([0.5], dtype=dt),
            colors=torch.ones(1, 3, dtype=dt),
            viewmats=torch.eye(4, dtype=dt)[None],
            Ks=torch.tensor([[[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]]], dtype=dt),
            width=8,
            height=8,
            backgrounds=torch.zeros(1, 3, dtype=dt),
        )
        out.colors.sum().backward()


def rasterize_numba(
    *,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
) -> RenderOutput:
    """Render C cameras on CPU with the compiled kernels; arguments as :func:`meshsplat.render.rasterize`.

    CPU float32/float64 tensors only. The first call in a process compiles the kernels (or loads them
    from numba's on-disk cache); :func:`warm_up` does that ahead of time.
    """
    if means.device.type != "cpu":
        raise MeshsplatError(f"backend='numba' needs CPU tensors, got tensors on {means.device}")
    if means.dtype not in (torch.float32, torch.float64):
        raise MeshsplatError(f"backend='numba' needs float32 or float64 tensors, got {means.dtype}")
    if not numba_available():
        raise MeshsplatError("backend='numba' needs numba: pip install numba (or use backend='torch')")
    W, H, C, N = int(width), int(height), viewmats.shape[0], means.shape[0]
    if viewmats.requires_grad or Ks.requires_grad:  # camera gradients: torch's projection (autograd)
        proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, W, H, near_plane, far_plane)
    else:
        k = _kernels()
        proj = project_numba((k.project, k.project_backward), means, quats, scales, opacities, viewmats, Ks, W, H,
                             near_plane, far_plane)  # fmt: skip
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    cols, bg = colors, backgrounds
    if render_mode == "RGB+ED":
        per_cam = colors if colors.dim() == 3 else colors[None].expand(C, N, colors.shape[-1])
        cols = torch.cat([per_cam, proj.depths[..., None]], dim=-1)
        if bg is not None:
            bg = torch.cat([bg, torch.zeros_like(bg[:, :1])], dim=-1)
    geo = _Geometry(proj, N, cols.dim() == 2, W, H, TILE_SIZE)
    img, alpha = _Composite.apply(means2d, proj.conics, opacities, cols, bg, geo)
    out = render_output(proj, means2d, C, W, H, img, alpha, render_mode, "numba")
    out.meta["n_isects"] = int(geo.isect.shape[0])  # (tile, Gaussian) intersections
    out.meta["kernel"] = geo.kernel
    return out
