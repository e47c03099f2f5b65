"""Run folders are owned: training never overwrites a capture or a foreign folder, two trainings never share
one run, a resume never continues on another capture, synth never writes over a capture, and a process
group left over in the environment is named instead of waited for (issue 52)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from _train_kit import make_tiny_dataset, small_config
from meshsplat.errors import MeshsplatError
from meshsplat.io.folder_lock import FolderLock, lock_holder
from meshsplat.run_folder import RunFolder, check_training_target
from meshsplat.synth.capture import synth_capture
from meshsplat.train import Trainer
from meshsplat.train.distributed import LAUNCHER_VAR, check_launcher
from meshsplat.train.launch import launch, usable_cores


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("own") / "sphere")


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_training_into_the_capture_itself_is_refused_and_nothing_is_written(capture):
    before = _snapshot(capture)
    with pytest.raises(MeshsplatError, match="is the capture being trained"):
        Trainer(small_config(capture, capture, 2))
    assert _snapshot(capture) == before


def test_training_into_another_capture_is_refused(capture, tmp_path):
    other = make_tiny_dataset(tmp_path / "other")
    before = _snapshot(other)
    with pytest.raises(MeshsplatError, match=r"holds a capture \(native layout\)"):
        Trainer(small_config(capture, other, 2))
    assert _snapshot(other) == before


def test_training_into_a_foreign_folder_is_refused_and_its_files_kept(capture, tmp_path):
    foreign = tmp_path / "project"
    foreign.mkdir()
    (foreign / "config.json").write_text('{"theme": "dark"}')
    (foreign / "log.csv").write_text("a,b\n1,2\n")
    before = _snapshot(foreign)
    with pytest.raises(MeshsplatError, match=r"not a training run \(it holds config.json, log.csv\)"):
        Trainer(small_config(capture, foreign, 2))
    assert _snapshot(foreign) == before


def test_a_new_or_empty_folder_trains_and_records_the_capture(capture, tmp_path):
    (tmp_path / "empty").mkdir()
    for out in (tmp_path / "empty", tmp_path / "new"):
        Trainer(small_config(capture, out, 2)).train()
        ident = json.loads((out / "run.json").read_text())
        assert ident["data"] == str(capture.resolve())
        assert ident["capture"]["vertices"] == 162 and ident["capture"]["cameras"] == 1
        assert len(ident["recipe"]) == 16
        assert not (out / "train.lock").exists()  # released at the end
        check_training_target(out, capture)  # a finished run is a run folder: resuming it is allowed


def _hold_lock(path: Path) -> subprocess.Popen:
    code = (
        "import sys, time\nfrom meshsplat.io.folder_lock import FolderLock\n"
        f"FolderLock({str(path)!r}, 'test').acquire()\nprint('held', flush=True)\ntime.sleep(120)\n"
    )
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None and p.stdout.readline().strip() == "held"
    return p


def test_a_run_being_trained_by_another_process_is_refused_until_it_ends(capture, tmp_path):
    out = tmp_path / "run"
    Trainer(small_config(capture, out, 2)).train()
    holder = _hold_lock(RunFolder(out).lock_path)
    try:
        assert lock_holder(RunFolder(out).lock_path)["pid"] == holder.pid
        with pytest.raises(MeshsplatError, match=rf"being trained right now by process {holder.pid}"):
            Trainer(small_config(capture, out, 4), resume=True)
        with pytest.raises(MeshsplatError, match=rf"in use right now by process {holder.pid}"):
            FolderLock(RunFolder(out).lock_path, "the run").acquire()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert RunFolder(out).lock_path.exists()  # a killed holder leaves its file, but no lock
    assert lock_holder(RunFolder(out).lock_path) is None
    t = Trainer(small_config(capture, out, 4), resume=True)
    t.train()
    assert t.iteration == 4


def test_a_second_training_started_meanwhile_cannot_take_the_lock(capture, tmp_path):
    """Both passed the early check; the one that starts second is refused before writing anything."""
    out = tmp_path / "run"
    first = Trainer(small_config(capture, out, 2))
    second = Trainer(small_config(capture, out, 2))
    with FolderLock(RunFolder(out).lock_path, "the run"):  # what `first.train()` holds while it runs
        pass
    holder = _hold_lock(RunFolder(out).lock_path)
    try:
        with pytest.raises(MeshsplatError, match="in use right now"):
            second.train()
        assert not (out / "config.json").exists() and not (out / "log.csv").exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    first.train()
    assert (out / "checkpoints").is_dir()


def test_resume_on_another_capture_is_refused_and_on_the_moved_one_continues(capture, tmp_path):
    out = tmp_path / "run"
    Trainer(small_config(capture, out, 2)).train()
    other = make_tiny_dataset(tmp_path / "someone_else", size=40)
    with pytest.raises(MeshsplatError, match=r"is another capture \(image sizes differ\)"):
        Trainer(small_config(other, out, 4), resume=True)
    moved = shutil.copytree(capture, tmp_path / "moved")
    t = Trainer(small_config(moved, out, 4), resume=True)
    assert t.resumed_from is not None
    t.train()
    assert t.iteration == 4


def test_synth_never_writes_into_an_existing_capture_without_overwrite(capture, tmp_path):
    before = _snapshot(capture)
    for fmt in ("native", "meshseq"):
        with pytest.raises(MeshsplatError, match=r"exists and is not empty .*--overwrite"):
            synth_capture("CesiumMan", capture, format=fmt, frames=1, resolution=16)
    with pytest.raises(MeshsplatError, match="exists and is not empty"):  # nor into a kept native copy
        synth_capture("CesiumMan", tmp_path / "new", format="meshseq", native_dir=capture, frames=1, resolution=16)
    assert _snapshot(capture) == before


def test_a_process_group_left_in_the_environment_is_named(monkeypatch):
    for key in ("TORCHELASTIC_RUN_ID", LAUNCHER_VAR):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("MASTER_ADDR", "10.0.0.9")
    with pytest.raises(MeshsplatError, match=r"WORLD_SIZE=4.*neither torchrun nor train --nproc.*env -u RANK"):
        check_launcher()
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "abc")  # what torchrun sets
    check_launcher()
    monkeypatch.delenv("TORCHELASTIC_RUN_ID")
    monkeypatch.setenv(LAUNCHER_VAR, "manual")
    check_launcher()
    monkeypatch.setenv("WORLD_SIZE", "1")  # a world of one is no process group
    monkeypatch.delenv(LAUNCHER_VAR)
    check_launcher()


def test_train_cli_with_a_stale_process_group_ends_in_one_line(capture, tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("TORCHELASTIC_RUN_ID", LAUNCHER_VAR)}
    env.update(WORLD_SIZE="2", RANK="0", LOCAL_RANK="0", MASTER_ADDR="127.0.0.1", MASTER_PORT="29999")
    t0 = time.monotonic()
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "meshsplat.cli.main",
            "train",
            str(capture),
            "--out",
            str(tmp_path / "run"),
            "--iters",
            "2",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert p.returncode != 0 and time.monotonic() - t0 < 200
    lines = [ln for ln in p.stderr.strip().splitlines() if ln]
    assert lines and "neither torchrun nor train --nproc" in lines[-1] and "Traceback" not in p.stderr


def test_nproc_beyond_the_cores_is_refused_before_starting_anything(capture, tmp_path):
    n = usable_cores() + 1
    cfg = small_config(capture, tmp_path / "run", 2, [f"batch_size={n}"])
    with pytest.raises(MeshsplatError, match=rf"--nproc {n} is more processes than the {n - 1} CPU core"):
        launch(cfg, n)
    assert not (tmp_path / "run").exists()


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(x) for x in path.read_text().split()] if path.exists() else []


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the worker processes through /proc")
def test_sigterm_to_the_nproc_launcher_reaches_every_worker_and_a_second_training_is_refused(capture, tmp_path):
    run = tmp_path / "run"
    args = [str(capture), "--out", str(run), "--iters", "100000", "--no-progress", "--device", "cpu", "--nproc", "2"]
    sets = ["batch_size=2", "loss.lambda_lpips=0", "backend=torch", "model.n_init=200", "checkpoint_every=2"]
    sets += ["keep_checkpoints=2", "preview_every=100000", "strategy.max_gaussians=500"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2] / "src") + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, "-m", "meshsplat.cli.main", "train"]
    parent = subprocess.Popen([*cmd, *args, "--set", *sets], env=env, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not RunFolder(run).checkpoints() and time.monotonic() < deadline and parent.poll() is None:
            time.sleep(0.05)
        workers = _children(parent.pid)
        assert len(workers) == 2 and RunFolder(run).checkpoints(), "the job should be training"
        second = subprocess.run(
            [*cmd, *[a for a in args if a not in ("--nproc", "2")], "--resume", "--set", *sets],
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert second.returncode == 2
        assert f"being trained right now by process {parent.pid}" in second.stderr.strip().splitlines()[-1]
        parent.send_signal(signal.SIGTERM)  # the launcher alone, as a scheduler or `kill PID` does
        _, err = parent.communicate(timeout=120)
    finally:
        if parent.poll() is None:
            parent.kill()
    assert parent.returncode != 0 and "Traceback" not in err
    assert "stopped by a signal" in err and "--resume" in err, err
    for w in workers:  # every worker ended (no orphan trains on)
        assert not Path(f"/proc/{w}").exists() or "Z" in Path(f"/proc/{w}/stat").read_text().split()[2]
    assert lock_holder(RunFolder(run).lock_path) is None


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_workers_of_a_killed_launcher_stop_instead_of_training_on(capture, tmp_path):
    run = tmp_path / "run"
    args = [str(capture), "--out", str(run), "--iters", "100000", "--no-progress", "--device", "cpu", "--nproc", "2"]
    sets = ["batch_size=2", "loss.lambda_lpips=0", "backend=torch", "model.n_init=200", "checkpoint_every=2"]
    sets += ["keep_checkpoints=2", "preview_every=100000", "strategy.max_gaussians=500"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2] / "src") + os.pathsep + env.get("PYTHONPATH", "")
    parent = subprocess.Popen(
        [sys.executable, "-m", "meshsplat.cli.main", "train", *args, "--set", *sets],
        env=env,
        stderr=subprocess.DEVNULL,
    )
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 300
        while not RunFolder(run).checkpoints() and time.monotonic() < deadline and parent.poll() is None:
            time.sleep(0.05)
        workers = _children(parent.pid)
        assert len(workers) == 2, "the job should be training"
        parent.send_signal(signal.SIGKILL)  # no chance to pass anything on: the kernel tells the workers
        parent.wait()
        deadline = time.monotonic() + 60
        alive = workers
        while alive and time.monotonic() < deadline:
            time.sleep(0.2)
            alive = [w for w in workers if Path(f"/proc/{w}").exists()]
        assert not alive, f"workers {alive} went on training without their launcher"
    finally:
        for w in workers:
            if Path(f"/proc/{w}").exists():
                os.kill(w, signal.SIGKILL)
    assert lock_holder(RunFolder(run).lock_path) is None
