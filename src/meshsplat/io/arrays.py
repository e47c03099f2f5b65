"""Reading numpy files safely: ``.npz`` archives and ``.npy`` arrays with ``allow_pickle=False``.

The one place where meshsplat opens numpy files from users: a truncated or corrupt archive, an
object array (Python objects, which would need unpickling: never done), an empty file or a file of
another kind each become one :class:`MeshsplatError` line naming the file (and the array). numpy's
own advice to load with ``allow_pickle=True`` never reaches the user.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from meshsplat.errors import MeshsplatError, os_error_text

__all__ = ["read_npz", "npz_keys", "read_npy", "array_error_text", "OBJECT_ARRAY_TEXT"]

OBJECT_ARRAY_TEXT = (
    "holds Python objects (an object array); meshsplat reads numbers only and never unpickles a file: "
    "save it with numeric arrays"
)
_CORRUPT = (zipfile.BadZipFile, EOFError, zlib.error, KeyError, NotImplementedError)


def array_error_text(exc: BaseException, kind: str = "npz archive") -> str:
    """What went wrong reading a numpy file, in words a user can act on (no ``allow_pickle`` advice)."""
    text = str(exc)
    if isinstance(exc, OSError) and not isinstance(exc, zipfile.BadZipFile) and exc.errno is not None:
        return os_error_text(exc)
    if "pickle" in text.lower() or "Python objects" in text:
        return OBJECT_ARRAY_TEXT
    if isinstance(exc, EOFError) or "No data left" in text:
        return f"the file is empty or cut short (not a complete {kind})"
    if isinstance(exc, _CORRUPT) or "zip" in text.lower():
        return f"not a readable {kind} (truncated or corrupt: {text or type(exc).__name__}); write it again"
    first = text.splitlines()[0] if text else type(exc).__name__
    return f"not a readable {kind} ({first})"


def read_npz(path: str | os.PathLike, what: str = "") -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path`` as a dict (``allow_pickle=False``); one MeshsplatError
    line, naming the file and ``what`` it is, for a missing, empty, truncated or corrupt archive, a file
    that is not an archive, or an object array."""
    p = Path(path)
    label = f"{p}" + (f" ({what})" if what else "")
    if not p.is_file():
        raise MeshsplatError(f"{label}: file not found")
    try:
        z = np.load(p, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - every failure is one reported line
        raise MeshsplatError(f"{label}: {array_error_text(exc)}") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise MeshsplatError(f"{label}: a single .npy array, not an .npz archive of named arrays")
    out: dict[str, np.ndarray] = {}
    with z:
        for k in z.files:
            try:
                out[k] = np.asarray(z[k])
            except Exception as exc:  # noqa: BLE001
                raise MeshsplatError(f"{label}: array {k!r} {array_error_text(exc)}") from None
    return out


def npz_keys(path: str | os.PathLike, what: str = "") -> list[str]:
    """The names of the arrays in the ``.npz`` at ``path``, without reading them (errors as :func:`read_npz`)."""
    p = Path(path)
    label = f"{p}" + (f" ({what})" if what else "")
    if not p.is_file():
        raise MeshsplatError(f"{label}: file not found")
    try:
        z = np.load(p, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001
        raise MeshsplatError(f"{label}: {array_error_text(exc)}") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise MeshsplatError(f"{label}: a single .npy array, not an .npz archive of named arrays")
    with z:
        return list(z.files)


def read_npy(path: str | os.PathLike, what: str = "", mmap: bool = False) -> np.ndarray:
    """The array of the ``.npy`` at ``path`` (``allow_pickle=False``; memory-mapped with ``mmap``); one
    MeshsplatError line for a missing, empty, truncated or corrupt file or an object array."""
    p = Path(path)
    label = f"{p}" + (f" ({what})" if what else "")
    if not p.is_file():
        raise MeshsplatError(f"{label}: file not found")
    try:
        a = np.load(p, mmap_mode="r" if mmap else None, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001
        raise MeshsplatError(f"{label}: {array_error_text(exc, '.npy array')}") from None
    if isinstance(a, np.lib.npyio.NpzFile):
        a.close()
        raise MeshsplatError(f"{label}: an .npz archive, expected a single .npy array")
    return a
