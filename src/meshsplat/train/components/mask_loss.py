"""Component ``mask_loss``: the rendered alpha held to the capture's mask (frames with masks)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meshsplat.gaussians.avatar import AvatarRender
from meshsplat.train.components.base import Component

__all__ = ["MaskLossConfig", "MaskLoss"]


@dataclass
class MaskLossConfig:
    """L1 between the rendered alpha and the ground-truth mask; off: no silhouette term (the paper)."""

    enabled: bool = False
    weight: float = 0.1

    def checks(self) -> list[tuple[bool, str]]:
        return [(self.weight >= 0, "mask_loss.weight must be >= 0")]


class MaskLoss(Component):
    name = "mask_loss"
    log_column = "mask"

    def loss(self, out: AvatarRender, mask: torch.Tensor | None) -> torch.Tensor | None:
        return None if mask is None else (out.alpha - mask).abs().mean()
