"""`meshsplat train DATA --minutes N`: the schedule fitted to a time budget on this machine, from a measured
probe; schedule positions scale with the iterations, per-iteration rates keep their value; the choice is
said and stored in the run's config."""

from __future__ import annotations

import json

import pytest

from _capture_kit import _capture
from meshsplat.cli.main import main
from meshsplat.errors import MeshsplatError
from meshsplat.train import TrainConfig
from meshsplat.train.budget import (
    GROWTH_FACTOR,
    KEPT_KEYS,
    MIN_ITERATIONS,
    NOISE_MARGIN,
    SCALED_KEYS,
    Measurement,
    mean_gaussians,
    plan_budget,
    planned_seconds,
    scale_schedule,
)
from meshsplat.train.recipes import recipe_config


def _value(cfg: TrainConfig, key: str) -> int:
    node: object = cfg
    for part in key.split("."):
        node = getattr(node, part)
    return int(node)  # type: ignore[call-overload]


def test_scaling_moves_the_schedule_positions_and_keeps_the_rates():
    cfg = recipe_config("quality")
    cfg.optim.lr_delay_steps = 0  # off stays off
    scaled, pairs = scale_schedule(cfg, 1500)
    assert scaled.iterations == 1500 and pairs[0] == "iterations=1500"
    assert scaled.strategy.refine_start_iter == 30 and scaled.strategy.refine_stop_iter == 750  # 600, 15000 x 0.05
    assert scaled.checkpoint_every == 250 and scaled.preview_every == 50
    assert scaled.optim.lr_delay_steps == 0 and not [p for p in pairs if p.startswith("optim.lr_delay_steps")]
    for key in KEPT_KEYS:
        assert _value(scaled, key) == _value(cfg, key), key
    for key in SCALED_KEYS:
        if _value(cfg, key):
            assert f"{key}={_value(scaled, key)}" in pairs
    tiny, _ = scale_schedule(cfg, 10)  # never below 1
    assert tiny.strategy.refine_start_iter == 1 and tiny.preview_every == 1


def test_the_mean_model_size_over_a_schedule_that_grows_it():
    """n_init until refine_start, a linear growth to the planned size at refine_stop, that size after; the
    same mean for the schedule scaled to any length."""
    cfg = recipe_config("quality")
    cfg.model.n_init, cfg.iterations = 100, 1000
    cfg.strategy.refine_start_iter, cfg.strategy.refine_stop_iter = 100, 600
    assert mean_gaussians(cfg, 500) == pytest.approx(100 * 0.1 + 300 * 0.5 + 500 * 0.4)  # 360
    assert mean_gaussians(scale_schedule(cfg, 250)[0], 500) == pytest.approx(360)
    assert mean_gaussians(cfg, 100) == pytest.approx(100)  # no growth
    cfg.strategy.refine_stop_iter = 5000  # densifying to the end: half-way mean over the growth
    assert mean_gaussians(cfg, 500) == pytest.approx(100 * 0.1 + 300 * 0.9)


def test_the_plan_counts_growth_and_extra_work():
    """Planned seconds: setup, each frame read once, the iterations at their mean cost with the margin, the
    components' extra renders; the initial cost alone where growth was not measured."""
    m = Measurement(5.0, 0.1, 0.02, 10, 100, 500, 0.3, 0.2, 40, 0.05)
    assert m.per_iteration_s == 0.2 and m.extra_s == pytest.approx(2.0)
    assert planned_seconds(m, 1000) == pytest.approx(5.0 + 10 * 0.02 + 1000 * 0.2 * NOISE_MARGIN + 2.0)
    plain = Measurement(5.0, 0.1, 0.02, 10)
    assert plain.per_iteration_s == 0.1 and planned_seconds(plain, 4) == pytest.approx(
        5.0 + 4 * 0.02 + 0.4 * NOISE_MARGIN
    )


def test_a_budget_is_measured_on_this_machine_and_fits_the_iterations(tmp_path):
    root = _capture(tmp_path / "cap")
    cfg = recipe_config("quality", data=str(root), out=str(tmp_path / "run"), device="cpu", progress=False)
    cfg.model.n_init = 200
    scaled, budget = plan_budget(cfg, 2.0)
    m = budget.measured
    assert m.iteration_s > 0 and m.frame_s > 0 and m.setup_s >= 0 and m.frames == 4  # 6 frames, 4 for training
    # the growth densification is planned for, measured on a model of that size (the recipe caps at 150,000)
    assert m.gaussians == 200 and m.grown_gaussians == round(GROWTH_FACTOR * 200) and m.grown_iteration_s > 0
    assert (
        m.iteration_s
        <= m.per_iteration_s
        == pytest.approx(
            m.iteration_s
            + max(m.grown_iteration_s - m.iteration_s, 0)
            / (m.grown_gaussians - 200)
            * (mean_gaussians(cfg, 1000) - 200)
        )
    )
    assert m.extra_renders == 0 and m.extra_s == 0  # a mesh capture: no pose polish
    assert budget.planned_s == planned_seconds(m, budget.iterations) <= 2.0 * 60
    assert planned_seconds(m, budget.iterations + 1) > 2.0 * 60  # the most that fit
    assert MIN_ITERATIONS <= budget.iterations < 30_000
    assert scaled.iterations == budget.iterations and budget.factor == pytest.approx(budget.iterations / 30_000)
    assert scaled.strategy.refine_stop_iter == round(15_000 * budget.factor)
    assert not (tmp_path / "run").exists()  # the probe trained in a temporary folder
    assert f"--iters {budget.iterations} --set strategy.refine_start_iter=" in budget.summary()
    assert "at 1,000 Gaussians, the growth planned for" in budget.summary()
    capped = recipe_config("quality", data=str(root), out=str(tmp_path / "run"), device="cpu", progress=False)
    capped.model.n_init, capped.strategy.max_gaussians, capped.strategy.enabled = 200, 300, True
    assert plan_budget(capped, 2.0)[1].measured.grown_gaussians == 300  # at most max_gaussians
    capped.strategy.enabled = False  # no densification: no growth measured
    off = plan_budget(capped, 2.0)[1].measured
    assert off.grown_gaussians == 200 and off.grown_iteration_s == 0 and off.per_iteration_s == off.iteration_s
    with pytest.raises(MeshsplatError, match=r"--minutes 0\.001: too short on this machine .* give more minutes"):
        plan_budget(cfg, 0.001)


def test_the_cli_says_what_it_chose_and_the_run_keeps_it(tmp_path, capsys):
    root = _capture(tmp_path / "cap")
    run = tmp_path / "run"
    args = ["train", str(root), "--out", str(run), "--minutes", "2", "--device", "cpu", "--no-progress"]
    # a configured schedule of 60 iterations fits in 2 minutes: the whole of it is trained
    assert main([*args, "--set", "model.n_init=100", "loss.lambda_lpips=0", "iterations=60"]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("budget 2 min: measured"))
    assert "training 60 iterations (the full schedule fits; planned " in line
    assert json.loads((run / "config.json").read_text())["iterations"] == 60
    assert "iteration 60," in out
    with pytest.raises(SystemExit):  # argparse: one of the two
        main([*args, "--iters", "5"])
    assert "argument --iters: not allowed with argument --minutes" in capsys.readouterr().err
    assert main([*args, "--resume"]) == 2
    assert "a resumed run keeps its schedule" in capsys.readouterr().err
    args[args.index("2")] = "0"
    assert main(args) == 2
    assert "--minutes: expected 0.1..525600 minutes, got 0" in capsys.readouterr().err


def test_a_budget_is_refused_in_a_process_group(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(MeshsplatError, match=r"--minutes: this process is one of 2 \(WORLD_SIZE\).* --iters"):
        plan_budget(recipe_config("quality", data=str(tmp_path), out=str(tmp_path / "run")), 5.0)
