"""Rasterizer backends: ``torch_ref`` (pure PyTorch, any device), ``numba_cpu`` (compiled, CPU) and ``gsplat_cuda``.

gsplat is only looked up here (``find_spec``, no import): importing it is deferred to
``gsplat_cuda`` and happens only for CUDA tensors, since gsplat JIT-compiles CUDA code.
"""

from __future__ import annotations

import importlib.util
from functools import lru_cache

from meshsplat._numba import NO_NUMBA_ENV, numba_available

__all__ = ["gsplat_available", "numba_available", "NO_NUMBA_ENV"]


@lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """True when the gsplat package can be found (it is not imported)."""
    return importlib.util.find_spec("gsplat") is not None
