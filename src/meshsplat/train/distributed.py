"""Data-parallel training over processes with ``torch.distributed`` (gloo on CPU, NCCL on CUDA).

Every rank holds the whole model and the same random generators, draws the same batch of training
frames and renders its share of it (batch positions ``rank, rank + world, ...``). After the backward
passes the gradients and the densification statistics are all-reduced (sums; screen radii: max), so
every rank takes the same optimizer step, and densify / prune / walk, being deterministic functions of
identical parameters, statistics and generators, make the same decisions everywhere. Rank 0 alone
writes the run folder (config, log, previews, checkpoints).

A process group is joined when the environment names one (``WORLD_SIZE`` > 1, with ``RANK``,
``MASTER_ADDR``, ``MASTER_PORT``, ``LOCAL_RANK``): what ``torchrun`` and ``meshsplat.train.launch``
set. Without it ``DataParallel.single()`` does nothing at all, so one process trains as before.
A ``WORLD_SIZE`` > 1 that no launcher set (torchrun sets ``TORCHELASTIC_RUN_ID``, ``--nproc`` sets
``LAUNCHER_VAR``; processes started some other way set ``LAUNCHER_VAR=manual``) is refused in one line: left
over in a shell, it would make a plain ``train`` wait for peers that never come.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import timedelta

import torch
import torch.distributed as dist

from meshsplat.errors import MeshsplatError

__all__ = ["DataParallel", "env_world_size", "check_launcher", "LAUNCHER_VAR"]

SETTLE_TIMEOUT_S = 5.0
LAUNCHER_VAR = "MESHSPLAT_LAUNCHER"  # set by ``train --nproc`` for its workers (or by hand: ``manual``)
_TORCHRUN_VAR = "TORCHELASTIC_RUN_ID"
_GROUP_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def _cpp_refs(tensor: torch.Tensor) -> int:
    """References to ``tensor``'s C++ object (torch's private ``_use_count``; 0 on a build without it,
    which turns ``_settle`` off)."""
    count = getattr(tensor, "_use_count", None)
    return int(count()) if count is not None else 0


def _settle(tensor: torch.Tensor, use_count: int) -> None:
    """Wait (releasing the GIL) until a gloo worker thread has dropped its references to ``tensor``.

    gloo frees a finished collective's work on its own thread after ``wait()`` returns, and dropping a
    Python-made tensor there takes the GIL. If that happens while the interpreter shuts down, the thread
    is killed in the middle of C++ code and the process aborts ("terminate called without an active
    exception"): what a worker did about once in 80 finished runs right after its last all-reduce.
    """
    deadline = time.monotonic() + SETTLE_TIMEOUT_S
    while _cpp_refs(tensor) > use_count and time.monotonic() < deadline:
        time.sleep(0)


def env_world_size() -> int:
    """``WORLD_SIZE`` from the environment (1 when unset)."""
    try:
        return int(os.environ.get("WORLD_SIZE", "1"))
    except ValueError:
        raise MeshsplatError(f"WORLD_SIZE={os.environ['WORLD_SIZE']!r} is not a number of processes") from None


def check_launcher() -> None:
    """Refuse a process group named by the environment that no launcher started (see the module docstring)."""
    if env_world_size() <= 1 or os.environ.get(_TORCHRUN_VAR) or os.environ.get(LAUNCHER_VAR):
        return
    found = " ".join(f"{k}={os.environ[k]}" for k in _GROUP_VARS if k in os.environ)
    raise MeshsplatError(
        f"the environment names a process group ({found}) but neither torchrun nor train --nproc started this "
        f"process: left over from an earlier launch? unset them (env -u {' -u '.join(_GROUP_VARS)} meshsplat ...), "
        f"or set {LAUNCHER_VAR}=manual when you start the processes yourself"
    )


@dataclass
class DataParallel:
    """This process's place in the job: ``rank`` of ``world`` processes; collectives run on ``device``
    (NCCL reduces CUDA tensors only)."""

    rank: int = 0
    world: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @classmethod
    def single(cls) -> DataParallel:
        return cls(0, 1)

    @classmethod
    def from_env(cls, device: torch.device) -> tuple[DataParallel, torch.device]:
        """Join the process group the environment names (once per process); returns it and this rank's
        device (``cuda:LOCAL_RANK`` on CUDA)."""
        world = env_world_size()
        if world <= 1:
            return cls.single(), device
        check_launcher()
        if device.type == "cuda":
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(device)
        if not dist.is_initialized():
            for key in ("RANK", "MASTER_ADDR", "MASTER_PORT"):
                if key not in os.environ:
                    raise MeshsplatError(
                        f"WORLD_SIZE={world} but {key} is not set: launch with meshsplat train --nproc N or torchrun"
                    )
            backend = "nccl" if device.type == "cuda" else "gloo"
            dist.init_process_group(backend, timeout=timedelta(minutes=30))
        return cls(dist.get_rank(), dist.get_world_size(), device), device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1

    def _all_reduce(self, tensor: torch.Tensor, op: dist.ReduceOp.RedOpType = dist.ReduceOp.SUM) -> None:
        """``dist.all_reduce`` in place that returns only once the process group holds no reference to
        ``tensor`` (on CPU; NCCL frees its work later, on its watchdog thread)."""
        use_count = _cpp_refs(tensor)
        dist.all_reduce(tensor, op=op)
        if tensor.device.type == "cpu":
            _settle(tensor, use_count)

    def share(self, n: int) -> list[int]:
        """This rank's positions in a batch of ``n`` images."""
        return list(range(self.rank, n, self.world))

    def check_batch(self, batch_size: int) -> None:
        if batch_size < self.world:
            raise MeshsplatError(
                f"batch_size {batch_size} is smaller than the {self.world} processes: every process renders at "
                f"least one image per iteration; use --set batch_size={self.world} (or more) or fewer processes"
            )

    def all_reduce_grads(self, tensors: Sequence[torch.Tensor]) -> None:
        """Sum the ``.grad`` of ``tensors`` over ranks (a gradient missing on a rank counts as zero; one
        missing on every rank stays None, as in one process)."""
        if not self.active or not tensors:
            return
        dev = tensors[0].device
        present = torch.tensor([t.grad is not None for t in tensors], dtype=torch.float32, device=dev)
        self._all_reduce(present, op=dist.ReduceOp.MAX)
        live = [t for t, p in zip(tensors, present.tolist(), strict=True) if p > 0]
        if not live:
            return
        flat = torch.cat([(t.grad if t.grad is not None else torch.zeros_like(t)).reshape(-1) for t in live])
        self._all_reduce(flat)
        at = 0
        for t in live:
            n = t.numel()
            t.grad = flat[at : at + n].view_as(t).clone()
            at += n

    def sum(self, values: torch.Tensor) -> torch.Tensor:
        """``values`` summed over ranks (a new tensor; unchanged in one process)."""
        if not self.active:
            return values
        out = values.to(self.device, copy=True)
        self._all_reduce(out)
        return out.to(values.device)

    def reduce_statistics(self, grad2d: torch.Tensor, count: torch.Tensor, radii: torch.Tensor) -> None:
        """In place: densification statistics of one batch summed (gradient norms, counts) and maxed
        (screen radii) over ranks."""
        if not self.active:
            return
        self._all_reduce(grad2d)
        self._all_reduce(count)
        self._all_reduce(radii, op=dist.ReduceOp.MAX)

    def check_same(self, what: str, value: int) -> None:
        """Every rank must hold the same ``value`` (e.g. the number of Gaussians); one clear error if not."""
        if not self.active:
            return
        t = torch.tensor([value, -value], dtype=torch.float64, device=self.device)
        self._all_reduce(t, op=dist.ReduceOp.MAX)
        if int(t[0]) != value or int(-t[1]) != value:
            raise MeshsplatError(f"rank {self.rank}: {what} differs between processes ({value} here); please report")

    def barrier(self) -> None:
        if self.active:
            dist.barrier()

    def close(self) -> None:
        if self.active and dist.is_initialized():
            dist.destroy_process_group()
