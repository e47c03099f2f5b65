"""An exclusive lock on a folder while a process writes it (``RUN/train.lock`` while training).

The lock is an ``flock`` (Windows: ``msvcrt.locking`` of a byte past the record) on a small file holding the owner's PID, host and start time: the kernel releases
it when the owner exits, however it ends (a killed process leaves no stale lock; the file it leaves
behind is not a lock). :func:`lock_holder` tells who holds it without waiting; :class:`FolderLock`
takes it or refuses in one line naming the holder. A worker started by the holder (``train --nproc``:
the launcher holds the lock for its workers) may pass ``parent_ok``.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
import warnings
from pathlib import Path
from typing import Any

from meshsplat.errors import MeshsplatError, MeshsplatWarning, os_error_text

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None  # type: ignore[assignment]
    import msvcrt

__all__ = ["FolderLock", "lock_holder", "holder_text", "held_by_parent"]

_WIN_LOCK_AT = 1 << 20  # Windows locks a byte range: one far past the record, so the record stays readable


class _NoLocks(OSError):
    """The file system refuses locks (some network file systems)."""


def _try_lock(fd: int, shared: bool = False) -> bool:
    """Lock ``fd`` without waiting; False when another holds it; ``_NoLocks`` where locks are not supported."""
    try:
        if fcntl is not None:
            fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        else:
            os.lseek(fd, _WIN_LOCK_AT, os.SEEK_SET)
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
    except (BlockingIOError, PermissionError):
        return False
    except OSError as exc:
        if fcntl is None:  # msvcrt says "deadlock avoided" (EDEADLOCK) when the byte is locked
            return False
        raise _NoLocks(exc.errno, exc.strerror) from None
    return True


def _unlock(fd: int) -> None:
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_UN)
    else:
        os.lseek(fd, _WIN_LOCK_AT, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)


def _read(fd: int) -> dict[str, Any]:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = json.loads(os.read(fd, 4096).decode("utf-8", "replace") or "{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def lock_holder(path: str | os.PathLike) -> dict[str, Any] | None:
    """``{"pid", "host", "started"}`` (as far as written) of the process holding the lock ``path``; None when
    nobody does (no file, or a file left by a process that has ended)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        if not _try_lock(fd, shared=True):
            return _read(fd)
        _unlock(fd)
        return None
    except _NoLocks:
        return None
    finally:
        os.close(fd)


def holder_text(holder: dict[str, Any]) -> str:
    """``process 1234 on host, since 14:02:11`` from :func:`lock_holder`'s dict."""
    pid = holder.get("pid", "?")
    host = f" on {holder['host']}" if holder.get("host") else ""
    started = holder.get("started")
    since = (
        f", since {time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(started))}" if isinstance(started, float) else ""
    )
    return f"process {pid}{host}{since}"


def held_by_parent(holder: dict[str, Any] | None) -> bool:
    """Whether ``holder`` is this process's parent on this host (the ``--nproc`` launcher of a worker)."""
    return holder is not None and holder.get("pid") == os.getppid() and holder.get("host") == socket.gethostname()


class FolderLock:
    """``with FolderLock(path, what):`` holds the lock ``path`` (created with its folder) for the block.

    ``acquire`` refuses in one MeshsplatError naming the holder and ``what`` is locked when another process
    holds it; with ``parent_ok`` the holder being this process's parent counts as held (nothing is taken).
    ``release`` removes the file and unlocks.
    """

    def __init__(self, path: str | os.PathLike, what: str, parent_ok: bool = False) -> None:
        self.path, self.what, self.parent_ok = Path(path), what, parent_ok
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> FolderLock:
        if self._fd is not None:
            return self
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            for _ in range(20):  # the holder may remove the file between our open and flock: try the new one
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
                try:
                    locked = _try_lock(fd)
                except _NoLocks as exc:
                    os.close(fd)
                    warnings.warn(
                        f"{self.path.parent}: this file system does not lock files ({exc.strerror}); nothing stops "
                        f"a second process writing {self.what} at the same time",
                        MeshsplatWarning,
                        stacklevel=2,
                    )
                    return self
                if not locked:
                    holder = _read(fd)
                    os.close(fd)
                    if self.parent_ok and held_by_parent(holder):
                        return self
                    raise MeshsplatError(
                        f"{self.what} is in use right now by {holder_text(holder)} (lock {self.path}); wait for it "
                        "to finish or stop it, or choose another folder"
                    )
                try:
                    same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
                except FileNotFoundError:
                    same = False
                if not same:
                    os.close(fd)
                    continue
                os.ftruncate(fd, 0)
                os.lseek(fd, 0, os.SEEK_SET)
                record = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
                os.write(fd, (json.dumps(record) + "\n").encode())
                self._fd = fd
                return self
        except OSError as exc:
            raise MeshsplatError(f"cannot lock {self.what}: {os_error_text(exc)}") from None
        raise MeshsplatError(f"cannot lock {self.what}: {self.path} keeps being replaced; try again")

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)  # while still locked (POSIX): nobody locks the old file after this
        if fcntl is None:  # Windows removes no open file: unlock, close, then remove
            with contextlib.suppress(OSError):
                _unlock(fd)
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(self.path)
            return
        os.close(fd)

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
