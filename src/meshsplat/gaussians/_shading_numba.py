"""``Shading.irradiance`` compiled with numba (CPU): the SH2 irradiance of each Gaussian's normal, clamped at 0, plus
its shadowed directional lights, and the gradient, in one pass each. The torch path's ``[N,9] @ [9,3]`` products
run on a slow matrix path for three columns (0.5 ms each at 19k Gaussians, eight of them in a training step).

float64 inside, results in the inputs' dtype. Serial kernels over ranges of Gaussians (``_numba.run_ranges``). The
gradients of the SH coefficients and the lights (sums over the Gaussians) are summed in fixed blocks of
``BLOCK`` Gaussians, then the blocks in order, so the result does not depend on the thread count."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import torch

from meshsplat._numba import njit_driver, njit_serial, run_ranges

__all__ = ["irradiance_compiled", "BLOCK"]

BLOCK = 512  # Gaussians per partial sum of the coefficients' gradient

_C0 = 0.28209479177387814  # the SH2 basis' constants (shading.sh9_basis)
_C1 = 0.4886025119029199
_C2 = 1.0925484305920792
_C20 = 0.31539156525252005
_C22 = 0.5462742152960396


def _forward_kernel(normals, coeffs, dirs, light, visible, out, lo, hi):  # pragma: no cover - compiled
    """``out [N,3]`` for the Gaussians ``lo..hi-1``: ``max(0, SH9(n) . coeffs [9,3])`` plus, for each light ``k``
    (``dirs [K,3]``, ``light [K,3]`` already clamped at 0; K may be 0), ``visible[i,k] max(0, n . dir_k) light_k``."""
    for i in range(lo, hi):
        x, y, z = np.float64(normals[i, 0]), np.float64(normals[i, 1]), np.float64(normals[i, 2])
        for c in range(3):
            s = _C0 * coeffs[0, c] + _C1 * (y * coeffs[1, c] + z * coeffs[2, c] + x * coeffs[3, c])
            s += _C2 * (x * y * coeffs[4, c] + y * z * coeffs[5, c] + x * z * coeffs[7, c])
            s += _C20 * (3.0 * z * z - 1.0) * coeffs[6, c] + _C22 * (x * x - y * y) * coeffs[8, c]
            out[i, c] = max(s, 0.0)
        for k in range(dirs.shape[0]):
            cos = x * dirs[k, 0] + y * dirs[k, 1] + z * dirs[k, 2]
            if cos >= 0.0:
                t = visible[i, k] * cos
                for c in range(3):
                    out[i, c] += t * light[k, c]


def _backward_kernel(
    normals, coeffs, dirs, light, visible, g_out, g_normals, partials, lo, hi
):  # pragma: no cover - compiled
    """For the blocks ``lo..hi-1`` of ``BLOCK`` Gaussians: ``g_normals [N,3]`` and each block's sums of the
    gradients of ``coeffs`` and ``light`` into ``partials [blocks, 9 + K, 3]``, for ``g_out [N,3]``."""
    n = normals.shape[0]
    for blk in range(lo, hi):
        for r in range(partials.shape[1]):
            for c in range(3):
                partials[blk, r, c] = 0.0
        for i in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            x, y, z = np.float64(normals[i, 0]), np.float64(normals[i, 1]), np.float64(normals[i, 2])
            gx = gy = gz = 0.0
            for c in range(3):
                s = _C0 * coeffs[0, c] + _C1 * (y * coeffs[1, c] + z * coeffs[2, c] + x * coeffs[3, c])
                s += _C2 * (x * y * coeffs[4, c] + y * z * coeffs[5, c] + x * z * coeffs[7, c])
                s += _C20 * (3.0 * z * z - 1.0) * coeffs[6, c] + _C22 * (x * x - y * y) * coeffs[8, c]
                if s < 0.0:  # clamp_min: no gradient where clamped
                    continue
                g = np.float64(g_out[i, c])
                partials[blk, 0, c] += _C0 * g
                partials[blk, 1, c] += _C1 * y * g
                partials[blk, 2, c] += _C1 * z * g
                partials[blk, 3, c] += _C1 * x * g
                partials[blk, 4, c] += _C2 * x * y * g
                partials[blk, 5, c] += _C2 * y * z * g
                partials[blk, 6, c] += _C20 * (3.0 * z * z - 1.0) * g
                partials[blk, 7, c] += _C2 * x * z * g
                partials[blk, 8, c] += _C22 * (x * x - y * y) * g
                gx += g * (
                    _C1 * coeffs[3, c] + _C2 * (y * coeffs[4, c] + z * coeffs[7, c]) + 2.0 * _C22 * x * coeffs[8, c]
                )
                gy += g * (
                    _C1 * coeffs[1, c] + _C2 * (x * coeffs[4, c] + z * coeffs[5, c]) - 2.0 * _C22 * y * coeffs[8, c]
                )
                gz += g * (
                    _C1 * coeffs[2, c] + _C2 * (y * coeffs[5, c] + x * coeffs[7, c]) + 6.0 * _C20 * z * coeffs[6, c]
                )
            for k in range(dirs.shape[0]):
                cos = x * dirs[k, 0] + y * dirs[k, 1] + z * dirs[k, 2]
                if cos >= 0.0:
                    vis = np.float64(visible[i, k])
                    g_cos = 0.0
                    for c in range(3):
                        g = np.float64(g_out[i, c])
                        partials[blk, 9 + k, c] += vis * cos * g
                        g_cos += light[k, c] * g
                    g_cos *= vis
                    gx += g_cos * dirs[k, 0]
                    gy += g_cos * dirs[k, 1]
                    gz += g_cos * dirs[k, 2]
            g_normals[i, 0], g_normals[i, 1], g_normals[i, 2] = gx, gy, gz


# Plain Python until _kernels() rebinds them: numba's prange and the serial kernels the parallel drivers call.
_prange: Any = range
_forward_serial: Any = None
_backward_serial: Any = None


def _forward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_forward_kernel`` over the ranges ``bounds [R+1]`` in numba's parallel loop (``run_ranges``'s driver)."""
    for j in _prange(bounds.shape[0] - 1):
        _forward_serial(*args, bounds[j], bounds[j + 1])


def _backward_ranges(bounds, *args):  # pragma: no cover - compiled
    """``_backward_kernel`` over the ranges ``bounds [R+1]`` (of blocks) in numba's parallel loop."""
    for j in _prange(bounds.shape[0] - 1):
        _backward_serial(*args, bounds[j], bounds[j + 1])


@lru_cache(maxsize=1)
def _kernels() -> Any:
    """(forward, backward, forward driver, backward driver)."""
    global _prange, _forward_serial, _backward_serial
    import numba

    ser = njit_serial(numba)
    fwd, bwd = ser(_forward_kernel), ser(_backward_kernel)
    _prange, _forward_serial, _backward_serial = numba.prange, fwd, bwd
    par = njit_driver(numba)
    return fwd, bwd, par(_forward_ranges), par(_backward_ranges)


class _Irradiance(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, normals: torch.Tensor, coeffs: torch.Tensor, dirs: torch.Tensor, light: torch.Tensor,
                visible: torch.Tensor) -> torch.Tensor:  # fmt: skip
        fwd, _, fwd_par, _ = _kernels()
        arrays = tuple(t.detach().contiguous().numpy() for t in (normals, coeffs, dirs, light, visible))
        out = torch.empty(normals.shape[0], 3, dtype=normals.dtype)
        run_ranges(fwd, fwd_par, normals.shape[0], *arrays, out.numpy())
        ctx.arrays = arrays
        return out

    @staticmethod
    def backward(ctx: Any, g_out: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        _, bwd, _, bwd_par = _kernels()
        normals, coeffs, dirs, light, visible = ctx.arrays
        n = normals.shape[0]
        blocks = -(-n // BLOCK)
        g_normals = np.empty_like(normals)
        partials = np.empty((blocks, 9 + dirs.shape[0], 3), np.float64)
        g = g_out.contiguous().numpy()
        run_ranges(bwd, bwd_par, blocks, normals, coeffs, dirs, light, visible, g, g_normals, partials)
        total = np.zeros(partials.shape[1:], np.float64)
        for blk in range(blocks):  # in block order: the same sums on any thread count
            total += partials[blk]
        t = torch.from_numpy(total).to(g_out.dtype)
        return torch.from_numpy(g_normals), t[:9], None, t[9:], None


def irradiance_compiled(
    normals: torch.Tensor,
    coeffs: torch.Tensor,
    directions: torch.Tensor | None = None,
    light: torch.Tensor | None = None,
    visible: torch.Tensor | None = None,
) -> torch.Tensor:
    """``E(n) [N,3]``: ``max(0, SH9(n) . coeffs)`` for unit ``normals [N,3]`` and ``coeffs [9,3]``, plus
    ``visible [N,K] * max(0, n . directions [K,3]) @ max(0, light [K,3])`` when lights are given (CPU tensors);
    differentiable in ``normals``, ``coeffs`` and ``light``."""
    dtype = normals.dtype
    if directions is None or light is None or visible is None:
        directions, light, visible = (torch.zeros(0, 3, dtype=dtype), torch.zeros(0, 3, dtype=dtype),
                                      torch.zeros(normals.shape[0], 0, dtype=dtype))  # fmt: skip
    return _Irradiance.apply(
        normals, coeffs.to(dtype), directions.to(dtype), light.to(dtype).clamp_min(0.0), visible.to(dtype)
    )
