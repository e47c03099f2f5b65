"""User-facing error type: the CLI prints its message without a traceback."""
from __future__ import annotations

__all__ = ["MeshsplatError"]


class MeshsplatError(ValueError):
    """Bad input or state that the user can fix; the message names the problem."""
