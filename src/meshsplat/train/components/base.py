"""What a training component is: a feature beyond the published method, in one place.

A component owns its config section (a dataclass whose ``enabled`` switches it on; the default is off, the
published method), its hooks in the training step, its checkpoint state and its notes. The trainer calls the
hooks of the enabled components in ``COMPONENTS`` order (``meshsplat.train.components``):

    start()                      fresh run: the Gaussians exist, the generators are seeded
    posed(idx)                   vertices [V,3] to render training frame idx in (None: the capture's)
    loss(out, mask)              an unweighted loss term (weighted by ``weight``, logged in ``log_column``)
    parameters()                 the tensors it steps (data-parallel training all-reduces their gradients)
    after_step(it, rows)         after the avatar's Adam steps: its own step, projections, stages
    finish(render_error, on_step) after the last iteration: work left to do (``finishing``)
    extra_renders()              how many frame renders beyond the iterations it makes (a time budget plans them)
    state_dict() / load_state_dict(state, checkpoint)   its part of a checkpoint
    on_checkpoint(folder)        files beside a checkpoint (readable without torch)

Adding a loss term or a lighting feature is a new module here with its config dataclass and component class,
listed in ``COMPONENTS``, plus its test and a line in docs/config.md.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, Protocol

import torch

from meshsplat.data.dataset import AvatarDataset
from meshsplat.gaussians.avatar import AvatarRender
from meshsplat.gaussians.shading import Shading
from meshsplat.mesh import TriMesh
from meshsplat.run_folder import RunFolder

__all__ = ["Component", "TrainingState"]


class TrainingState(Protocol):
    """What a component may read of the trainer (``meshsplat.train.trainer.Trainer``)."""

    params: dict[str, torch.Tensor]
    mesh: TriMesh
    extent: float
    device: torch.device
    lr_factor: float
    iteration: int
    dataset: AvatarDataset
    train_ids: list[int]

    @property
    def iterations(self) -> int: ...  # the run's last iteration

    @property
    def model_dir(self) -> str | None: ...  # body/head model files

    @property
    def clamp_to_face(self) -> bool: ...  # walking off: Gaussians clipped to their triangle

    @property
    def eps(self) -> float: ...  # Adam's epsilon

    @property
    def shading(self) -> Shading | None: ...

    def training_error(self, idx: int) -> torch.Tensor: ...  # L1 of training frame idx rendered now (no RNG drawn)


class Component:
    """Base class: every hook does nothing. ``name`` is the config section and checkpoint key."""

    name: ClassVar[str]
    log_column: ClassVar[str | None] = None  # its loss term's column in log.csv (unweighted)

    def __init__(self, cfg: Any, state: TrainingState) -> None:
        self.cfg = cfg
        self.state = state

    @classmethod
    def build(cls, cfg: Any, state: TrainingState) -> tuple[Component | None, str | None]:
        """The component for an enabled section, or None and a one-line note of why it stays off."""
        return cls(cfg, state), None

    @property
    def weight(self) -> float:
        return float(getattr(self.cfg, "weight", 0.0))

    def start(self) -> None:
        return None

    def posed(self, idx: int) -> torch.Tensor | None:
        return None

    def loss(self, out: AvatarRender, mask: torch.Tensor | None) -> torch.Tensor | None:
        return None

    def parameters(self) -> list[torch.Tensor]:
        return []

    def after_step(self, it: int, rows: list[int]) -> None:
        return None

    @property
    def finishing(self) -> bool:
        """Whether ``finish`` has work left once the last iteration is done."""
        return False

    def finish(self, render_error: Callable[[int], torch.Tensor], on_step: Callable[[], None] | None = None) -> None:
        return None

    def extra_renders(self) -> int:
        """At most how many training-frame renders, each with its backward, this component makes beyond the
        iterations (``finish``, or work at a set iteration): a time budget (``train --minutes``) plans them."""
        return 0

    def state_dict(self) -> Any:
        return None

    def load_state_dict(self, state: Any, checkpoint: dict[str, Any]) -> None:
        return None

    def on_checkpoint(self, folder: RunFolder) -> None:
        return None
