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
    GROWTH_PER_ROUND,
    KEPT_KEYS,
    MIN_ITERATIONS,
    NOISE_MARGIN,
    PROBE_GROWTH,
    SCALED_KEYS,
    Growth,
    Measurement,
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


def test_the_growth_planned_over_a_schedule():
    """GROWTH_PER_ROUND per densification step between refine_start and refine_stop, at most max_gaussians; the
    mean size: n_init until the start, linear growth to the final size at the stop, that size after. A shorter
    schedule has fewer steps and grows less; densification off: no growth."""
    cfg = recipe_config("quality")
    cfg.model.n_init, cfg.iterations, cfg.strategy.max_gaussians = 100, 1000, 10_000
    cfg.strategy.refine_start_iter, cfg.strategy.refine_stop_iter, cfg.strategy.refine_every = 100, 600, 50
    g = Growth.of(cfg)
    assert (g.gaussians, g.most, g.start, g.stop, g.every) == (100, 10_000, 0.1, 0.6, 50)
    n1 = 100 * GROWTH_PER_ROUND**10  # 500 iterations of densification, a step every 50
    assert g.size(1000) == pytest.approx(n1)
    assert g.mean(1000) == pytest.approx(100 * 0.1 + 0.5 * (100 + n1) * 0.5 + n1 * 0.4)
    assert g.size(500) == pytest.approx(100 * GROWTH_PER_ROUND**5)  # the schedule scaled: half the steps
    assert g.size(10**6) == 10_000  # capped
    assert Growth.of(scale_schedule(cfg, 500)[0]).size(500) == pytest.approx(g.size(500), rel=0.02)
    cfg.strategy.enabled = False
    assert Growth.of(cfg).size(1000) == 100


def test_the_plan_counts_growth_and_extra_work():
    """Planned seconds: setup, each frame read once, the iterations at their mean cost (linear in the
    Gaussians between the two probes) with the margin, the extra renders scaled to the planned final size;
    it grows with the iterations. Without the larger probe, the first cost alone."""
    g = Growth(100, 10_000, 0.1, 0.6, 50)
    m = Measurement(5.0, 0.1, 0.02, 10, g, 500, 0.3, 40, 0.05)
    assert m.iteration_cost(100) == 0.1 and m.iteration_cost(500) == pytest.approx(0.3)
    assert m.iteration_cost(300) == pytest.approx(0.2) and m.iteration_cost(50) == 0.1
    mean = 0.1 + 0.2 / 400 * (g.mean(1000) - 100)
    assert m.per_iteration_s(1000) == pytest.approx(mean)
    extra = 40 * 0.05 * m.iteration_cost(g.size(1000)) / 0.3
    assert m.extra_s(1000) == pytest.approx(extra)
    assert planned_seconds(m, 1000) == pytest.approx(5.0 + 10 * 0.02 + 1000 * mean * NOISE_MARGIN + extra)
    times = [planned_seconds(m, n) for n in range(0, 3000, 7)]
    assert times == sorted(times)
    plain = Measurement(5.0, 0.1, 0.02, 10)
    assert plain.per_iteration_s(4) == 0.1 and planned_seconds(plain, 4) == pytest.approx(
        5.0 + 4 * 0.02 + 0.4 * NOISE_MARGIN
    )


def test_a_budget_is_measured_on_this_machine_and_fits_the_iterations(tmp_path):
    root = _capture(tmp_path / "cap")
    cfg = recipe_config("quality", data=str(root), out=str(tmp_path / "run"), device="cpu", progress=False)
    cfg.model.n_init = 200
    scaled, budget = plan_budget(cfg, 2.0)
    m = budget.measured
    assert m.iteration_s > 0 and m.frame_s > 0 and m.setup_s >= 0 and m.frames == 4  # 6 frames, 4 for training
    # the larger probe: PROBE_GROWTH times n_init (the recipe caps at 150,000), the growth the schedule plans
    assert m.growth == Growth.of(cfg) and m.probe_gaussians == round(PROBE_GROWTH * 200) and m.probe_iteration_s > 0
    n = budget.iterations
    assert m.iteration_s <= m.per_iteration_s(n) == pytest.approx(m.iteration_cost(m.growth.mean(n)))
    assert m.extra_renders == 0 and m.extra_s(n) == 0  # a mesh capture: no pose polish
    assert budget.planned_s == planned_seconds(m, budget.iterations) <= 2.0 * 60
    assert planned_seconds(m, budget.iterations + 1) > 2.0 * 60  # the most that fit
    assert MIN_ITERATIONS <= budget.iterations < 30_000
    assert scaled.iterations == budget.iterations and budget.factor == pytest.approx(budget.iterations / 30_000)
    assert scaled.strategy.refine_stop_iter == round(15_000 * budget.factor)
    assert not (tmp_path / "run").exists()  # the probe trained in a temporary folder
    assert f"--iters {budget.iterations} --set strategy.refine_start_iter=" in budget.summary()
    assert "at 1,000 Gaussians; planned to grow to " in budget.summary()
    capped = recipe_config("quality", data=str(root), out=str(tmp_path / "run"), device="cpu", progress=False)
    capped.model.n_init, capped.strategy.max_gaussians = 200, 300
    assert plan_budget(capped, 2.0)[1].measured.probe_gaussians == 300  # at most max_gaussians
    capped.strategy.enabled = False  # no densification: no growth measured
    off = plan_budget(capped, 2.0)[1].measured
    assert off.growth is None and off.probe_iteration_s == 0 and off.per_iteration_s(1000) == off.iteration_s
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
