"""How much memory this process may still allocate, on Linux, macOS and Windows, with the standard
library only (no Unix-only module imported where it does not exist).

- Linux: ``MemAvailable`` from /proc/meminfo (free memory plus what the page cache would give back).
- Windows: ``GlobalMemoryStatusEx`` (available physical memory, and the process's free address space).
- macOS, the BSDs, and Linux without a readable /proc: the installed memory (``os.sysconf``), a bound
  that never refuses what would fit.
- Where the system sets an address-space limit (``ulimit -v``; the ``resource`` module, POSIX only),
  what is left below it caps the answer.

``None`` when none of these answers; the caller then says it could not check.
"""

from __future__ import annotations

import ctypes
import os
import sys
from types import ModuleType

resource: ModuleType | None
try:
    import resource
except ImportError:  # Windows (and any system without it): no address-space limit to read
    resource = None

__all__ = ["available_memory"]


def available_memory() -> int | None:
    """Bytes this process may still allocate, or ``None`` where the system does not say."""
    avail = _windows_available() if sys.platform == "win32" else _meminfo_available()
    if avail is None:
        avail = _installed_memory()
    limit = _address_space_left()
    if limit is not None:
        avail = limit if avail is None else min(avail, limit)
    return avail


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _installed_memory() -> int | None:
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):  # no sysconf (Windows) or no such name
        return None
    return pages * size if pages > 0 and size > 0 else None


def _address_space_left() -> int | None:
    """What an address-space limit (RLIMIT_AS) leaves, ``None`` without one (or on Windows)."""
    if resource is None:
        return None
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (OSError, ValueError, AttributeError):
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/statm") as fh:
            used = int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        used = 0
    return max(0, soft - used)


def _windows_available() -> int | None:  # pragma: no cover - Windows
    if sys.platform != "win32":
        return None

    class MemoryStatusEx(ctypes.Structure):
        _fields_ = [
            ("dwLength", ctypes.c_ulong),
            ("dwMemoryLoad", ctypes.c_ulong),
            ("ullTotalPhys", ctypes.c_ulonglong),
            ("ullAvailPhys", ctypes.c_ulonglong),
            ("ullTotalPageFile", ctypes.c_ulonglong),
            ("ullAvailPageFile", ctypes.c_ulonglong),
            ("ullTotalVirtual", ctypes.c_ulonglong),
            ("ullAvailVirtual", ctypes.c_ulonglong),
            ("ullAvailExtendedVirtual", ctypes.c_ulonglong),
        ]

    status = MemoryStatusEx()
    status.dwLength = ctypes.sizeof(MemoryStatusEx)
    try:
        ok = ctypes.windll.kernel32.GlobalMemoryStatusEx(ctypes.byref(status))
    except (AttributeError, OSError):
        return None
    if not ok:
        return None
    return int(min(status.ullAvailPhys, status.ullAvailVirtual))
