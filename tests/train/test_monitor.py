"""Watching training: TensorBoard events in the run folder (every loss term, train PSNR, Gaussian count,
learning rates, previews), a resumed run's events continuing without duplicates, a progress line that
fits 80 columns, and eval's loss curves labelled term by term (log.csv's empty cells read as gaps)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from tqdm import tqdm

from _capture_kit import _capture
from meshsplat.eval.report import loss_curves, plot_curves, read_log
from meshsplat.train.monitor import LOSS_TERMS, MONITOR_DIR, PROGRESS_FORMAT, progress_postfix
from meshsplat.train.recipes import recipe_config
from meshsplat.train.run_log import LOG_COLUMNS
from meshsplat.train.trainer import Trainer


def _events(log_dir: Path) -> dict[str, list]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(log_dir), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    tags = acc.Tags()
    out: dict[str, list] = {t: [(e.step, e.value) for e in acc.Scalars(t)] for t in tags["scalars"]}
    out.update({t: [(e.step, e.width, e.height) for e in acc.Images(t)] for t in tags["images"]})
    return out


def test_tensorboard_shows_every_term_psnr_gaussians_learning_rates_and_previews(tmp_path):
    pytest.importorskip("tensorboard", reason="the [monitor] extra (tensorboard) is not installed")
    root = _capture(tmp_path / "cap")
    cfg = recipe_config(
        "quality", data=str(root), out=str(tmp_path / "run"), iterations=6, device="cpu", progress=False
    )
    cfg.model.n_init = 100
    cfg.loss.lambda_lpips = 0.0
    cfg.mask_loss.weight = 0.1
    cfg.log_every = 1
    cfg.preview_every = 3
    cfg.checkpoint_every = 4
    trainer = Trainer(cfg)
    trainer.train(until=4)
    events = _events(tmp_path / "run" / MONITOR_DIR)
    for tag in ("loss/total", "loss/l1", "loss/scale", "loss/mask", "train/psnr", "train/gaussians"):
        assert [s for s, _ in events[tag]] == [1, 2, 3, 4], tag
    assert {f"loss/{t}" for t in LOSS_TERMS} <= set(events)  # as log.csv: a term with weight 0 logs 0
    lrs = {t for t in events if t.startswith("lr/")}
    assert {"lr/duv", "lr/d", "lr/sh0"} <= lrs and all(v > 0 for t in lrs for _, v in events[t])
    with open(tmp_path / "run" / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert set(LOSS_TERMS) <= set(LOG_COLUMNS)  # log.csv keeps every term too
    for row, (step, value) in zip(rows, events["loss/l1"], strict=True):
        assert int(row["iteration"]) == step and float(row["l1"]) == pytest.approx(value, rel=1e-5)
    assert [int(r["n_gaussians"]) for r in rows] == [v for _, v in events["train/gaussians"]]
    (step, width, height), *_ = events["preview"]
    assert step == 3 and width == 2 * height  # render | ground truth

    # a resumed run continues the same curves; nothing after the checkpoint's iteration is kept twice
    cfg.iterations = 6
    Trainer(cfg, resume=True).train()
    events = _events(tmp_path / "run" / MONITOR_DIR)
    assert [s for s, _ in events["loss/total"]] == [1, 2, 3, 4, 5, 6]
    assert [s for s, *_ in events["preview"]] == [3, 6]


def test_a_session_resumed_within_the_second_of_the_last_one_still_purges_after_it(tmp_path):
    """TensorBoard reads event files in name order (start second, host, pid, a per-process count): a resumed
    session's file must sort after the one it continues, or its purge of the later steps is read first and the
    old steps survive. An earlier file named to sort last within its second (and one second ahead of the clock)
    is waited out."""
    pytest.importorskip("tensorboard", reason="the [monitor] extra (tensorboard) is not installed")
    import time

    from meshsplat.train.monitor import TensorBoardMonitor

    first = TensorBoardMonitor.open(tmp_path)
    for step in (1, 2, 3, 4):
        first.writer.add_scalar("loss/total", float(step), step)
    first.close()
    (old,) = (tmp_path / MONITOR_DIR).iterdir()
    old.rename(old.with_name(f"events.out.tfevents.{int(time.time()) + 1}.zzzz.99999.9"))
    resumed = TensorBoardMonitor.open(tmp_path, iteration=2)  # the checkpoint's iteration: steps 3, 4 again
    for step in (3, 4, 5):
        resumed.writer.add_scalar("loss/total", 10.0 * step, step)
    resumed.close()
    assert _events(tmp_path / MONITOR_DIR)["loss/total"] == [(1, 1.0), (2, 2.0), (3, 30.0), (4, 40.0), (5, 50.0)]


def test_the_train_command_says_where_to_watch(tmp_path, capsys):
    pytest.importorskip("tensorboard", reason="the [monitor] extra (tensorboard) is not installed")
    from meshsplat.cli.main import main

    root = _capture(tmp_path / "cap")
    args = ["train", str(root), "--out", str(tmp_path / "run"), "--iters", "2", "--device", "cpu"]
    assert main([*args, "--set", "model.n_init=100", "loss.lambda_lpips=0"]) == 0
    err = capsys.readouterr().err
    assert f"watch it live: tensorboard --logdir {tmp_path / 'run' / MONITOR_DIR}" in err
    assert any((tmp_path / "run" / MONITOR_DIR).glob("events.out.tfevents.*"))


def test_training_without_tensorboard_writes_no_events(tmp_path):
    """The monitor is optional: when torch's writer cannot be imported the run trains the same."""
    from meshsplat.train.monitor import TensorBoardMonitor, tensorboard_available

    if tensorboard_available():
        assert TensorBoardMonitor.open(tmp_path / "r") is not None
        assert (tmp_path / "r" / MONITOR_DIR).is_dir()
    else:
        assert TensorBoardMonitor.open(tmp_path / "r") is None
        assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    ("n", "total", "elapsed", "loss", "psnr", "gaussians"),
    [
        (1, 30_000, 0.5, 0.5, 9.99, 100),
        (29_999, 30_000, 5 * 3600.0, 0.012345, 31.25, 2_345_678),
        (7, 200, 12.0, 1.0, 100.0, 54_321),
    ],
)
def test_the_progress_line_fits_80_columns_with_its_values(n, total, elapsed, loss, psnr, gaussians):
    postfix = progress_postfix(loss, psnr, gaussians)
    line = tqdm.format_meter(
        n, total, elapsed, ncols=80, prefix="train", bar_format=PROGRESS_FORMAT, postfix=postfix, unit="it"
    )
    assert len(line) <= 80, line
    assert line.endswith(postfix + "]") or line.endswith(postfix), line  # the values whole, PSNR included
    assert f"{psnr:.2f} dB" in line and f"loss {loss:.4f}" in line


def _write_log(path: Path, n: int = 60) -> None:
    with open(path, "w", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=["iteration", "loss", "l1", "lpips", "scale", "mse", "psnr", "n_gaussians"])
        wr.writeheader()
        for i in range(1, n + 1):
            it = 10 * i
            scale = 0.02 if it >= 500 else 0.0  # the scale term starts when Gaussians grow past the threshold
            lpips = "" if i % 4 else f"{0.3 / i:.4f}"  # loss.lpips_every: computed on every 4th row only
            wr.writerow(
                {"iteration": it, "loss": 0.1 / i + scale, "l1": 0.1 / i, "lpips": lpips, "scale": scale, "mse": 0.0}
                | {"psnr": 20 + i / 10, "n_gaussians": 1000 + i}
            )


def test_eval_curves_label_each_loss_term(tmp_path):
    _write_log(tmp_path / "log.csv")
    log = read_log(tmp_path / "log.csv")
    assert len(log["lpips"]) == 60 and int(np.isfinite(log["lpips"]).sum()) == 15  # empty cells: gaps, kept
    curves = loss_curves(log)
    assert curves == [("loss", "total"), ("l1", "L1"), ("lpips", "LPIPS"), ("scale", "scale (rel. to mesh)")]
    path = plot_curves(log, tmp_path / "curves.png")  # MSE never computed (all zero): no curve
    assert path is not None and path.stat().st_size > 0
    from PIL import Image

    assert Image.open(path).size[0] > Image.open(path).size[1]
