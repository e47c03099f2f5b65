"""``albedo_prior.albedo_smoothness`` compiled with numba (CPU): the value and its gradient in two passes over the
pairs, without the ``[N,k,3]`` temporaries of the torch path. float64 inside. Each Gaussian's row is summed by
one thread and the rows, and the gradient's scatter to the neighbours, in a fixed serial order, so the result
does not depend on the thread count (training stays bit-reproducible)."""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
import torch

from meshsplat._numba import njit_parallel, numba_threads

_prange: Any = range  # rebound to numba.prange when the kernels are compiled


def _forward_kernel(a, nb, inv_sigma2, w):  # pragma: no cover - compiled
    """The sum over pairs of ``w |a_i - a_j|`` for albedos ``a [N,3]`` and neighbours ``nb [N,k]``; fills the
    weights ``w [N,k]``."""
    n, k = nb.shape
    chroma = np.empty((n, 3), np.float64)  # the albedo clamped at 1e-4, over its sum (as the torch path)
    for i in _prange(n):
        c0, c1, c2 = max(a[i, 0], 1e-4), max(a[i, 1], 1e-4), max(a[i, 2], 1e-4)
        s = c0 + c1 + c2
        chroma[i, 0], chroma[i, 1], chroma[i, 2] = c0 / s, c1 / s, c2 / s
    rows = np.zeros(n, np.float64)
    for i in _prange(n):
        acc = 0.0
        for q in range(k):
            j = nb[i, q]
            d2 = (chroma[i, 0] - chroma[j, 0]) ** 2 + (chroma[i, 1] - chroma[j, 1]) ** 2
            d2 += (chroma[i, 2] - chroma[j, 2]) ** 2
            wq = math.exp(-d2 * inv_sigma2)
            w[i, q] = wq
            acc += wq * (abs(a[i, 0] - a[j, 0]) + abs(a[i, 1] - a[j, 1]) + abs(a[i, 2] - a[j, 2]))
        rows[i] = acc
    total = 0.0
    for i in range(n):
        total += rows[i]
    return total


def _backward_kernel(a, nb, w, scale):  # pragma: no cover - compiled
    """The gradient ``[N,3]`` of ``scale`` times the forward's sum by ``a``."""
    n, k = nb.shape
    term = np.empty((n, k, 3), np.float64)  # each pair's term of d/da_i; -term is its term of d/da_j
    grad = np.zeros((n, 3), np.float64)
    for i in _prange(n):
        for q in range(k):
            j = nb[i, q]
            for c in range(3):
                d = a[i, c] - a[j, c]
                t = scale * w[i, q] * (np.float64(d > 0.0) - np.float64(d < 0.0))  # 0 where equal, as torch's
                term[i, q, c] = t
                grad[i, c] += t
    for i in range(n):  # to the neighbours, in a fixed order
        for q in range(k):
            j = nb[i, q]
            for c in range(3):
                grad[j, c] -= term[i, q, c]
    return grad


@lru_cache(maxsize=1)
def _kernels() -> Any:
    return njit_parallel(globals(), _forward_kernel, _backward_kernel)


class _AlbedoPrior(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, a: torch.Tensor, nb: torch.Tensor, inv_sigma2: float) -> torch.Tensor:
        fwd, _ = _kernels()
        a64 = np.ascontiguousarray(a.detach().numpy(), dtype=np.float64)
        nb64 = np.ascontiguousarray(nb.numpy(), dtype=np.int64)
        w = np.empty(nb64.shape, np.float64)
        with numba_threads():
            total = fwd(a64, nb64, inv_sigma2, w)
        ctx.saved = (a64, nb64, w, a.dtype)
        return torch.tensor(total / (nb64.size * 3), dtype=a.dtype)

    @staticmethod
    def backward(ctx: Any, grad_out: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        _, bwd = _kernels()
        a64, nb64, w, dtype = ctx.saved
        with numba_threads():
            grad = bwd(a64, nb64, w, float(grad_out) / (nb64.size * 3))
        return torch.from_numpy(grad).to(dtype), None, None


def albedo_smoothness_compiled(a: torch.Tensor, neighbours: torch.Tensor, sigma: float) -> torch.Tensor:
    """The prior's mean ``w |a_i - a_j|`` over the pairs of ``neighbours [N,k]`` (``k >= 1``) for the albedos
    ``a [N,3]`` (CPU), chromaticity weights at ``sigma``; differentiable in ``a``."""
    return _AlbedoPrior.apply(a, neighbours, 1.0 / sigma**2)
