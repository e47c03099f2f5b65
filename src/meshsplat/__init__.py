"""meshsplat: animatable avatars of 3D Gaussians embedded on a driving mesh.

Subpackages are imported on first use so that ``import meshsplat`` stays light
(no gsplat, smplx or video backends).
"""
from __future__ import annotations

import importlib

__version__ = "0.1.0"

_SUBMODULES = (
    "mesh", "embedding", "gaussians", "render", "train", "data",
    "drivers", "synth", "io", "metrics",
)

__all__ = ["__version__", "MeshsplatError", *_SUBMODULES]

from meshsplat.errors import MeshsplatError  # noqa: E402


def __getattr__(name: str):
    if name in _SUBMODULES:
        return importlib.import_module(f"meshsplat.{name}")
    raise AttributeError(f"module 'meshsplat' has no attribute {name!r}")
