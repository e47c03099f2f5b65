"""Device selection shared by training, evaluation and the CLI, and the CPU cores this process may use."""

from __future__ import annotations

import os

import torch

from meshsplat.errors import MeshsplatError

__all__ = ["resolve_device", "usable_cores"]


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``None``/``"auto"``: CUDA when available, else CPU; otherwise the named device (checked)."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise MeshsplatError(f"device: unknown device {device!r}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise MeshsplatError(f"device: {str(device)!r} requested but CUDA is not available")
    return dev


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the system has one, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # macOS, Windows
        return os.cpu_count() or 1
