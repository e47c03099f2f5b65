"""Whether numba can be used, and running its parallel kernels on torch's thread count (one home for both the
compiled rasterizer, ``render.backends.numba_cpu``, and the compiled shadow maps, ``mesh.visibility``)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from functools import lru_cache
from typing import Any

__all__ = ["numba_available", "numba_threads", "njit_parallel", "NO_NUMBA_ENV"]

NO_NUMBA_ENV = "MESHSPLAT_NO_NUMBA"  # set to 1: behave as if numba were not installed


@lru_cache(maxsize=1)
def _numba_importable() -> bool:
    try:
        import numba  # noqa: F401  (imported, not just found: a broken llvmlite/numpy pairing must fall back)
    except Exception:  # noqa: BLE001 - ImportError, or an incompatible numpy/llvmlite raising at import
        return False
    return True


def numba_available() -> bool:
    """True when numba imports and ``MESHSPLAT_NO_NUMBA`` is not set to a true value (1/true/yes).

    Imports numba on the first call (only CPU work asks, and it then uses numba anyway).
    """
    if os.environ.get(NO_NUMBA_ENV, "").strip().lower() in ("1", "true", "yes"):
        return False
    return _numba_importable()


@contextlib.contextmanager
def numba_threads() -> Iterator[None]:
    """Run numba's parallel kernels on ``torch.get_num_threads()`` threads (capped by numba's pool), and
    give torch its count back afterwards: numba's OpenMP layer shares the runtime and would raise it."""
    import numba
    import torch

    n = torch.get_num_threads()
    pool = int(getattr(numba.config, "NUMBA_NUM_THREADS", 1))
    numba.set_num_threads(max(1, min(n, pool)))
    try:
        yield
    finally:
        if torch.get_num_threads() != n:
            torch.set_num_threads(n)


def njit_parallel(namespace: dict[str, Any], *kernels: Callable[..., Any]) -> tuple[Any, ...]:
    """The plain-Python ``kernels`` wrapped by ``numba.njit(parallel=True)`` (cached on disk, no fastmath), after
    binding ``_prange`` in their module's ``namespace`` (its ``globals()``) to ``numba.prange``: the kernels are
    written with ``for i in _prange(n)``, which runs as a plain loop until then. Imports numba."""
    import numba

    namespace["_prange"] = numba.prange
    par = numba.njit(parallel=True, cache=True, fastmath=False, nogil=True)
    return tuple(par(k) for k in kernels)
