"""Recipes: named training setups, each a list of components and a few settings over the published method.

    quality   the default of ``meshsplat train``: components shading (a learned SH2 irradiance with a key light
              found in training and its soft shadow from the posed mesh; a key more than 45 degrees from the
              learned irradiance's direction is folded into it, one 15-45 degrees away moves to it),
              albedo_prior, mask_loss, offset_bound and pose_refine (its poses polished once more at the end,
              the avatar frozen), plus colours initialised from 8 frames, colour lr 1e-2, LPIPS on the box
              around the subject on every second iteration (at twice the weight) and densification at half the
              paper's gradient threshold. What each is worth: docs/quality.md
    paper     the published method (SplattingAvatar, CVPR 2024): ``TrainConfig()``, no component

A recipe sets the same keys whatever it starts from, so applying it to any config gives that recipe's model
(``meshsplat train --resume --recipe NAME`` relies on it: the resume check then refuses another recipe than the
run's). Schedules (iterations, when densification runs) are not part of a recipe.

    from meshsplat.train import recipe_config, train
    cfg = recipe_config("quality")
    cfg.data, cfg.out = "path/to/dataset", "runs/quality"
    train(cfg)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from meshsplat.errors import MeshsplatError
from meshsplat.io.dataclass_dict import flat_items
from meshsplat.train.components import COMPONENTS
from meshsplat.train.config import TrainConfig, apply_overrides

__all__ = ["Recipe", "RECIPES", "DEFAULT_RECIPE", "recipe_overrides", "recipe_config", "recipe_differences"]


@dataclass(frozen=True)
class Recipe:
    """The components a recipe switches on and its ``section.key=value`` settings over ``TrainConfig()``."""

    components: tuple[str, ...]
    settings: tuple[str, ...] = ()


_QUALITY_SETTINGS = (
    "model.init_color_frames=8",
    "optim.lr_color=1e-2",
    "loss.crop_to_subject=true",
    "loss.lpips_every=2",
    "strategy.grow_grad2d=1e-4",
    "shading.key_agree_deg=45",
    "shading.key_snap_deg=15",
    "pose_refine.polish_steps=20",
    "pose_refine.polish_lr=3e-3",
)
_PAPER_SETTINGS = (  # the published values of the keys the other recipes set
    "model.init_color_frames=1",
    "optim.lr_color=2.5e-3",
    "loss.crop_to_subject=false",
    "loss.lpips_every=1",
    "strategy.grow_grad2d=2e-4",
    "shading.key_agree_deg=0",
    "shading.key_snap_deg=0",
    "pose_refine.polish_steps=0",
    "pose_refine.polish_lr=1e-3",
)
RECIPES: dict[str, Recipe] = {
    "quality": Recipe(("shading", "albedo_prior", "mask_loss", "offset_bound", "pose_refine"), _QUALITY_SETTINGS),
    "paper": Recipe((), _PAPER_SETTINGS),
}
DEFAULT_RECIPE = "quality"


def recipe_overrides(name: str) -> tuple[str, ...]:
    """The ``key=value`` overrides of recipe ``name`` (every component's switch, then its settings); one
    MeshsplatError for an unknown name."""
    if name not in RECIPES:
        raise MeshsplatError(f"recipe: expected one of {', '.join(RECIPES)}, got {name!r}")
    recipe = RECIPES[name]
    switches = tuple(f"{c.name}.enabled={str(c.name in recipe.components).lower()}" for c, _ in COMPONENTS)
    return (f"recipe={name}", *switches, *recipe.settings)


def recipe_config(name: str = DEFAULT_RECIPE, **fields: Any) -> TrainConfig:
    """A new ``TrainConfig`` of recipe ``name``, with top-level ``fields`` set (``data=..., out=..., iterations=...``)."""
    cfg = apply_overrides(TrainConfig(), list(recipe_overrides(name)))
    return dataclasses.replace(cfg, **fields) if fields else cfg


_NOT_RECIPE = ("data", "data_format", "model_dir", "out", "device", "progress", "recipe")


def recipe_differences(cfg: TrainConfig, name: str | None = None) -> list[str]:
    """``"key=value (recipe: value)"`` for each key where ``cfg`` differs from recipe ``name`` (default: the
    recipe ``cfg`` names), paths and how it runs left out."""
    want = dict(flat_items(recipe_config(name or cfg.recipe).to_dict()))
    out = []
    for key, value in flat_items(cfg.to_dict()):
        if key.split(".")[0] not in _NOT_RECIPE and want.get(key) != value:
            out.append(f"{key}={value!r} (recipe: {want.get(key)!r})")
    return out
