"""Training recipes: quality is the default of `meshsplat train`, paper is the published method (TrainConfig())."""

from __future__ import annotations

import json

import pytest

from meshsplat.errors import MeshsplatError
from meshsplat.train import DEFAULT_RECIPE, RECIPES, TrainConfig, apply_overrides, load_config, recipe_config
from meshsplat.train.components import COMPONENTS
from meshsplat.train.config import CONFIG_FORMAT, CONFIG_VERSION
from meshsplat.train.recipes import recipe_differences, recipe_overrides


def test_quality_is_the_default_recipe():
    assert DEFAULT_RECIPE == "quality" and set(RECIPES) == {"quality", "paper"}
    q = recipe_config()
    assert q == recipe_config("quality") and q.recipe == "quality"
    assert q.shading.enabled and (q.shading.occlusion, q.shading.key_soft, q.shading.grid) == ("key", 12.0, 96)
    assert (q.model.init_color_frames, q.optim.lr_color, q.loss.crop_to_subject) == (8, 1e-2, True)


def test_paper_recipe_is_the_published_method():
    c = recipe_config("paper")
    # model: one colour per Gaussian (SH degree 0, no shading), colours from the first training frame
    m = c.model
    assert (m.sh_degree, m.init_color, m.init_color_frames) == (0, "image", 1)
    assert (m.n_init, m.init_opacity, m.init_knn, m.sh_frame) == (10_000, 0.1, 3, "world")
    assert not m.freeze_embedding and not m.antialiased
    # sqrt_area is our documented fix of the published pose scale (README "Where we differ"); area is the paper's
    assert m.scale_mode == "sqrt_area"
    # the paper's (3DGS) learning rates
    o = c.optim
    assert (o.lr_embedding, o.lr_embedding_final, o.lr_delay_mult, o.lr_delay_steps) == (1.6e-4, 1.6e-6, 0.01, 0)
    assert (o.lr_color, o.lr_shN, o.lr_opacity, o.lr_scale, o.lr_rotation) == (2.5e-3, 2.5e-3 / 20, 5e-2, 5e-3, 1e-3)
    assert o.eps == 1e-15 and o.uv_lr_units == "world"
    # L1 + 0.01 LPIPS + the scale regulariser (T_s = 0.004 x bbox diagonal, T_r = 10), nothing else
    los = c.loss
    assert (los.lambda_l1, los.lambda_lpips, los.lambda_scale, los.scale_max, los.scale_ratio) == (
        1.0,
        0.01,
        1.0,
        0.008,
        10.0,
    )
    assert (los.lambda_mse, los.lambda_ssim, los.lpips_every) == (0.0, 0.0, 1)
    assert not los.crop_to_subject  # LPIPS on the full frame
    # the 30k-iteration schedule: densify 600..15000 every 100, opacity reset every 3000
    s = c.strategy
    assert c.iterations == 30_000 and s.enabled
    assert (s.refine_start_iter, s.refine_stop_iter, s.refine_every, s.reset_every) == (600, 15_000, 100, 3000)
    assert (s.grow_grad2d, s.grow_scale3d, s.prune_opa, s.prune_scale3d) == (2e-4, 0.01, 0.005, 0.1)
    assert (s.reset_opa, s.split_n, s.max_gaussians) == (0.01, 2, 150_000)
    # gsplat's 0.15 of the image (docs/config.md: the paper's code used 20 px, 0.078 at 256 px)
    assert s.prune_scale2d == 0.15
    # walking on triangles (Algorithm 1) every 100 iterations, the paper's re-expression
    assert (c.walk.enabled, c.walk.every, c.walk.mode) == (True, 100, "paper")
    assert c.background == "random" and c == TrainConfig()
    # no component: one colour per Gaussian, no silhouette term, offsets unbounded, the tracker's poses kept
    assert not any(getattr(c, comp.name).enabled for comp, _ in COMPONENTS)


def test_recipes_set_the_same_keys_and_differ_only_there():
    keys = {name: [item.split("=")[0] for item in recipe_overrides(name)] for name in RECIPES}
    assert keys["quality"] == keys["paper"]
    # applying a recipe's overrides to any config gives that recipe's model
    assert apply_overrides(recipe_config("quality"), list(recipe_overrides("paper"))) == recipe_config("paper")
    assert apply_overrides(recipe_config("paper"), list(recipe_overrides("quality"))) == recipe_config("quality")
    # the quality recipe: five components and nine values over the published method, nothing else
    assert recipe_differences(recipe_config("paper"), "quality") == [
        "model.init_color_frames=1 (recipe: 8)",
        "optim.lr_color=0.0025 (recipe: 0.01)",
        "loss.crop_to_subject=False (recipe: True)",
        "loss.lpips_every=1 (recipe: 2)",
        "strategy.grow_grad2d=0.0002 (recipe: 0.0001)",
        "shading.enabled=False (recipe: True)",
        "shading.key_agree_deg=0.0 (recipe: 45.0)",
        "shading.key_snap_deg=0.0 (recipe: 15.0)",
        "albedo_prior.enabled=False (recipe: True)",
        "mask_loss.enabled=False (recipe: True)",
        "offset_bound.enabled=False (recipe: True)",
        "pose_refine.enabled=False (recipe: True)",
        "pose_refine.polish_steps=0 (recipe: 20)",
        "pose_refine.polish_lr=0.001 (recipe: 0.003)",
    ]
    assert recipe_differences(recipe_config("paper")) == []
    with pytest.raises(MeshsplatError, match="recipe: expected one of quality, paper, got 'best'"):
        recipe_config("best")


def test_config_json_carries_its_format_and_every_key(tmp_path):
    cfg = apply_overrides(recipe_config("quality"), ["seed=4"])
    cfg.to_json(tmp_path / "config.json")
    doc = json.loads((tmp_path / "config.json").read_text())
    assert (doc["format"], doc["version"], doc["recipe"]) == (CONFIG_FORMAT, CONFIG_VERSION, "quality")
    assert load_config(tmp_path / "config.json") == cfg
    assert load_config(tmp_path / "config.json", base=recipe_config("paper")) == cfg  # full: the base is unused
