"""``mesh.visibility`` compiled with numba (CPU): the same surface samples, cells and bias, without arrays of
samples per direction. float64 inside. Serial kernels over ranges (``_numba.run_ranges`` on torch's thread
count): each direction's map is filled by one range (and a maximum does not depend on the order), each point's
row of ``lit`` by one range, so the result does not depend on the thread count."""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
import torch

from meshsplat._numba import njit_driver, njit_serial, run_ranges

_BLOCK = 4096  # samples per block (96 KiB of float64 points)


def _samples_kernel(verts, faces, centre, spacing):  # pragma: no cover - compiled
    """Surface samples ``[S,3]`` of ``verts [V,3]``/``faces [F,3]`` relative to ``centre [3]``: the vertices, then
    each face's lattice (``surface_samples``: steps = ceil(longest edge / spacing)) without its corners."""
    n_v, n_f = verts.shape[0], faces.shape[0]
    steps = np.empty(n_f, np.int64)
    total = n_v
    for f in range(n_f):  # the lattice of surface_samples: steps = ceil(longest edge / spacing)
        ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
        e = 0.0
        for p, q in ((ia, ic), (ib, ia), (ic, ib)):
            d2 = (verts[p, 0] - verts[q, 0]) ** 2 + (verts[p, 1] - verts[q, 1]) ** 2 + (verts[p, 2] - verts[q, 2]) ** 2
            e = max(e, math.sqrt(d2))
        s = max(1, math.ceil(e / spacing))
        steps[f] = s
        if s > 1:
            total += (s + 1) * (s + 2) // 2 - 3
    pts = np.empty((total, 3), np.float64)
    for v in range(n_v):
        for c in range(3):
            pts[v, c] = verts[v, c] - centre[c]
    n = n_v
    for f in range(n_f):
        s = steps[f]
        if s <= 1:
            continue
        ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
        for i in range(s + 1):
            for j in range(s + 1 - i):
                if (i == 0 and j == 0) or (i == s and j == 0) or (i == 0 and j == s):
                    continue  # the corners: the vertices
                u, w = i / s, j / s
                t = (s - i - j) / s
                for c in range(3):
                    pts[n, c] = u * verts[ia, c] + w * verts[ib, c] + t * verts[ic, c] - centre[c]
                n += 1
    return pts


def _depth_kernel(pts, frame, radius, inv_cell, grid, parts, depth, lo, hi):  # pragma: no cover - compiled
    """Heights into ``depth [K*grid*grid]`` (-inf where no sample fell) of the samples ``pts [S,3]`` seen along
    each of the ``K`` frames (``frame [3K,3]``: rows a_1..a_K, b_1..b_K, w_1..w_K); part t of ``parts`` (for t in
    ``lo..hi-1``) fills maps t, t + parts, ...: blocks of samples stay in its thread's cache."""
    total, k = pts.shape[0], frame.shape[0] // 3
    cells = grid * grid
    g1 = grid - 1
    for t in range(lo, hi):
        for m0 in range(0, total, _BLOCK):
            m1 = min(m0 + _BLOCK, total)
            for d in range(t, k, parts):
                a0, a1, a2 = frame[d, 0], frame[d, 1], frame[d, 2]
                b0, b1, b2 = frame[k + d, 0], frame[k + d, 1], frame[k + d, 2]
                w0, w1, w2 = frame[2 * k + d, 0], frame[2 * k + d, 1], frame[2 * k + d, 2]
                o = d * cells
                for m in range(m0, m1):
                    x, y, z = pts[m, 0], pts[m, 1], pts[m, 2]
                    fi = (a0 * x + a1 * y + a2 * z + radius) * inv_cell  # floor, clamped to the grid
                    fj = (b0 * x + b1 * y + b2 * z + radius) * inv_cell
                    gi = 0 if fi < 0.0 else min(int(fi), g1)
                    gj = 0 if fj < 0.0 else min(int(fj), g1)
                    idx = o + gi * grid + gj
                    depth[idx] = max(depth[idx], w0 * x + w1 * y + w2 * z)  # branch-free


def _lit_kernel(
    depth, frame, rel, normals, radius, inv_cell, grid, cell, bias_cells, slope_cells, max_tan, lit, lo, hi
):  # pragma: no cover - compiled
    """Into the zeroed ``lit [N,K]``, for the points ``lo..hi-1``: 1.0 where the points ``rel [N,3]`` (relative to
    the grid's centre; unit ``normals [N,3]``) are not below their cell's height by more than the slope-scaled
    bias."""
    k = frame.shape[0] // 3
    g1, cells = grid - 1, grid * grid
    for p in range(lo, hi):
        x, y, z = rel[p, 0], rel[p, 1], rel[p, 2]
        for d in range(k):
            w0, w1, w2 = frame[2 * k + d, 0], frame[2 * k + d, 1], frame[2 * k + d, 2]
            fi = (frame[d, 0] * x + frame[d, 1] * y + frame[d, 2] * z + radius) * inv_cell
            fj = (frame[k + d, 0] * x + frame[k + d, 1] * y + frame[k + d, 2] * z + radius) * inv_cell
            gi = 0 if fi < 0.0 else min(int(fi), g1)
            gj = 0 if fj < 0.0 else min(int(fj), g1)
            c = min(max(abs(w0 * normals[p, 0] + w1 * normals[p, 1] + w2 * normals[p, 2]), 1e-6), 1.0)
            tan = min(math.sqrt(max(1.0 - c * c, 0.0)) / c, max_tan)
            if w0 * x + w1 * y + w2 * z >= depth[d * cells + gi * grid + gj] - cell * (bias_cells + slope_cells * tan):
                lit[p, d] = 1.0


# Plain Python until _kernel() rebinds them: numba's prange and the serial kernels the parallel drivers call.
_prange: Any = range
_depth_serial: Any = None
_lit_serial: Any = None


def _depth_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_depth_kernel`` over the ranges ``bounds [R+1]`` in numba's parallel loop (``run_ranges``'s driver)."""
    for j in _prange(bounds.shape[0] - 1):
        _depth_serial(*args, bounds[j], bounds[j + 1])


def _lit_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_lit_kernel`` over the ranges ``bounds [R+1]`` in numba's parallel loop."""
    for j in _prange(bounds.shape[0] - 1):
        _lit_serial(*args, bounds[j], bounds[j + 1])


@lru_cache(maxsize=1)
def _kernel() -> Any:
    """(samples, depth, lit, depth driver, lit driver)."""
    global _prange, _depth_serial, _lit_serial
    import numba

    ser = njit_serial(numba)
    samples, depth, lit = ser(_samples_kernel), ser(_depth_kernel), ser(_lit_kernel)
    _prange, _depth_serial, _lit_serial = numba.prange, depth, lit
    par = njit_driver(numba)
    return samples, depth, lit, par(_depth_ranges), par(_lit_ranges)


def depth_compiled(
    verts: torch.Tensor,
    faces: torch.Tensor,
    frame: torch.Tensor,
    centre: torch.Tensor,
    radius: float,
    cell: float,
    grid: int,
) -> torch.Tensor:
    """``ShadowMaps.depth`` ``[K*grid*grid]`` (float64) of ``verts [V,3]``/``faces [F,3]`` along ``frame [3K,3]``
    around ``centre [3]``, compiled for CPU tensors."""
    samples_k, depth_k, _, depth_par, _ = _kernel()
    faces64 = np.ascontiguousarray(faces.cpu().numpy(), dtype=np.int64)
    pts = samples_k(_as64(verts), faces64, _as64(centre), cell / 2)
    k = frame.shape[0] // 3
    depth = np.full(k * int(grid) * int(grid), -np.inf, np.float64)
    parts = max(1, min(torch.get_num_threads(), k))  # one part per thread: each a comb of maps
    run_ranges(depth_k, depth_par, parts, pts, _as64(frame), float(radius), 1.0 / cell, int(grid), parts, depth)
    return torch.from_numpy(depth)


def lit_compiled(
    depth: torch.Tensor,
    frame: torch.Tensor,
    rel: torch.Tensor,
    normals: torch.Tensor,
    radius: float,
    cell: float,
    grid: int,
    bias: tuple[float, float, float],
) -> torch.Tensor:
    """``ShadowMaps.lit``'s ``[N,K]`` (0 or 1, float64), compiled: the points ``rel [N,3]`` (less the grid's
    centre) with unit ``normals [N,3]`` looked up in ``depth`` (from :func:`depth_compiled`) along ``frame [3K,3]``;
    ``bias``: (cells, slope cells, largest tangent)."""
    _, _, lit_k, _, lit_par = _kernel()
    lit = np.zeros((rel.shape[0], frame.shape[0] // 3), np.float64)
    args = (_as64(depth), _as64(frame), _as64(rel), _as64(normals), float(radius), 1.0 / cell, int(grid), float(cell))
    run_ranges(lit_k, lit_par, rel.shape[0], *args, *bias, lit)
    return torch.from_numpy(lit)


def _as64(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)
