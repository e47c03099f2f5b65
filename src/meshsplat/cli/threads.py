"""``--threads`` for the heavy commands: torch CPU threads, by default the count that measures fastest.

On a small machine shared with other jobs torch's default (one thread per core) can cost many
times the CPU time of one thread, so ``auto`` times a short representative workload (batched
matrix products and an image-sized convolution) at 1 thread and at torch's default count (all
cores unless ``OMP_NUM_THREADS`` says otherwise) and keeps the faster, saying how it chose.
"""

from __future__ import annotations

import argparse
import os
import time

from meshsplat.errors import MeshsplatError

__all__ = ["add_threads_argument", "apply_threads", "choose_threads"]


def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--threads",
        default="auto",
        metavar="N|auto",
        help="torch CPU threads (default auto: the faster of 1 and all cores, measured at start)",
    )


def _workload_seconds(threads: int, repeats: int = 3) -> float:
    import torch

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    a = torch.rand(64, 96, 96, generator=g)
    img = torch.rand(1, 3, 128, 128, generator=g)
    w = torch.rand(8, 3, 5, 5, generator=g)
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(4):
            (a @ a).sum()
            torch.nn.functional.conv2d(img, w, padding=2).relu_().mean()
        best = min(best, time.perf_counter() - t)
    return best


def choose_threads(value: str | int = "auto") -> tuple[int, str]:
    """``(threads, how chosen)`` for ``value``: a positive count, or ``auto`` (measured)."""
    import torch

    if str(value).lower() != "auto":
        try:
            n = int(value)
        except ValueError:
            raise MeshsplatError(f"--threads: expected a positive integer or auto, got {value!r}") from None
        if n < 1:
            raise MeshsplatError(f"--threads: expected a positive integer or auto, got {value!r}")
        return n, "--threads"
    cores = max(1, min(os.cpu_count() or 1, torch.get_num_threads() or 1, 16))
    if cores == 1:
        why = "one core" if (os.cpu_count() or 1) == 1 else "torch's default is 1 (OMP_NUM_THREADS)"
        return 1, f"auto: {why}"
    times = {n: _workload_seconds(n) for n in (1, cores)}
    n = min(times, key=lambda k: times[k])
    measured = ", ".join(f"{k} thread{'s' if k > 1 else ''} {1000 * t:.1f} ms" for k, t in times.items())
    return n, f"auto: measured {measured}"


def apply_threads(args: argparse.Namespace) -> int:
    """Set torch's thread count from ``args.threads`` and print the choice; returns it."""
    import torch

    n, how = choose_threads(getattr(args, "threads", "auto"))
    torch.set_num_threads(n)
    print(f"threads: {n} ({how})")
    return n
