"""User-facing error and warning types: the CLI prints their messages without a traceback."""

from __future__ import annotations

import errno

__all__ = ["MeshsplatError", "MeshsplatWarning", "os_error_text"]


class MeshsplatError(ValueError):
    """Bad input or state that the user can fix; the message names the problem."""


class MeshsplatWarning(UserWarning):
    """Something the user should know that does not stop the work (a fallback taken, a choice made for
    them). Every ``warnings.warn`` of meshsplat uses it; the command line prints each distinct one once
    per command as one ``note:`` line, without the file and line it came from."""


_OS_HINTS = {
    errno.ENOSPC: "the disk is full; free some space",
    errno.EDQUOT: "the disk quota is exhausted; free some space",
    errno.EFBIG: "the file is larger than this system allows",
    errno.EROFS: "the file system is read-only; choose another location",
    errno.EACCES: "check the permissions, or choose a location you can write",
    errno.EPERM: "check the permissions, or choose a location you can write",
    errno.ENOTDIR: "a file stands where a folder is needed; choose another location",
    errno.EISDIR: "a folder stands where a file is needed; choose another name",
    errno.EEXIST: "a file of that name already exists",
    errno.ENAMETOOLONG: "the name is too long",
}


def os_error_text(exc: OSError) -> str:
    """One line for an OS error: what failed, on which path, and what to do."""
    where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
    hint = _OS_HINTS.get(exc.errno) if exc.errno is not None else None
    text = str(exc).strip()
    what = exc.strerror or (text.splitlines()[0] if text else type(exc).__name__)
    return f"{what}{where}" + (f": {hint}" if hint else "")
