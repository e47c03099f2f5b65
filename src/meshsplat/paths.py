"""Where the shared real assets live.

Looked up in order: ``$MESHSPLAT_ASSETS``, ``<project>/../shared/assets``,
``<project>/assets``. Tests skip and the CLI errors clearly when absent.
"""
from __future__ import annotations

import os
from pathlib import Path

from meshsplat.errors import MeshsplatError

__all__ = ["assets_dir", "asset"]

_PROJECT_ROOT = Path(__file__).resolve().parents[2]


def assets_dir() -> Path | None:
    candidates = []
    if os.environ.get("MESHSPLAT_ASSETS"):
        candidates.append(Path(os.environ["MESHSPLAT_ASSETS"]))
    candidates += [_PROJECT_ROOT.parent / "shared" / "assets", _PROJECT_ROOT / "assets"]
    for c in candidates:
        if c.is_dir():
            return c
    return None


def asset(relpath: str) -> Path:
    """Path to a shared asset such as ``"gltf/CesiumMan.glb"``; raises if missing."""
    root = assets_dir()
    if root is None or not (root / relpath).exists():
        raise MeshsplatError(
            f"asset {relpath!r} not found; set MESHSPLAT_ASSETS to the folder holding gltf/ and ict_facekit/"
        )
    return root / relpath
