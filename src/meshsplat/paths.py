"""The bundled assets: package data in ``meshsplat/assets`` (licences and attribution in its README.md).

``asset("gltf/CesiumMan.glb")`` looks in ``$MESHSPLAT_ASSETS`` first (a folder laid out the same way,
optional), then in the package. ``resolve_input`` lets any file argument name a bundled asset
(``CesiumMan``, ``RobotExpressive``, ``RiggedSimple``, ``ict``, ``aist_demo``). Nothing outside the
package, or the folder the user names, is ever read.
"""

from __future__ import annotations

import os
from pathlib import Path

from meshsplat.errors import MeshsplatError

__all__ = ["PACKAGE_ASSETS", "BUNDLED", "assets_dir", "asset", "bundled_asset", "resolve_input"]

PACKAGE_ASSETS = Path(__file__).resolve().parent / "assets"

# name a user types -> file below the assets folder
BUNDLED: dict[str, str] = {
    "CesiumMan": "gltf/CesiumMan.glb",
    "RobotExpressive": "gltf/RobotExpressive.glb",
    "RiggedSimple": "gltf/RiggedSimple.glb",
    "ict": "ict_facekit/ict_face_arkit53.npz",
    "aist_demo": "motion/aist_demo.npz",
}
_ALIASES = {"ict_face": "ict", "ict_facekit": "ict", "ict_face_arkit53": "ict"}


def assets_dir() -> Path:
    """The folder of the bundled assets (in a clone: ``src/meshsplat/assets``)."""
    return PACKAGE_ASSETS


def asset(relpath: str) -> Path:
    """Path to a bundled asset such as ``"gltf/CesiumMan.glb"`` (``$MESHSPLAT_ASSETS`` first); raises if missing."""
    extra = os.environ.get("MESHSPLAT_ASSETS")
    for root in ([Path(extra)] if extra else []) + [PACKAGE_ASSETS]:
        if (root / relpath).is_file():
            return root / relpath
    where = f"$MESHSPLAT_ASSETS ({extra}) or " if extra else ""
    raise MeshsplatError(
        f"asset {relpath!r} not found in {where}{PACKAGE_ASSETS}: the installation is incomplete; reinstall meshsplat"
    )


def bundled_asset(name: str) -> Path | None:
    """The bundled file a name stands for (case-insensitive, with or without its extension), else None."""
    p = Path(name)
    if p.name != name:  # a path with folders is a path, not a name
        return None
    lowered = {n.lower(): n for n in BUNDLED}
    canonical = lowered.get(p.stem.lower()) or _ALIASES.get(p.stem.lower())
    if canonical is None or (p.suffix and p.suffix.lower() != Path(BUNDLED[canonical]).suffix):
        return None
    return asset(BUNDLED[canonical])


def resolve_input(arg: str | Path) -> Path:
    """A file argument as a path: an existing path wins, else a bundled asset's name (``CesiumMan``,
    ``aist_demo.npz``, ...), else the path as given (the caller reports it missing)."""
    p = Path(arg)
    if p.exists():
        return p
    return bundled_asset(str(arg)) or p
