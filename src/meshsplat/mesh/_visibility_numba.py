"""``mesh.visibility`` compiled with numba (CPU): the same surface samples, cells and bias, without arrays of
samples per direction. float64 inside. Each direction's map is filled by one thread (and a maximum does not
depend on the order), so the result does not depend on the thread count."""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
import torch

from meshsplat._numba import njit_parallel, numba_threads

_prange: Any = range  # rebound to numba.prange when the kernel is compiled
_BLOCK = 4096  # samples per block (96 KiB of float64 points)


def _depth_kernel(verts, faces, frame, centre, radius, inv_cell, grid, spacing, threads):  # pragma: no cover - compiled
    """Heights ``[K*grid*grid]`` (-inf where no sample fell) of ``verts [V,3]``/``faces [F,3]`` seen along each
    of the ``K`` frames (``frame [3K,3]``: rows a_1..a_K, b_1..b_K, w_1..w_K), relative to ``centre [3]``."""
    n_v, n_f, k = verts.shape[0], faces.shape[0], frame.shape[0] // 3
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
    cells = grid * grid
    depth = np.full(k * cells, -np.inf, np.float64)
    g1 = grid - 1
    for t in _prange(threads):  # thread t fills maps t, t + threads, ...: blocks of samples stay in its cache
        for m0 in range(0, total, _BLOCK):
            m1 = min(m0 + _BLOCK, total)
            for d in range(t, k, threads):
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
    return depth


def _lit_kernel(
    depth, frame, rel, normals, radius, inv_cell, grid, cell, bias_cells, slope_cells, max_tan
):  # pragma: no cover - compiled
    """``[N,K]`` 1.0 where the points ``rel [N,3]`` (relative to the grid's centre; unit ``normals [N,3]``) are
    not below their cell's height by more than the slope-scaled bias, else 0.0."""
    n, k = rel.shape[0], frame.shape[0] // 3
    g1, cells = grid - 1, grid * grid
    lit = np.zeros((n, k), np.float64)
    for p in _prange(n):
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
    return lit


@lru_cache(maxsize=1)
def _kernel() -> Any:
    return njit_parallel(globals(), _depth_kernel, _lit_kernel)


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
    import numba

    depth_k, _ = _kernel()
    with numba_threads():
        faces64 = np.ascontiguousarray(faces.cpu().numpy(), dtype=np.int64)
        args = (_as64(verts), faces64, _as64(frame), _as64(centre), float(radius), 1.0 / cell, int(grid), cell / 2)
        return torch.from_numpy(depth_k(*args, numba.get_num_threads()))


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
    _, lit_k = _kernel()
    with numba_threads():
        lit = lit_k(
            _as64(depth),
            _as64(frame),
            _as64(rel),
            _as64(normals),
            float(radius),
            1.0 / cell,
            int(grid),
            float(cell),
            *bias,
        )
    return torch.from_numpy(lit)


def _as64(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)
