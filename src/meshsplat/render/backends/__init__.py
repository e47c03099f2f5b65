"""Rasterizer backends: ``torch_ref`` (pure PyTorch, any device), ``numba_cpu`` (compiled, CPU) and ``gsplat_cuda``.

gsplat is only looked up here (``find_spec``, no import): importing it is deferred to
``gsplat_cuda`` and happens only for CUDA tensors, since gsplat JIT-compiles CUDA code.
"""

from __future__ import annotations

import importlib.util
import os
from functools import lru_cache

__all__ = ["gsplat_available", "numba_available", "NO_NUMBA_ENV"]

NO_NUMBA_ENV = "MESHSPLAT_NO_NUMBA"  # set to 1: behave as if numba were not installed


@lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """True when the gsplat package can be found (it is not imported)."""
    return importlib.util.find_spec("gsplat") is not None


@lru_cache(maxsize=1)
def _numba_importable() -> bool:
    try:
        import numba  # noqa: F401  (imported, not just found: a broken llvmlite/numpy pairing must fall back)
    except Exception:  # noqa: BLE001 - ImportError, or an incompatible numpy/llvmlite raising at import
        return False
    return True


def numba_available() -> bool:
    """True when numba imports and ``MESHSPLAT_NO_NUMBA`` is not set to a true value (1/true/yes).

    Imports numba on the first call (only CPU rendering asks, and it then uses numba anyway).
    """
    if os.environ.get(NO_NUMBA_ENV, "").strip().lower() in ("1", "true", "yes"):
        return False
    return _numba_importable()
