"""Compiling numba kernels ahead, in several processes at once, into numba's on-disk cache.

After an install every kernel compiles on its first call, one after the other, in the one process that calls it
(numba compiles on one thread). A *manifest* names the kernels a job will call from Python and the argument types
of each call (recorded from a real run: :func:`record`); :func:`compile_ahead` finds those not yet in the disk cache
and compiles them in this process and in worker processes at the same time (``python -m meshsplat._numba_ahead``),
each process taking the next kernel from one queue (:class:`AheadSession`), so that the job's first calls load
them. Same kernels, same cache entries as a first call makes: this only moves the work to more cores, or earlier
(a session's workers may start before the job). Anything unexpected (a worker failing, numba's internals changing)
leaves the rest to the first calls, as before.

A manifest entry: ``{"kernel": "module.qualname", "args": [type, ...], "seconds": s}``; a type is
``{"array": dtype, "ndim": n, "layout": "C", "readonly": false}``, a scalar's dtype name (``"int64"``,
``"float32"``, ``"bool"``) or ``{"tuple": [type, ...]}`` (a driver's ``*args``, as numba passes them);
``seconds`` is what compiling it took when recorded (the longest are handed out first).
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from contextlib import ExitStack, nullcontext, suppress
from typing import Any

from meshsplat._numba import kernel_named

__all__ = [
    "type_to_json", "type_from_json", "record", "missing", "compile_here", "compile_ahead", "AheadSession", "AheadResult",
]  # fmt: skip

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


class AheadResult(dict):
    """What :func:`compile_ahead` (or :meth:`AheadSession.finish`) did: ``compiled`` (entries), ``processes``,
    ``seconds`` (wall clock), ``failed`` (a worker's last error line, or ``""``)."""


class AheadSession:
    """Compiling ahead from one queue: the missing entries, longest recorded first, each taken by the next process
    that is free (this one, in :meth:`finish`, and the worker processes of :meth:`add_workers`), so no process
    waits on a share fixed beforehand. Workers can start early, before the job that needs the kernels (the demo
    starts one while its capture renders); :meth:`finish` then compiles what is left with them. Close (or
    ``finish``) a session: :meth:`close` stops its workers."""

    def __init__(self, factories: list[str], entries: Iterable[Entry]) -> None:
        call_factories(factories)
        self.factories = factories
        self.todo = sorted(missing(entries), key=lambda e: -float(e.get("seconds", 1.0)))
        self._queue = list(reversed(self.todo))  # pop() takes the longest left
        self._lock = threading.Lock()
        self._workers: list[tuple[subprocess.Popen, threading.Thread, Any]] = []
        self._busy: set[int] = set()  # the workers compiling an entry now
        self._ending = False  # the queue is empty for good: a worker that exits now is not a failure
        self._stack = ExitStack()
        self.failed = ""

    @property
    def processes(self) -> int:
        """The worker processes started so far, and this one."""
        return len(self._workers) + 1

    @property
    def left(self) -> int:
        """The entries not compiled yet: still queued, or being compiled by a worker."""
        with self._lock:
            return len(self._queue) + len(self._busy)

    def _take(self, worker: int | None = None) -> Entry | None:
        with self._lock:
            if not self._queue:
                return None
            if worker is not None:
                self._busy.add(worker)
            return self._queue.pop()

    def _fail(self, why: str) -> None:
        with self._lock:
            self.failed = self.failed or why

    def add_workers(self, n: int) -> None:
        """Start ``n`` more worker processes (no more than there are entries left), each fed from the queue. When a
        process cannot start, no more are tried and ``failed`` says why; this process still compiles the queue."""
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
        with self._lock:
            n = min(n, len(self._queue))
        for _ in range(max(0, n)):
            # its stderr (a pipe may fill), closed with the session
            log = self._stack.enter_context(tempfile.TemporaryFile(mode="w+"))  # noqa: SIM115
            try:
                proc = _start_worker(log, env)
            except OSError as exc:  # no process to start here (a sandbox, a process limit, an interpreter that
                # cannot be run again): this process compiles the queue, as with no second core
                self._fail(f"no worker process could start ({_one_line(exc)})")
                return
            feeder = threading.Thread(target=self._feed, args=(len(self._workers), proc, log), daemon=True,
                                      name="numba-ahead-feeder")  # fmt: skip
            self._workers.append((proc, feeder, log))
            feeder.start()

    def _feed(self, worker: int, proc: subprocess.Popen, log: Any) -> None:
        """One worker's entries, one at a time, as long as the queue has any (run on a thread of this process)."""
        assert proc.stdin is not None and proc.stdout is not None
        try:
            proc.stdin.write(json.dumps({"factories": self.factories}) + "\n")
            proc.stdin.flush()
            if proc.stdout.readline().strip() != "ready":  # its loaders ran: only now take an entry for it
                raise EOFError
            while (entry := self._take(worker)) is not None:
                proc.stdin.write(json.dumps(entry) + "\n")
                proc.stdin.flush()
                if proc.stdout.readline().strip() != "ok":
                    raise EOFError
                with self._lock:
                    self._busy.discard(worker)
        except (EOFError, OSError, ValueError):  # the worker failed (its reason on stderr) or was stopped
            proc.wait()
            with self._lock:
                stopped_idle = self._ending and worker not in self._busy  # with nothing left to give it
                self._busy.discard(worker)  # (its entry, if any, is left to the first call)
            if stopped_idle:
                return
            log.seek(0)
            lines = [ln for ln in log.read().splitlines() if ln.strip()]
            self._fail(lines[-1] if lines else f"a worker exited with status {proc.returncode}")
        finally:
            with suppress(OSError):
                proc.stdin.close()  # end of input: the worker exits

    def finish(self) -> AheadResult:
        """Compile the entries left in this process while the workers take theirs; wait for the workers. The
        kernels of an entry that failed compile on their first call, as without this."""
        t0 = time.perf_counter()
        try:
            while (entry := self._take()) is not None:
                try:
                    compile_here([entry])
                except Exception as exc:  # noqa: BLE001 - as a worker's failure: the first call compiles it
                    self._fail(_one_line(exc))
            with self._lock:  # nothing left: a worker still starting up, or between entries, is not waited for
                self._ending = True
                idle = [proc for i, (proc, _, _) in enumerate(self._workers) if i not in self._busy]
            _stop(idle)
            for proc, feeder, _ in self._workers:
                feeder.join()
                proc.wait()
        finally:
            self.close()
        return AheadResult(compiled=self.todo, processes=self.processes if self.todo else 0,
                           seconds=time.perf_counter() - t0, failed=self.failed)  # fmt: skip

    def close(self) -> None:
        """Stop the workers still running (interrupted, or a session not finished) and drop their logs."""
        with self._lock:
            self._queue.clear()
            self._ending = True
        _stop([proc for proc, _, _ in self._workers])
        for _, feeder, _ in self._workers:
            feeder.join()  # (it sees its worker's end at once)
        self._stack.close()


def compile_ahead(
    factories: list[str],
    entries: list[Entry],
    processes: int,
    announce: Callable[[int, int], None] | None = None,
    session: AheadSession | None = None,
) -> AheadResult:
    """Compile the ``entries`` (made by the ``factories``, kernel loaders run here first) that are not in numba's
    disk cache, in up to ``processes`` processes at once (this one and workers, an :class:`AheadSession`; or
    ``session``, one already started, with the workers it has); returns at once when none is left.
    ``announce(kernels left, processes)`` is called before the work starts. A failed worker is reported in
    ``failed`` (its last error line); its kernels then compile on their first call, as without this."""
    if session is None:
        session = AheadSession(factories, entries)
    try:
        if session.left:
            session.add_workers(max(1, processes) - session.processes)
            if announce is not None:
                announce(session.left, session.processes)
    except BaseException:
        session.close()
        raise
    return session.finish()


def _start_worker(log: Any, env: dict[str, str]) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "meshsplat._numba_ahead"]
    return subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, env=env, text=True)


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
    """A worker: on stdin a JSON line ``{"factories": [...]}``, then one entry per line, each compiled into the disk
    cache; on stdout ``ready`` once the loaders ran, then ``ok`` per entry; it exits at the end of its input. On
    failure the last line on stderr says why (:func:`_one_line`) and the exit status is 1."""
    try:
        call_factories(json.loads(sys.stdin.readline())["factories"])
        print("ready", flush=True)
        for line in sys.stdin:
            compile_here([json.loads(line)])
            print("ok", flush=True)
    except Exception as exc:  # noqa: BLE001 - reported to the parent in one line
        print(_one_line(exc), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(_worker())
