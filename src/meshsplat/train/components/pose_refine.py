"""Component ``pose_refine``: the tracker's per-frame body/head-model parameters refined with the avatar.

Each training frame's parameters named in ``params`` (those the capture's model has) get a trainable offset,
optimised with a lazy Adam (``meshsplat.train.pose_refine.PoseRefiner``); test frames keep the tracker's. Its
checkpoint state is the refiner's; beside each checkpoint it writes ``RUN/refined_params.npz``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.run_folder import RunFolder
from meshsplat.train.components.base import Component, TrainingState
from meshsplat.train.pose_refine import PoseRefiner

__all__ = ["PoseRefineConfig", "PoseRefinement"]


@dataclass
class PoseRefineConfig:
    """Refine when the capture's meshes come from SMPL/SMPL-X/FLAME parameters and the model files are found
    (else train without, saying why); with ``required`` such a capture is the only one accepted."""

    enabled: bool = False
    required: bool = False  # refuse a capture whose poses cannot be refined
    # bench/reports/pose_refine.md: with the evidence gate, the start and the depth rule below, 1e-3 beats 3e-4
    # (the default before) on exact and noisy poses alike; 2e-3 moves exact poses too far
    lr: float = 1e-3
    params: str = "global_orient,body_pose,transl,neck_pose,jaw_pose,expression"
    # a pull of each offset towards zero (its gradient gains prior * offset): keeps a pose where the images say
    # nothing (e.g. depth in a monocular capture); 0: none (bench/reports/pose_refine.md)
    prior: float = 0.0
    # the fraction of the run's iterations trained on the tracker's poses before they move: early gradients come
    # from an avatar that does not yet look like the subject and push right poses away; 0: from the first step
    start: float = 0.3
    # a mesh whose training frames all come from one camera: its translation offset does not move along that
    # camera's line of sight to the subject (depth, which one camera hardly sees; the avatar's size absorbs it)
    keep_depth: bool = True
    # each Adam step times (|m| / sqrt(v))^evidence, the agreement of a number's recent gradients (1: one sign
    # throughout; noise about a right pose flips it and moves less); 0: plain Adam
    evidence: float = 4.0
    # after the last iteration: this many Adam steps on the refined poses alone, the avatar frozen; 0: none. A
    # frame keeps a step only where it lowered its image error by polish_min_gain (a fraction), else the step is
    # undone and that frame's rate halves: a right pose stays, a wrong one moves as far as its images ask
    polish_steps: int = 0
    polish_lr: float = 1e-3
    polish_min_gain: float = 1e-3
    # a polish also at this fraction of the run's iterations (the avatar then trains on in the polished poses); 0:
    # at the end only
    polish_mid: float = 0.0

    def checks(self) -> list[tuple[bool, str]]:
        return [
            (self.lr > 0, "pose_refine.lr must be > 0"),
            (self.prior >= 0, "pose_refine.prior must be >= 0"),
            (0 <= self.evidence <= 8, "pose_refine.evidence must be in [0, 8]"),
            (0 <= self.start < 1, "pose_refine.start must be in [0, 1) (a fraction of the iterations)"),
            (0 <= self.polish_steps <= 100_000, "pose_refine.polish_steps must be in [0, 100000]"),
            (self.polish_lr > 0, "pose_refine.polish_lr must be > 0"),
            (0 <= self.polish_min_gain < 1, "pose_refine.polish_min_gain must be in [0, 1) (a fraction)"),
            (0 <= self.polish_mid < 1, "pose_refine.polish_mid must be in [0, 1) (a fraction of the iterations)"),
        ]


class PoseRefinement(Component):
    name = "pose_refine"
    cfg: PoseRefineConfig

    def __init__(self, cfg: PoseRefineConfig, state: TrainingState, refiner: PoseRefiner) -> None:
        super().__init__(cfg, state)
        self.refiner = refiner
        self.polish_counts: dict[str, int] | None = None  # the latest polish's (PoseRefiner.fit_guarded)
        self.depth_dirs = self._depth_directions() if cfg.keep_depth and "transl" in refiner.offsets else {}

    def _depth_directions(self) -> dict[int, torch.Tensor]:
        """Per refined mesh row seen by one camera only: the unit vector ``[3]`` from that camera's centre to the
        tracked mesh's centroid (rows seen by several cameras have their depth in the images: none)."""
        ds = self.state.dataset
        cams: dict[int, set[str]] = {}
        first: dict[int, int] = {}
        for i in self.state.train_ids:
            row = self._row(i)
            cams.setdefault(row, set()).add(str(ds.frame_info(i)["camera"]))
            first.setdefault(row, i)
        dirs = {}
        for row, ids in cams.items():
            if len(ids) == 1 and self.refiner.refines(row):
                d = ds.vertices(first[row]).mean(0) - ds.frame_camera(first[row]).center.to(torch.float32)
                dirs[row] = (d / d.norm().clamp_min(1e-9)).to(self.state.device)
        return dirs

    @classmethod
    def build(cls, cfg: PoseRefineConfig, state: TrainingState) -> tuple[Component | None, str | None]:
        ds = state.dataset
        if not cfg.required and (ds.driver_info is None or ds.driver_params is None):
            return None, None  # meshes without model parameters: nothing to refine, nothing to say
        try:
            refiner = PoseRefiner(
                state.dataset,
                state.train_ids,
                cfg.params,
                cfg.lr * state.lr_factor,
                state.model_dir,
                state.device,
                prior=cfg.prior,
                evidence=cfg.evidence,
            )
        except MeshsplatError as exc:
            if cfg.required:
                raise
            return None, f"pose refinement off, the tracker's poses are kept: {exc}"
        kind = str((state.dataset.driver_info or {}).get("type", "model")).upper()
        note = f"pose refinement on: {', '.join(refiner.names)} of {len(refiner.row_of)} training meshes ({kind})"
        return cls(cfg, state, refiner), note

    def _row(self, idx: int) -> int:
        return int(self.state.dataset.frame_info(idx)["mesh"])

    @property
    def started(self) -> bool:
        """Whether the poses move this iteration (``start`` of the run's iterations are behind)."""
        return self.state.iteration > int(self.cfg.start * self.state.iterations)

    def posed(self, idx: int) -> torch.Tensor | None:
        row = self._row(idx)
        if not self.started or not self.refiner.refines(row):
            return None  # the stored mesh, the tracker's pose (the offsets are zero until the start), posed once
        return self.refiner.vertices(row)  # changes every step

    def parameters(self) -> list[torch.Tensor]:
        return list(self.refiner.offsets.values())

    def after_step(self, it: int, rows: list[int]) -> None:
        if self.cfg.polish_steps and self.cfg.polish_mid and it == int(self.cfg.polish_mid * self.state.iterations):
            self._polish(self.state.training_error)
        if not self.started:
            return
        mesh_rows = [self._row(i) for i in rows]
        # the batch's rows only: a frame not drawn keeps its pose and its Adam state
        self.refiner.step(mesh_rows)
        for row in set(mesh_rows):
            self._keep_depth(row)
        self.refiner.polished = False  # the poses moved with the avatar: fit them again at the end

    def _keep_depth(self, row: int) -> None:
        """Projected steps: a one-camera row's translation offset back onto the plane across that camera's line
        of sight (``keep_depth``)."""
        d = self.depth_dirs.get(row)
        if d is not None:
            j, transl = self.refiner.row_of[row], self.refiner.offsets["transl"].data
            transl[j] -= (transl[j] @ d) * d

    @property
    def finishing(self) -> bool:
        return self.cfg.polish_steps > 0 and not self.refiner.polished

    def extra_renders(self) -> int:
        """Each polish (at the end, and at ``polish_mid``) renders every training frame at most once per step and
        once more to measure the last (``PoseRefiner.fit_guarded``)."""
        polishes = int(self.finishing) + int(bool(self.cfg.polish_steps and self.cfg.polish_mid))
        return polishes * (self.cfg.polish_steps + 1) * len(self.state.train_ids)

    def finish(self, render_error: Callable[[int], torch.Tensor], on_step: Callable[[], None] | None = None) -> None:
        self._polish(render_error, on_step)
        self.refiner.polished = True

    def _polish(self, render_error: Callable[[int], torch.Tensor], on_step: Callable[[], None] | None = None) -> None:
        """``polish_steps`` Adam steps on the refined training poses, the avatar frozen: each mesh row's sum of
        ``render_error(idx)`` over its training frames, one backward per row, a step kept only where it lowered
        that error by ``polish_min_gain`` (``PoseRefiner.fit_guarded``)."""
        frames: dict[int, list[int]] = {}
        for i in self.state.train_ids:
            frames.setdefault(self._row(i), []).append(i)

        def row_error(row: int) -> torch.Tensor:
            return torch.stack([render_error(i) for i in frames[row]]).sum()

        self.polish_counts = self.refiner.fit_guarded(
            row_error, self.cfg.polish_steps, self.cfg.polish_lr, self.cfg.polish_min_gain, self._keep_depth, on_step
        )

    def state_dict(self) -> Any:
        return self.refiner.state_dict()

    def load_state_dict(self, state: Any, checkpoint: dict[str, Any]) -> None:
        self.refiner.load_state_dict(state)

    def on_checkpoint(self, folder: RunFolder) -> None:
        arrays: dict[str, Any] = self.refiner.refined_params()  # readable without torch
        np.savez(folder.refined_params_path, **arrays)
