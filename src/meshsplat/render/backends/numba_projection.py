"""Compiled EWA projection (numba), forward and backward, with ``render.projection``'s conventions.

The same arithmetic as :func:`meshsplat.render.projection.project_gaussians` (quaternion -> rotation,
``R S S^T R^T``, world -> camera, Jacobian at the field-of-view-clamped ``x/z, y/z``, 0.3 px² dilation,
conic, opacity-aware radii, culling), evaluated per (camera, Gaussian) in float64 and rounded to the
input dtype, so float32 outputs agree with the torch version to rounding. Backward is the hand-derived
chain rule of the same steps; camera matrices get no gradient here (the numba backend hands projection
to torch when ``viewmats`` or ``Ks`` require grad). Both kernels run over ranges of Gaussians
(``_numba.run_ranges``), each Gaussian summing its cameras in camera order: bit-identical for any thread count.
The forward allocates its scratch matrices once per range (once per Gaussian before: 1.3x slower at 500k), the
backward once per block of ``_BLOCK`` Gaussians (ten small allocations per Gaussian before: 1.2x faster at 50k).
The backward takes ``J W Σ W^T`` from the forward's ``Σ u``, ``Σ v`` (not a 3x3 product per camera) and skips
Gaussians no camera sees: 500k @ 512² 72 -> 53 ms. The forward computes a Gaussian's covariance only for a camera
that may see it: a bound on its radii from the scales alone (any rotation) culls those surely off screen first
(the benchmark avatar's 37% outside the image: 500k @ 512² 50 -> 45 ms).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from meshsplat._numba import njit_driver, njit_serial, run_ranges
from meshsplat.render._constants import ALPHA_THRESHOLD, EPS2D, FOV_CLAMP_MARGIN, MAX_EXTEND
from meshsplat.render.projection import Projection

__all__ = ["project_numba"]

_BLOCK = 256  # Gaussians per block of the backward (scratch arrays allocated once per block)
# Plain Python until compile_kernels() rebinds them: numba's prange and the serial kernels the drivers call.
_prange: Any = range
_project_serial: Any = None
_project_backward_serial: Any = None


def _project_kernel(
    means, quats, scales, opac, viewmats, ks, width, height, near, far, m2, con, depth, radii, vis, lo, hi
):  # pragma: no cover - compiled
    """Gaussians ``lo..hi-1`` into the zeroed outputs means2d [C,N,2], conics [C,N,3], depths [C,N] (input dtype),
    radii [C,N,2] int32, visible [C,N] bool."""
    n_cams = viewmats.shape[0]
    lims = _fov_limits(ks, width, height)
    rows = _row_norms(viewmats)
    rot = np.empty((3, 3), np.float64)  # scratch, once per range (a range is one call)
    sig = np.empty((3, 3), np.float64)  # R S S^T R^T
    for i in range(lo, hi):
        s2 = 0.0  # sum of the squared scales: the screen cull's bound on Σ
        for k in range(3):
            sk = np.float64(scales[i, k])
            s2 += sk * sk
        have_sig = False  # Σ and the extent are computed for the first camera that may see the Gaussian
        op, ext = 0.0, 0.0
        for cam in range(n_cams):
            w = viewmats[cam]
            x = w[0, 3] + w[0, 0] * means[i, 0] + w[0, 1] * means[i, 1] + w[0, 2] * means[i, 2]
            y = w[1, 3] + w[1, 0] * means[i, 0] + w[1, 1] * means[i, 1] + w[1, 2] * means[i, 2]
            z = w[2, 3] + w[2, 0] * means[i, 0] + w[2, 1] * means[i, 1] + w[2, 2] * means[i, 2]
            if not (near <= z <= far):
                continue
            fx, fy, cx, cy = ks[cam, 0, 0], ks[cam, 1, 1], ks[cam, 0, 2], ks[cam, 1, 2]
            tx, ty, _, _ = _clamped_xy(x, y, z, lims[cam])
            rz = 1.0 / z
            j00, j02, j11, j12 = fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz
            mx = fx * x * rz + cx
            my = fy * y * rz + cy
            if _off_screen(mx, my, j00, j02, j11, j12, rows[cam], s2, width, height):
                continue
            if not have_sig:
                _quat_rotation(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3], rot)
                for r in range(3):
                    for c in range(3):
                        acc = 0.0
                        for k in range(3):
                            sk = np.float64(scales[i, k])
                            acc += rot[r, k] * sk * sk * rot[c, k]
                        sig[r, c] = acc
                op = np.float64(opac[i])
                ext = min(math.sqrt(2.0 * math.log(max(op, ALPHA_THRESHOLD) / ALPHA_THRESHOLD)), MAX_EXTEND)
                have_sig = True
            a, b, c, _, _, _, _, _, _ = _screen_cov(w, sig, j00, j02, j11, j12)
            a += EPS2D
            c += EPS2D
            det = a * c - b * b
            if not (det > 0.0) or op < ALPHA_THRESHOLD:
                continue
            rx = math.ceil(ext * math.sqrt(max(a, 0.0)))
            ry = math.ceil(ext * math.sqrt(max(c, 0.0)))
            if not (rx > 0 or ry > 0) or mx + rx <= 0 or mx - rx >= width or my + ry <= 0 or my - ry >= height:
                continue
            vis[cam, i] = True
            radii[cam, i, 0], radii[cam, i, 1] = int(rx), int(ry)
            m2[cam, i, 0], m2[cam, i, 1] = mx, my
            con[cam, i, 0], con[cam, i, 1], con[cam, i, 2] = c / det, -b / det, a / det
            depth[cam, i] = z
    return m2, con, depth, radii, vis


def _quat_rotation_py(qw, qx, qy, qz, r):  # pragma: no cover - compiled
    """Writes the rotation matrix [3,3] float64 of a quaternion (wxyz, normalised with norm clamped at 1e-12)
    into ``r``."""
    w, x, y, z = np.float64(qw), np.float64(qx), np.float64(qy), np.float64(qz)
    nrm = max(math.sqrt(w * w + x * x + y * y + z * z), 1e-12)
    w, x, y, z = w / nrm, x / nrm, y / nrm, z / nrm
    r[0, 0], r[0, 1], r[0, 2] = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)
    r[1, 0], r[1, 1], r[1, 2] = 2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)
    r[2, 0], r[2, 1], r[2, 2] = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)


def _fov_limits_py(ks, width, height):  # pragma: no cover - compiled
    """``[C, 4]``: each camera's limits of ``x/z`` (right, left) and ``y/z`` (down, up), the field of view widened by
    the margin (once per kernel call, not per Gaussian)."""
    lims = np.empty((ks.shape[0], 4), np.float64)
    for cam in range(ks.shape[0]):
        fx, fy, cx, cy = ks[cam, 0, 0], ks[cam, 1, 1], ks[cam, 0, 2], ks[cam, 1, 2]
        tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
        lims[cam, 0] = (width - cx) / fx + FOV_CLAMP_MARGIN * tan_x
        lims[cam, 1] = cx / fx + FOV_CLAMP_MARGIN * tan_x
        lims[cam, 2] = (height - cy) / fy + FOV_CLAMP_MARGIN * tan_y
        lims[cam, 3] = cy / fy + FOV_CLAMP_MARGIN * tan_y
    return lims


def _row_norms_py(viewmats):  # pragma: no cover - compiled
    """``[C, 3]``: the lengths of the rows of each camera's rotation part (for :func:`_off_screen_py`)."""
    out = np.empty((viewmats.shape[0], 3), np.float64)
    for cam in range(viewmats.shape[0]):
        for r in range(3):
            out[cam, r] = math.sqrt(viewmats[cam, r, 0] ** 2 + viewmats[cam, r, 1] ** 2 + viewmats[cam, r, 2] ** 2)
    return out


def _off_screen_py(mx, my, j00, j02, j11, j12, rows, s2, width, height):  # pragma: no cover - compiled
    """Whether a Gaussian at (mx, my) is off screen whatever its rotation and opacity, before its covariance is
    computed: the radii :func:`_project_kernel` would find are at most ``MAX_EXTEND sqrt(|u|² s2 + EPS2D)`` (and so
    for v), for the rows u, v of ``J W`` (``|u| <= |j00| |W0| + |j02| |W2|``, ``rows``: the ``|W_r|``) and ``s2`` the
    sum of the squared scales (``u^T Σ u <= |u|² s2``), here widened by 1e-6 against rounding. NaN: False."""
    ub = abs(j00) * rows[0] + abs(j02) * rows[2]
    vb = abs(j11) * rows[1] + abs(j12) * rows[2]
    rx = math.ceil(MAX_EXTEND * math.sqrt((ub * ub * s2 + EPS2D) * (1.0 + 1e-6)))
    ry = math.ceil(MAX_EXTEND * math.sqrt((vb * vb * s2 + EPS2D) * (1.0 + 1e-6)))
    return mx + rx <= 0 or mx - rx >= width or my + ry <= 0 or my - ry >= height


def _clamped_xy_py(x, y, z, lim):  # pragma: no cover - compiled
    """``z * clamp(x/z)``, ``z * clamp(y/z)`` (``lim``: the camera's row of :func:`_fov_limits_py`) and whether each
    is clamped."""
    ux = min(lim[0], max(-lim[1], x / z))
    uy = min(lim[2], max(-lim[3], y / z))
    return z * ux, z * uy, ux != x / z, uy != y / z


def _screen_cov_py(w, sig, j00, j02, j11, j12):  # pragma: no cover - compiled
    """(a, b, c) of ``J W Σ W^T J^T`` for J = [[j00, 0, j02], [0, j11, j12]] (no dilation), then ``Σ u`` and ``Σ v``
    for the rows u, v of ``J W`` (the backward's ``J W Σ W^T = [Σ u, Σ v]^T W^T``)."""
    # rows of J W: u = j00 * W0 + j02 * W2, v = j11 * W1 + j12 * W2
    u0 = j00 * w[0, 0] + j02 * w[2, 0]
    u1 = j00 * w[0, 1] + j02 * w[2, 1]
    u2 = j00 * w[0, 2] + j02 * w[2, 2]
    v0 = j11 * w[1, 0] + j12 * w[2, 0]
    v1 = j11 * w[1, 1] + j12 * w[2, 1]
    v2 = j11 * w[1, 2] + j12 * w[2, 2]
    su0 = sig[0, 0] * u0 + sig[0, 1] * u1 + sig[0, 2] * u2
    su1 = sig[1, 0] * u0 + sig[1, 1] * u1 + sig[1, 2] * u2
    su2 = sig[2, 0] * u0 + sig[2, 1] * u1 + sig[2, 2] * u2
    sv0 = sig[0, 0] * v0 + sig[0, 1] * v1 + sig[0, 2] * v2
    sv1 = sig[1, 0] * v0 + sig[1, 1] * v1 + sig[1, 2] * v2
    sv2 = sig[2, 0] * v0 + sig[2, 1] * v1 + sig[2, 2] * v2
    a, b, c = u0 * su0 + u1 * su1 + u2 * su2, u0 * sv0 + u1 * sv1 + u2 * sv2, v0 * sv0 + v1 * sv1 + v2 * sv2
    return a, b, c, su0, su1, su2, sv0, sv1, sv2


_quat_rotation: Any = _quat_rotation_py
_row_norms: Any = _row_norms_py
_off_screen: Any = _off_screen_py
_clamped_xy: Any = _clamped_xy_py
_fov_limits: Any = _fov_limits_py
_screen_cov: Any = _screen_cov_py


def _project_backward_kernel(
    means, quats, scales, viewmats, ks, width, height, vis, v_m2, v_con, v_depth, g_means, g_quats, g_scales, lo, hi
):  # pragma: no cover - compiled
    """d(loss)/d(means [N,3], quats [N,4], scales [N,3]) (input dtype) from the gradients of the visible outputs,
    for the blocks of ``_BLOCK`` Gaussians ``lo..hi-1``, into the zeroed ``g_*``."""
    n = means.shape[0]
    lims = _fov_limits(ks, width, height)
    for blk in range(lo, hi):
        rot, sig, g_sig = np.empty((3, 3), np.float64), np.empty((3, 3), np.float64), np.empty((3, 3), np.float64)
        g_rot, s, gm = np.empty((3, 3), np.float64), np.empty(3, np.float64), np.empty(3, np.float64)
        t = np.empty((2, 3), np.float64)
        for i in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            if _culled(vis, quats, scales, i):  # no camera sees it: its gradients stay zero
                continue
            _backward_one(means, quats, scales, viewmats, ks, lims, vis, v_m2, v_con, v_depth, i,
                          rot, sig, g_sig, g_rot, s, gm, t, g_means, g_quats, g_scales)  # fmt: skip


def _backward_one_py(
    means,
    quats,
    scales,
    viewmats,
    ks,
    lims,
    vis,
    v_m2,
    v_con,
    v_depth,
    i,
    rot,
    sig,
    g_sig,
    g_rot,
    s,
    gm,
    t,
    g_means,
    g_quats,
    g_scales,
):  # pragma: no cover - compiled
    """Gaussian i of :func:`_project_backward_kernel` (the arrays after ``i``: scratch, overwritten)."""
    n_cams = viewmats.shape[0]
    _quat_rotation(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3], rot)
    for k in range(3):
        s[k] = np.float64(scales[i, k])
    for r in range(3):
        for c in range(3):
            acc = 0.0
            for k in range(3):
                acc += rot[r, k] * s[k] * s[k] * rot[c, k]
            sig[r, c] = acc
    g_sig[:, :] = 0.0  # summed over cameras
    gm[:] = 0.0
    for cam in range(n_cams):
        if not vis[cam, i]:
            continue
        w = viewmats[cam]
        x = w[0, 3] + w[0, 0] * means[i, 0] + w[0, 1] * means[i, 1] + w[0, 2] * means[i, 2]
        y = w[1, 3] + w[1, 0] * means[i, 0] + w[1, 1] * means[i, 1] + w[1, 2] * means[i, 2]
        z = w[2, 3] + w[2, 0] * means[i, 0] + w[2, 1] * means[i, 1] + w[2, 2] * means[i, 2]
        fx, fy = ks[cam, 0, 0], ks[cam, 1, 1]
        tx, ty, clamp_x, clamp_y = _clamped_xy(x, y, z, lims[cam])
        rz = 1.0 / z
        j00, j02, j11, j12 = fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz
        a, b, c, su0, su1, su2, sv0, sv1, sv2 = _screen_cov(w, sig, j00, j02, j11, j12)
        a += EPS2D
        c += EPS2D
        det = a * c - b * b
        # conic (c, -b, a) / det -> (a, b, c)
        va_c, vb_c, vc_c = np.float64(v_con[cam, i, 0]), np.float64(v_con[cam, i, 1]), np.float64(v_con[cam, i, 2])
        d2 = det * det
        ga = (-c * c * va_c + b * c * vb_c - b * b * vc_c) / d2
        gb = (2.0 * b * c * va_c - (a * c + b * b) * vb_c + 2.0 * a * b * vc_c) / d2
        gc = (-b * b * va_c + a * b * vb_c - a * a * vc_c) / d2
        # screen covariance G (symmetric) = [[ga, gb/2], [gb/2, gc]]; with T = J W: g_sig += T^T G T
        for k in range(3):
            t[0, k] = j00 * w[0, k] + j02 * w[2, k]
            t[1, k] = j11 * w[1, k] + j12 * w[2, k]
        g01 = 0.5 * gb
        for r in range(3):
            for q in range(3):
                g_sig[r, q] += t[0, r] * (ga * t[0, q] + g01 * t[1, q]) + t[1, r] * (g01 * t[0, q] + gc * t[1, q])
        # d/dJ of J S J^T with S = W Σ W^T: 2 G J S; only J00, J02, J11, J12 are variables. Rows 0 and 1 of
        # J S = J W Σ W^T: (Σ u)^T W^T and (Σ v)^T W^T
        js00 = su0 * w[0, 0] + su1 * w[0, 1] + su2 * w[0, 2]
        js01 = su0 * w[1, 0] + su1 * w[1, 1] + su2 * w[1, 2]
        js02 = su0 * w[2, 0] + su1 * w[2, 1] + su2 * w[2, 2]
        js10 = sv0 * w[0, 0] + sv1 * w[0, 1] + sv2 * w[0, 2]
        js11 = sv0 * w[1, 0] + sv1 * w[1, 1] + sv2 * w[1, 2]
        js12 = sv0 * w[2, 0] + sv1 * w[2, 1] + sv2 * w[2, 2]
        # (G J S)[r, k] = G[r,0] js0[k] + G[r,1] js1[k]
        v_j00 = 2.0 * (ga * js00 + g01 * js10)
        v_j02 = 2.0 * (ga * js02 + g01 * js12)
        v_j11 = 2.0 * (g01 * js01 + gc * js11)
        v_j12 = 2.0 * (g01 * js02 + gc * js12)
        vmx, vmy = np.float64(v_m2[cam, i, 0]), np.float64(v_m2[cam, i, 1])
        v_rz = fx * v_j00 + fy * v_j11 - 2.0 * fx * tx * rz * v_j02 - 2.0 * fy * ty * rz * v_j12
        v_rz += fx * x * vmx + fy * y * vmy
        v_tx = -fx * rz * rz * v_j02
        v_ty = -fy * rz * rz * v_j12
        vx = fx * rz * vmx
        vy = fy * rz * vmy
        vz = -rz * rz * v_rz + np.float64(v_depth[cam, i])
        if clamp_x:
            vz += (tx / z) * v_tx
        else:
            vx += v_tx
        if clamp_y:
            vz += (ty / z) * v_ty
        else:
            vy += v_ty
        for k in range(3):
            gm[k] += w[0, k] * vx + w[1, k] * vy + w[2, k] * vz
    for k in range(3):
        g_means[i, k] = gm[k]
    # Σ = M M^T, M = R diag(s): dM = 2 g_sig M (g_sig symmetric)
    for k in range(3):
        gs = 0.0  # summed in float64, rounded to the output's dtype once
        for r in range(3):
            gmk = 0.0
            for q in range(3):
                gmk += (g_sig[r, q] + g_sig[q, r]) * rot[q, k] * s[k]
            g_rot[r, k] = gmk * s[k]
            gs += gmk * rot[r, k]
        g_scales[i, k] = gs
    _quat_backward(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3], g_rot, g_quats[i])


_backward_one: Any = _backward_one_py


def _culled_py(vis, quats, scales, i):  # pragma: no cover - compiled
    """Whether Gaussian i is visible in no camera, with finite quaternion and scales (so that its gradients are
    zero: non-finite ones still go through the chain rule, which makes them NaN as in the torch projection)."""
    for cam in range(vis.shape[0]):
        if vis[cam, i]:
            return False
    finite = True
    for k in range(4):
        finite &= math.isfinite(quats[i, k])
    for k in range(3):
        finite &= math.isfinite(scales[i, k])
    return finite


_culled: Any = _culled_py


def _quat_backward_py(qw, qx, qy, qz, g, out):  # pragma: no cover - compiled
    """Writes d/dq (wxyz, before normalisation) given d/dR ``g [3,3]`` into ``out [4]``."""
    w, x, y, z = np.float64(qw), np.float64(qx), np.float64(qy), np.float64(qz)
    raw = math.sqrt(w * w + x * x + y * y + z * z)
    nrm = max(raw, 1e-12)
    w, x, y, z = w / nrm, x / nrm, y / nrm, z / nrm
    gw = 2.0 * (-z * g[0, 1] + y * g[0, 2] + z * g[1, 0] - x * g[1, 2] - y * g[2, 0] + x * g[2, 1])
    gx = 2.0 * (y * g[0, 1] + z * g[0, 2] + y * g[1, 0] - 2.0 * x * g[1, 1] - w * g[1, 2])
    gx += 2.0 * (z * g[2, 0] + w * g[2, 1] - 2.0 * x * g[2, 2])
    gy = 2.0 * (-2.0 * y * g[0, 0] + x * g[0, 1] + w * g[0, 2] + x * g[1, 0] + z * g[1, 2])
    gy += 2.0 * (-w * g[2, 0] + z * g[2, 1] - 2.0 * y * g[2, 2])
    gz = 2.0 * (-2.0 * z * g[0, 0] - w * g[0, 1] + x * g[0, 2] + w * g[1, 0] - 2.0 * z * g[1, 1])
    gz += 2.0 * (y * g[1, 2] + x * g[2, 0] + y * g[2, 1])
    if raw < 1e-12:  # below the clamp the normalisation is a fixed scale
        out[0], out[1], out[2], out[3] = gw / nrm, gx / nrm, gy / nrm, gz / nrm
        return
    dot = w * gw + x * gx + y * gy + z * gz
    out[0] = (gw - w * dot) / nrm
    out[1] = (gx - x * dot) / nrm
    out[2] = (gy - y * dot) / nrm
    out[3] = (gz - z * dot) / nrm


_quat_backward: Any = _quat_backward_py


def _project_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_project_kernel`` over the ranges ``bounds [R+1]`` in numba's parallel loop (``run_ranges``'s driver)."""
    for j in _prange(bounds.shape[0] - 1):
        _project_serial(*args, bounds[j], bounds[j + 1])


def _project_backward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_project_backward_kernel`` over the block ranges ``bounds [R+1]`` in numba's parallel loop."""
    for j in _prange(bounds.shape[0] - 1):
        _project_backward_serial(*args, bounds[j], bounds[j + 1])


def compile_kernels(numba: Any) -> tuple[Any, Any]:
    """The projection and its backward (called once by the numba backend's kernel loader): serial kernels
    (``njit_serial``) over ranges of Gaussians, run by ``run_ranges`` on torch's thread count; same arguments and
    results as before they took ranges."""
    global _quat_rotation, _clamped_xy, _fov_limits, _screen_cov, _quat_backward, _backward_one, _culled
    global _row_norms, _off_screen
    global _prange, _project_serial, _project_backward_serial
    helper = njit_serial(numba)
    _quat_rotation = helper(_quat_rotation_py)
    _clamped_xy = helper(_clamped_xy_py)
    _row_norms = helper(_row_norms_py)
    _off_screen = helper(_off_screen_py)
    _fov_limits = helper(_fov_limits_py)
    _screen_cov = helper(_screen_cov_py)
    _quat_backward = helper(_quat_backward_py)
    _culled = helper(_culled_py)
    _backward_one = njit_serial(numba, inline=True)(_backward_one_py)
    fwd, bwd = helper(_project_kernel), helper(_project_backward_kernel)
    _prange, _project_serial, _project_backward_serial = numba.prange, fwd, bwd
    par = njit_driver(numba)
    fwd_par, bwd_par = par(_project_ranges), par(_project_backward_ranges)

    def project(means, quats, scales, opac, viewmats, ks, width, height, near, far):
        """means2d [C,N,2], conics [C,N,3], depths [C,N] (the dtype of ``means``: float64 rounded once, on store),
        radii [C,N,2] int32, visible [C,N] bool."""
        c, n, dt = viewmats.shape[0], means.shape[0], means.dtype
        out = (np.zeros((c, n, 2), dt), np.zeros((c, n, 3), dt), np.zeros((c, n), dt), np.zeros((c, n, 2), np.int32),
               np.zeros((c, n), np.bool_))  # fmt: skip
        run_ranges(fwd, fwd_par, n, means, quats, scales, opac, viewmats, ks, width, height, near, far, *out)
        return out

    def project_backward(means, quats, scales, viewmats, ks, width, height, vis, v_m2, v_con, v_depth):
        """d(loss)/d(means [N,3], quats [N,4], scales [N,3]) in the dtype of ``means`` (float64 inside)."""
        n, dt = means.shape[0], means.dtype
        out = (np.zeros((n, 3), dt), np.zeros((n, 4), dt), np.zeros((n, 3), dt))
        args = (means, quats, scales, viewmats, ks, width, height, vis, v_m2, v_con, v_depth, *out)
        run_ranges(bwd, bwd_par, (n + _BLOCK - 1) // _BLOCK, *args)
        return out

    return project, project_backward


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, ks, width, height, near, far, kernels):
        arrs = [t.detach().contiguous().numpy() for t in (means, quats, scales, opacities)]
        cams = [t.detach().double().contiguous().numpy() for t in (viewmats, ks)]
        m2, con, depth, radii, vis = kernels[0](*arrs, *cams, float(width), float(height), float(near), float(far))
        ctx.kernels, ctx.size, ctx.cams = kernels, (float(width), float(height)), cams
        ctx.save_for_backward(means, quats, scales)
        ctx.vis = vis
        radii_t, vis_t = torch.from_numpy(radii), torch.from_numpy(vis)
        ctx.mark_non_differentiable(radii_t, vis_t)
        return (
            torch.from_numpy(m2),
            torch.from_numpy(con),
            torch.from_numpy(depth),
            radii_t,
            vis_t,
        )

    @staticmethod
    def backward(ctx, v_m2, v_con, v_depth, _r, _v):
        means, quats, scales = ctx.saved_tensors
        c, n = ctx.vis.shape

        def arr(g: torch.Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
            return np.zeros(shape, np.float64) if g is None else g.detach().contiguous().numpy()

        gm, gq, gs = ctx.kernels[1](
            *(t.detach().contiguous().numpy() for t in (means, quats, scales)),
            *ctx.cams,
            *ctx.size,
            ctx.vis,
            arr(v_m2, (c, n, 2)),
            arr(v_con, (c, n, 3)),
            arr(v_depth, (c, n)),
        )
        out = [torch.from_numpy(g) for g in (gm, gq, gs)]
        return out[0], out[1], out[2], None, None, None, None, None, None, None, None


def project_numba(
    kernels: tuple[Any, Any],
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
) -> Projection:
    """:func:`meshsplat.render.projection.project_gaussians` compiled (CPU; no gradient for viewmats/Ks);
    ``kernels`` from :func:`compile_kernels` (on torch's thread count)."""
    m2, con, depth, radii, vis = _Project.apply(
        means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, kernels
    )
    return Projection(means2d=m2, conics=con, depths=depth, radii=radii, visible=vis)
