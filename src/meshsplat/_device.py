"""Device selection shared by training, evaluation and the CLI."""

from __future__ import annotations

import torch

from meshsplat.errors import MeshsplatError

__all__ = ["resolve_device"]


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
