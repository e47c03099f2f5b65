"""A training run's checkpoint: what ``Trainer`` saves and how it continues from one (mixed into ``Trainer``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.avatar import Avatar
from meshsplat.gaussians.params import EMBEDDING_STATE_KEYS
from meshsplat.io.checkpoint import save_checkpoint
from meshsplat.run_folder import RunFolder
from meshsplat.train.components import Component
from meshsplat.train.config import TrainConfig
from meshsplat.train.optim import build_optimizers
from meshsplat.train.resume import capture_rng, restore_rng

__all__ = ["TrainerCheckpoints"]


class TrainerCheckpoints:
    """``state_dict`` / ``save_checkpoint`` / ``_restore`` of the attributes ``Trainer`` sets."""

    cfg: TrainConfig
    device: torch.device
    folder: RunFolder
    components: list[Component]
    notes: list[str]
    params: dict[str, torch.Tensor]
    optimizers: dict[str, Any]
    lrs: dict[str, float]
    strategy_state: dict[str, Any]
    order_gen: torch.Generator
    bg_gen: torch.Generator
    order: torch.Tensor
    order_pos: int
    iteration: int
    elapsed: float
    avatar: Callable[[], Avatar]

    def state_dict(self) -> dict[str, Any]:
        rng = capture_rng({"order": self.order_gen, "background": self.bg_gen}, self.device)
        strat = {k: (v.detach().cpu() if isinstance(v, torch.Tensor) else v) for k, v in self.strategy_state.items()}
        return {
            "iteration": self.iteration,
            "elapsed_s": self.elapsed,
            "config": self.cfg.to_dict(),
            "avatar": self.avatar().state_dict(),
            "trainable": sorted(k for k, v in self.params.items() if getattr(v, "requires_grad", False)),
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
            "strategy_state": strat,
            "rng": rng,
            "data_order": {"order": self.order.clone(), "pos": self.order_pos},
            "components": {comp.name: comp.state_dict() for comp in self.components},
            "torch_threads": torch.get_num_threads(),  # a resume on another count matches only to rounding
        }

    def save_checkpoint(self) -> Path:
        for comp in self.components:
            comp.on_checkpoint(self.folder)
        path = self.folder.checkpoint_path(self.iteration)
        return save_checkpoint(path, self.state_dict(), keep_last=self.cfg.keep_checkpoints)

    def _restore(self, st: dict[str, Any]) -> None:
        dev = self.device
        trainable = set(st.get("trainable", []))
        self.params = {}
        for k, v in st["avatar"]["params"].items():
            v = v.to(dev)
            self.params[k] = v if k in EMBEDDING_STATE_KEYS else torch.nn.Parameter(v, requires_grad=k in trainable)
        self.optimizers = build_optimizers(self.params, self.lrs, self.cfg.optim.eps)
        if set(self.optimizers) != set(st["optimizers"]):
            raise MeshsplatError(
                "checkpoint: optimizer keys do not match the configuration "
                f"({sorted(st['optimizers'])} vs {sorted(self.optimizers)})"
            )
        for k, opt in self.optimizers.items():
            # this machine's fused-Adam choice, not the saving run's, set before loading: torch places the step
            # counts (on the parameters' device for the fused kernel, else on the CPU) by the loaded groups' flag
            saved = st["optimizers"][k]
            mine = [g.get("fused") for g in opt.param_groups]
            groups = [{**g, "fused": f} for g, f in zip(saved["param_groups"], mine, strict=False)]  # torch: counts
            opt.load_state_dict({**saved, "param_groups": groups})
        self.strategy_state = {
            k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in st["strategy_state"].items()
        }
        gens = restore_rng(st["rng"], ("order", "background"), dev)
        self.order_gen, self.bg_gen = gens["order"], gens["background"]
        self._restore_components(st)
        self.order = st["data_order"]["order"].clone()
        self.order_pos = int(st["data_order"]["pos"])
        self.iteration = int(st["iteration"])
        self.elapsed = float(st.get("elapsed_s", 0.0))

    def _restore_components(self, st: dict[str, Any]) -> None:
        """Each enabled component's state; a checkpoint with a component this configuration lacks is refused."""
        saved = st.get("components")
        if not isinstance(saved, dict):
            raise MeshsplatError(
                "checkpoint: written by a pre-release meshsplat (before 0.1.0; no component states); finish that run "
                "with the version that started it, or start a new run"
            )
        names = {c.name for c in self.components}
        extra = sorted(set(saved) - names)
        if extra:
            why = f" ({'; '.join(self.notes)})" if self.notes else ""
            raise MeshsplatError(
                f"checkpoint: it was trained with {', '.join(extra)}, which this configuration does not do{why}; "
                "resume with the same settings and model files (--model-dir) or start a new run"
            )
        for comp in self.components:
            if comp.name not in saved:
                raise MeshsplatError(
                    f"checkpoint: it was trained without {comp.name}; resume without it or start a new run"
                )
            comp.load_state_dict(saved[comp.name], st)
