"""Compiling the CPU kernels ahead in several processes (``_numba_ahead``, ``train.cpu_kernels``): the manifest
matches what training calls, and after ``compile_ahead`` into an empty numba cache a training job compiles
nothing itself."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from meshsplat._numba import numba_available

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is a dependency; not importable here")

TESTS = Path(__file__).resolve().parents[1]
SRC = TESTS.parent / "src"


def _python(code: str, *args: str, cache: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), str(TESTS)]))
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, timeout=900)


def test_types_round_trip_through_json():
    import numba
    from numba.core import types

    from meshsplat._numba_ahead import type_from_json, type_to_json

    samples = [
        np.zeros((2, 3), np.float32),
        np.zeros(4, np.int64)[::2],  # not contiguous: layout A
        np.zeros((2, 2), np.float64, order="F"),
        np.zeros(3, np.bool_),
        np.int64(3),
        1.5,
        True,
        (np.zeros(2), 1.0, 3, np.zeros((1, 1), np.int32)),  # a driver's *args
        (np.zeros(2), np.zeros(2)),  # a UniTuple
    ]
    ro = np.zeros(2)
    ro.flags.writeable = False
    samples.append(ro)
    for value in samples:
        t = numba.typeof(value)
        d = json.loads(json.dumps(type_to_json(t)))
        assert type_from_json(d) == t, (value, d)
    with pytest.raises(TypeError, match="no JSON form"):
        type_to_json(types.unicode_type)


def test_manifest_names_only_kernels_the_loaders_make():
    from meshsplat._numba import kernel_named
    from meshsplat._numba_ahead import call_factories
    from meshsplat.train.cpu_kernels import FACTORIES, manifest

    call_factories(FACTORIES)
    entries = manifest()["entries"]
    assert manifest()["threads"] >= 2 and entries
    for e in entries:
        assert kernel_named(e["kernel"]) is not None, e["kernel"]
        assert e["seconds"] >= 0
    with pytest.raises(ValueError, match="not a meshsplat kernel loader"):
        call_factories(["os:getcwd"])


_SUM = "meshsplat.train._albedo_prior_numba._sum_kernel"
_VECTOR = {"array": "float64", "ndim": 1, "layout": "C", "readonly": False}


def test_the_queue_compiles_each_entry_and_reports_a_failure_in_one_line(tmp_path):
    """Into an empty cache, this process and a worker take the entries from one queue, longest recorded first:
    afterwards none is missing from the cache, and one that cannot compile (here: a type the kernel cannot take)
    is reported in ``failed``, in one line, not raised, and is no longer counted as left, also when a worker took
    it. A session closed before its end stops its worker."""
    code = f"""
import json, time
from meshsplat._numba_ahead import AheadSession, missing
from meshsplat.train.cpu_kernels import FACTORIES
ok64 = {{"kernel": "{_SUM}", "args": [{_VECTOR!r}], "seconds": 0.2}}
ok32 = {{"kernel": "{_SUM}", "args": [dict({_VECTOR!r}, array="float32")], "seconds": 0.1}}
bad = {{"kernel": "{_SUM}", "args": ["bool"], "seconds": 5.0}}
session = AheadSession(FACTORIES, [ok32, bad, ok64])
order = [e["seconds"] for e in session.todo]
session.add_workers(1)
done = session.finish()
unfinished = AheadSession(FACTORIES, [dict(ok64, args=[dict({_VECTOR!r}, array="int64")])])
unfinished.add_workers(1)
unfinished.close()
lone = AheadSession(FACTORIES, [bad])  # only a worker takes it, and fails: nothing is left, the failure is told
lone.add_workers(1)
deadline = time.time() + 300
while lone.left and time.time() < deadline:
    time.sleep(0.05)
lone_left = lone.left
lone.close()
print(json.dumps({{"order": order, "done": done, "missing": missing([ok64, ok32]),
                  "stopped": [p.poll() is not None for p, _, _ in unfinished._workers],
                  "lone": [lone_left, lone.failed]}}))
"""
    out = _python(code, cache=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["order"] == [5.0, 0.2, 0.1]
    assert got["done"]["processes"] == 2 and len(got["done"]["compiled"]) == 3
    assert got["done"]["failed"].startswith("TypingError: ") and "\n" not in got["done"]["failed"]
    assert got["missing"] == [] and got["stopped"] == [True]
    assert got["lone"][0] == 0 and got["lone"][1].startswith("TypingError: ")


def test_a_worker_started_early_is_taken_over_by_the_training(tmp_path):
    """``start_compiling_early`` (the demo, while it renders) starts one worker on the manifest; the training's
    ``compile_ahead`` goes on with it and announces only what is left; afterwards nothing is missing. An early
    worker that training never takes is stopped by ``stop_compiling_early``; on one thread none starts."""
    from meshsplat._device import usable_cores

    if usable_cores() < 2:
        pytest.skip("one core: nothing is compiled ahead (CI has two)")
    code = f"""
import json
import meshsplat.train.cpu_kernels as ck
from meshsplat._numba_ahead import missing
entries = [{{"kernel": "{_SUM}", "args": [dict({_VECTOR!r}, array=t)], "seconds": 0.1}}
           for t in ("float64", "float32", "int64", "int32")]
ck.manifest = lambda: {{"threads": 2, "entries": entries}}
one_thread = ck.start_compiling_early(1)
started = ck.start_compiling_early(2)
early = ck._EARLY[0]
said = []
done = ck.compile_ahead(2, lambda kernels, processes: said.append([kernels, processes]))
after = missing(entries)
entries = [dict(entries[0], args=[dict({_VECTOR!r}, array="int16")])]
again = ck.start_compiling_early(2)
worker = ck._EARLY[0]._workers[0][0]
ck.stop_compiling_early()
print(json.dumps({{"one_thread": one_thread, "started": started, "said": said, "after": after, "again": again,
                  "stopped": worker.poll() is not None, "left": ck._EARLY, "failed": done["failed"]}}))
"""
    out = _python(code, cache=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["one_thread"] is False and got["started"] is True and got["again"] is True
    assert all(k <= 4 and p == 2 for k, p in got["said"])  # what was left, in 2 processes (or all done: nothing)
    assert got["after"] == [] and got["failed"] == ""
    assert got["stopped"] is True and got["left"] == []


def test_no_worker_process_can_start_and_this_process_compiles_the_queue(tmp_path):
    """Where no process can be started (here the interpreter is a path that does not exist: a sandbox, a process
    limit or an embedded Python look the same), the session says so in one line and this process compiles every
    entry; the demo's early start reports that nothing started and keeps no session."""
    from meshsplat._device import usable_cores

    if usable_cores() < 2:
        pytest.skip("one core: nothing is compiled ahead (CI has two)")
    code = f"""
import json, sys
import meshsplat.train.cpu_kernels as ck
from meshsplat._numba_ahead import AheadSession, missing
from meshsplat.train.cpu_kernels import FACTORIES
sys.executable = {str(tmp_path / "no-such-python")!r}
entries = [{{"kernel": "{_SUM}", "args": [dict({_VECTOR!r}, array=t)], "seconds": 0.1}} for t in ("float64", "int64")]
session = AheadSession(FACTORIES, entries)
session.add_workers(1)
done = session.finish()
ck.manifest = lambda: {{"threads": 2, "entries": [dict(entries[0], args=[dict({_VECTOR!r}, array="int32")])]}}
early = ck.start_compiling_early(2)
print(json.dumps({{"done": done, "missing": missing(entries), "early": early, "kept": len(ck._EARLY)}}))
"""
    out = _python(code, cache=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["done"]["processes"] == 1 and len(got["done"]["compiled"]) == 2 and got["missing"] == []
    assert got["done"]["failed"].startswith("no worker process could start (FileNotFoundError: ")
    assert "\n" not in got["done"]["failed"]
    assert got["early"] is False and got["kept"] == 0


def test_a_worker_says_ready_then_ok_per_entry_and_why_it_failed():
    """The worker's protocol: ``ready`` after its loaders ran, ``ok`` per compiled entry; on a failure exit
    status 1, the reason on its last stderr line."""
    from meshsplat.train.cpu_kernels import FACTORIES

    env = dict(os.environ, PYTHONPATH=str(SRC))
    ok = {"kernel": _SUM, "args": [_VECTOR], "seconds": 0.2}
    bad = {"kernel": _SUM, "args": ["bool"], "seconds": 0.1}
    lines = [json.dumps({"factories": FACTORIES}), json.dumps(ok), json.dumps(bad), json.dumps(ok)]
    out = subprocess.run([sys.executable, "-m", "meshsplat._numba_ahead"], input="\n".join(lines) + "\n", env=env,
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode == 1
    assert out.stdout.split() == ["ready", "ok"]
    assert out.stderr.strip().splitlines()[-1].startswith("TypingError: ")


def test_a_broken_manifest_is_a_note_not_an_error(monkeypatch, capsys):
    """Compiling ahead is a head start only: when it cannot run (here the manifest is unreadable, as in a broken
    install) training is told in one line and goes on (its first step compiles)."""
    import meshsplat.train.cpu_kernels as ck
    from meshsplat._device import usable_cores

    if usable_cores() < 2:
        pytest.skip("one core: nothing is compiled ahead (CI has two)")

    def unreadable():
        raise OSError("cpu_kernels.json: no such file")

    monkeypatch.setattr(ck, "manifest", unreadable)
    ck.prepare_cpu_kernels(2, progress=True)
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["note: the CPU kernels could not be compiled ahead (OSError: cpu_kernels.json: no such file); "
                   "the first step compiles them"]  # fmt: skip


@pytest.mark.slow
def test_manifest_matches_what_training_calls():
    """The shipped manifest lists exactly the kernels (and argument types) the tiny demo's training calls from
    Python on 2 threads; if not, rewrite it: python tests/_kernel_manifest.py."""
    code = (
        "import json, sys, tempfile\nfrom pathlib import Path\n"
        "from _kernel_manifest import record_training, tiny_data\n"
        "print(json.dumps(record_training(tiny_data(Path(tempfile.mkdtemp())))))\n"
    )
    out = _python(code)
    assert out.returncode == 0, out.stderr[-3000:]
    recorded = json.loads(out.stdout.strip().splitlines()[-1])
    from meshsplat.train.cpu_kernels import manifest

    def key(e):
        return e["kernel"], json.dumps(e["args"])

    shipped = manifest()["entries"]
    assert sorted(map(key, recorded)) == sorted(map(key, shipped)), "stale: python tests/_kernel_manifest.py"


@pytest.mark.slow
def test_after_compile_ahead_training_compiles_nothing(tmp_path):
    """Into an empty numba cache: a training job on 2 threads announces the compile, compiles the manifest in 2
    processes (itself and a worker), and then its steps compile nothing (every kernel is loaded)."""
    from meshsplat._device import usable_cores
    from meshsplat.train.cpu_kernels import manifest

    if usable_cores() < 2:
        pytest.skip("one core: nothing is compiled ahead (CI has two)")
    code = r"""
import json, sys, tempfile
from pathlib import Path
import torch
from numba.core import event as ev
from _kernel_manifest import tiny_data
from meshsplat.demo import PRESETS, demo_train_config
from meshsplat.train import Trainer

torch.set_num_threads(2)
compiled = []
class Listener(ev.Listener):
    def on_start(self, event):
        compiled.append(event.data["dispatcher"].py_func.__qualname__)
    def on_end(self, event):
        pass
data = tiny_data(Path(tempfile.mkdtemp()))
cfg = demo_train_config(data, Path(tempfile.mkdtemp()) / "run", PRESETS["tiny"], [], progress=True)
trainer = Trainer(cfg)
step = trainer.step
def listened_step():  # compiles from here on are the steps' own (compile_ahead compiles a share in this process)
    if not listening:
        ev.register("numba:compile", Listener())
        listening.append(True)
    return step()
listening = []
trainer.step = listened_step
trainer.train(until=3)
assert listening
print(json.dumps(compiled))
"""
    out = _python(code, cache=tmp_path / "cache")
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
    n = len(manifest()["entries"])
    assert f"compiling the CPU kernels (once after an install): {n} in 2 processes" in out.stderr
    assert "compiled in" in out.stderr and "the first step compiles the rest" not in out.stderr


@pytest.mark.slow
def test_the_nproc_launcher_compiles_ahead_for_its_workers(tmp_path):
    """``train --nproc 2`` into an empty numba cache: the launcher compiles the kernels once, in 2 processes,
    before its workers start (instead of each worker compiling all of them in its first step)."""
    from meshsplat._device import usable_cores
    from meshsplat.train.cpu_kernels import manifest

    if usable_cores() < 2:
        pytest.skip("--nproc 2 needs two cores (CI has two)")
    from _train_kit import make_tiny_dataset

    data = make_tiny_dataset(tmp_path / "sphere")  # here: rendering it compiles kernels, not in the empty cache
    code = r"""
import sys
from pathlib import Path
from _train_kit import small_config
from meshsplat.train.launch import launch

tmp = Path(sys.argv[1])
cfg = small_config(Path(sys.argv[2]), tmp / "run", 2, ["backend=auto", "batch_size=2", "loss.lambda_lpips=0"])
cfg.progress = True
launch(cfg, nproc=2)
"""
    out = _python(code, str(tmp_path), str(data), cache=tmp_path / "cache")
    assert out.returncode == 0, out.stderr[-3000:]
    n = len(manifest()["entries"])
    assert f"compiling the CPU kernels (once after an install): {n} in 2 processes" in out.stderr
    assert out.stderr.count("compiling the CPU kernels") == 1  # the launcher only, not each worker
