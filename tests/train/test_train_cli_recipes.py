"""meshsplat train --recipe / --config / --set precedence, --set forms, what it prints, resuming across recipes."""

from __future__ import annotations

import json

import pytest

from meshsplat.cli import train_cmd
from meshsplat.cli.main import build_parser, main
from meshsplat.errors import MeshsplatError
from meshsplat.io.checkpoint import load_checkpoint
from meshsplat.train import apply_overrides, recipe_config


def _config(argv: list[str]):
    return train_cmd.build_config(build_parser("train").parse_args(["train", *argv]))


def _model(cfg) -> tuple:
    return cfg.shading.enabled, cfg.model.init_color_frames, cfg.optim.lr_color


def test_precedence_recipe_then_config_then_set_then_flags(tmp_path):
    base = ["DATA", "--out", str(tmp_path / "r")]
    assert _config(base) == apply_overrides(recipe_config("quality"), ["data=DATA", f"out={tmp_path / 'r'}"])
    assert _model(_config(base + ["--recipe", "paper"])) == (False, 1, 2.5e-3)
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"seed": 7, "model": {"init_color_frames": 3}}))
    cfg = _config(base + ["--recipe", "paper", "--config", str(partial)])
    assert _model(cfg) == (False, 3, 2.5e-3) and cfg.seed == 7  # the file over the recipe
    cfg = _config(base + ["--config", str(partial), "--set", "model.init_color_frames=5", "seed=9", "--seed", "11"])
    assert _model(cfg) == (True, 5, 1e-2) and cfg.seed == 11  # --set over the file, flags over --set
    named = tmp_path / "named.yaml"
    named.write_text("recipe: paper\nseed: 5\n")  # a file naming its recipe
    assert _model(_config(base + ["--config", str(named)])) == (False, 1, 2.5e-3)
    with pytest.raises(MeshsplatError, match=r"--recipe quality and .*named\.yaml \(recipe: paper\) differ"):
        _config(base + ["--config", str(named), "--recipe", "quality"])
    named.write_text("recipe: best\n")
    with pytest.raises(MeshsplatError, match="recipe: expected one of quality, paper, got 'best'"):
        _config(base + ["--config", str(named)])


def test_train_prints_the_recipe_and_what_differs_from_it():
    cfg = apply_overrides(recipe_config("quality"), ["seed=3", "mask_loss.weight=0.3"])
    assert train_cmd.recipe_summary(cfg).splitlines() == [
        "recipe quality, 2 key(s) set otherwise:",
        "  seed=3 (recipe: 0)",
        "  mask_loss.weight=0.3 (recipe: 0.1)",
    ]
    assert train_cmd.recipe_summary(recipe_config("paper")) == "recipe paper as it is"
    many = apply_overrides(recipe_config("quality"), [f"strategy.{k}=7" for k in ("refine_every", "reset_every")])
    many = apply_overrides(many, ["seed=1", "iterations=9", "walk.every=3", "log_every=2", "preview_every=4"])
    lines = train_cmd.recipe_summary(many, shown=6).splitlines()
    assert len(lines) == 8 and lines[-1].startswith("  ... and 1 more (all keys: ")


@pytest.mark.parametrize(
    "argv",
    [
        ["DATA", "--set", "seed=3", "walk.every=7", "--out", "R"],
        ["DATA", "--out", "R", "--set", "seed=3", "walk.every=7"],
        ["DATA", "--set", "seed=3", "--out", "R", "--set", "walk.every=7"],
        ["--set", "seed=3", "walk.every=7", "--out", "R", "DATA"],
        ["--out", "R", "DATA", "--set", "seed=3", "--set", "walk.every=7"],
    ],
)
def test_set_takes_several_pairs_and_repeats(argv):
    args = build_parser("train").parse_args(["train", *argv])
    assert (args.dataset, args.out, args.set) == ("DATA", "R", ["seed=3", "walk.every=7"])
    cfg = train_cmd.build_config(args)
    assert (cfg.seed, cfg.walk.every) == (3, 7)


def test_set_before_the_dataset_is_one_clear_error(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser("train").parse_args(["train", "--set", "seed=3", "DATA", "--out", "R"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == (
        "meshsplat train: error: argument --set: expected KEY=VALUE, got 'DATA'; --set takes every word "
        "up to the next option, so put the dataset before --set (meshsplat train DATA --out RUN --set "
        "a.b=1 c.d=2)"
    )


def test_resume_refuses_another_recipe(tiny_dataset, tmp_path, capsys):
    out = str(tmp_path / "run")
    common = ["train", str(tiny_dataset), "--out", out, "--device", "cpu", "--no-progress", "--threads", "1"]
    small = ["--set", "model.n_init=60", "backend=torch", "loss.lambda_lpips=0", "checkpoint_every=2"]
    assert main(common + ["--iters", "2", "--recipe", "paper"] + small) == 0
    assert not json.loads((tmp_path / "run" / "config.json").read_text())["shading"]["enabled"]
    assert "recipe paper, " in capsys.readouterr().out
    assert main(common + ["--iters", "3", "--resume", "--recipe", "quality"]) == 2
    err = capsys.readouterr().err
    assert "cannot resume from ckpt_00000002.pt with a changed config" in err
    assert "shading.enabled: False -> True" in err and "optim.lr_color: 0.0025 -> 0.01" in err
    assert main(common + ["--iters", "3", "--resume"]) == 0  # no --recipe: the run's own
    assert main(common + ["--iters", "4", "--resume", "--recipe", "paper"]) == 0
    ckpt = load_checkpoint(tmp_path / "run" / "checkpoints" / "ckpt_00000004.pt")
    assert not ckpt["config"]["shading"]["enabled"] and ckpt["config"]["recipe"] == "paper"


def test_a_partial_yaml_config_trains_the_default_recipe_with_its_keys_changed(tiny_dataset, tmp_path):
    mine = tmp_path / "mine.yaml"
    mine.write_text("model:\n  n_init: 60\nmask_loss:\n  weight: 0.3\nloss:\n  lambda_lpips: 0\n")
    out = tmp_path / "run"
    argv = ["train", str(tiny_dataset), "--out", str(out), "--config", str(mine), "--iters", "2"]
    assert main([*argv, "--device", "cpu", "--no-progress", "--threads", "1", "--set", "backend=torch"]) == 0
    written = json.loads((out / "config.json").read_text())
    want = apply_overrides(recipe_config("quality"), ["model.n_init=60", "mask_loss.weight=0.3", "loss.lambda_lpips=0"])
    for section in ("model", "shading", "albedo_prior", "mask_loss", "offset_bound", "pose_refine", "strategy"):
        assert written[section] == want.to_dict()[section], section
    assert written["recipe"] == "quality" and written["iterations"] == 2
    assert (out / "checkpoints" / "ckpt_00000002.pt").is_file()
