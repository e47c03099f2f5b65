"""meshsplat train --preset / --config / --set precedence, --set forms, resuming across presets and versions."""

from __future__ import annotations

import json

import pytest
import torch

from meshsplat.cli import train_cmd
from meshsplat.cli.main import build_parser, main
from meshsplat.io.checkpoint import load_checkpoint, save_checkpoint
from meshsplat.train import Trainer, apply_overrides, load_config, preset_config, preset_overrides
from meshsplat.train.config import CONFIG_VERSION
from test_train import small_config, tiny_dataset  # noqa: F401  (fixture)


def _config(argv: list[str]):
    return train_cmd.build_config(build_parser("train").parse_args(["train", *argv]))


def _model(cfg) -> tuple:
    return cfg.model.shading, cfg.model.init_color_frames, cfg.optim.lr_color


def test_precedence_preset_then_config_then_set_then_flags(tmp_path, capsys):
    base = ["DATA", "--out", str(tmp_path / "r")]
    assert _config(base) == apply_overrides(preset_config("quality"), ["data=DATA", f"out={tmp_path / 'r'}"])
    assert _model(_config(base + ["--preset", "paper"])) == ("none", 1, 2.5e-3)
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"version": 2, "seed": 7, "model": {"init_color_frames": 3}}))
    cfg = _config(base + ["--preset", "paper", "--config", str(partial)])
    assert _model(cfg) == ("none", 3, 2.5e-3) and cfg.seed == 7  # the file over the preset
    assert "init_color_frames=3 (the paper preset's: 1)" in capsys.readouterr().out
    cfg = _config(base + ["--config", str(partial), "--set", "model.init_color_frames=5", "seed=9", "--seed", "11"])
    assert _model(cfg) == ("sh2", 5, 1e-2) and cfg.seed == 11  # --set over the file, flags over --set


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


def test_resume_refuses_another_preset(tiny_dataset, tmp_path, capsys):  # noqa: F811
    out = str(tmp_path / "run")
    common = ["train", str(tiny_dataset), "--out", out, "--device", "cpu", "--no-progress", "--threads", "1"]
    small = ["--set", "model.n_init=60", "backend=torch", "loss.lambda_lpips=0", "checkpoint_every=2"]
    assert main(common + ["--iters", "2", "--preset", "paper"] + small) == 0
    assert json.loads((tmp_path / "run" / "config.json").read_text())["model"]["shading"] == "none"
    capsys.readouterr()
    assert main(common + ["--iters", "3", "--resume", "--preset", "quality"]) == 2
    err = capsys.readouterr().err
    assert "cannot resume from ckpt_00000002.pt with a changed config" in err
    assert "model.shading: 'none' -> 'sh2'" in err and "optim.lr_color: 0.0025 -> 0.01" in err
    assert main(common + ["--iters", "3", "--resume"]) == 0  # no --preset: the run's own
    assert main(common + ["--iters", "4", "--resume", "--preset", "paper"]) == 0
    assert (
        load_checkpoint(tmp_path / "run" / "checkpoints" / "ckpt_00000004.pt")["config"]["model"]["shading"] == "none"
    )


def test_run_folder_of_an_older_version_resumes_as_written(tiny_dataset, tmp_path):  # noqa: F811
    """A paper run written before presets and before the shading keys (no version, no model.shading or
    model.init_color_frames in config.json or the checkpoint, nor loss.crop_to_subject, loss.lpips_every or
    model.occlusion)
    resumes bit for bit under the quality defaults."""
    paper = list(preset_overrides("paper"))
    full = Trainer(small_config(tiny_dataset, tmp_path / "full", 20, paper))
    full.train()
    st = load_checkpoint(tmp_path / "full" / "checkpoints" / "ckpt_00000010.pt")
    for key in ("shading", "init_color_frames", "occlusion"):
        del st["config"]["model"][key]
    del st["config"]["loss"]["crop_to_subject"]
    del st["config"]["loss"]["lpips_every"]
    (tmp_path / "old" / "checkpoints").mkdir(parents=True)
    save_checkpoint(tmp_path / "old" / "checkpoints" / "ckpt_00000010.pt", st)
    old = dict(st["config"], out=str(tmp_path / "old"))
    (tmp_path / "old" / "config.json").write_text(json.dumps(old))  # no "version": older meshsplat
    cfg = load_config(tmp_path / "old" / "config.json")
    assert (cfg.model.shading, cfg.model.init_color_frames, cfg.optim.lr_color) == ("none", 1, 2.5e-3)
    assert not cfg.loss.crop_to_subject and cfg.loss.lpips_every == 1 and cfg.model.occlusion == "none"
    res = Trainer(cfg, resume=True)
    res.train()
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k
    assert json.loads((tmp_path / "old" / "config.json").read_text())["version"] == CONFIG_VERSION  # rewritten, full
