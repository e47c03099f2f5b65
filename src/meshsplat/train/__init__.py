"""Training: config dataclasses, optimizers and lr schedule, densification strategy, Trainer.

Losses live in ``meshsplat.train.losses``. Python API::

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
from meshsplat.train.strategy import DensifyStrategy, walk_embeddings
from meshsplat.train.trainer import LOG_COLUMNS, Trainer, mesh_extent, train

__all__ = [
    "TrainConfig", "ModelConfig", "OptimConfig", "LossConfig", "StrategyConfig", "WalkConfig",
    "apply_overrides", "load_config", "expon_lr", "base_learning_rates", "build_optimizers", "LrSchedule",
    "DensifyStrategy", "walk_embeddings", "Trainer", "train", "mesh_extent", "LOG_COLUMNS",
]
