"""Training: config dataclasses, optimizers and lr schedule, densification strategy, Trainer.

Losses live in ``meshsplat.train.losses``. ``TrainConfig()`` is the ``quality`` preset;
``preset_config("paper")`` the published method (``meshsplat.train.presets``). Python API::

    from meshsplat.train import TrainConfig, train
    run_dir = train(TrainConfig(data="path/to/dataset", out="runs/x", iterations=2000))
"""

from meshsplat.train.config import (
    LossConfig,
    ModelConfig,
    OptimConfig,
    StrategyConfig,
    TrainConfig,
    WalkConfig,
    apply_overrides,
    load_config,
)
from meshsplat.train.optim import LrSchedule, base_learning_rates, build_optimizers, expon_lr
from meshsplat.train.presets import DEFAULT_PRESET, PRESETS, preset_config, preset_overrides
from meshsplat.train.strategy import DensifyStrategy, walk_embeddings
from meshsplat.train.trainer import LOG_COLUMNS, Trainer, mesh_extent, train

__all__ = [
    "TrainConfig",
    "ModelConfig",
    "OptimConfig",
    "LossConfig",
    "StrategyConfig",
    "WalkConfig",
    "apply_overrides",
    "load_config",
    "expon_lr",
    "base_learning_rates",
    "build_optimizers",
    "LrSchedule",
    "DensifyStrategy",
    "walk_embeddings",
    "Trainer",
    "train",
    "mesh_extent",
    "LOG_COLUMNS",
    "PRESETS",
    "DEFAULT_PRESET",
    "preset_config",
    "preset_overrides",
]
