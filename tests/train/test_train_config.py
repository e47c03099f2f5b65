"""Training config (JSON round trip, --set overrides) and learning-rate schedule."""

from __future__ import annotations

import json
import math

import pytest
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.train.components import COMPONENTS
from meshsplat.train.config import OptimConfig, TrainConfig, apply_overrides, load_config
from meshsplat.train.optim import LrSchedule, base_learning_rates, build_optimizers, expon_lr
from meshsplat.train.recipes import recipe_config, recipe_differences


def test_defaults_are_the_published_method_and_every_component_is_off():
    c = TrainConfig()
    assert (c.model.init_color_frames, c.optim.lr_color, c.strategy.grow_grad2d) == (1, 2.5e-3, 2e-4)
    assert (c.loss.crop_to_subject, c.loss.lpips_every, c.recipe) == (False, 1, "paper")
    assert c.iterations == 30_000 and c.model.n_init == 10_000 and c.model.sh_degree == 0
    s = c.strategy
    assert (s.refine_start_iter, s.refine_stop_iter, s.refine_every, s.reset_every) == (600, 15_000, 100, 3000)
    assert not any(getattr(c, comp.name).enabled for comp, _ in COMPONENTS)
    assert TrainConfig() == recipe_config("paper")


def test_a_partial_yaml_config_changes_only_its_keys_over_the_recipe(tmp_path):
    (tmp_path / "mine.yaml").write_text("strategy:\n  max_gaussians: 5000\nmask_loss:\n  weight: 0.3\n")
    cfg = load_config(tmp_path / "mine.yaml", base=recipe_config("quality"))
    want = apply_overrides(recipe_config("quality"), ["strategy.max_gaussians=5000", "mask_loss.weight=0.3"])
    assert cfg == want and cfg.recipe == "quality" and cfg.shading.enabled
    assert recipe_differences(cfg) == [
        "strategy.max_gaussians=5000 (recipe: 150000)",
        "mask_loss.weight=0.3 (recipe: 0.1)",
    ]
    (tmp_path / "paper.yml").write_text("recipe: paper\n")  # a file may name its recipe
    assert load_config(tmp_path / "paper.yml").recipe == "paper"
    (tmp_path / "empty.yaml").write_text("")
    assert load_config(tmp_path / "empty.yaml") == TrainConfig()
    (tmp_path / "bad.yaml").write_text("model: [1, 2\n")
    with pytest.raises(MeshsplatError, match=r"bad.yaml: not valid YAML"):
        load_config(tmp_path / "bad.yaml")
    (tmp_path / "code.yaml").write_text("model: !!python/object/apply:os.system ['echo no']\n")
    with pytest.raises(MeshsplatError, match="not valid YAML"):  # safe loading: plain data only
        load_config(tmp_path / "code.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(MeshsplatError, match="expected a training config"):
        load_config(tmp_path / "list.yaml")


def test_config_files_of_another_format_or_version_are_refused_in_one_line(tmp_path):
    for doc, match in [
        ({"format": "meshsplat-train-config", "version": 14}, "pre-release meshsplat"),
        ({"format": "something-else"}, "is not a training config"),
        ({"format": "meshsplat-config", "version": 2}, "newer than this meshsplat"),
        ({"version": "1"}, "positive integer"),
    ]:
        with pytest.raises(MeshsplatError, match=match):
            TrainConfig.from_dict(doc)
    TrainConfig().to_json(tmp_path / "c.json")
    assert json.loads((tmp_path / "c.json").read_text())["format"] == "meshsplat-config"


def test_json_roundtrip(tmp_path):
    c = apply_overrides(
        TrainConfig(),
        [
            "strategy.refine_every=200",
            "walk.enabled=false",
            "loss.lambda_mse=10",
            "model.scale_mode=area",
            "iterations=1e3",
            "seed=7",
        ],
    )
    assert c.strategy.refine_every == 200 and c.walk.enabled is False and c.loss.lambda_mse == 10.0
    assert c.model.scale_mode == "area" and c.iterations == 1000 and c.seed == 7
    c.to_json(tmp_path / "c.json")
    c2 = load_config(tmp_path / "c.json")
    assert c2 == c
    (tmp_path / "partial.json").write_text(json.dumps({"strategy": {"max_gaussians": 5000}}))
    p = load_config(tmp_path / "partial.json")
    assert p.strategy.max_gaussians == 5000 and p.strategy.refine_every == 100


@pytest.mark.parametrize(
    "item, match",
    [
        ("strategy.nope=1", "unknown key"),
        ("nope.x=1", "unknown section"),
        ("walk.enabled=maybe", "true/false"),
        ("strategy.refine_every=1.5", "expects int"),
        ("loss.lambda_l1=abc", "expects float"),
        ("strategy", "key=value"),
        ("model=3", "unknown key"),
        ("strategy.refine_start=5", "unknown key"),
        ("strategy.prune_scale2d=20", "fraction of the image size"),
        ("backend=vulkan", "backend: auto"),
        ("loss.lpips_every=0", r"^config: loss\.lpips_every must be >= 1 \(1 = LPIPS on every iteration\)$"),
        ("loss.lpips_every=-4", r"loss\.lpips_every must be >= 1"),
        ("loss.lpips_every=2.5", "loss.lpips_every expects int"),
    ],
)
def test_override_errors(item, match):
    with pytest.raises(MeshsplatError, match=match):
        apply_overrides(TrainConfig(), [item]).validate()


def test_validate_and_bad_files(tmp_path):
    with pytest.raises(MeshsplatError, match="scale_mode"):
        apply_overrides(TrainConfig(), ["model.scale_mode=cube"]).validate()
    for margin in ("-0.1", "1.5"):
        with pytest.raises(MeshsplatError, match=r"loss\.crop_margin must be in"):
            apply_overrides(TrainConfig(), [f"loss.crop_margin={margin}"]).validate()
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(MeshsplatError, match="not valid JSON"):
        load_config(tmp_path / "bad.json")
    with pytest.raises(MeshsplatError, match="not found"):
        load_config(tmp_path / "missing.json")
    with pytest.raises(MeshsplatError, match="unknown key"):
        TrainConfig.from_dict({"model": {"colour": 1}})


def test_expon_lr_matches_3dgs_schedule():
    assert expon_lr(0, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-4)
    assert expon_lr(100, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-6)
    assert expon_lr(50, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-5)  # geometric midpoint
    assert expon_lr(500, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-6)
    # delay multiplier: warm-up from 0.01x to 1x over the delay steps (3DGS)
    assert expon_lr(0, 1.0, 1.0, 100, lr_delay_steps=10, lr_delay_mult=0.01) == pytest.approx(0.01)
    assert expon_lr(5, 1.0, 1.0, 100, lr_delay_steps=10, lr_delay_mult=0.01) == pytest.approx(
        0.01 + 0.99 * math.sin(math.pi / 4)
    )
    assert expon_lr(10, 1.0, 1.0, 100, lr_delay_steps=10, lr_delay_mult=0.01) == pytest.approx(1.0)


def test_embedding_lrs_scale_with_mesh_and_decay():
    cfg = OptimConfig()
    lrs = base_learning_rates(cfg, extent=2.0, mean_edge=0.05)
    assert lrs["d"] == pytest.approx(1.6e-4 * 2.0)
    assert lrs["duv"] == pytest.approx(1.6e-4 * 2.0 / 0.05)
    bary = base_learning_rates(OptimConfig(uv_lr_units="barycentric"), 2.0, 0.05)
    assert bary["duv"] == pytest.approx(1.6e-4)
    params = {k: torch.nn.Parameter(torch.zeros(3, 2)) for k in ("duv", "d", "sh0", "rotation")}
    params["uv"] = torch.zeros(3, 2)
    opts = build_optimizers(params, lrs)
    assert set(opts) == {"duv", "d", "sh0", "rotation"}
    assert all(o.defaults["eps"] == 1e-15 for o in opts.values())
    sched = LrSchedule(cfg, lrs, max_steps=1000)
    got = sched.apply(opts, 1000)
    assert got["d"] == pytest.approx(1.6e-6 * 2.0) and got["sh0"] == pytest.approx(cfg.lr_color)  # colour: constant
    assert opts["duv"].param_groups[0]["lr"] == pytest.approx(1.6e-6 * 2.0 / 0.05)


def test_optimizers_are_torchs_fused_adam_on_cpu_with_adams_arithmetic():
    """Where torch has a fused Adam for the device (CPU since torch 2.4) every Gaussian optimizer uses it: after
    twenty steps the tensors agree with torch's default Adam to float rounding."""
    gen = torch.Generator().manual_seed(0)
    start = {k: torch.randn(50, 3, generator=gen) for k in ("duv", "sh0", "rotation")}
    grads = [{k: torch.randn(50, 3, generator=gen) for k in start} for _ in range(20)]
    lrs = {"duv": 1e-2, "sh0": 2.5e-3, "rotation": 1e-3}
    params = {k: torch.nn.Parameter(v.clone()) for k, v in start.items()}
    opts = build_optimizers(params, lrs)
    fused_here = tuple(int(v) for v in torch.__version__.split("+")[0].split(".")[:2]) >= (2, 4)
    assert all(bool(o.param_groups[0]["fused"]) == fused_here for o in opts.values())
    plain = {k: torch.nn.Parameter(v.clone()) for k, v in start.items()}
    ref = {k: torch.optim.Adam([plain[k]], lr=lrs[k], eps=1e-15) for k in plain}
    for g in grads:
        for k in start:
            params[k].grad, plain[k].grad = g[k].clone(), g[k].clone()
            opts[k].step()
            ref[k].step()
    for k in start:
        torch.testing.assert_close(params[k].detach(), plain[k].detach(), rtol=1e-6, atol=1e-7)
        assert not torch.equal(params[k].detach(), start[k])


def test_colour_lr_decay_hits_both_ends_and_none_keeps_todays_lrs(tmp_path):
    base = OptimConfig(lr_color=1e-2)  # the quality recipe's
    lrs = base_learning_rates(base, extent=2.0, mean_edge=0.05)
    today = LrSchedule(base, lrs, max_steps=1000)
    assert OptimConfig().lr_color_final is None
    for step in (0, 1, 500, 1000, 1200):  # None: every key as before (colour constant, embedding decays)
        for key in lrs:
            ratio = base.lr_embedding_final / base.lr_embedding
            want = lrs[key] if key not in ("duv", "d") else expon_lr(step, lrs[key], lrs[key] * ratio, 1000)
            assert today.lr(key, step) == want, (key, step)
    cfg = OptimConfig(lr_color=1e-2, lr_color_final=1e-3)
    sched = LrSchedule(cfg, lrs, max_steps=1000)
    assert sched.lr("sh0", 0) == pytest.approx(1e-2) and sched.lr("sh0", 1000) == pytest.approx(1e-3)
    assert sched.lr("sh0", 500) == pytest.approx(math.sqrt(1e-2 * 1e-3))  # log-linear
    assert sched.lr("sh0", 5000) == pytest.approx(1e-3)  # past the end: the final lr
    assert sched.lr("shN", 0) == pytest.approx(cfg.lr_shN) and sched.lr("shN", 1000) == pytest.approx(cfg.lr_shN / 10)
    for key in ("duv", "d", "opacity_logit", "log_scale", "rotation"):  # only the colour keys change
        assert [sched.lr(key, s) for s in (0, 700, 1000)] == [today.lr(key, s) for s in (0, 700, 1000)], key
    # scaled base lrs (batches: times sqrt(batch size)) keep the ratio
    big = LrSchedule(cfg, {k: 2 * v for k, v in lrs.items()}, max_steps=10)
    assert big.lr("sh0", 10) == pytest.approx(2e-3)


def test_lr_color_final_parses_round_trips_and_validates(tmp_path):
    base = TrainConfig()
    assert apply_overrides(base, ["optim.lr_color_final=1e-3"]).optim.lr_color_final == 1e-3
    for none in ("null", "None", "none"):
        assert apply_overrides(base, [f"optim.lr_color_final={none}"]).optim.lr_color_final is None
    cfg = apply_overrides(base, ["optim.lr_color_final=3e-4"])
    cfg.to_json(tmp_path / "c.json")
    assert load_config(tmp_path / "c.json").optim.lr_color_final == 3e-4
    base.to_json(tmp_path / "d.json")
    assert json.loads((tmp_path / "d.json").read_text())["optim"]["lr_color_final"] is None
    assert load_config(tmp_path / "d.json").optim.lr_color_final is None
    with pytest.raises(MeshsplatError, match="lr_color_final expects float"):
        apply_overrides(base, ["optim.lr_color_final=fast"])
    for bad in (
        ["optim.lr_color_final=0"],
        ["optim.lr_color_final=-1e-3"],
        ["optim.lr_color=0", "optim.lr_color_final=1e-3"],
    ):
        with pytest.raises(MeshsplatError, match="lr_color_final"):
            apply_overrides(base, bad).validate()
