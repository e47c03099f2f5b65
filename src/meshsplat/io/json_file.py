"""Reading a JSON (or YAML) object from a file with one clear error line (missing, not parseable, not an object)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from meshsplat.errors import MeshsplatError

__all__ = ["read_json_object", "read_config_file", "YAML_SUFFIXES"]

YAML_SUFFIXES = (".yaml", ".yml")


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


def read_config_file(path: str | os.PathLike) -> dict[str, Any]:
    """The object in a config file: YAML for ``.yaml`` / ``.yml`` (safe loading: plain data only), else JSON."""
    path = Path(path)
    if path.suffix.lower() not in YAML_SUFFIXES:
        return read_json_object(path, "a training config (an object of sections and keys)")
    import yaml  # a base dependency, imported when a YAML file is read

    if not path.is_file():
        raise MeshsplatError(f"{path}: file not found")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MeshsplatError(f"{path}: not valid YAML ({first})") from None
    except RecursionError:
        raise MeshsplatError(f"{path}: nested too deeply to be a training config") from None
    if data is None:
        data = {}  # an empty file: nothing changed
    if not isinstance(data, dict):
        raise MeshsplatError(
            f"{path}: expected a training config (an object of sections and keys), got {type(data).__name__}"
        )
    return data
