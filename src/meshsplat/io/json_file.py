"""Reading a JSON object from a file with one clear error line (missing, not JSON, not an object)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from meshsplat.errors import MeshsplatError

__all__ = ["read_json_object"]


def read_json_object(path: str | os.PathLike, expected: str = "a JSON object") -> dict[str, Any]:
    """The object stored in ``path``; ``expected`` says what the file should hold in the error line."""
    path = Path(path)
    if not path.is_file():
        raise MeshsplatError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        raise MeshsplatError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:  # thousands of nested [ or {: no file meshsplat reads nests like that
        raise MeshsplatError(f"{path}: nested too deeply to be {expected}") from None
    if not isinstance(data, dict):
        raise MeshsplatError(f"{path}: expected {expected}, got {type(data).__name__}")
    return data
