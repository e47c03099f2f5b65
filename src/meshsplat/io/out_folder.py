"""The rule for a folder a command writes a capture into: new, or empty, or ``overwrite`` given."""

from __future__ import annotations

import os
from pathlib import Path

from meshsplat.errors import MeshsplatError

__all__ = ["empty_or_new_folder"]


def empty_or_new_folder(out: str | os.PathLike, overwrite: bool = False) -> Path:
    """``out`` as a Path once it is new, an empty folder, or ``overwrite`` is set; nothing is created.

    A file at ``out`` is refused even with ``overwrite`` (writing would need a folder there).
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise MeshsplatError(f"{out}: is a file, not a folder; give a new or empty folder")
    if out.exists() and not overwrite and any(out.iterdir()):
        raise MeshsplatError(f"{out}: exists and is not empty (pass --overwrite, or overwrite=True in Python)")
    return out
