"""Reading numpy files safely: ``.npz`` archives and ``.npy`` arrays with ``allow_pickle=False``.

The one place where meshsplat opens numpy files from users: a truncated or corrupt archive, an
object array (Python objects, which would need unpickling: never done), an empty file or a file of
another kind each become one :class:`MeshsplatError` line naming the file (and the array). numpy's
own advice to load with ``allow_pickle=True`` never reaches the user.

Sizes are checked before memory is spent: every array's size is read from its ``.npy`` header (a few
bytes) and an archive whose arrays would take more than ``MAX_ARRAY_BYTES`` unpacked (a few MB of zeros
compress to many GB), or whose header promises more data than the file holds, is refused in one line.
"""

from __future__ import annotations

import math
import os
import zipfile
import zlib
from pathlib import Path
from typing import IO

import numpy as np

from meshsplat.errors import MeshsplatError, os_error_text

__all__ = ["read_npz", "npz_keys", "read_npy", "array_error_text", "OBJECT_ARRAY_TEXT", "MAX_ARRAY_BYTES"]

MAX_ARRAY_BYTES = 4 * 2**30  # an archive's arrays together, unpacked (a 20,000-frame 50k-vertex capture: 12 GB)

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


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB"


def _header_bytes(fh: IO[bytes]) -> tuple[int, int]:
    """``(array bytes, header length)`` from the ``.npy`` header at ``fh``'s position (nothing else read)."""
    start = fh.tell() if fh.seekable() else 0
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
    header = (fh.tell() - start) if fh.seekable() else 0
    return (0 if dtype.hasobject else math.prod(int(d) for d in shape) * dtype.itemsize), header


def _check_npz_sizes(p: Path, label: str, limit: int) -> None:
    """Refuse an archive whose arrays' headers promise more than ``limit`` bytes together, or more bytes
    than their members hold (a lying header would allocate that much before failing)."""
    try:
        with zipfile.ZipFile(p) as zf:
            total = 0
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with zf.open(info) as fh:
                    try:
                        nbytes, _ = _header_bytes(fh)
                    except (ValueError, EOFError):
                        continue  # np.load names the broken header
                name = info.filename[: -len(".npy")]
                if nbytes > info.file_size:
                    raise MeshsplatError(
                        f"{label}: array {name!r} claims {_gb(nbytes)} but its member holds {info.file_size} bytes "
                        "(corrupt or forged header); write it again"
                    )
                total += nbytes
                if total > limit:
                    raise MeshsplatError(
                        f"{label}: its arrays would take more than {_gb(total)} once unpacked (at most "
                        f"{_gb(limit)}; array {name!r} passes it); the file holds {_gb(p.stat().st_size)} "
                        "compressed: split or decimate it"
                    )
    except (zipfile.BadZipFile, OSError, zlib.error, NotImplementedError, EOFError):
        return  # not a readable zip: np.load says so in its words


def read_npz(path: str | os.PathLike, what: str = "", limit: int = MAX_ARRAY_BYTES) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path`` as a dict (``allow_pickle=False``); one MeshsplatError
    line, naming the file and ``what`` it is, for a missing, empty, truncated or corrupt archive, a file
    that is not an archive, or an object array; also for arrays over ``limit`` bytes unpacked, refused
    from their headers before reading them."""
    p = Path(path)
    label = f"{p}" + (f" ({what})" if what else "")
    if not p.is_file():
        raise MeshsplatError(f"{label}: file not found")
    if zipfile.is_zipfile(p):
        _check_npz_sizes(p, label, limit)
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
            except Exception as exc:  # noqa: BLE001 - every failure is one reported line
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
    except Exception as exc:  # noqa: BLE001 - every failure is one reported line
        raise MeshsplatError(f"{label}: {array_error_text(exc)}") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise MeshsplatError(f"{label}: a single .npy array, not an .npz archive of named arrays")
    with z:
        return list(z.files)


def read_npy(path: str | os.PathLike, what: str = "", mmap: bool = False, limit: int = MAX_ARRAY_BYTES) -> np.ndarray:
    """The array of the ``.npy`` at ``path`` (``allow_pickle=False``; memory-mapped with ``mmap``); one
    MeshsplatError line for a missing, empty, truncated or corrupt file or an object array, and (read from
    the header first) for a header promising more bytes than the file holds or, unless mapped, than ``limit``."""
    p = Path(path)
    label = f"{p}" + (f" ({what})" if what else "")
    if not p.is_file():
        raise MeshsplatError(f"{label}: file not found")
    try:
        with open(p, "rb") as fh:
            nbytes, header = _header_bytes(fh)
    except (ValueError, EOFError, OSError):
        nbytes = header = 0  # np.load names what is wrong
    if header and nbytes > p.stat().st_size - header:
        raise MeshsplatError(
            f"{label}: its header claims {_gb(nbytes)} but the file holds {p.stat().st_size} bytes (cut short, "
            "or a forged header); write it again"
        )
    if not mmap and nbytes > limit:
        raise MeshsplatError(f"{label}: the array would take {_gb(nbytes)} of memory (at most {_gb(limit)})")
    try:
        a = np.load(p, mmap_mode="r" if mmap else None, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - every failure is one reported line
        raise MeshsplatError(f"{label}: {array_error_text(exc, '.npy array')}") from None
    if isinstance(a, np.lib.npyio.NpzFile):
        a.close()
        raise MeshsplatError(f"{label}: an .npz archive, expected a single .npy array")
    return a
