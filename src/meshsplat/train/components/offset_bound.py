"""Component ``offset_bound``: Gaussians kept near their triangle along its normal."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meshsplat.train.components.base import Component

__all__ = ["OffsetBoundConfig", "OffsetBound"]


@dataclass
class OffsetBoundConfig:
    """|d| (the offset along the normal) clamped after every step; off: unbounded (the paper)."""

    enabled: bool = False
    max_offset: float = 0.15  # relative: times the mesh extent

    def checks(self) -> list[tuple[bool, str]]:
        return [(self.max_offset > 0, "offset_bound.max_offset must be > 0 (turn the bound off with enabled=false)")]


class OffsetBound(Component):
    name = "offset_bound"
    cfg: OffsetBoundConfig

    def after_step(self, it: int, rows: list[int]) -> None:
        with torch.no_grad():  # a projection, like the lighting's
            bound = self.cfg.max_offset * self.state.extent
            self.state.params["d"].clamp_(-bound, bound)
