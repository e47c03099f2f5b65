"""Intel MKL (torch's CPU math in the x86 wheels): set up once per process, on one thread.

torch computes ``sqrt``, ``exp``, ``log`` and other functions of contiguous float tensors with MKL's
vector math (VML), splitting a tensor of more than 2,048 values across its threads. VML sets itself up on
its first call in a process. When that first call ran on two threads at once, the calling thread's share
now and then came back at VML's low-accuracy setting: ``sqrt`` as an unrefined reciprocal-square-root
estimate, about 1e-4 relative, so a training run could take another trajectory than its re-run.
Importing this module makes one call of each function on one value, on the importing thread, before any
threaded call. ``meshsplat._checks`` imports it, so every module that computes with torch does.
(``MKL_CBWR``, MKL's other setting, is in ``meshsplat/__init__.py``: it must precede importing torch.)
"""

from __future__ import annotations

import torch

__all__ = ["warm_vector_math"]


def warm_vector_math() -> None:
    """One call of each VML-backed function on one value of each float dtype, on this thread."""
    for dtype in (torch.float32, torch.float64):
        x = torch.full((1,), 0.5, dtype=dtype)
        for fn in (torch.sqrt, torch.rsqrt, torch.exp, torch.expm1, torch.log, torch.log1p, torch.tanh):
            fn(x)


warm_vector_math()
