"""A training budget a person can say: ``meshsplat train DATA --minutes N``.

The schedule is fitted to the time and the machine: a throwaway trainer (in a temporary folder) measures
this capture's setup and a few iterations on this machine, and the iterations that fit are the budget,
less the setup, over the measured time per iteration times ``GROWTH_MARGIN`` (densification adds
Gaussians, so later iterations cost more than the first ones). At most the configured schedule
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
from meshsplat.train.trainer import Trainer

__all__ = [
    "SCALED_KEYS",
    "KEPT_KEYS",
    "PROBE_ITERATIONS",
    "GROWTH_MARGIN",
    "MIN_ITERATIONS",
    "Budget",
    "measure_iteration",
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
    "model.occlusion_key_iter",
)
PROBE_ITERATIONS = 4  # timed after one warm-up iteration (even: LPIPS every second iteration is averaged)
GROWTH_MARGIN = 1.5  # later iterations hold more Gaussians than the measured first ones
MIN_ITERATIONS = 50


@dataclasses.dataclass(frozen=True)
class Budget:
    """What ``plan_budget`` chose, and why."""

    minutes: float
    setup_s: float  # opening the capture and initialising, measured
    iteration_s: float  # one iteration at the start, measured
    iterations: int
    factor: float  # iterations / the configured schedule's
    overrides: tuple[str, ...]  # the schedule as --set pairs (iterations first)

    def summary(self) -> str:
        fitted = "the full schedule fits" if self.factor >= 1 else f"the schedule scaled by {self.factor:.3g}"
        return (
            f"budget {self.minutes:g} min: measured {self.iteration_s:.3g} s an iteration and {self.setup_s:.0f} s "
            f"of setup on this machine; training {self.iterations:,} iterations ({fitted}), the same as "
            f"--iters {self.iterations} --set {' '.join(self.overrides[1:])}"
        )


def _get(cfg: TrainConfig, key: str) -> int:
    node: object = cfg
    for part in key.split("."):
        node = getattr(node, part)
    return int(node)  # type: ignore[call-overload]


def measure_iteration(cfg: TrainConfig, iterations: int = PROBE_ITERATIONS) -> tuple[float, float]:
    """``(setup seconds, seconds per iteration)`` of ``cfg`` on this machine, measured by a trainer that
    writes to a temporary folder (removed after): setup is construction plus the first iteration (compiled
    kernels load, caches fill) less one iteration; then ``iterations`` are timed."""
    with tempfile.TemporaryDirectory(prefix="meshsplat-budget-") as tmp:
        probe = dataclasses.replace(cfg, out=str(Path(tmp) / "probe"), progress=False)
        t0 = time.perf_counter()
        trainer = Trainer(probe)
        trainer.train(until=1)
        t1 = time.perf_counter()
        trainer.train(until=1 + iterations)
        per_iteration = (time.perf_counter() - t1) / iterations
        trainer.dp.close()
    return max(0.0, t1 - t0 - per_iteration), per_iteration


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
    setup_s, iteration_s = measure_iteration(cfg)
    available = minutes * 60.0 - setup_s  # the real run's setup, as measured
    fits = int(available / (iteration_s * GROWTH_MARGIN)) if available > 0 else 0
    if fits < MIN_ITERATIONS:
        need = (setup_s + MIN_ITERATIONS * iteration_s * GROWTH_MARGIN) / 60.0
        raise MeshsplatError(
            f"--minutes {minutes:g}: too short on this machine (setup {setup_s:.0f} s, {iteration_s:.3g} s an "
            f"iteration); {MIN_ITERATIONS} iterations need about {need:.1f} min; give more minutes or lower "
            "the image size (--downscale) or model.n_init"
        )
    iterations = min(fits, cfg.iterations)
    scaled, pairs = scale_schedule(cfg, iterations)
    budget = Budget(minutes, setup_s, iteration_s, iterations, iterations / cfg.iterations, pairs)
    return scaled, budget
