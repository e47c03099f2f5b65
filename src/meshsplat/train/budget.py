"""A training budget a person can say: ``meshsplat train DATA --minutes N``.

The schedule is fitted to the time and the machine. Throwaway trainers (in a temporary folder) measure, for
this capture on this machine: the setup, a few iterations, reading a frame, and the same iterations with the
model at the size densification is assumed to reach (``GROWTH_FACTOR`` times ``model.n_init``, at most
``strategy.max_gaussians``); an iteration's cost is taken as linear in the Gaussians between the two. The
model is assumed to grow linearly from ``refine_start_iter`` to ``refine_stop_iter`` and to keep its size after,
which gives the mean cost of an iteration over the schedule. The components' work beyond the iterations (the
pose polish: ``Component.extra_renders`` frame renders with a backward, each timed on the grown model) is
planned too. The iterations that fit are the budget, less the setup, reading each training frame once (the
trainer keeps them) and that extra work, over the mean cost of an iteration times ``NOISE_MARGIN``. At most
the configured schedule (``iterations``, 30,000 by default), at least ``MIN_ITERATIONS``.

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
    "GROWTH_FACTOR",
    "NOISE_MARGIN",
    "MIN_ITERATIONS",
    "Budget",
    "Measurement",
    "measure_iteration",
    "mean_gaussians",
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
GROWN_PROBE_ITERATIONS = 4  # the same on the grown model
# the growth densification is planned for: the default recipe's models grew 2-5.7x from n_init in the
# bench runs (a person filling a 512² frame: 4.9x, 10k -> 49k Gaussians); bench/reports/train_speed.md
GROWTH_FACTOR = 5.0
NOISE_MARGIN = 1.1  # timing noise of a few probe iterations
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
    iteration_s: float  # an iteration at the initial size, on a frame already read (the frame cache warm)
    frame_s: float  # reading a training frame the first time (decoding its image and mask)
    frames: int  # training frames: each is read once, then kept
    gaussians: int = 0  # the initial size (model.n_init)
    grown_gaussians: int = 0  # the size densification is planned to reach (the initial one without it)
    grown_iteration_s: float = 0.0  # an iteration at that size (0: not measured, as the initial one)
    mean_iteration_s: float = 0.0  # an iteration's mean over the schedule as planned (0: iteration_s)
    extra_renders: int = 0  # the components' frame renders beyond the iterations (the pose polish)
    render_s: float = 0.0  # one of those: a training frame rendered and its error's backward, on the grown model

    @property
    def per_iteration_s(self) -> float:
        """The mean cost of an iteration over the schedule (``iteration_s`` where growth was not measured)."""
        return self.mean_iteration_s or self.iteration_s

    @property
    def extra_s(self) -> float:
        """The components' work beyond the iterations."""
        return self.extra_renders * self.render_s


def _planned_size(cfg: TrainConfig) -> int:
    """The model size densification is planned to reach: ``GROWTH_FACTOR`` times the initial one, at most
    ``strategy.max_gaussians`` (the initial size where densification is off or cannot grow it)."""
    n0, st = cfg.model.n_init, cfg.strategy
    if not st.enabled or st.refine_start_iter > min(st.refine_stop_iter, cfg.iterations):
        return n0
    return max(n0, min(st.max_gaussians, round(GROWTH_FACTOR * n0)))


def mean_gaussians(cfg: TrainConfig, grown: int) -> float:
    """The mean model size over ``cfg``'s schedule: ``model.n_init`` until ``refine_start_iter``, growing
    linearly to ``grown`` at ``refine_stop_iter`` (or the last iteration), ``grown`` after. The positions
    scale with the iterations (``scale_schedule``), so the mean does not depend on how many are trained."""
    n0, total = float(cfg.model.n_init), float(cfg.iterations)
    start = min(float(cfg.strategy.refine_start_iter), total) / total
    stop = min(max(float(cfg.strategy.refine_stop_iter), start * total), total) / total
    return n0 * start + 0.5 * (n0 + grown) * (stop - start) + grown * (1.0 - stop)


def _time_iterations(trainer: Trainer, iterations: int) -> float:
    """Seconds per iteration of ``iterations`` more iterations of ``trainer``."""
    t0 = time.perf_counter()
    trainer.train(until=trainer.iteration + iterations)
    return (time.perf_counter() - t0) / iterations


def _time_render(trainer: Trainer) -> float:
    """Seconds to render a training frame and backpropagate its error, as a pose polish does per frame."""
    idx = trainer.train_ids[0]
    trainer.training_error(idx)  # its frame read and cached, not timed
    t0 = time.perf_counter()
    trainer.training_error(idx).backward()
    return time.perf_counter() - t0


def measure_iteration(cfg: TrainConfig, iterations: int = PROBE_ITERATIONS) -> Measurement:
    """Time ``cfg`` on this machine with trainers that write to a temporary folder (removed after): its
    setup, ``iterations`` timed iterations, and reading a frame (``dataset[i]``, uncached), which the timed
    iterations did for each new frame they drew and the run does once per frame; then, where densification
    is on, ``GROWN_PROBE_ITERATIONS`` iterations of a model initialised at the planned grown size
    (``_planned_size``) and a frame's render with its backward for the components' extra work."""
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
        extra_renders = sum(c.extra_renders() for c in trainer.components)
        trainer.dp.close()
        n0, grown = cfg.model.n_init, _planned_size(cfg)
        grown_s = render_s = 0.0
        if grown > n0 or extra_renders:
            big = dataclasses.replace(
                probe, out=str(Path(tmp) / "grown"), model=dataclasses.replace(cfg.model, n_init=grown)
            )
            grown_trainer = Trainer(big)
            grown_trainer.train(until=1)
            if grown > n0:
                grown_s = _time_iterations(grown_trainer, GROWN_PROBE_ITERATIONS)
            if extra_renders:
                render_s = _time_render(grown_trainer)
            grown_trainer.dp.close()
    frames = len(trainer.train_ids)
    first_visits = min(iterations, max(frames - 1, 0))  # the first epoch draws each frame once
    probe_s = (t2 - t1) / iterations
    iteration_s = max(probe_s - frame_s * first_visits / iterations, 0.25 * probe_s)
    mean_s = iteration_s
    if grown_s:  # linear in the Gaussians between the two sizes, never below the initial cost
        slope = max(grown_s - iteration_s, 0.0) / (grown - n0)
        mean_s = iteration_s + slope * (mean_gaussians(cfg, grown) - n0)
    return Measurement(
        max(0.0, t1 - t0 - probe_s),
        iteration_s,
        frame_s,
        frames,
        gaussians=n0,
        grown_gaussians=grown,
        grown_iteration_s=grown_s,
        mean_iteration_s=mean_s,
        extra_renders=extra_renders,
        render_s=render_s,
    )


def planned_seconds(m: Measurement, iterations: int) -> float:
    """The planned wall time of ``iterations``: setup, each frame read once, iterations at their mean cost with
    the margin, the components' extra work."""
    reads = min(iterations, m.frames) * m.frame_s
    return m.setup_s + reads + iterations * m.per_iteration_s * NOISE_MARGIN + m.extra_s


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
        grown = (
            f" ({m.grown_iteration_s:.3g} s at {m.grown_gaussians:,} Gaussians, the growth planned for; "
            f"{m.per_iteration_s:.3g} s on average)"
            if m.grown_iteration_s
            else ""
        )
        extra = f", {m.extra_s:.0f} s for the pose polish" if m.extra_renders else ""
        return (
            f"budget {self.minutes:g} min: measured {m.iteration_s:.3g} s an iteration{grown}, {m.frame_s:.2g} s to "
            f"read a frame and {m.setup_s:.0f} s of setup on this machine{extra}; training {self.iterations:,} "
            f"iterations "
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
    per, fixed = m.per_iteration_s * NOISE_MARGIN, m.setup_s + m.extra_s
    fits = int((budget_s - fixed - m.frames * m.frame_s) / per)  # every frame read
    if fits < m.frames:  # fewer iterations than frames: each reads a new one
        fits = int((budget_s - fixed) / (per + m.frame_s))
    if fits < MIN_ITERATIONS:
        need = planned_seconds(m, MIN_ITERATIONS) / 60.0
        raise MeshsplatError(
            f"--minutes {minutes:g}: too short on this machine (setup {m.setup_s:.0f} s, {m.per_iteration_s:.3g} s "
            f"an iteration); {MIN_ITERATIONS} iterations need about {need:.1f} min; give more minutes or lower "
            "the image size (--downscale) or model.n_init"
        )
    iterations = min(fits, cfg.iterations)
    scaled, pairs = scale_schedule(cfg, iterations)
    budget = Budget(minutes, m, iterations, iterations / cfg.iterations, pairs, planned_seconds(m, iterations))
    return scaled, budget
