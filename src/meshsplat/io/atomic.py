"""Writing a file atomically: to a temporary name in the same folder, flushed, then renamed into place.

A full disk or a killed process leaves either the previous file or none, never a truncated one (the
temporary file is removed on failure). Used by checkpoints, exports and the viewer bundle.

The temporary file is created with mode 0666 less the user's umask, as ``open()`` would, so the file in
place is as readable as any other the user writes (0644 under umask 022; ``tempfile.mkstemp`` would
leave 0600, unreadable to a web server or a group).
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

__all__ = ["atomic_write", "write_bytes_atomic", "write_text_atomic", "write_with", "fsync_dir", "TMP_SUFFIX"]

TMP_SUFFIX = ".tmp"


def _create_temp(folder: Path, prefix: str, suffix: str) -> tuple[int, str]:
    """A new file ``folder/prefix<random>suffix`` opened for writing: (descriptor, path). Like
    ``tempfile.mkstemp`` (exclusive creation, no symlink followed) but with the user's umask."""
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        name = os.path.join(folder, f"{prefix}{secrets.token_hex(6)}{suffix}")
        try:
            return os.open(name, flags, 0o666), name
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name in {folder} after 100 tries")


def fsync_dir(folder: str | os.PathLike) -> None:
    """Make a rename in ``folder`` durable (no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, fsync: bool = True) -> Iterator[IO[bytes]]:
    """``with atomic_write(path) as fh: fh.write(...)``: the bytes go to ``.<name>.<random>.tmp`` next to
    ``path``, which replaces ``path`` only when the block ends without an error; on any error (a full
    disk: OSError) the temporary file is removed and the error propagates, ``path`` untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_temp(path.parent, f".{path.name}.", TMP_SUFFIX)
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
            fh.flush()
            if fsync:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    if fsync:
        fsync_dir(path.parent)


def write_bytes_atomic(path: str | os.PathLike, data: bytes | bytearray | memoryview, fsync: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_write`)."""
    with atomic_write(path, fsync) as fh:
        fh.write(data)
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str, fsync: bool = True, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_write`)."""
    return write_bytes_atomic(path, text.encode(encoding), fsync)


def write_with(path: str | os.PathLike, writer: Callable[[Path], object], fsync: bool = True) -> Path:
    """Let ``writer(tmp_path)`` write a file (a library that insists on a path), then move it into place
    atomically; the temporary file is removed when ``writer`` fails."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = _create_temp(path.parent, f".{path.name}.", path.suffix or TMP_SUFFIX)
    os.close(fd)
    tmp = Path(name)
    try:
        writer(tmp)
        if fsync:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    if fsync:
        fsync_dir(path.parent)
    return path
