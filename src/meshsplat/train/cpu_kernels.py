"""The compiled CPU kernels training calls, compiled ahead on several cores after an install.

``cpu_kernels.json`` (the manifest) lists the numba kernels CPU training calls from Python on two or more threads
(mostly the kernels' parallel drivers) with the argument types of each call, as recorded from a real run by
``tests/_kernel_manifest.py``. Before the first step (``Trainer.train``; the ``train --nproc`` launcher, once for
its workers), :func:`compile_ahead` compiles those missing from numba's disk cache in one process per thread the job
may use (this one and workers, ``meshsplat._numba_ahead``, each taking the next kernel from one queue), so the first
step loads them instead of compiling them one after the other; a job with other work first (the demo renders its
capture on one thread) can start a worker early (:func:`start_compiling_early`). On one thread nothing changes (one
process compiles as fast as one worker).
When the manifest is stale (a kernel's arguments changed), the changed kernel compiles on its first call as
before; a test fails until the manifest is rewritten.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch

from meshsplat._device import usable_cores
from meshsplat._numba_ahead import AheadResult, AheadSession
from meshsplat._numba_ahead import compile_ahead as _compile_ahead

__all__ = [
    "MANIFEST",
    "FACTORIES",
    "manifest",
    "compile_ahead",
    "start_compiling_early",
    "stop_compiling_early",
    "ahead_processes",
    "prepare_cpu_kernels",
    "uses_cpu_kernels",
]

MANIFEST = Path(__file__).with_name("cpu_kernels.json")

# the loaders of the kernels a training step may call (rasterizer, shadow maps, albedo prior, compose, irradiance);
# each makes its kernels without compiling them
FACTORIES = [
    "meshsplat.render.backends.numba_cpu:_kernels",
    "meshsplat.mesh._visibility_numba:_kernel",
    "meshsplat.train._albedo_prior_numba:_kernels",
    "meshsplat.gaussians._compose_numba:_kernels",
    "meshsplat.gaussians._shading_numba:_kernels",
]


@lru_cache(maxsize=1)
def manifest() -> dict[str, Any]:
    """The shipped manifest: ``{"threads": 2, "entries": [entry, ...]}`` (``_numba_ahead``'s entries, recorded on
    that many threads)."""
    return json.loads(MANIFEST.read_text())


def uses_cpu_kernels(device: torch.device, backend: str) -> bool:
    """Whether training on ``device`` with render ``backend`` runs the compiled CPU kernels, numba permitting."""
    return device.type == "cpu" and backend in ("auto", "numba")


def ahead_processes(threads: int) -> int:
    """How many processes compile ahead for a job on ``threads`` threads: one per thread, no more than the usable
    cores; 0 when that is one (a single process compiles as fast on the first step)."""
    n = min(threads, usable_cores())
    return n if n >= 2 else 0


_EARLY: list[AheadSession] = []  # a session started by :func:`start_compiling_early`, until training takes it


def start_compiling_early(threads: int) -> bool:
    """Start compiling what training on ``threads`` threads will need in one worker process now, while this process
    does other work on one core (the demo renders its capture); the training's :func:`compile_ahead` then goes on
    with that worker instead of starting from nothing. Returns whether a worker started (not on one core, nor when
    the cache has everything). Close it with :func:`stop_compiling_early` if training will not run."""
    if ahead_processes(threads) < 2 or _EARLY:
        return False
    session = AheadSession(FACTORIES, manifest()["entries"])
    if not session.todo:
        return False
    session.add_workers(1)
    if session.processes < 2:  # no worker could start: nothing runs beside this process
        session.close()
        return False
    _EARLY.append(session)
    return True


def stop_compiling_early() -> None:
    """Stop the worker of :func:`start_compiling_early` if training did not take it (an interrupted demo)."""
    while _EARLY:
        _EARLY.pop().close()


def compile_ahead(threads: int, announce: Callable[[int, int], None] | None = None) -> AheadResult:
    """Compile what training on ``threads`` threads calls and numba's disk cache lacks, in
    :func:`ahead_processes` processes (``announce(kernels, processes)`` first; with the worker of
    :func:`start_compiling_early` if one runs); returns at once when the cache has it all, or when there is no
    second process to use."""
    processes = ahead_processes(threads)
    early = _EARLY.pop() if _EARLY else None
    if not processes:
        if early is not None:
            early.close()
        return AheadResult(compiled=[], processes=0, seconds=0.0, failed="")
    return _compile_ahead(FACTORIES, manifest()["entries"], processes, announce, session=early)


def prepare_cpu_kernels(threads: int, progress: bool) -> None:
    """What training does before its first step on the CPU (``Trainer.train``; the ``--nproc`` launcher for its
    workers): :func:`compile_ahead`, saying so (when ``progress``) and how long it took; on one thread, a note that
    the first step may compile. Never raises: this is only a head start, the first step compiles what is missing."""
    if not ahead_processes(threads):
        stop_compiling_early()
        if progress:
            print("first step: loading the compiled CPU kernels (after an install: compiling them, on one core, "
                  "for up to a minute)", file=sys.stderr)  # fmt: skip
        return

    announced = []

    def announce(kernels: int, processes: int) -> None:
        announced.append(kernels)
        if progress:
            print(f"compiling the CPU kernels (once after an install): {kernels} in {processes} processes",
                  file=sys.stderr)  # fmt: skip

    try:
        done = compile_ahead(threads, announce)
    except Exception as exc:  # noqa: BLE001 - only a head start (e.g. a broken install's manifest)
        print(f"note: the CPU kernels could not be compiled ahead ({type(exc).__name__}: {exc}); the first step "
              "compiles them", file=sys.stderr)  # fmt: skip
        return
    if progress and announced:
        note = f"; {done['failed']} (the first step compiles the rest)" if done["failed"] else ""
        print(f"compiled in {done['seconds']:.0f} s{note}", file=sys.stderr)
