"""A training budget a person can say: ``meshsplat train DATA --minutes N``.

The schedule is fitted to the time and the machine: a throwaway trainer (in a temporary folder) measures
this capture's setup, a few iterations and reading a frame on this machine, and the iterations that fit
are the budget, less the setup and reading each training frame once (the trainer keeps them), over the
measured time per iteration times ``GROWTH_MARGIN`` (densification adds Gaussians, so later iterations
cost more than the first ones). At most the configured schedule
(``iterations``, 30,000 by default), at least ``MIN_ITERATIONS``.

The schedule's positions scale with it, in proportion to ``iterations``: ``SCALED_KEYS`` (when
densification starts and stops, the embedding lr warm-up, checkpoint and preview cadence; the lr decay
follows ``iterations`` by itself). Rates per iteration keep their value (``KEPT_KEYS``): how often
densification and walking run, the opacity reset interval (it needs thousands of iterations to recover,
so a short run, stopping densification before its first reset, has none, as the demo's schedules),
log rows, the LPIPS cadence and the key light's stages. The chosen schedule is written in the run's
``config.json`` like any other, so a resume continues it and ``--iters``/``--set`` reproduce it.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

from meshsplat.errors import MeshsplatError
from meshsplat.train.config import TrainConfig, apply_overrides
from meshsplat.train.distributed import env_world_size
from meshsplat.train.trainer import Trainer

__all__ = [
    "SCALED_KEYS",
    "KEPT_KEYS",
    "PROBE_ITERATIONS",
    "GROWTH_MARGIN",
    "MIN_ITERATIONS",
    "Budget",
    "Measurement",
    "measure_iteration",
    "planned_seconds",
    "scale_schedule",
    "plan_budget",
]

SCALED_KEYS = (
    "strategy.refine_start_iter",
    "strategy.refine_stop_iter",
    "optim.lr_delay_steps",
    "checkpoint_every",
    "preview_every",
)
KEPT_KEYS = (
    "strategy.refine_every",
    "strategy.reset_every",
    "walk.every",
    "log_every",
    "loss.lpips_every",
    "shading.key_iter",
)
PROBE_ITERATIONS = 6  # timed after one warm-up iteration (even: LPIPS every second iteration is averaged)
GROWTH_MARGIN = 1.5  # later iterations hold more Gaussians than the measured first ones
MIN_ITERATIONS = 50


def _get(cfg: TrainConfig, key: str) -> int:
    node: object = cfg
    for part in key.split("."):
        node = getattr(node, part)
    return int(node)  # type: ignore[call-overload]


@dataclasses.dataclass(frozen=True)
class Measurement:
    """What a probe measured on this machine, in seconds."""

    setup_s: float  # constructing the trainer (capture, initialisation) and the first iteration, less one
    iteration_s: float  # an iteration on a frame already read (the frame cache warm)
    frame_s: float  # reading a training frame the first time (decoding its image and mask)
    frames: int  # training frames: each is read once, then kept


def measure_iteration(cfg: TrainConfig, iterations: int = PROBE_ITERATIONS) -> Measurement:
    """Time ``cfg`` on this machine with a trainer that writes to a temporary folder (removed after): its
    setup, ``iterations`` timed iterations, and reading a frame (``dataset[i]``, uncached), which the timed
    iterations did for each new frame they drew and the run does once per frame."""
    with tempfile.TemporaryDirectory(prefix="meshsplat-budget-") as tmp:
        probe = dataclasses.replace(cfg, out=str(Path(tmp) / "probe"), progress=False)
        t0 = time.perf_counter()
        trainer = Trainer(probe)
        trainer.train(until=1)
        t1 = time.perf_counter()
        trainer.train(until=1 + iterations)
        t2 = time.perf_counter()
        ids, fresh = trainer.train_ids[-2:], trainer.dataset.with_meshes({})  # a copy, its frame cache empty
        for idx in ids:
            fresh[idx]
        frame_s = (time.perf_counter() - t2) / len(ids)
        trainer.dp.close()
    frames = len(trainer.train_ids)
    first_visits = min(iterations, max(frames - 1, 0))  # the first epoch draws each frame once
    probe_s = (t2 - t1) / iterations
    iteration_s = max(probe_s - frame_s * first_visits / iterations, 0.25 * probe_s)
    return Measurement(max(0.0, t1 - t0 - probe_s), iteration_s, frame_s, frames)


def planned_seconds(m: Measurement, iterations: int) -> float:
    """The planned wall time of ``iterations``: setup, each frame read once, iterations with the margin."""
    return m.setup_s + min(iterations, m.frames) * m.frame_s + iterations * m.iteration_s * GROWTH_MARGIN


@dataclasses.dataclass(frozen=True)
class Budget:
    """What ``plan_budget`` chose, and why."""

    minutes: float
    measured: Measurement
    iterations: int
    factor: float  # iterations / the configured schedule's
    overrides: tuple[str, ...]  # the schedule as --set pairs (iterations first)
    planned_s: float  # the wall time planned for the run (with the margin)

    def summary(self) -> str:
        m = self.measured
        fitted = "the full schedule fits" if self.factor >= 1 else f"the schedule scaled by {self.factor:.3g}"
        return (
            f"budget {self.minutes:g} min: measured {m.iteration_s:.3g} s an iteration, {m.frame_s:.2g} s to read "
            f"a frame and {m.setup_s:.0f} s of setup on this machine; training {self.iterations:,} iterations "
            f"({fitted}; planned {self.planned_s / 60:.1f} min), the same as --iters {self.iterations} --set "
            + " ".join(self.overrides[1:])
        )


def scale_schedule(cfg: TrainConfig, iterations: int) -> tuple[TrainConfig, tuple[str, ...]]:
    """``cfg`` with ``iterations`` and the ``SCALED_KEYS`` scaled in proportion (each at least 1 where it
    was; 0, "off", stays 0); returns the config and its schedule as ``--set`` pairs."""
    factor = iterations / cfg.iterations
    pairs = [f"iterations={int(iterations)}"]
    for key in SCALED_KEYS:
        value = _get(cfg, key)
        if value > 0:
            pairs.append(f"{key}={max(1, round(value * factor))}")
    return apply_overrides(cfg, pairs).validate(), tuple(pairs)


def plan_budget(cfg: TrainConfig, minutes: float) -> tuple[TrainConfig, Budget]:
    """The config whose schedule fits ``minutes`` of wall time on this machine (see the module's notes)."""
    if not minutes == minutes or minutes <= 0:  # NaN too
        raise MeshsplatError(f"--minutes: expected a positive number of minutes, got {minutes:g}")
    if env_world_size() > 1:  # each process would measure, and plan, a schedule of its own
        raise MeshsplatError(
            f"--minutes: this process is one of {env_world_size()} (WORLD_SIZE); a time budget plans one process's "
            "run: give the schedule with --iters (and --set) instead"
        )
    m = measure_iteration(cfg)
    budget_s = minutes * 60.0
    per = m.iteration_s * GROWTH_MARGIN
    fits = int((budget_s - m.setup_s - m.frames * m.frame_s) / per)  # every frame read
    if fits < m.frames:  # fewer iterations than frames: each reads a new one
        fits = int((budget_s - m.setup_s) / (per + m.frame_s))
    if fits < MIN_ITERATIONS:
        need = planned_seconds(m, MIN_ITERATIONS) / 60.0
        raise MeshsplatError(
            f"--minutes {minutes:g}: too short on this machine (setup {m.setup_s:.0f} s, {m.iteration_s:.3g} s an "
            f"iteration); {MIN_ITERATIONS} iterations need about {need:.1f} min; give more minutes or lower "
            "the image size (--downscale) or model.n_init"
        )
    iterations = min(fits, cfg.iterations)
    scaled, pairs = scale_schedule(cfg, iterations)
    budget = Budget(minutes, m, iterations, iterations / cfg.iterations, pairs, planned_seconds(m, iterations))
    return scaled, budget
