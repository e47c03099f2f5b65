"""Compiling numba kernels ahead, in several processes at once, into numba's on-disk cache.

After an install every kernel compiles on its first call, one after the other, in the one process that calls it
(numba compiles on one thread). A *manifest* names the kernels a job will call from Python and the argument types
of each call (recorded from a real run: :func:`record`); :func:`compile_ahead` finds those not yet in the disk cache
and compiles them in shares, one in this process and the others in worker processes at the same time
(``python -m meshsplat._numba_ahead``), so that the job's first calls load them. Same kernels, same cache entries
as a first call makes: this only moves the work to more cores. Anything unexpected (a share failing, numba's
internals changing) leaves the rest to the first calls, as before.

A manifest entry: ``{"kernel": "module.qualname", "args": [type, ...], "seconds": s}``; a type is
``{"array": dtype, "ndim": n, "layout": "C", "readonly": false}``, a scalar's dtype name (``"int64"``,
``"float32"``, ``"bool"``) or ``{"tuple": [type, ...]}`` (a driver's ``*args``, as numba passes them);
``seconds`` is what compiling it took when recorded (to share the work out).
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable
from contextlib import ExitStack, nullcontext
from typing import Any

from meshsplat._numba import kernel_named

__all__ = ["type_to_json", "type_from_json", "record", "missing", "compile_here", "compile_ahead", "AheadResult"]

Entry = dict[str, Any]


def type_to_json(t: Any) -> Any:
    """A numba argument type as JSON (arrays, scalars and tuples of them: what the kernels take)."""
    from numba.core import types as numba_types

    types: Any = numba_types  # (numba's stubs do not know its tuple types' fields)
    if isinstance(t, types.Array):
        return {"array": str(t.dtype), "ndim": t.ndim, "layout": t.layout, "readonly": not t.mutable}
    if isinstance(t, (types.Integer, types.Float, types.Boolean)):
        return "bool" if isinstance(t, types.Boolean) else str(t)
    if isinstance(t, types.BaseTuple):  # a driver's ``*args``, as numba passes them
        return {"tuple": [type_to_json(u) for u in t.types]}
    raise TypeError(f"no JSON form for the numba type {t}")


def type_from_json(d: Any) -> Any:
    """The numba type of :func:`type_to_json`'s JSON."""
    import numba
    import numpy as np
    from numba.core import types as numba_types

    types: Any = numba_types
    if isinstance(d, str):
        return numba.from_dtype(np.dtype(d))
    if "tuple" in d:
        return types.BaseTuple.from_types([type_from_json(u) for u in d["tuple"]])
    return types.Array(numba.from_dtype(np.dtype(d["array"])), int(d["ndim"]), str(d["layout"]),
                       readonly=bool(d["readonly"]))  # fmt: skip


def call_factories(factories: Iterable[str]) -> None:
    """Run each ``"meshsplat.module:function"`` (a module's kernel loader: it makes the kernels, compiles nothing)."""
    for spec in factories:
        module, _, fn = spec.partition(":")
        if not module.startswith("meshsplat."):
            raise ValueError(f"not a meshsplat kernel loader: {spec!r}")
        getattr(importlib.import_module(module), fn)()


def record(run: Callable[[], None]) -> list[Entry]:
    """The kernels ``run()`` calls from Python and the argument types of each call that compiled (or loaded from
    the disk cache) a specialization, with the CPU seconds that took, in call order (a kernel compiled inside
    another's compilation is not listed: compiling the outer one compiles it)."""
    from numba.core import dispatcher as numba_dispatcher

    Dispatcher: Any = numba_dispatcher.Dispatcher
    names: dict[int, str] = {}  # id(dispatcher) -> "module.qualname", for the kernels njit_serial/njit_driver made
    entries: list[Entry] = []
    original = Dispatcher._compile_for_args

    def recording(self: Any, *args: Any, **kws: Any) -> Any:
        n_before = len(self.overloads)
        t0 = time.process_time()
        try:
            return original(self, *args, **kws)
        finally:
            spent = time.process_time() - t0
            name = names.get(id(self)) or _name_of(self)
            if name is not None and len(self.overloads) > n_before:  # compiled or loaded a specialization
                names[id(self)] = name
                sig = [type_to_json(self.typeof_pyval(a)) for a in args]  # as the call typed them
                entries.append({"kernel": name, "args": sig, "seconds": round(spent, 2)})

    Dispatcher._compile_for_args = recording
    try:
        run()
    finally:
        Dispatcher._compile_for_args = original
    return entries


def _name_of(dispatcher: Any) -> str | None:
    fn = dispatcher.py_func
    name = f"{fn.__module__}.{fn.__qualname__}"
    kernel = kernel_named(name)
    return name if kernel is not None and kernel.dispatcher is dispatcher else None


def _signature(entry: Entry) -> tuple[Any, ...]:
    return tuple(type_from_json(t) for t in entry["args"])


def _in_disk_cache(dispatcher: Any, sig: tuple[Any, ...]) -> bool:
    """Whether numba's disk cache holds ``sig`` for ``dispatcher`` (numba's own index lookup, without loading);
    also true where that cannot be told (not cached on disk, or numba's internals changed): nothing to do ahead."""
    if sig in dispatcher.overloads:
        return True
    cache: Any = getattr(dispatcher, "_cache", None)
    index = getattr(cache, "_cache_file", None)
    if index is None:  # not cached on disk (a NullCache)
        return True
    try:
        return cache._index_key(sig, dispatcher.targetctx.codegen()) in index._load_index()
    except (AttributeError, TypeError):  # another numba's internals: leave it to the first call
        return True


def missing(entries: Iterable[Entry]) -> list[Entry]:
    """The entries whose kernel (made by its loader in this process) lacks their specialization in the disk cache.
    An entry whose kernel was not made here is left out (its loader did not run: nothing would call it)."""
    out = []
    for e in entries:
        kernel = kernel_named(e["kernel"])
        if kernel is not None and not _in_disk_cache(kernel.dispatcher, _signature(e)):
            out.append(e)
    return out


def compile_here(entries: Iterable[Entry]) -> None:
    """Compile each entry in this process, as its first call would (inside its kernel's compile context), which
    saves it to the disk cache."""
    for e in entries:
        kernel = kernel_named(e["kernel"])
        if kernel is None:
            raise LookupError(f"no kernel {e['kernel']!r} was made in this process (its loader has not run)")
        with kernel.compile_context() if kernel.compile_context else nullcontext():
            kernel.dispatcher.compile(_signature(e))


WORKER_START_S = 3.0  # a worker's start (python, torch, numba, the kernel loaders) on the 2-core test VM


def _shares(entries: list[Entry], n: int, head_start: float = WORKER_START_S) -> list[list[Entry]]:
    """``entries`` in ``n`` shares of about equal recorded seconds (longest first, each to the lightest share);
    the first is compiled here, and the others start ``head_start`` seconds late (a new process)."""
    shares: list[list[Entry]] = [[] for _ in range(n)]
    load = [0.0] + [head_start] * (n - 1)
    for e in sorted(entries, key=lambda e: -float(e.get("seconds", 1.0))):
        i = load.index(min(load))
        shares[i].append(e)
        load[i] += float(e.get("seconds", 1.0))
    return [s for s in shares if s]


class AheadResult(dict):
    """What :func:`compile_ahead` did: ``compiled`` (entries), ``processes``, ``seconds`` (wall clock),
    ``failed`` (a worker's last error line, or ``""``)."""


def compile_ahead(
    factories: list[str],
    entries: list[Entry],
    processes: int,
    announce: Callable[[int, int], None] | None = None,
) -> AheadResult:
    """Compile the ``entries`` (made by the ``factories``, kernel loaders run here first) that are not in numba's
    disk cache, in up to ``processes`` processes at once (this one and ``processes - 1`` workers, the workers'
    shares smaller by what starting one costs); returns at once when none is missing.
    ``announce(kernels, processes)`` is called before the work starts. A failed worker is reported in ``failed``
    (its last error line); its kernels then compile on their first call, as without this."""
    call_factories(factories)
    todo = missing(entries)
    if not todo:
        return AheadResult(compiled=[], processes=0, seconds=0.0, failed="")
    shares = _shares(todo, max(1, min(processes, len(todo))))
    if announce is not None:
        announce(len(todo), len(shares))
    t0 = time.perf_counter()
    # one thread each: numba compiles on one, and torch's pool would only take cores from the other workers
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    with ExitStack() as stack:
        logs = [stack.enter_context(tempfile.TemporaryFile(mode="w+")) for _ in shares[1:]]  # (a pipe may fill)
        workers: list[subprocess.Popen] = []
        stack.callback(_stop, workers)  # interrupted (Ctrl-C) or failed to start: no worker outlives the job
        workers.extend(_start_worker(log, env) for log in logs)
        for proc, share in zip(workers, shares[1:], strict=True):
            assert proc.stdin is not None
            proc.stdin.write(json.dumps({"factories": factories, "entries": share}))
            proc.stdin.close()
        failed = ""
        try:  # the first share here, while the workers start up
            compile_here(shares[0])
        except Exception as exc:  # noqa: BLE001 - as a worker's failure: the first call compiles it instead
            failed = _one_line(exc)
        for proc, log in zip(workers, logs, strict=True):
            if proc.wait() != 0 and not failed:
                log.seek(0)
                lines = [ln for ln in log.read().splitlines() if ln.strip()]
                failed = lines[-1] if lines else f"a worker exited with status {proc.returncode}"
    return AheadResult(compiled=todo, processes=len(shares), seconds=time.perf_counter() - t0, failed=failed)


def _start_worker(log: Any, env: dict[str, str]) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "meshsplat._numba_ahead"]
    return subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log, env=env, text=True)


def _stop(workers: list[subprocess.Popen]) -> None:
    for proc in workers:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _one_line(exc: BaseException) -> str:
    """``"TypeName: first line of the message"`` (numba's typing errors run over many lines)."""
    first = next((ln.strip() for ln in str(exc).splitlines() if ln.strip()), "")
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def _worker() -> int:
    """A worker: a JSON ``{"factories": [...], "entries": [...]}`` on stdin; compiles them into the disk cache.
    On failure the last line on stderr says why (:func:`_one_line`) and the exit status is 1."""
    try:
        job = json.loads(sys.stdin.read())
        call_factories(job["factories"])
        compile_here(job["entries"])
    except Exception as exc:  # noqa: BLE001 - reported to the parent in one line
        print(_one_line(exc), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(_worker())
