"""``meshsplat train --nproc N``: start N training processes on this machine, as ``torchrun`` would.

The parent writes the finished config to a temporary JSON file and starts N workers
(``python -m meshsplat.train.launch CONFIG [--resume]``) with ``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``,
``MASTER_ADDR=127.0.0.1`` and a free ``MASTER_PORT``; each builds a ``Trainer``, which joins the
process group (``meshsplat.train.distributed``). When a worker fails or is killed the others are
stopped and one ``MeshsplatError`` names the worker, how it ended and the newest checkpoint (written
by rank 0 only at iteration boundaries, atomically, so it is intact): ``--resume`` continues from it,
with the same or another number of processes.

The launcher holds the run's lock (``RUN/train.lock``) for its workers, so a second training into the same
folder is refused. At most one process per CPU core this process may use. SIGTERM (or SIGHUP) to the
launcher is passed on to every worker, which checkpoint and stop together as on Ctrl-C; a worker whose
launcher dies is sent SIGTERM by the kernel (Linux), so none is left training alone.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from meshsplat._device import resolve_device, usable_cores
from meshsplat._numba import numba_available
from meshsplat.errors import MeshsplatError
from meshsplat.io.folder_lock import FolderLock
from meshsplat.run_folder import RunFolder, check_training_target
from meshsplat.train.config import TrainConfig
from meshsplat.train.cpu_kernels import prepare_cpu_kernels, uses_cpu_kernels
from meshsplat.train.distributed import LAUNCHER_VAR
from meshsplat.train.resume import TrainingInterrupted, signal_name
from meshsplat.train.trainer import Trainer

__all__ = ["launch", "free_port", "worker_main", "usable_cores"]

STOP_GRACE_S = 10.0  # after one worker fails, the others get this long to exit before SIGKILL
EXIT_INTERRUPTED = 130  # a worker stopped by SIGINT/SIGTERM after its checkpoint


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (for the workers' rendezvous)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _die_with_parent() -> None:  # runs in the child before exec (Linux: PR_SET_PDEATHSIG)
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).prctl(1, signal.SIGTERM)


def _how(code: int) -> str:
    return f"was killed by {signal_name(-code)}" if code < 0 else f"exited with code {code}"


def launch(config: TrainConfig, nproc: int, resume: bool = False, poll_s: float = 0.2) -> Path:
    """Train ``config`` with ``nproc`` local processes (data-parallel over each batch); returns the run
    folder. ``config.batch_size`` must be at least ``nproc``."""
    if nproc < 1:
        raise MeshsplatError(f"--nproc: expected at least 1 process, got {nproc}")
    if config.batch_size < nproc:
        raise MeshsplatError(
            f"--nproc {nproc} needs batch_size >= {nproc} (each process renders its share of every batch); "
            f"add --set batch_size={nproc}"
        )
    cores = usable_cores()
    if nproc > cores:
        raise MeshsplatError(
            f"--nproc {nproc} is more processes than the {cores} CPU core(s) this process may use; "
            f"use --nproc {cores} or fewer"
        )
    check_training_target(config.out, config.data)
    if uses_cpu_kernels(resolve_device(config.device), config.backend) and numba_available():
        # the workers' kernels, compiled once here on every core rather than by each worker in its first step (the
        # kernels of 2+ threads; compiling them caches the one-thread kernels they call as well)
        prepare_cpu_kernels(usable_cores(), config.progress)
    run = RunFolder(config.out)
    with (
        FolderLock(run.lock_path, f"the run {run.root}"),
        tempfile.TemporaryDirectory(prefix="meshsplat-launch-") as tmp,
    ):
        cfg_path = Path(tmp) / "config.json"
        config.to_json(cfg_path)
        port = free_port()
        procs = []
        for rank in range(nproc):
            env = dict(
                os.environ,
                RANK=str(rank),
                LOCAL_RANK=str(rank),
                WORLD_SIZE=str(nproc),
                LOCAL_WORLD_SIZE=str(nproc),
                MASTER_ADDR="127.0.0.1",
                MASTER_PORT=str(port),
                **{LAUNCHER_VAR: "nproc"},
            )
            env.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // nproc)))  # no oversubscription
            # numba's thread pool (the kernels' parallel drivers run on it when a worker has 2+ threads): its OpenMP
            # layer, beside torch's OpenMP runtime and gloo's threads, made about one worker in six abort at exit
            # ("terminate called without an active exception")
            env.setdefault("NUMBA_THREADING_LAYER", "workqueue")
            cmd = [sys.executable, "-m", "meshsplat.train.launch", str(cfg_path)] + (["--resume"] if resume else [])
            procs.append(subprocess.Popen(cmd, env=env, preexec_fn=_die_with_parent if os.name == "posix" else None))
        failed = _wait(procs, poll_s)
    if failed is None:
        return run.root
    rank, code = failed
    ckpts = run.checkpoints()
    last = f"the last checkpoint, {ckpts[-1][1]}, is intact" if ckpts else "no checkpoint was written yet"
    if code == EXIT_INTERRUPTED:
        raise TrainingInterrupted(f"training stopped by a signal; {last}: continue with --resume", signal.SIGINT, None)
    raise MeshsplatError(
        f"training process {rank} of {nproc} {_how(code)}; the other processes were stopped and {last}: "
        "continue with the same command and --resume (any --nproc)"
    )


def _wait(procs: list[subprocess.Popen], poll_s: float) -> tuple[int, int] | None:
    """Wait for every worker; on the first failure stop the rest. Returns (rank, exit code) of it or None.
    SIGTERM/SIGHUP to this process are passed on to every worker, then all are waited for (they checkpoint)."""
    forwarded: list[int] = []

    def forward(signum: int, frame: object) -> None:
        forwarded.append(signum)
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)

    passed_on = [signal.SIGTERM] + ([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])
    main_thread = threading.current_thread() is threading.main_thread()  # handlers can be set there only
    old = {s: signal.signal(s, forward) for s in passed_on} if main_thread else {}
    try:
        while True:
            if forwarded:
                raise KeyboardInterrupt
            codes = [p.poll() for p in procs]
            bad = [(r, c) for r, c in enumerate(codes) if c not in (None, 0)]
            if bad:
                _stop(procs)
                return min(bad, key=_cause_first)
            if all(c == 0 for c in codes):
                return None
            time.sleep(poll_s)
    except KeyboardInterrupt:  # Ctrl-C reached the workers too: they checkpoint and stop together
        for p in procs:
            p.wait()
        return next(((r, c) for r, p in enumerate(procs) if (c := p.returncode) != 0), None)
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _cause_first(rank_code: tuple[int, int]) -> tuple[bool, bool, int]:
    """Sort key of failed workers, the likely cause first: a worker killed by a signal before one that exited
    with an error, and among the killed an outside kill before SIGABRT (what a worker does to itself when the
    process group loses a peer: gloo's "terminate called"), then the lower rank."""
    rank, code = rank_code
    return (code >= 0, code == -signal.SIGABRT, rank)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for p in procs:
        try:
            p.wait(max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def worker_main(argv: list[str]) -> int:
    """One worker: ``CONFIG_JSON [--resume]``; the environment names its rank."""
    rank = os.environ.get("RANK", "?")
    try:
        cfg = TrainConfig.from_dict(json.loads(Path(argv[0]).read_text()))
        trainer = Trainer(cfg, resume="--resume" in argv[1:])
        try:
            trainer.train()
        finally:
            trainer.dp.close()
    except TrainingInterrupted:
        return EXIT_INTERRUPTED
    except MeshsplatError as exc:
        print(f"meshsplat: error: process {rank}: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # gloo/NCCL: another process went away mid-collective
        print(
            f"meshsplat: error: process {rank}: lost the process group ({str(exc).splitlines()[0][:200]})",
            file=sys.stderr,
        )
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(worker_main(sys.argv[1:]))
