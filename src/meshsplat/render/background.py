"""Backgrounds: parse a colour, and composite a masked ground-truth image over it.

Training and evaluation render the avatar on a background colour and compare it with the ground
truth composited over the same colour through its mask, so the loss and the metrics score the
subject, not the recorded background.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from meshsplat.errors import MeshsplatError

__all__ = ["BACKGROUNDS", "background_color", "composite"]

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def background_color(background: str | Sequence[float] | torch.Tensor) -> torch.Tensor:
    """``"white"``, ``"black"``, ``"R,G,B"`` or three floats in [0, 1] -> ``[3]`` float32."""
    if isinstance(background, str):
        if background in BACKGROUNDS:
            return torch.tensor(BACKGROUNDS[background])
        try:
            background = [float(x) for x in background.split(",")]
        except ValueError:
            raise MeshsplatError(f"background: expected white, black or R,G,B in [0,1], got {background!r}") from None
    bg = torch.as_tensor(background, dtype=torch.float32).reshape(-1)
    if bg.numel() != 3 or not bool(torch.isfinite(bg).all()) or bool((bg < 0).any() | (bg > 1).any()):
        raise MeshsplatError(f"background: expected three values in [0, 1], got {bg.tolist()}")
    return bg


def composite(image: torch.Tensor, mask: torch.Tensor | None, background: torch.Tensor) -> torch.Tensor:
    """``image [H,W,3]`` over ``background [3]`` through ``mask [H,W,1]`` in [0, 1]; without a mask the
    image is returned as recorded."""
    if mask is None:
        return image
    return image * mask + background * (1 - mask)
