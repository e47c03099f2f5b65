"""Train an avatar in one call: ``meshsplat.train_avatar``, the front door's training function.

    run_dir = meshsplat.train_avatar("data/cesium", "runs/cesium", iterations=2000)
    run_dir = meshsplat.train_avatar(config=TrainConfig(data="data/cesium", out="runs/x"))

A recipe is a named training setup (``meshsplat.train.recipes``: ``quality``, the default, or ``paper``);
``overrides`` (the same strings as ``meshsplat train --set``) apply after it. Like ``meshsplat train``,
the run keeps the dataset's ``source_map.npz`` so the run alone can be animated by its source asset.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from meshsplat.data.source_map import copy_source_map
from meshsplat.errors import MeshsplatError
from meshsplat.train import DEFAULT_RECIPE, TrainConfig, Trainer, apply_overrides, recipe_config

__all__ = ["train_avatar"]


def train_avatar(
    dataset: str | Path | None = None,
    out: str | Path | None = None,
    *,
    recipe: str | None = None,
    iterations: int | None = None,
    overrides: Sequence[str] = (),
    config: TrainConfig | None = None,
    device: str | None = None,
    progress: bool | None = None,
    resume: bool = False,
) -> Path:
    """Train an avatar on the capture ``dataset`` (any layout ``open_capture`` reads) into the run folder
    ``out``; returns the run folder (read it back with ``load_run`` / ``load_avatar``).

    The config is ``config`` if given, else the recipe: the overrides of ``recipe`` (default
    ``"quality"``; giving both is an error). Then ``dataset``, ``out``, ``overrides`` (``section.key=value``
    strings), ``iterations``, ``device`` and ``progress`` replace what they name when given. ``resume``
    continues the run in ``out`` from its newest checkpoint; without it a folder holding a run is refused.
    """
    if isinstance(overrides, str):
        raise MeshsplatError(f"overrides: expected a list of 'section.key=value' strings, got the string {overrides!r}")
    if config is not None:
        if not isinstance(config, TrainConfig):
            raise MeshsplatError(f"config: expected a TrainConfig, got {type(config).__name__}")
        if recipe is not None:
            raise MeshsplatError("give a recipe or a config, not both (a config already says everything)")
        cfg = TrainConfig.from_dict(config.to_dict())
    else:
        cfg = recipe_config(DEFAULT_RECIPE if recipe is None else recipe)
    if dataset is not None:
        cfg.data = str(dataset)
    if out is not None:
        cfg.out = str(out)
    cfg = apply_overrides(cfg, list(overrides))
    if iterations is not None:
        cfg.iterations = int(iterations)
    if device is not None:
        cfg.device = device
    if progress is not None:
        cfg.progress = bool(progress)
    if not cfg.data:
        raise MeshsplatError("dataset: no capture to train on (pass a dataset folder, or a config with data)")
    if not Path(cfg.data).exists():
        raise MeshsplatError(f"dataset not found: {cfg.data}")
    trainer = Trainer(cfg.validate(), resume=resume)
    copy_source_map(cfg.data, trainer.cfg.out)
    return trainer.train()
