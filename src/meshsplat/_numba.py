"""Whether numba can be used, and running compiled kernels on torch's thread count (one home for the compiled
rasterizer, ``render.backends.numba_cpu``, the compiled shadow maps, ``mesh.visibility``, and the albedo prior).

Kernels are serial (``njit_serial``: a kernel over ``[lo, hi)`` ranges of its items) and run on several threads by
``run_ranges``. numba's ``parallel=True`` loops around a whole kernel compiled several times slower (the
rasterizer's four largest kernels: about 20 s of CPU against 7 s serial, bench/reports/raster_cpu.md), which is
what the first run after an install waits for; on one thread nothing parallel is compiled at all, on more each
kernel gets a small parallel driver (compiled on first use, cached) that runs it over ranges."""

from __future__ import annotations

import os
import platform
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from functools import lru_cache
from typing import Any, NamedTuple

__all__ = [
    "numba_available", "njit_serial", "njit_driver", "run_ranges", "run_ranges_compiling_in", "llvm_options",
    "LLVM_DEFAULTS", "NO_NUMBA_ENV", "Kernel", "kernel_named", "float_from_bits", "host_is_arm64",
]  # fmt: skip

NO_NUMBA_ENV = "MESHSPLAT_NO_NUMBA"  # set to 1: behave as if numba were not installed


@lru_cache(maxsize=1)
def _numba_importable() -> bool:
    try:
        import numba  # noqa: F401  (imported, not just found: a broken llvmlite/numpy pairing must fall back)
    except Exception:  # noqa: BLE001 - ImportError, or an incompatible numpy/llvmlite raising at import
        return False
    return True


def numba_available() -> bool:
    """True when numba imports and ``MESHSPLAT_NO_NUMBA`` is not set to a true value (1/true/yes).

    Imports numba on the first call (only CPU work asks, and it then uses numba anyway).
    """
    if os.environ.get(NO_NUMBA_ENV, "").strip().lower() in ("1", "true", "yes"):
        return False
    return _numba_importable()


CompileContext = Callable[[], AbstractContextManager[Any]]


class Kernel(NamedTuple):
    """A function compiled by ``njit_serial``/``njit_driver``: its numba dispatcher, and what numba's compilations of
    it must run inside (``None``: nothing), e.g. an LLVM option (``numba_lanes``)."""

    dispatcher: Any
    compile_context: CompileContext | None


_KERNELS: dict[str, Kernel] = {}  # "module.qualname" of the Python function -> its kernel, as made in this process


def kernel_named(name: str) -> Kernel | None:
    """The kernel made from the Python function ``name`` (``"module.qualname"``) in this process, if it was made
    (its module's loader has run); what ``_numba_ahead`` compiles by name."""
    return _KERNELS.get(name)


def _registered(decorator: Callable[[Callable[..., Any]], Any], context: CompileContext | None) -> Any:
    def wrap(fn: Callable[..., Any]) -> Any:
        dispatcher = decorator(fn)
        _KERNELS[f"{fn.__module__}.{fn.__qualname__}"] = Kernel(dispatcher, context)
        return dispatcher

    return wrap


def njit_serial(
    numba: Any, inline: bool = False, cache: bool = True, compile_context: CompileContext | None = None
) -> Callable[[Callable[..., Any]], Any]:
    """The decorator of serial kernels and their helpers: cached on disk (unless ``cache`` is false), no fastmath,
    GIL released, and numpy's error model (a division by zero gives inf or nan, as in numba's parallel loops,
    instead of raising: the checks would stop LLVM from vectorizing). ``inline``: inlined into the caller at
    numba's IR level. ``compile_context``: what compiling it ahead (``_numba_ahead``) must run inside, as its
    first call does. Each function it compiles is known by name (:func:`kernel_named`)."""
    opts: dict[str, Any] = {"cache": cache, "fastmath": False, "nogil": True, "error_model": "numpy"}
    if inline:
        opts["inline"] = "always"
    return _registered(numba.njit(**opts), compile_context)


def njit_driver(
    numba: Any, cache: bool = True, compile_context: CompileContext | None = None
) -> Callable[[Callable[..., Any]], Any]:
    """The decorator of ``run_ranges``'s drivers: ``parallel=True``, cached on disk (unless ``cache`` is false), no
    fastmath, GIL released. A driver is a module-level function (numba caches no closure across processes) of the
    form ``for j in prange(bounds.shape[0] - 1): kernel(*args, bounds[j], bounds[j + 1])``."""
    return _registered(numba.njit(parallel=True, cache=cache, fastmath=False, nogil=True), compile_context)


CHUNKS_PER_THREAD = 4  # ranges per thread: uneven items (tiles) still balance


def run_ranges(kernel: Callable[..., Any], driver: Callable[..., Any], n: int, *args: Any) -> None:
    """``kernel(*args, lo, hi)`` over ``[0, n)`` on ``torch.get_num_threads()`` threads: one call when that is 1
    (nothing parallel is compiled); else ``driver(bounds, *args)``, a ``parallel=True`` loop over
    ``CHUNKS_PER_THREAD`` contiguous ranges per thread that calls the kernel on each (numba's threads share the
    OpenMP runtime with torch's: a pool of Python threads instead measured 10-25% slower beside torch's spinning
    threads). Each item is computed on its own into the output arrays among ``args``, so the results do not depend
    on the thread count."""
    import torch

    threads = max(1, torch.get_num_threads())
    if threads == 1 or n < 2:
        kernel(*args, 0, n)
        return
    import numba
    import numpy as np

    chunks = min(n, CHUNKS_PER_THREAD * threads)
    bounds = np.array([n * j // chunks for j in range(chunks + 1)], np.int64)
    numba.set_num_threads(max(1, min(threads, int(getattr(numba.config, "NUMBA_NUM_THREADS", 1)))))
    try:
        driver(bounds, *args)
    finally:  # numba's OpenMP layer shares the runtime with torch and would change its count
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


def run_ranges_compiling_in(
    context: CompileContext, seen: set[tuple[Any, ...]], key: tuple[Any, ...], kernel: Callable[..., Any],
    driver: Callable[..., Any], n: int, *args: Any,
) -> None:  # fmt: skip
    """``run_ranges``, inside ``context`` the first time ``key`` (with serial or parallel added) is seen in this
    process (``seen``: the caller's set): the call that compiles a kernel, or loads it from numba's cache, then runs
    inside the LLVM options the kernel must compile with (``llvm_options``). ``key``: what makes numba specialize
    (e.g. the float types); a specialization outside the keys compiles outside the options (same results)."""
    import torch

    key = (*key, n >= 2 and torch.get_num_threads() > 1)
    if key in seen:
        run_ranges(kernel, driver, n, *args)
        return
    with context():
        run_ranges(kernel, driver, n, *args)
    seen.add(key)


# LLVM's defaults of the options the compiled kernels change while they compile (LLVM 20): ``force-vector-width``
# (0: the cost model's), and the most run-time checks the loop vectorizer adds before it gives up on a loop
# (``vectorize-scev-check-threshold``: assumptions about index arithmetic; ``runtime-memory-check-threshold``:
# pairs of arrays that might overlap).
LLVM_DEFAULTS = {"force-vector-width": 0, "vectorize-scev-check-threshold": 16, "runtime-memory-check-threshold": 8}


def host_is_arm64() -> bool:
    """Whether this is an arm64 host (Apple silicon, Graviton): SIMD is NEON's 128 bits on every such CPU, where
    LLVM's cost model leaves some of the kernels' loops scalar (the lane and projection kernels force a width)."""
    return platform.machine().lower() in ("arm64", "aarch64")


@contextmanager
def llvm_options(options: dict[str, int]) -> Iterator[None]:
    """Numba compilations inside run with these LLVM options (names of ``LLVM_DEFAULTS``; empty: nothing changes).
    The options are global to LLVM, so numba's compiler lock is held throughout and they are reset to LLVM's
    defaults after; LLVM's remarks on the loops it leaves scalar are kept off stderr (``_llvm_remarks_dropped``)."""
    if not options:
        yield
        return
    unknown = set(options) - set(LLVM_DEFAULTS)
    if unknown:
        raise ValueError(f"llvm_options: no default known for {sorted(unknown)}")
    from llvmlite import binding as llvm
    from numba.core.compiler_lock import global_compiler_lock

    with global_compiler_lock, _llvm_remarks_dropped():
        for name, value in options.items():
            llvm.set_option("", f"-{name}={value}")
        try:
            yield
        finally:
            for name in options:
                llvm.set_option("", f"-{name}={LLVM_DEFAULTS[name]}")


@lru_cache(maxsize=1)
def float_from_bits() -> tuple[Any, Any]:
    """Two numba intrinsics, ``(f32, f64)``: an int32's bits as a float32, an int64's as a float64 (an LLVM bitcast).
    The vectorizable ``exp`` polynomials put ``2^n`` into the exponent bits with them (``numba_lanes``, the albedo
    prior). Imports numba."""
    from llvmlite import ir
    from numba.core import types
    from numba.extending import intrinsic

    def bitcast(int_type: Any, float_type: Any, ir_type: Any) -> Any:
        @intrinsic
        def from_bits(typingctx, i):
            def codegen(context, builder, signature, args):
                return builder.bitcast(args[0], ir_type)

            return float_type(int_type), codegen

        return from_bits

    return bitcast(types.int32, types.float32, ir.FloatType()), bitcast(types.int64, types.float64, ir.DoubleType())


_REMARK = re.compile(r"remark: [^\n]*loop not vectorized[^\n]*\n?")


@contextmanager
def _llvm_remarks_dropped() -> Iterator[None]:
    """At a forced width LLVM prints a remark for every loop it leaves scalar (31 lines for a first multi-thread
    render), on the process's stderr (file descriptor 2, below Python). Inside, descriptor 2 goes to a temporary
    file; what was written there, less those remarks, goes to stderr after (delayed, not lost)."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no stderr (e.g. pythonw): nothing to keep clean
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            kept = _REMARK.sub("", tmp.read().decode(errors="replace"))
            if kept:
                sys.stderr.write(kept)
                sys.stderr.flush()
