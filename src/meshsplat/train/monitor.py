"""Watching a training run: TensorBoard event files and a progress line that fits 80 columns.

With the ``tensorboard`` package installed (the ``[monitor]`` extra; PyTorch's writer, no TensorFlow),
the trainer writes ``RUN/tensorboard/`` as it goes, on the rows it writes to ``log.csv``
(``log_every``): every loss term under ``loss/`` (unweighted, as in log.csv; ``loss/total`` is the
weighted sum that is minimised), ``train/psnr``, ``train/gaussians``, ``train/walked``, each
optimiser's learning rate under ``lr/``, and each preview (render | ground truth, ``preview_every``)
under ``preview``. Watch it with ``tensorboard --logdir RUN/tensorboard``. A resumed run drops the
events after its checkpoint's iteration (``purge_step``), as log.csv does. Without the package
nothing is written and training is unchanged.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from meshsplat.errors import MeshsplatWarning

__all__ = [
    "MONITOR_DIR",
    "LOSS_TERMS",
    "TensorBoardMonitor",
    "tensorboard_available",
    "learning_rates",
    "PROGRESS_FORMAT",
    "progress_postfix",
]

MONITOR_DIR = "tensorboard"  # RUN/tensorboard/
LOSS_TERMS = ("l1", "lpips", "scale", "mse", "dssim", "mask", "albedo")  # log.csv's loss columns

# The progress line: no rate (the remaining time says it), a short postfix (its legend is printed once above)
PROGRESS_FORMAT = "{desc} {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}]{postfix}"


def tensorboard_available() -> bool:
    """Whether PyTorch's TensorBoard writer can be imported (the ``tensorboard`` package is installed)."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401 - only its presence is asked
    except ImportError:
        return False
    return True


def learning_rates(optimizers: Mapping[str, Any]) -> dict[str, float]:
    """Each optimiser's current learning rate (its first parameter group's): ``{name: lr}``."""
    return {name: float(opt.param_groups[0]["lr"]) for name, opt in optimizers.items() if opt.param_groups}


EVENTS_PREFIX = "events.out.tfevents."  # then the writer's start time in whole seconds (10 digits), host, pid, count
MAX_EVENTS_WAIT_S = 2.0


def _wait_past_existing_events(log_dir: Path) -> None:
    """TensorBoard reads a folder's event files in name order, and a resumed session's purge of the steps after
    its checkpoint only works when its file comes last. Names start with the writer's start second, then host, pid
    and a per-process count (``.9`` sorts after ``.10``): a session resumed within the second of the newest file
    (a test, a notebook) waits for the next second, at most ``MAX_EVENTS_WAIT_S`` (a file from further in the
    future, a clock set back, cannot be helped)."""
    newest = 0
    for f in log_dir.glob(EVENTS_PREFIX + "*"):
        stamp = f.name[len(EVENTS_PREFIX) :].split(".", 1)[0]
        if stamp.isdigit():
            newest = max(newest, int(stamp))
    wait = newest + 1 - time.time()
    if 0 < wait <= MAX_EVENTS_WAIT_S:
        time.sleep(wait)


class TensorBoardMonitor:
    """Writes a run's scalars and previews as TensorBoard events in ``RUN/tensorboard/``."""

    def __init__(self, writer: Any, log_dir: Path) -> None:
        self.writer = writer
        self.log_dir = log_dir

    @classmethod
    def open(cls, run_dir: str | Path, iteration: int = 0) -> TensorBoardMonitor | None:
        """A monitor writing under ``run_dir/tensorboard`` from ``iteration`` on (events after it, left by
        an earlier session, are dropped), or ``None`` when the ``tensorboard`` package is missing."""
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            return None
        log_dir = Path(run_dir) / MONITOR_DIR
        if iteration:
            _wait_past_existing_events(log_dir)
        try:
            writer = SummaryWriter(log_dir=str(log_dir), purge_step=iteration + 1 if iteration else None)
        except OSError as exc:  # a monitor that cannot write never stops training
            warnings.warn(f"TensorBoard events not written to {log_dir}: {exc}", MeshsplatWarning, stacklevel=2)
            return None
        return cls(writer, log_dir)

    def scalars(self, row: Mapping[str, float], lrs: Mapping[str, float]) -> None:
        """One ``log.csv`` row (``iteration``, ``loss``, the terms of ``LOSS_TERMS``, ``psnr``, ``n_gaussians``,
        ``walked``) and the learning rates ``{name: lr}``."""
        it = int(row["iteration"])
        add = self.writer.add_scalar
        add("loss/total", float(row["loss"]), it)
        for name in LOSS_TERMS:
            value = row.get(name)
            if value is not None and math.isfinite(float(value)):  # nan: not computed on this iteration
                add(f"loss/{name}", float(value), it)
        add("train/psnr", float(row["psnr"]), it)
        add("train/gaussians", int(row["n_gaussians"]), it)
        if "walked" in row:
            add("train/walked", int(row["walked"]), it)
        for name, lr in lrs.items():
            add(f"lr/{name}", float(lr), it)

    def preview(self, image: np.ndarray, iteration: int) -> None:
        """A preview image ``[H, W, 3]`` uint8 (render | ground truth)."""
        self.writer.add_image("preview", np.ascontiguousarray(image), int(iteration), dataformats="HWC")

    def close(self) -> None:
        self.writer.close()


def _count(n: int) -> str:
    return f"{n / 1e6:.2f}M" if n >= 1e6 else f"{n / 1e3:.1f}k" if n >= 1e4 else str(n)


def progress_postfix(loss: float, psnr: float, gaussians: int) -> str:
    """The progress line's values, short enough that the line fits 80 columns: ``loss 0.0123, 25.12 dB,
    12.3k G`` (its legend, what the PSNR is, is printed once above the bar)."""
    return f"loss {loss:.4f}, {psnr:.2f} dB, {_count(gaussians)} G"
