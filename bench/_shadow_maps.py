"""Shared by the bench scripts that time the key light's shadow maps against their torch baseline."""

from __future__ import annotations

import meshsplat.mesh.visibility as _visibility
from meshsplat._numba import numba_available


def use_torch_maps(on: bool) -> None:
    """Build ``mesh.visibility``'s shadow maps in pure torch (``on``: as without numba) or compiled when numba
    is installed (the default); the rasterizer is not affected."""
    _visibility.numba_available = (lambda: False) if on else numba_available
