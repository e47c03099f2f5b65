"""The geometric half of ``compose`` compiled with numba (CPU): for each Gaussian, its surface point, Phong normal,
pose rotation and scale factor from the posed mesh, then its mean, rotation and scale, in one pass (and the
gradient in one more), without the ``[N,3,C]`` corner temporaries and the ~60 small torch operations of the
reference path (``embedding.embed``, ``embedding.pose_frame``, ``quat_multiply``/``quat_normalize``).

float64 inside, results in the inputs' dtype. The backward recomputes the forward's quantities from the inputs
(nothing is saved but the inputs). Serial kernels over ranges of Gaussians (``_numba.run_ranges``): each Gaussian
is computed on its own, and the gradient's scatter to the pose's vertices (pose refinement) runs serially in
Gaussian order, so the results do not depend on the thread count."""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
import torch

from meshsplat._numba import njit_driver, njit_serial, run_ranges

__all__ = ["compose_geometry_compiled", "SCALE_MODE_CODES"]

SCALE_MODE_CODES = {"area": 0, "sqrt_area": 1, "none": 2}  # embedding.SCALE_MODES as the kernels' integers

_NORMAL_EPS = 1e-12  # mesh.geometry.safe_normalize's
_QUAT_EPS = 1e-12  # mesh.quaternion.quat_normalize's (pose_frame's and compose's)


def _forward_kernel(
    table, ratio, faces, face, per, mode, means, normals, quats, scales, dq, points, lo, hi
):  # pragma: no cover - compiled
    """For the Gaussians ``lo..hi-1``. ``table [V,10]``: the posed vertices, their normals and quaternions (wxyz);
    ``ratio [F]``: posed / canonical face areas; ``per [N,10]``: ``uv`` (2), ``d`` (1), the raw rotation (4), the
    unposed scales ``exp(log_scale)`` (3). Writes ``means``, ``normals``, ``scales``, ``points`` (the surface
    points, before the offset ``d``) ``[N,3]`` and ``quats``, ``dq`` (the pose rotations) ``[N,4]``."""
    for i in range(lo, hi):
        f = face[i]
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        u, v = np.float64(per[i, 0]), np.float64(per[i, 1])
        sb, sc = _aligned(table, a, b, c)
        w = 1.0 - u - v
        p0, p1, p2 = _blend3(table, 0, a, b, c, u, v, w)
        nr = _blend3(table, 3, a, b, c, u, v, w)
        n0, n1, n2, _ = _unit3(nr[0], nr[1], nr[2])
        qr = _blend4(table, a, b, c, u, sb * v, sc * w)
        q0, q1, q2, q3, _ = _unit4(qr[0], qr[1], qr[2], qr[3])
        r0, r1, r2, r3, _ = _unit4(
            np.float64(per[i, 3]), np.float64(per[i, 4]), np.float64(per[i, 5]), np.float64(per[i, 6])
        )
        m = _hamilton((q0, q1, q2, q3), (r0, r1, r2, r3))
        m0, m1, m2, m3, _ = _unit4(m[0], m[1], m[2], m[3])
        d = np.float64(per[i, 2])
        normals[i, 0], normals[i, 1], normals[i, 2] = n0, n1, n2
        means[i, 0], means[i, 1], means[i, 2] = p0 + d * n0, p1 + d * n1, p2 + d * n2
        points[i, 0], points[i, 1], points[i, 2] = p0, p1, p2
        dq[i, 0], dq[i, 1], dq[i, 2], dq[i, 3] = q0, q1, q2, q3
        quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3] = m0, m1, m2, m3
        factor = _scale_factor(np.float64(ratio[f]), mode)
        for j in range(3):
            scales[i, j] = per[i, 7 + j] * factor


def _aligned(table, a, b, c):  # pragma: no cover - compiled
    """The signs (±1) of the quaternions of corners ``b`` and ``c``: -1 where one points away from corner ``a``'s
    (``pose_frame``: q and -q are one rotation)."""
    db = dc = 0.0
    for j in range(6, 10):
        qa = np.float64(table[a, j])
        db += table[b, j] * qa
        dc += table[c, j] * qa
    return (-1.0 if db < 0.0 else 1.0), (-1.0 if dc < 0.0 else 1.0)


def _blend3(table, col, a, b, c, wa, wb, wc):  # pragma: no cover - compiled
    """The blend of ``table``'s columns ``col..col+2`` at the corners ``a, b, c``."""
    return (
        wa * table[a, col] + wb * table[b, col] + wc * table[c, col],
        wa * table[a, col + 1] + wb * table[b, col + 1] + wc * table[c, col + 1],
        wa * table[a, col + 2] + wb * table[b, col + 2] + wc * table[c, col + 2],
    )


def _blend4(table, a, b, c, wa, wb, wc):  # pragma: no cover - compiled
    """The blend of the quaternions (``table``'s columns 6..9) at the corners ``a, b, c``."""
    return (
        wa * table[a, 6] + wb * table[b, 6] + wc * table[c, 6],
        wa * table[a, 7] + wb * table[b, 7] + wc * table[c, 7],
        wa * table[a, 8] + wb * table[b, 8] + wc * table[c, 8],
        wa * table[a, 9] + wb * table[b, 9] + wc * table[c, 9],
    )


def _unit3(x0, x1, x2):  # pragma: no cover - compiled
    """``x * rsqrt(max(|x|², eps²))`` (``safe_normalize``) and the factor."""
    inv = 1.0 / math.sqrt(max(x0 * x0 + x1 * x1 + x2 * x2, _NORMAL_EPS * _NORMAL_EPS))
    return x0 * inv, x1 * inv, x2 * inv, inv


def _unit4(x0, x1, x2, x3):  # pragma: no cover - compiled
    """``x / max(|x|, eps)`` (``quat_normalize``) and the norm."""
    n = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3)
    k = max(n, _QUAT_EPS)
    return x0 / k, x1 / k, x2 / k, x3 / k, n


def _hamilton(a, b):  # pragma: no cover - compiled
    """``a (x) b`` (wxyz 4-tuples, ``mesh.quaternion.quat_multiply``)."""
    return (
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    )


def _hamilton_backward(a, b, g):  # pragma: no cover - compiled
    """The gradients of ``a (x) b`` with respect to ``a`` and ``b`` for the output gradient ``g``."""
    g0, g1, g2, g3 = g
    ga = (
        g0 * b[0] + g1 * b[1] + g2 * b[2] + g3 * b[3],
        -g0 * b[1] + g1 * b[0] - g2 * b[3] + g3 * b[2],
        -g0 * b[2] + g1 * b[3] + g2 * b[0] - g3 * b[1],
        -g0 * b[3] - g1 * b[2] + g2 * b[1] + g3 * b[0],
    )
    gb = (
        g0 * a[0] + g1 * a[1] + g2 * a[2] + g3 * a[3],
        -g0 * a[1] + g1 * a[0] + g2 * a[3] - g3 * a[2],
        -g0 * a[2] - g1 * a[3] + g2 * a[0] + g3 * a[1],
        -g0 * a[3] + g1 * a[2] - g2 * a[1] + g3 * a[0],
    )
    return ga, gb


def _unit4_backward(x, n, g):  # pragma: no cover - compiled
    """The gradient at ``x`` (4-tuple, norm ``n``) of ``x / max(|x|, eps)`` for the output gradient ``g`` (as
    torch's ``norm`` then ``clamp_min``: nothing through the norm where it is clamped)."""
    if n < _QUAT_EPS:
        return g[0] / _QUAT_EPS, g[1] / _QUAT_EPS, g[2] / _QUAT_EPS, g[3] / _QUAT_EPS
    k = (g[0] * x[0] + g[1] * x[1] + g[2] * x[2] + g[3] * x[3]) / (n * n * n)
    return g[0] / n - x[0] * k, g[1] / n - x[1] * k, g[2] / n - x[2] * k, g[3] / n - x[3] * k


def _scale_factor(a, mode):  # pragma: no cover - compiled
    """The scale factor of the area ratio ``a`` (``SCALE_MODE_CODES``: area, its square root, 1)."""
    if mode == 0:
        return a
    if mode == 1:
        return math.sqrt(max(a, 0.0) + 1e-20)
    return 1.0


def _backward_kernel(
    table, ratio, faces, face, per, mode, grads, g_per, corner_terms, ratio_terms, lo, hi
):  # pragma: no cover - compiled
    """For the Gaussians ``lo..hi-1``: ``grads [N,17]`` (the gradients of means, normals (3 each), quats (4), scales
    (3) and dq (4)) back to ``g_per [N,10]`` (``per``'s layout). With pose gradients (``corner_terms [N,3,10]``,
    ``ratio_terms [N]``; else empty): each corner's gradient in ``table``'s layout and the face ratio's, scattered
    by ``_scatter_kernel``. The forward's quantities are recomputed."""
    want_pose = corner_terms.shape[0] > 0
    for i in range(lo, hi):
        f = face[i]
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        u, v = np.float64(per[i, 0]), np.float64(per[i, 1])
        w = 1.0 - u - v
        sb, sc = _aligned(table, a, b, c)
        wb, wc = sb * v, sc * w
        nr = _blend3(table, 3, a, b, c, u, v, w)
        n0, n1, n2, inv = _unit3(nr[0], nr[1], nr[2])
        qr = _blend4(table, a, b, c, u, wb, wc)
        q0, q1, q2, q3, qn = _unit4(qr[0], qr[1], qr[2], qr[3])
        r = (np.float64(per[i, 3]), np.float64(per[i, 4]), np.float64(per[i, 5]), np.float64(per[i, 6]))
        r0, r1, r2, r3, rn = _unit4(r[0], r[1], r[2], r[3])
        m = _hamilton((q0, q1, q2, q3), (r0, r1, r2, r3))
        mn = math.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3])
        d = np.float64(per[i, 2])
        # means = p + d n; n = nr * inv (safe_normalize: nothing through the clamped norm)
        gp0, gp1, gp2 = np.float64(grads[i, 0]), np.float64(grads[i, 1]), np.float64(grads[i, 2])
        gn0, gn1, gn2 = grads[i, 3] + d * gp0, grads[i, 4] + d * gp1, grads[i, 5] + d * gp2
        g_d = gp0 * n0 + gp1 * n1 + gp2 * n2
        k = (
            (gn0 * n0 + gn1 * n1 + gn2 * n2) * inv
            if nr[0] * nr[0] + nr[1] * nr[1] + nr[2] * nr[2] >= _NORMAL_EPS * _NORMAL_EPS
            else 0.0
        )
        gr0, gr1, gr2 = gn0 * inv - n0 * k, gn1 * inv - n1 * k, gn2 * inv - n2 * k
        # quats = unit(dq (x) unit(r)), dq = unit(qr)
        gq = (np.float64(grads[i, 6]), np.float64(grads[i, 7]), np.float64(grads[i, 8]), np.float64(grads[i, 9]))
        gm = _unit4_backward(m, mn, gq)
        ga, g_rn = _hamilton_backward((q0, q1, q2, q3), (r0, r1, r2, r3), gm)
        ga = (ga[0] + grads[i, 13], ga[1] + grads[i, 14], ga[2] + grads[i, 15], ga[3] + grads[i, 16])
        g_r = _unit4_backward(r, rn, g_rn)
        gb0, gb1, gb2, gb3 = _unit4_backward(qr, qn, ga)
        # the weights (u, v, 1 - u - v): each corner's values against the blends' gradients
        g_wa = _corner_dot(table, a, gp0, gp1, gp2, gr0, gr1, gr2, gb0, gb1, gb2, gb3, 1.0)
        g_wb = _corner_dot(table, b, gp0, gp1, gp2, gr0, gr1, gr2, gb0, gb1, gb2, gb3, sb)
        g_wc = _corner_dot(table, c, gp0, gp1, gp2, gr0, gr1, gr2, gb0, gb1, gb2, gb3, sc)
        g_per[i, 0], g_per[i, 1], g_per[i, 2] = g_wa - g_wc, g_wb - g_wc, g_d
        g_per[i, 3], g_per[i, 4], g_per[i, 5], g_per[i, 6] = g_r
        # scales = exp(log_scale) * factor(ratio[f]), the exp taken by torch
        ra = np.float64(ratio[f])
        factor = _scale_factor(ra, mode)
        g_factor = 0.0
        for j in range(3):
            g_per[i, 7 + j] = grads[i, 10 + j] * factor
            g_factor += grads[i, 10 + j] * np.float64(per[i, 7 + j])
        if want_pose:
            for k3 in range(3):
                wk = u if k3 == 0 else (v if k3 == 1 else w)
                wq = u if k3 == 0 else (wb if k3 == 1 else wc)
                corner_terms[i, k3, 0], corner_terms[i, k3, 1], corner_terms[i, k3, 2] = wk * gp0, wk * gp1, wk * gp2
                corner_terms[i, k3, 3], corner_terms[i, k3, 4], corner_terms[i, k3, 5] = wk * gr0, wk * gr1, wk * gr2
                corner_terms[i, k3, 6], corner_terms[i, k3, 7] = wq * gb0, wq * gb1
                corner_terms[i, k3, 8], corner_terms[i, k3, 9] = wq * gb2, wq * gb3
            if mode == 0:
                ratio_terms[i] = g_factor
            elif mode == 1:
                ratio_terms[i] = g_factor * 0.5 / factor if ra >= 0.0 else 0.0
            else:
                ratio_terms[i] = 0.0


def _corner_dot(table, c, gp0, gp1, gp2, gr0, gr1, gr2, gb0, gb1, gb2, gb3, sign):  # pragma: no cover - compiled
    """A corner weight's gradient: corner ``c``'s position, normal and (``sign``-aligned) quaternion against the
    gradients of the blends."""
    acc = gp0 * table[c, 0] + gp1 * table[c, 1] + gp2 * table[c, 2]
    acc += gr0 * table[c, 3] + gr1 * table[c, 4] + gr2 * table[c, 5]
    return acc + sign * (gb0 * table[c, 6] + gb1 * table[c, 7] + gb2 * table[c, 8] + gb3 * table[c, 9])


def _scatter_kernel(faces, face, corner_terms, ratio_terms, g_table, g_ratio):  # pragma: no cover - compiled
    """The corner terms ``[N,3,10]`` added to ``g_table [V,10]`` and the ratio terms ``[N]`` to ``g_ratio [F]``, in
    Gaussian order (a fixed order: the same bits on any thread count)."""
    for i in range(face.shape[0]):
        f = face[i]
        for k in range(3):
            c = faces[f, k]
            for j in range(10):
                g_table[c, j] += corner_terms[i, k, j]
        g_ratio[f] += ratio_terms[i]


# Plain Python until _kernels() rebinds them: numba's prange, the helpers and the serial kernels the parallel
# drivers call.
_prange: Any = range
_HELPERS = ("_aligned", "_blend3", "_blend4", "_unit3", "_unit4", "_hamilton", "_hamilton_backward", "_unit4_backward",
            "_scale_factor", "_corner_dot")  # fmt: skip
_forward_serial: Any = None
_backward_serial: Any = None


def _forward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_forward_kernel`` over the ranges ``bounds [R+1]`` in numba's parallel loop (``run_ranges``'s driver)."""
    for j in _prange(bounds.shape[0] - 1):
        _forward_serial(*args, bounds[j], bounds[j + 1])


def _backward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_backward_kernel`` over the ranges ``bounds [R+1]`` in numba's parallel loop."""
    for j in _prange(bounds.shape[0] - 1):
        _backward_serial(*args, bounds[j], bounds[j + 1])


@lru_cache(maxsize=1)
def _kernels() -> Any:
    """(forward, backward, scatter, forward driver, backward driver)."""
    global _prange, _forward_serial, _backward_serial
    import numba

    ser = njit_serial(numba)
    # the helpers compiled, then called by the kernels under the same names (LLVM inlines them: as fast as numba's
    # own inlining, which compiled 0.5 s slower)
    for name in _HELPERS:
        globals()[name] = ser(globals()[name])
    fwd, bwd, scatter = (ser(f) for f in (_forward_kernel, _backward_kernel, _scatter_kernel))
    _prange, _forward_serial, _backward_serial = numba.prange, fwd, bwd
    par = njit_driver(numba)
    return fwd, bwd, scatter, par(_forward_ranges), par(_backward_ranges)


class _ComposeGeometry(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, table: torch.Tensor, ratio: torch.Tensor, faces: torch.Tensor, face: torch.Tensor,
                per: torch.Tensor, mode: int) -> tuple[torch.Tensor, ...]:  # fmt: skip
        fwd, _, _, fwd_par, _ = _kernels()
        arrays = (
            table.detach().contiguous().numpy(),
            ratio.detach().contiguous().numpy(),
            faces.contiguous().numpy(),
            face.contiguous().numpy(),
            per.detach().contiguous().numpy(),
        )
        n, dtype = per.shape[0], per.dtype
        out = [torch.empty(n, k, dtype=dtype) for k in (3, 3, 4, 3, 4, 3)]  # means, normals, quats, scales, dq, points
        run_ranges(fwd, fwd_par, n, *arrays, mode, *(t.numpy() for t in out))
        ctx.arrays, ctx.mode, ctx.dtype = arrays, mode, dtype
        ctx.mark_non_differentiable(out[5])
        return tuple(out)

    @staticmethod
    def backward(ctx: Any, *grads: torch.Tensor | None) -> tuple[torch.Tensor | None, ...]:
        _, bwd, scatter, _, bwd_par = _kernels()
        table, ratio, faces, face, per = ctx.arrays
        n = per.shape[0]
        dtype = ctx.dtype
        widths = (3, 3, 4, 3, 4)  # means, normals, quats, scales, dq (points take none)
        parts = [torch.zeros(n, k, dtype=dtype) if g is None else g for g, k in zip(grads[:5], widths, strict=True)]
        g_out = torch.cat(parts, 1).to(dtype).contiguous().numpy()  # [N,17]
        g_per = np.empty((n, 10), per.dtype)
        want_pose = ctx.needs_input_grad[0] or ctx.needs_input_grad[1]
        corner_terms = np.empty((n if want_pose else 0, 3, 10), np.float64)
        ratio_terms = np.empty(n if want_pose else 0, np.float64)
        run_ranges(bwd, bwd_par, n, table, ratio, faces, face, per, ctx.mode, g_out, g_per, corner_terms, ratio_terms)
        g_table = g_ratio = None
        if want_pose:
            g_table64, g_ratio64 = np.zeros(table.shape, np.float64), np.zeros(ratio.shape, np.float64)
            scatter(faces, face, corner_terms, ratio_terms, g_table64, g_ratio64)
            g_table = torch.from_numpy(g_table64).to(dtype)
            g_ratio = torch.from_numpy(g_ratio64).to(dtype)
        return g_table, g_ratio, None, None, torch.from_numpy(g_per), None


def compose_geometry_compiled(
    verts: torch.Tensor,
    vertex_normals: torch.Tensor,
    vertex_quats: torch.Tensor,
    area_ratio: torch.Tensor,
    faces: torch.Tensor,
    face: torch.Tensor,
    uv: torch.Tensor,
    d: torch.Tensor,
    rotation: torch.Tensor,
    log_scale: torch.Tensor,
    scale_mode: str,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(means [N,3], normals [N,3], quats [N,4], scales [N,3], delta_q [N,4], points [N,3])`` of the Gaussians
    ``(face [N], uv [N,2], d [N], rotation [N,4], log_scale [N,3])`` on a posed mesh (``verts``, ``vertex_normals``
    ``[V,3]``, ``vertex_quats [V,4]``, ``area_ratio [F]``, ``faces [F,3]``), as ``embed``, ``pose_frame`` and
    ``compose`` compute them; ``points``: the surface points, without gradient. CPU tensors of one float dtype;
    differentiable in every float input."""
    table = torch.cat([verts, vertex_normals, vertex_quats], 1).to(uv.dtype)
    per = torch.cat([uv, d[:, None], rotation, log_scale.exp()], 1)  # torch's exp: vectorized, 10x numba's
    return _ComposeGeometry.apply(table, area_ratio.to(uv.dtype), faces, face, per, SCALE_MODE_CODES[scale_mode])
