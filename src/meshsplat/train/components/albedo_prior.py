"""Component ``albedo_prior``: nearby Gaussians of one hue share one albedo (``meshsplat.train.albedo_prior``).

Acts on shaded avatars only (component ``shading``): without lighting there is no albedo to separate from it.
Its checkpoint state is the neighbour search, so a resumed run uses the same neighbours.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.avatar import AvatarRender
from meshsplat.gaussians.compose import effective_uv
from meshsplat.gaussians.params import num_gaussians
from meshsplat.train.albedo_prior import MAX_REACH, NEIGHBOURS, REFRESH_EVERY, albedo_neighbours, albedo_smoothness
from meshsplat.train.components.base import Component

__all__ = ["AlbedoPriorConfig", "AlbedoPrior"]


@dataclass
class AlbedoPriorConfig:
    """The albedo prior's weight and reach; off: none (the paper)."""

    enabled: bool = False
    weight: float = 0.1
    # each Gaussian's 8 nearest, and with a reach above 8 another 8 spread evenly by rank over its `reach` nearest
    reach: int = 64

    def checks(self) -> list[tuple[bool, str]]:
        return [
            (self.weight >= 0, "albedo_prior.weight must be >= 0"),
            (NEIGHBOURS <= self.reach <= MAX_REACH, f"albedo_prior.reach must be in {NEIGHBOURS}..{MAX_REACH}"),
        ]


class AlbedoPrior(Component):
    name = "albedo_prior"
    log_column = "albedo"
    cfg: AlbedoPriorConfig

    def __init__(self, cfg: AlbedoPriorConfig, state: Any) -> None:
        super().__init__(cfg, state)
        self.neighbours: torch.Tensor | None = None  # [N,k] indices of each Gaussian's neighbours
        self.searched_at = 0  # the iteration that searched them

    def loss(self, out: AvatarRender, mask: torch.Tensor | None) -> torch.Tensor | None:
        if self.state.shading is None:
            return None
        return albedo_smoothness(self.state.params["sh0"], self._neighbours())

    def _neighbours(self) -> torch.Tensor:
        """Searched again every ``REFRESH_EVERY`` iterations and whenever the count of Gaussians changed."""
        st = self.state
        n, it = num_gaussians(st.params), st.iteration
        nb = self.neighbours
        if nb is None or nb.shape[0] != n or (it % REFRESH_EVERY == 1 and self.searched_at != it):
            uv = effective_uv(st.params, st.clamp_to_face)
            self.neighbours = albedo_neighbours(st.mesh.vertices, st.mesh.faces, st.params["face"], uv, self.cfg.reach)
            self.searched_at = it
        assert self.neighbours is not None
        return self.neighbours

    def state_dict(self) -> Any:
        return None if self.neighbours is None else {"neighbours": self.neighbours.cpu(), "iteration": self.searched_at}

    def load_state_dict(self, state: Any, checkpoint: dict[str, Any]) -> None:
        # saved after a densification they still index the Gaussians before it: the next step searches again,
        # as the uninterrupted run did
        if state is None:
            return
        nb = state["neighbours"]
        if (
            not isinstance(nb, torch.Tensor)
            or nb.dtype != torch.long
            or nb.ndim != 2
            or (nb.numel() and not 0 <= int(nb.min()) <= int(nb.max()) < nb.shape[0])
        ):
            raise MeshsplatError(
                "checkpoint: its albedo prior's neighbours are not indices of its Gaussians (a damaged file); "
                "resume from an earlier checkpoint or start a new run"
            )
        self.neighbours, self.searched_at = nb.to(self.state.device), int(state["iteration"])
