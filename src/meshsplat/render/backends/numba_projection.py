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

One camera (every training render) takes other kernels, ``_project_one_kernel`` and its backward: the same
operations in the same order with the cameras' loop, the scratch matrices and the branches gone, so that LLVM
turns the loop over Gaussians into vector code, 4 float64 lanes (``projection_llvm_options``). The same bits as the
general kernels; 500k @ 512², one thread, Zen 3: forward 44-47 -> 21-23 ms, backward 61-64 -> 24-30 ms
(bench/reports/raster_cpu.md).
"""

from __future__ import annotations

import math
from functools import partial
from typing import Any

import numpy as np
import torch

from meshsplat._numba import host_is_arm64, llvm_options, njit_driver, njit_serial, run_ranges, run_ranges_compiling_in
from meshsplat.render._constants import ALPHA_THRESHOLD, EPS2D, FOV_CLAMP_MARGIN, MAX_EXTEND
from meshsplat.render.projection import Projection

__all__ = ["project_numba"]

_INT32_MAX = 2147483647.0  # radii are capped here: a larger one (a splat at the camera plane) would wrap
_BLOCK = 256  # Gaussians per block of the backward (scratch arrays allocated once per block)
# Plain Python until compile_kernels() rebinds them: numba's prange and the serial kernels the drivers call.
_prange: Any = range
_project_serial: Any = None
_project_backward_serial: Any = None
_project_one_serial: Any = None
_project_one_backward_serial: Any = None


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
            radii[cam, i, 0], radii[cam, i, 1] = int(min(rx, _INT32_MAX)), int(min(ry, _INT32_MAX))  # no wrap
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


# ---- one camera: vector code over Gaussians ----------------------------------------------------------------------
# A training render has one camera. These kernels take the Gaussians in a plain loop with no inner loop, call or
# scratch array: LLVM vectorizes it across Gaussians (4 float64 lanes, ``projection_llvm_options``), branches become
# selects, and every lane runs the whole chain (the screen cull of the general kernel saves no work in vector code).
# The same float64 operations in the same order as the general kernels: the same bits (tested). Arrays are flat
# (``[N*3]`` for ``[N,3]``) and indexed by unsigned integers: LLVM then knows each access's stride and bounds (a
# 2-D numba array's row stride is a run-time value, and a signed index carries numba's wraparound).
_U1, _U2, _U3, _U4 = np.uint64(1), np.uint64(2), np.uint64(3), np.uint64(4)


def _camera_vector(viewmats: np.ndarray, ks: np.ndarray, width: float, height: float) -> np.ndarray:
    """``[20]`` float64: camera 0's view matrix rows 0-2 (12), fx, fy, cx, cy and its ``_fov_limits`` (4)."""
    k = ks[0]
    return np.concatenate([viewmats[0, :3, :].reshape(-1), [k[0, 0], k[1, 1], k[0, 2], k[1, 2]],
                           _fov_limits_py(ks[:1], width, height)[0]]).astype(np.float64)  # fmt: skip


def _project_one_kernel(
    means, quats, scales, opac, cam, width, height, near, far, m2, con, depth, radii, vis, lo, hi
):  # pragma: no cover - compiled
    """``_project_kernel`` for one camera (``cam``: ``_camera_vector``), flat arrays: means, scales ``[N*3]``, quats
    ``[N*4]``, opac ``[N]``; into the zeroed means2d ``[N*2]``, conics ``[N*3]``, depths ``[N]``, radii ``[N*2]``,
    visible ``[N]``."""
    ext = np.empty(hi - lo, np.float64)  # the opacity's extent (a log: libm, not vector code), -1: culled
    for i in range(lo, hi):
        op = np.float64(opac[i])
        e = min(math.sqrt(2.0 * math.log(max(op, ALPHA_THRESHOLD) / ALPHA_THRESHOLD)), MAX_EXTEND)
        ext[i - lo] = -1.0 if op < ALPHA_THRESHOLD else e
    cv = _camera_values(cam)
    fx, fy, cx, cy = cv[12], cv[13], cv[14], cv[15]
    ulo = np.uint64(lo)
    for i in range(ulo, np.uint64(hi)):
        x, y, z, _, _, _, _, rz, j00, j02, j11, j12 = _view_of(cv, means, i)
        mx = fx * x * rz + cx
        my = fy * y * rz + cy
        R00, R01, R02, R10, R11, R12, R20, R21, R22 = _rotation_of(quats, i)
        s0, s1, s2 = _scales_of(scales, i)
        S00, S01, S02, S10, S11, S12, S20, S21, S22 = _covariance_of(
            R00, R01, R02, R10, R11, R12, R20, R21, R22, s0, s1, s2
        )
        a, b, c, _, _, _, _, _, _, _, _, _, _, _, _ = _screen_of(cv, j00, j02, j11, j12, S00, S01, S02, S10, S11,
                                                                S12, S20, S21, S22)  # fmt: skip
        det = a * c - b * b
        e = ext[i - ulo]
        rx = math.ceil(e * math.sqrt(max(a, 0.0)))
        ry = math.ceil(e * math.sqrt(max(c, 0.0)))
        ok = (near <= z) & (z <= far) & (det > 0.0) & ((rx > 0) | (ry > 0))
        ok = ok and not ((mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height))
        vis[i] = ok
        radii[_U2 * i] = np.int32(min(rx, _INT32_MAX)) if ok else np.int32(0)
        radii[_U2 * i + _U1] = np.int32(min(ry, _INT32_MAX)) if ok else np.int32(0)
        m2[_U2 * i] = mx if ok else 0.0
        m2[_U2 * i + _U1] = my if ok else 0.0
        con[_U3 * i] = c / det if ok else 0.0
        con[_U3 * i + _U1] = -b / det if ok else 0.0
        con[_U3 * i + _U2] = a / det if ok else 0.0
        depth[i] = z if ok else 0.0


def _rotation_of_py(quats, i):  # pragma: no cover - compiled (inlined)
    """The rotation matrix (9 float64, row by row) of quaternion ``i`` of the flat ``quats [N*4]``, as
    ``_quat_rotation_py``."""
    w, x = np.float64(quats[_U4 * i]), np.float64(quats[_U4 * i + _U1])
    y, z = np.float64(quats[_U4 * i + _U2]), np.float64(quats[_U4 * i + _U3])
    nrm = max(math.sqrt(w * w + x * x + y * y + z * z), 1e-12)
    w, x, y, z = w / nrm, x / nrm, y / nrm, z / nrm
    return (
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )  # fmt: skip


_rotation_of: Any = _rotation_of_py


def _covariance_of_py(R00, R01, R02, R10, R11, R12, R20, R21, R22, s0, s1, s2):  # pragma: no cover - compiled
    """``R S S^T R^T`` (9 float64, row by row) summed as the general kernels sum it."""
    return (
        0.0 + R00 * s0 * s0 * R00 + R01 * s1 * s1 * R01 + R02 * s2 * s2 * R02,
        0.0 + R00 * s0 * s0 * R10 + R01 * s1 * s1 * R11 + R02 * s2 * s2 * R12,
        0.0 + R00 * s0 * s0 * R20 + R01 * s1 * s1 * R21 + R02 * s2 * s2 * R22,
        0.0 + R10 * s0 * s0 * R00 + R11 * s1 * s1 * R01 + R12 * s2 * s2 * R02,
        0.0 + R10 * s0 * s0 * R10 + R11 * s1 * s1 * R11 + R12 * s2 * s2 * R12,
        0.0 + R10 * s0 * s0 * R20 + R11 * s1 * s1 * R21 + R12 * s2 * s2 * R22,
        0.0 + R20 * s0 * s0 * R00 + R21 * s1 * s1 * R01 + R22 * s2 * s2 * R02,
        0.0 + R20 * s0 * s0 * R10 + R21 * s1 * s1 * R11 + R22 * s2 * s2 * R12,
        0.0 + R20 * s0 * s0 * R20 + R21 * s1 * s1 * R21 + R22 * s2 * s2 * R22,
    )


_covariance_of: Any = _covariance_of_py


def _camera_values_py(cam):  # pragma: no cover - compiled (inlined)
    """``cam`` (``_camera_vector``) as a tuple of 20 float64, read once before a kernel's loop: values the helpers
    below index at constant positions (reading the array inside the loop stops LLVM from vectorizing it)."""
    return (
        cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7], cam[8], cam[9],
        cam[10], cam[11], cam[12], cam[13], cam[14], cam[15], cam[16], cam[17], cam[18], cam[19],
    )  # fmt: skip


_camera_values: Any = _camera_values_py


def _scales_of_py(scales, i):  # pragma: no cover - compiled (inlined)
    """Gaussian ``i``'s scales (3 float64) from the flat ``scales [N*3]``."""
    return np.float64(scales[_U3 * i]), np.float64(scales[_U3 * i + _U1]), np.float64(scales[_U3 * i + _U2])


_scales_of: Any = _scales_of_py


def _view_of_py(cv, means, i):  # pragma: no cover - compiled (inlined)
    """Gaussian ``i``'s mean in the camera ``cv`` (``_camera_values``): ``x, y, z``, the field-of-view-clamped ``tx =
    z clamp(x / z)``, ``ty``, whether each is clamped, ``rz = 1 / z`` and the Jacobian's ``j00, j02, j11, j12``
    (``_clamped_xy_py`` and the general kernels' lines, in their order)."""
    px, py, pz = np.float64(means[_U3 * i]), np.float64(means[_U3 * i + _U1]), np.float64(means[_U3 * i + _U2])
    x = cv[3] + cv[0] * px + cv[1] * py + cv[2] * pz
    y = cv[7] + cv[4] * px + cv[5] * py + cv[6] * pz
    z = cv[11] + cv[8] * px + cv[9] * py + cv[10] * pz
    ux = min(cv[16], max(-cv[17], x / z))
    uy = min(cv[18], max(-cv[19], y / z))
    rz = 1.0 / z
    tx, ty = z * ux, z * uy
    fx, fy = cv[12], cv[13]
    return x, y, z, tx, ty, ux != x / z, uy != y / z, rz, fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz


_view_of: Any = _view_of_py


def _screen_of_py(cv, j00, j02, j11, j12, S00, S01, S02, S10, S11, S12, S20, S21, S22):  # pragma: no cover
    """``_screen_cov_py`` for the camera ``cv`` with the dilation: ``a, b, c`` of ``J W Σ W^T J^T + EPS2D``, the rows
    ``u, v`` of ``J W`` and ``Σ u``, ``Σ v``."""
    w00, w01, w02, w10, w11, w12, w20, w21, w22 = (
        cv[0],
        cv[1],
        cv[2],
        cv[4],
        cv[5],
        cv[6],
        cv[8],
        cv[9],
        cv[10],
    )
    u0, u1, u2 = j00 * w00 + j02 * w20, j00 * w01 + j02 * w21, j00 * w02 + j02 * w22
    v0, v1, v2 = j11 * w10 + j12 * w20, j11 * w11 + j12 * w21, j11 * w12 + j12 * w22
    su0, su1, su2 = S00 * u0 + S01 * u1 + S02 * u2, S10 * u0 + S11 * u1 + S12 * u2, S20 * u0 + S21 * u1 + S22 * u2
    sv0, sv1, sv2 = S00 * v0 + S01 * v1 + S02 * v2, S10 * v0 + S11 * v1 + S12 * v2, S20 * v0 + S21 * v1 + S22 * v2
    a = u0 * su0 + u1 * su1 + u2 * su2 + EPS2D
    b = u0 * sv0 + u1 * sv1 + u2 * sv2
    c = v0 * sv0 + v1 * sv1 + v2 * sv2 + EPS2D
    return a, b, c, u0, u1, u2, v0, v1, v2, su0, su1, su2, sv0, sv1, sv2


_screen_of: Any = _screen_of_py


def _project_one_backward_kernel(
    means, quats, scales, cam, vis, v_m2, v_con, v_depth, g_means, g_quats, g_scales, lo, hi
):  # pragma: no cover - compiled
    """``_project_backward_kernel`` for one camera, flat arrays as ``_project_one_kernel``'s (the gradients ``v_m2
    [N*2]``, ``v_con [N*3]``, ``v_depth [N]``; into ``g_means``, ``g_scales [N*3]``, ``g_quats [N*4]``). A Gaussian
    the camera does not see, with finite quaternion and scales, keeps zero gradients (``_culled_py``)."""
    cv = _camera_values(cam)
    w00, w01, w02, w10, w11, w12 = cv[0], cv[1], cv[2], cv[4], cv[5], cv[6]
    w20, w21, w22, fx, fy = cv[8], cv[9], cv[10], cv[12], cv[13]
    for i in range(np.uint64(lo), np.uint64(hi)):
        seen = vis[i]
        qw, qx = np.float64(quats[_U4 * i]), np.float64(quats[_U4 * i + _U1])
        qy, qz = np.float64(quats[_U4 * i + _U2]), np.float64(quats[_U4 * i + _U3])
        s0, s1, s2 = _scales_of(scales, i)
        finite = math.isfinite(qw) & math.isfinite(qx) & math.isfinite(qy) & math.isfinite(qz)
        keep = seen or not (finite & math.isfinite(s0) & math.isfinite(s1) & math.isfinite(s2))
        R00, R01, R02, R10, R11, R12, R20, R21, R22 = _rotation_of(quats, i)
        S00, S01, S02, S10, S11, S12, S20, S21, S22 = _covariance_of(
            R00, R01, R02, R10, R11, R12, R20, R21, R22, s0, s1, s2
        )
        # the camera's part (_backward_one_py), kept where the camera sees the Gaussian
        x, y, z, tx, ty, clamp_x, clamp_y, rz, j00, j02, j11, j12 = _view_of(cv, means, i)
        a, b, c, t00, t01, t02, t10, t11, t12, su0, su1, su2, sv0, sv1, sv2 = _screen_of(
            cv, j00, j02, j11, j12, S00, S01, S02, S10, S11, S12, S20, S21, S22
        )
        det = a * c - b * b
        va_c, vb_c, vc_c = (
            np.float64(v_con[_U3 * i]),
            np.float64(v_con[_U3 * i + _U1]),
            np.float64(v_con[_U3 * i + _U2]),
        )
        d2 = det * det
        ga = (-c * c * va_c + b * c * vb_c - b * b * vc_c) / d2
        gb = (2.0 * b * c * va_c - (a * c + b * b) * vb_c + 2.0 * a * b * vc_c) / d2
        gc = (-b * b * va_c + a * b * vb_c - a * a * vc_c) / d2
        hb = 0.5 * gb
        js00, js01, js02 = (
            su0 * w00 + su1 * w01 + su2 * w02,
            su0 * w10 + su1 * w11 + su2 * w12,
            su0 * w20 + su1 * w21 + su2 * w22,
        )
        js10, js11, js12 = (
            sv0 * w00 + sv1 * w01 + sv2 * w02,
            sv0 * w10 + sv1 * w11 + sv2 * w12,
            sv0 * w20 + sv1 * w21 + sv2 * w22,
        )
        v_j00 = 2.0 * (ga * js00 + hb * js10)
        v_j02 = 2.0 * (ga * js02 + hb * js12)
        v_j11 = 2.0 * (hb * js01 + gc * js11)
        v_j12 = 2.0 * (hb * js02 + gc * js12)
        vmx, vmy = np.float64(v_m2[_U2 * i]), np.float64(v_m2[_U2 * i + _U1])
        v_rz = fx * v_j00 + fy * v_j11 - 2.0 * fx * tx * rz * v_j02 - 2.0 * fy * ty * rz * v_j12
        v_rz += fx * x * vmx + fy * y * vmy
        v_tx = -fx * rz * rz * v_j02
        v_ty = -fy * rz * rz * v_j12
        vx = fx * rz * vmx
        vy = fy * rz * vmy
        vz = -rz * rz * v_rz + np.float64(v_depth[i])
        vz = vz + (tx / z) * v_tx if clamp_x else vz
        vx = vx if clamp_x else vx + v_tx
        vz = vz + (ty / z) * v_ty if clamp_y else vz
        vy = vy if clamp_y else vy + v_ty
        gm0 = 0.0 + (w00 * vx + w10 * vy + w20 * vz) if seen else 0.0
        gm1 = 0.0 + (w01 * vx + w11 * vy + w21 * vz) if seen else 0.0
        gm2 = 0.0 + (w02 * vx + w12 * vy + w22 * vz) if seen else 0.0
        # g_sig (G, symmetric sums of the screen covariance's gradient) back to the scales and the rotation
        G00 = 0.0 + (t00 * (ga * t00 + hb * t10) + t10 * (hb * t00 + gc * t10)) if seen else 0.0
        G01 = 0.0 + (t00 * (ga * t01 + hb * t11) + t10 * (hb * t01 + gc * t11)) if seen else 0.0
        G02 = 0.0 + (t00 * (ga * t02 + hb * t12) + t10 * (hb * t02 + gc * t12)) if seen else 0.0
        G10 = 0.0 + (t01 * (ga * t00 + hb * t10) + t11 * (hb * t00 + gc * t10)) if seen else 0.0
        G11 = 0.0 + (t01 * (ga * t01 + hb * t11) + t11 * (hb * t01 + gc * t11)) if seen else 0.0
        G12 = 0.0 + (t01 * (ga * t02 + hb * t12) + t11 * (hb * t02 + gc * t12)) if seen else 0.0
        G20 = 0.0 + (t02 * (ga * t00 + hb * t10) + t12 * (hb * t00 + gc * t10)) if seen else 0.0
        G21 = 0.0 + (t02 * (ga * t01 + hb * t11) + t12 * (hb * t01 + gc * t11)) if seen else 0.0
        G22 = 0.0 + (t02 * (ga * t02 + hb * t12) + t12 * (hb * t02 + gc * t12)) if seen else 0.0
        m00 = 0.0 + (G00 + G00) * R00 * s0 + (G01 + G10) * R10 * s0 + (G02 + G20) * R20 * s0
        m10 = 0.0 + (G10 + G01) * R00 * s0 + (G11 + G11) * R10 * s0 + (G12 + G21) * R20 * s0
        m20 = 0.0 + (G20 + G02) * R00 * s0 + (G21 + G12) * R10 * s0 + (G22 + G22) * R20 * s0
        m01 = 0.0 + (G00 + G00) * R01 * s1 + (G01 + G10) * R11 * s1 + (G02 + G20) * R21 * s1
        m11 = 0.0 + (G10 + G01) * R01 * s1 + (G11 + G11) * R11 * s1 + (G12 + G21) * R21 * s1
        m21 = 0.0 + (G20 + G02) * R01 * s1 + (G21 + G12) * R11 * s1 + (G22 + G22) * R21 * s1
        m02 = 0.0 + (G00 + G00) * R02 * s2 + (G01 + G10) * R12 * s2 + (G02 + G20) * R22 * s2
        m12 = 0.0 + (G10 + G01) * R02 * s2 + (G11 + G11) * R12 * s2 + (G12 + G21) * R22 * s2
        m22 = 0.0 + (G20 + G02) * R02 * s2 + (G21 + G12) * R12 * s2 + (G22 + G22) * R22 * s2
        gs0 = 0.0 + m00 * R00 + m10 * R10 + m20 * R20
        gs1 = 0.0 + m01 * R01 + m11 * R11 + m21 * R21
        gs2 = 0.0 + m02 * R02 + m12 * R12 + m22 * R22
        h00, h01, h02 = m00 * s0, m01 * s1, m02 * s2
        h10, h11, h12 = m10 * s0, m11 * s1, m12 * s2
        h20, h21, h22 = m20 * s0, m21 * s1, m22 * s2
        g_means[_U3 * i] = gm0 if keep else 0.0
        g_means[_U3 * i + _U1] = gm1 if keep else 0.0
        g_means[_U3 * i + _U2] = gm2 if keep else 0.0
        g_scales[_U3 * i] = gs0 if keep else 0.0
        g_scales[_U3 * i + _U1] = gs1 if keep else 0.0
        g_scales[_U3 * i + _U2] = gs2 if keep else 0.0
        # _quat_backward_py with g = (h)
        raw = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        nrm = max(raw, 1e-12)
        w, x, y, z = qw / nrm, qx / nrm, qy / nrm, qz / nrm
        gw = 2.0 * (-z * h01 + y * h02 + z * h10 - x * h12 - y * h20 + x * h21)
        gx = 2.0 * (y * h01 + z * h02 + y * h10 - 2.0 * x * h11 - w * h12)
        gx += 2.0 * (z * h20 + w * h21 - 2.0 * x * h22)
        gy = 2.0 * (-2.0 * y * h00 + x * h01 + w * h02 + x * h10 + z * h12)
        gy += 2.0 * (-w * h20 + z * h21 - 2.0 * y * h22)
        gz = 2.0 * (-2.0 * z * h00 - w * h01 + x * h02 + w * h10 - 2.0 * z * h11)
        gz += 2.0 * (y * h12 + x * h20 + y * h21)
        dot = w * gw + x * gx + y * gy + z * gz
        small = raw < 1e-12  # below the clamp the normalisation is a fixed scale
        g_quats[_U4 * i] = (gw / nrm if small else (gw - w * dot) / nrm) if keep else 0.0
        g_quats[_U4 * i + _U1] = (gx / nrm if small else (gx - x * dot) / nrm) if keep else 0.0
        g_quats[_U4 * i + _U2] = (gy / nrm if small else (gy - y * dot) / nrm) if keep else 0.0
        g_quats[_U4 * i + _U3] = (gz / nrm if small else (gz - z * dot) / nrm) if keep else 0.0


def projection_llvm_options() -> dict[str, int]:
    """The LLVM options the one-camera kernels compile with (``_numba.llvm_options``): 4 float64 lanes on an x86-64
    host (LLVM's cost model leaves the loop scalar on a Zen 3 host: 40 ms against 15 at 500k Gaussians), 2 on arm64
    (one NEON register; LLVM leaves the loop scalar there too: code seen under qemu-aarch64, speed not measured),
    enough run-time checks for the loop's 9 arrays and index assumptions; LLVM's own width elsewhere and where
    numba compiles for another x86-64 CPU than the host (``NUMBA_CPU_NAME``/``NUMBA_CPU_FEATURES``)."""
    import platform

    import numba

    config: Any = numba.config
    if host_is_arm64():
        width = 2
    else:
        x86 = platform.machine().lower() in ("x86_64", "amd64")
        width = 4 if x86 and not (config.CPU_NAME or config.CPU_FEATURES) else 0
    return {"force-vector-width": width, "vectorize-scev-check-threshold": 512, "runtime-memory-check-threshold": 64}


def _project_one_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_project_one_kernel`` over the ranges ``bounds [R+1]`` in numba's parallel loop."""
    for j in _prange(bounds.shape[0] - 1):
        _project_one_serial(*args, bounds[j], bounds[j + 1])


def _project_one_backward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_project_one_backward_kernel`` over the ranges ``bounds [R+1]`` in numba's parallel loop."""
    for j in _prange(bounds.shape[0] - 1):
        _project_one_backward_serial(*args, bounds[j], bounds[j + 1])


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
    global _row_norms, _off_screen, _rotation_of, _covariance_of, _scales_of, _view_of, _screen_of, _camera_values
    global _prange, _project_serial, _project_backward_serial, _project_one_serial, _project_one_backward_serial
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
    # one camera: vector code, compiled inside LLVM options (on the first call of each kind, or ahead)
    in_options = partial(llvm_options, projection_llvm_options())
    _rotation_of = njit_serial(numba, inline=True)(_rotation_of_py)
    _covariance_of = njit_serial(numba, inline=True)(_covariance_of_py)
    _scales_of = njit_serial(numba, inline=True)(_scales_of_py)
    _view_of = njit_serial(numba, inline=True)(_view_of_py)
    _camera_values = njit_serial(numba, inline=True)(_camera_values_py)
    _screen_of = njit_serial(numba, inline=True)(_screen_of_py)
    one = njit_serial(numba, compile_context=in_options)
    fwd1, bwd1 = one(_project_one_kernel), one(_project_one_backward_kernel)
    _project_one_serial, _project_one_backward_serial = fwd1, bwd1
    par1 = njit_driver(numba, compile_context=in_options)
    fwd1_par, bwd1_par = par1(_project_one_ranges), par1(_project_one_backward_ranges)
    seen: set[tuple[Any, ...]] = set()

    def project(means, quats, scales, opac, viewmats, ks, width, height, near, far):
        """means2d [C,N,2], conics [C,N,3], depths [C,N] (the dtype of ``means``: float64 rounded once, on store),
        radii [C,N,2] int32, visible [C,N] bool."""
        c, n, dt = viewmats.shape[0], means.shape[0], means.dtype
        make = np.empty if c == 1 else np.zeros  # the one-camera kernel writes every element
        out = (make((c, n, 2), dt), make((c, n, 3), dt), make((c, n), dt), make((c, n, 2), np.int32),
               make((c, n), np.bool_))  # fmt: skip
        if c == 1:
            cam = _camera_vector(viewmats, ks, width, height)
            flat = (means.reshape(-1), quats.reshape(-1), scales.reshape(-1), opac.reshape(-1), cam)
            args = (*flat, width, height, near, far, *(o.reshape(-1) for o in out))
            run_ranges_compiling_in(in_options, seen, ("fwd", dt, quats.dtype), fwd1, fwd1_par, n, *args)
            return out
        run_ranges(fwd, fwd_par, n, means, quats, scales, opac, viewmats, ks, width, height, near, far, *out)
        return out

    def project_backward(means, quats, scales, viewmats, ks, width, height, vis, v_m2, v_con, v_depth):
        """d(loss)/d(means [N,3], quats [N,4], scales [N,3]) in the dtype of ``means`` (float64 inside)."""
        n, dt = means.shape[0], means.dtype
        make = np.empty if vis.shape[0] == 1 else np.zeros  # the one-camera kernel writes every element
        out = (make((n, 3), dt), make((n, 4), dt), make((n, 3), dt))
        if vis.shape[0] == 1:
            cam = _camera_vector(viewmats, ks, width, height)
            grads = (vis, v_m2, v_con, v_depth)
            args = (means.reshape(-1), quats.reshape(-1), scales.reshape(-1), cam, *(g.reshape(-1) for g in grads))
            key = ("bwd", dt, quats.dtype, v_m2.dtype)
            run_ranges_compiling_in(in_options, seen, key, bwd1, bwd1_par, n, *args, *(o.reshape(-1) for o in out))
            return out
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
