"""A training budget a person can say: ``meshsplat train DATA --minutes N``.

The schedule is fitted to the time and the machine. Throwaway trainers (in a temporary folder) measure, for
this capture on this machine: the setup, a few iterations, reading a frame, and the same iterations with the
model initialised at ``PROBE_GROWTH`` times ``model.n_init`` (at most ``strategy.max_gaussians``); an
iteration's cost is taken as linear in the Gaussians. Densification is planned to multiply the model by
``GROWTH_PER_ROUND`` per densification step (``strategy.refine_every``) between ``refine_start_iter`` and
``refine_stop_iter``, up to ``max_gaussians``; a shorter schedule has fewer steps and grows less
(``Growth``). The components' work beyond the iterations (the pose polish: ``Component.extra_renders``
frame renders with a backward, timed on the larger probe and scaled to the planned size) is planned too.
The run gets the most iterations whose planned time (setup, each training frame read once, the iterations
at their mean cost times ``NOISE_MARGIN``, the extra work) fits the budget: at most the configured schedule
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
    "PROBE_GROWTH",
    "GROWTH_PER_ROUND",
    "NOISE_MARGIN",
    "MIN_ITERATIONS",
    "Budget",
    "Growth",
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
GROWN_PROBE_ITERATIONS = 4  # the same on the larger model
PROBE_GROWTH = 5.0  # the larger probe's size, times model.n_init
# a model's growth per densification step, planned: a person filling a 512² frame grew 4.9x in 23 steps
# (1.071 a step) and 2.9x in 13 (1.088) under the default recipe; bench/reports/track_bodies.md
GROWTH_PER_ROUND = 1.08
NOISE_MARGIN = 1.1  # timing noise of a few probe iterations
MIN_ITERATIONS = 50


def _get(cfg: TrainConfig, key: str) -> int:
    node: object = cfg
    for part in key.split("."):
        node = getattr(node, part)
    return int(node)  # type: ignore[call-overload]


@dataclasses.dataclass(frozen=True)
class Growth:
    """The model size densification is planned to give over a schedule; positions as fractions of the
    configured ``iterations`` (``scale_schedule`` keeps them), ``every`` as a rate."""

    gaussians: int  # model.n_init
    most: int  # strategy.max_gaussians (n_init where densification is off)
    start: float  # refine_start_iter / iterations
    stop: float  # refine_stop_iter / iterations, at most 1
    every: int  # refine_every

    @classmethod
    def of(cls, cfg: TrainConfig) -> Growth:
        st, total = cfg.strategy, float(cfg.iterations)
        start = min(st.refine_start_iter / total, 1.0)
        stop = min(max(st.refine_stop_iter / total, start), 1.0)
        most = max(st.max_gaussians, cfg.model.n_init) if st.enabled else cfg.model.n_init
        return cls(cfg.model.n_init, most, start, stop, max(1, st.refine_every))

    def size(self, iterations: int) -> float:
        """The planned final size: ``GROWTH_PER_ROUND`` per densification step, at most ``most``."""
        steps = (self.stop - self.start) * iterations / self.every
        return min(float(self.most), self.gaussians * GROWTH_PER_ROUND ** min(steps, 1000.0))

    def mean(self, iterations: int) -> float:
        """The mean size over the run: ``gaussians`` until ``start``, growing linearly to ``size`` at ``stop``,
        ``size`` after."""
        n0, n1 = float(self.gaussians), self.size(iterations)
        return n0 * self.start + 0.5 * (n0 + n1) * (self.stop - self.start) + n1 * (1.0 - self.stop)


@dataclasses.dataclass(frozen=True)
class Measurement:
    """What a probe measured on this machine, in seconds, and the growth it plans for."""

    setup_s: float  # constructing the trainer (capture, initialisation) and the first iteration, less one
    iteration_s: float  # an iteration at the initial size, on a frame already read (the frame cache warm)
    frame_s: float  # reading a training frame the first time (decoding its image and mask)
    frames: int  # training frames: each is read once, then kept
    growth: Growth | None = None  # None: the size stays (no growth planned)
    probe_gaussians: int = 0  # the larger probe's size
    probe_iteration_s: float = 0.0  # an iteration at that size (0: not measured)
    extra_renders: int = 0  # the components' frame renders beyond the iterations (the pose polish)
    render_s: float = 0.0  # one of those at the larger probe's size: a frame rendered, its error's backward

    def iteration_cost(self, gaussians: float) -> float:
        """Seconds an iteration of a model of ``gaussians``: linear between the two probes, never below the
        first (the first alone where the larger one was not measured)."""
        if not self.probe_iteration_s or self.growth is None or self.probe_gaussians <= self.growth.gaussians:
            return self.iteration_s
        slope = max(self.probe_iteration_s - self.iteration_s, 0.0) / (self.probe_gaussians - self.growth.gaussians)
        return self.iteration_s + slope * max(gaussians - self.growth.gaussians, 0.0)

    def per_iteration_s(self, iterations: int) -> float:
        """The mean cost of an iteration over a run of ``iterations``."""
        return self.iteration_s if self.growth is None else self.iteration_cost(self.growth.mean(iterations))

    def extra_s(self, iterations: int) -> float:
        """The components' extra work after a run of ``iterations``: renders at its planned final size."""
        if not self.extra_renders:
            return 0.0
        size = self.growth.size(iterations) if self.growth is not None else self.probe_gaussians
        scale = self.iteration_cost(size) / max(self.iteration_cost(self.probe_gaussians), 1e-12)
        return self.extra_renders * self.render_s * scale


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
    can grow the model or a component renders beyond the iterations, ``GROWN_PROBE_ITERATIONS`` iterations of
    a model initialised at ``PROBE_GROWTH`` times the size (at most ``strategy.max_gaussians``) and a frame's
    render with its backward."""
    growth = Growth.of(cfg)
    grows = growth.most > growth.gaussians and growth.stop > growth.start
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
        n0 = cfg.model.n_init
        n_probe = max(n0, min(growth.most, round(PROBE_GROWTH * n0))) if grows else n0
        probe_s = render_s = 0.0
        if n_probe > n0 or extra_renders:
            big = dataclasses.replace(
                probe, out=str(Path(tmp) / "grown"), model=dataclasses.replace(cfg.model, n_init=n_probe)
            )
            big_trainer = Trainer(big)
            big_trainer.train(until=1)
            if n_probe > n0:
                probe_s = _time_iterations(big_trainer, GROWN_PROBE_ITERATIONS)
            if extra_renders:
                render_s = _time_render(big_trainer)
            big_trainer.dp.close()
    frames = len(trainer.train_ids)
    first_visits = min(iterations, max(frames - 1, 0))  # the first epoch draws each frame once
    first_s = (t2 - t1) / iterations
    iteration_s = max(first_s - frame_s * first_visits / iterations, 0.25 * first_s)
    return Measurement(
        max(0.0, t1 - t0 - first_s),
        iteration_s,
        frame_s,
        frames,
        growth=growth if grows else None,
        probe_gaussians=n_probe,
        probe_iteration_s=probe_s,
        extra_renders=extra_renders,
        render_s=render_s,
    )


def planned_seconds(m: Measurement, iterations: int) -> float:
    """The planned wall time of ``iterations``: setup, each frame read once, the iterations at their mean cost
    with the margin, the components' extra work. It grows with ``iterations``."""
    reads = min(iterations, m.frames) * m.frame_s
    return m.setup_s + reads + iterations * m.per_iteration_s(iterations) * NOISE_MARGIN + m.extra_s(iterations)


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
        n, grown = self.iterations, ""
        if m.probe_iteration_s and m.growth is not None:
            grown = (
                f" ({m.probe_iteration_s:.3g} s at {m.probe_gaussians:,} Gaussians; planned to grow to "
                f"{m.growth.size(n):,.0f}: {m.per_iteration_s(n):.3g} s on average)"
            )
        extra = f", {m.extra_s(n):.0f} s for the pose polish" if m.extra_renders else ""
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
    least = min(MIN_ITERATIONS, cfg.iterations)  # a shorter configured schedule is trained whole if it fits
    if planned_seconds(m, least) > budget_s:
        need = planned_seconds(m, least) / 60.0
        raise MeshsplatError(
            f"--minutes {minutes:g}: too short on this machine (setup {m.setup_s:.0f} s, {m.iteration_s:.3g} s "
            f"an iteration); {least} iterations need about {need:.1f} min; give more minutes or lower "
            "the image size (--downscale) or model.n_init"
        )
    lo, hi = least, cfg.iterations  # the most iterations that fit: planned_seconds grows with them
    while lo < hi:
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if planned_seconds(m, mid) <= budget_s else (lo, mid - 1)
    iterations = lo
    scaled, pairs = scale_schedule(cfg, iterations)
    budget = Budget(minutes, m, iterations, iterations / cfg.iterations, pairs, planned_seconds(m, iterations))
    return scaled, budget
