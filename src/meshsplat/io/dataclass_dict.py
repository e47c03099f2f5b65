"""Nested dataclasses from plain dicts (JSON, YAML, ``key=value`` strings): every key known, every value
coerced to its field's type or one clear error line naming the key. Nothing is ever evaluated."""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Iterator
from typing import Any

from meshsplat.errors import MeshsplatError

__all__ = ["from_dict", "coerce", "merged", "flat_items"]


def merged(base: dict, over: dict) -> dict:
    """``base`` with the keys of ``over`` set in it (nested dicts merged key by key)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def flat_items(d: dict, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``("section.key", value)`` for every leaf of a nested dict."""
    for k, v in d.items():
        if isinstance(v, dict):
            yield from flat_items(v, f"{prefix}{k}.")
        else:
            yield prefix + k, v


def from_dict(cls: Any, d: Any, prefix: str = "", what: str = "config") -> Any:
    """An instance of dataclass ``cls`` from ``d`` (keys it does not set keep their defaults)."""
    if not isinstance(d, dict):
        raise MeshsplatError(f"{what}: {prefix.rstrip('.') or 'root'} must be an object, got {type(d).__name__}")
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise MeshsplatError(f"{what}: unknown key(s) {', '.join(prefix + k for k in unknown)} (docs/config.md)")
    kwargs = {}
    for name, value in d.items():
        tp = hints[name]
        if dataclasses.is_dataclass(tp):
            kwargs[name] = from_dict(tp, value, f"{prefix}{name}.", what)
        else:
            kwargs[name] = coerce(value, tp, prefix + name, what)
    return cls(**kwargs)


def coerce(value: Any, tp: Any, key: str, what: str = "config") -> Any:
    """``value`` as type ``tp`` (bool, int, float, str or Optional of one): "true"/"off", "3e4" and the like
    from text; a float with a fraction is not an int."""
    args = typing.get_args(tp)
    if len(args) == 2 and type(None) in args:  # Optional[X]: None, "none" or "null" (JSON / --set), else an X
        if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null")):
            return None
        tp = next(a for a in args if a is not type(None))
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return value.lower() in ("true", "1", "yes", "on")
        raise MeshsplatError(f"{what}: {key} expects true/false, got {value!r}")
    try:
        if tp is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            if isinstance(value, str) and "e" in value.lower():  # 3e4 is a whole number; 2.5e0 and 1e999 are not
                f = float(value)
                if not math.isfinite(f) or not f.is_integer():
                    raise ValueError
                return int(f)
            return int(value)
        if tp is float:
            if isinstance(value, bool):
                raise ValueError
            f = float(value)
            if not math.isfinite(f):
                raise MeshsplatError(f"{what}: {key} is {value!r}; expected a finite number")
            return f
        if tp is str:
            return str(value)
    except MeshsplatError:
        raise
    except (TypeError, ValueError, OverflowError):
        raise MeshsplatError(f"{what}: {key} expects {tp.__name__}, got {value!r}") from None
    return value
