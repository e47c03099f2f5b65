"""Training: config dataclasses, optimizers and lr schedule, densification strategy, Trainer.

Losses live in ``meshsplat.train.losses``; the features beyond the paper in ``meshsplat.train.components``.
``TrainConfig()`` is the published method; ``recipe_config("quality")`` the default of ``meshsplat train``
(``meshsplat.train.recipes``). Python API::

    from meshsplat.train import recipe_config, train
    cfg = recipe_config("quality")
    cfg.data, cfg.out, cfg.iterations = "path/to/dataset", "runs/x", 2000
    run_dir = train(cfg)
"""

from meshsplat.mesh import mesh_extent
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
from meshsplat.train.recipes import DEFAULT_RECIPE, RECIPES, recipe_config, recipe_overrides
from meshsplat.train.run_log import LOG_COLUMNS
from meshsplat.train.strategy import DensifyStrategy, walk_embeddings
from meshsplat.train.trainer import Trainer, train

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
    "RECIPES",
    "DEFAULT_RECIPE",
    "recipe_config",
    "recipe_overrides",
]
