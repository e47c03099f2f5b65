"""Batches and data-parallel training: ``--nproc 2`` (gloo, two real processes) equals one process with
the same batch size, across densification and walking; a killed process stops the job with the last
checkpoint intact, and the run resumes with another number of processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import torch.distributed as dist

from _train_kit import make_tiny_dataset, small_config
from meshsplat.errors import MeshsplatError
from meshsplat.io import load_checkpoint
from meshsplat.run_folder import RunFolder
from meshsplat.train import Trainer
from meshsplat.train.distributed import DataParallel
from meshsplat.train.launch import _wait, free_port, launch
from meshsplat.train.recipes import recipe_config

BATCH = [
    "batch_size=2",
    "loss.lambda_lpips=0",
    "strategy.refine_start_iter=2",
    "strategy.refine_every=3",
    "strategy.grow_grad2d=1e-6",
    "walk.every=2",
    "optim.lr_embedding=0.02",
    "optim.lr_embedding_final=0.01",
    "checkpoint_every=100",
    "preview_every=100",
]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("dp") / "sphere")


def _env_for_children(monkeypatch):
    src = str(Path(__file__).resolve().parents[2] / "src")
    monkeypatch.setenv("PYTHONPATH", src + os.pathsep + os.environ.get("PYTHONPATH", ""))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")


def _params(run: Path) -> dict[str, torch.Tensor]:
    ckpt = RunFolder(run).checkpoints()[-1][1]
    return load_checkpoint(ckpt)["avatar"]["params"]


def test_batch_one_is_the_default_and_batches_are_checked(tiny, tmp_path):

    assert recipe_config("quality").batch_size == 1
    with pytest.raises(MeshsplatError, match="batch_size"):
        Trainer(small_config(tiny, tmp_path / "r", 2, ["batch_size=0"]))
    with pytest.raises(MeshsplatError, match="batch_size=2"):
        launch(small_config(tiny, tmp_path / "r", 2), nproc=2)


@pytest.mark.slow
def test_two_processes_equal_one_process_with_the_same_batch(tiny, tmp_path, monkeypatch):
    _env_for_children(monkeypatch)
    iters = 7  # refinement at 3 and 6, walks at 2, 4, 6
    one = Trainer(small_config(tiny, tmp_path / "one", iters, BATCH))
    n0 = one.num_gaussians
    one.train()
    assert one.num_gaussians != n0, "the comparison must cross a densification step"
    assert sum(r["walked"] for r in one.history) > 0, "the comparison must cross a walk that moves Gaussians"
    launch(small_config(tiny, tmp_path / "two", iters, BATCH), nproc=2)
    a, b = _params(tmp_path / "one"), _params(tmp_path / "two")
    assert set(a) == set(b)
    for k in a:
        assert a[k].shape == b[k].shape, k
        if a[k].is_floating_point():
            scale = a[k].abs().max().clamp_min(1e-12)
            assert float((a[k] - b[k]).abs().max() / scale) <= 1e-6, k
        else:
            assert torch.equal(a[k], b[k]), k
    log = (tmp_path / "two" / "log.csv").read_text().splitlines()
    assert len(log) == iters + 1  # rank 0 alone writes the log: one header, one row per iteration


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(x) for x in path.read_text().split()] if path.exists() else []


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the worker processes through /proc")
def test_a_killed_process_stops_the_job_and_the_run_resumes(tiny, tmp_path):
    run = tmp_path / "run"
    args = [str(tiny), "--out", str(run), "--iters", "400", "--no-progress", "--device", "cpu", "--nproc", "2"]
    sets = ["batch_size=2", "loss.lambda_lpips=0", "backend=torch", "model.n_init=200", "checkpoint_every=2"]
    sets += ["keep_checkpoints=2", "preview_every=1000", "log_every=1", "strategy.max_gaussians=500"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2] / "src") + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, "-c", "import sys; from meshsplat.cli.main import main; sys.exit(main(sys.argv[1:]))"]
    parent = subprocess.Popen([*cmd, "train", *args, "--set", *sets], env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not RunFolder(run).checkpoints() and time.monotonic() < deadline and parent.poll() is None:
        time.sleep(0.05)
    workers = _children(parent.pid)
    assert len(workers) == 2 and RunFolder(run).checkpoints(), "the job should be training"
    os.kill(workers[1], signal.SIGKILL)
    _, err = parent.communicate(timeout=120)
    assert parent.returncode == 2
    last = err.strip().splitlines()[-1]
    assert "process 1 of 2 was killed by SIGKILL" in last and "is intact" in last and "--resume" in last, err
    ckpts = RunFolder(run).checkpoints()
    state = load_checkpoint(ckpts[-1][1])  # loads: intact
    assert 0 < state["iteration"] < 400
    for w in workers:
        assert not Path(f"/proc/{w}").exists() or "Z" in Path(f"/proc/{w}/stat").read_text().split()[2]
    # resume with another number of processes (one), to a short end
    done = subprocess.run(
        [
            *cmd,
            "train",
            *[a for a in args if a not in ("--nproc", "2")],
            "--resume",
            "--iters",
            str(state["iteration"] + 2),
        ]
        + ["--set", *sets],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert load_checkpoint(RunFolder(run).checkpoints()[-1][1])["iteration"] == state["iteration"] + 2


def test_an_outside_kill_is_named_before_a_peer_that_aborted():
    """When one worker is killed, its peer often aborts (SIGABRT, the process group lost) in the same poll:
    the report names the killed one, whatever the ranks."""
    aborts = [sys.executable, "-c", "import os; os.abort()"]
    killed = [sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"]
    procs = [subprocess.Popen(cmd, stderr=subprocess.DEVNULL) for cmd in (aborts, killed)]
    for p in procs:
        p.wait()
    assert _wait(procs, 0.01) == (1, -signal.SIGKILL)
    fails = [subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"]), procs[0]]
    assert _wait(fails, 0.01) == (1, -signal.SIGABRT)  # a signal before an error exit


def test_a_cpu_all_reduce_returns_once_gloo_let_go_of_the_tensor():
    """gloo frees a finished collective on its worker thread after ``wait()`` returns; a tensor it drops
    there while the interpreter exits aborts the process. ``DataParallel`` returns only once gloo holds no
    reference (without the wait, about one in four all-reduces here returned with one still held)."""
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{free_port()}", rank=0, world_size=1)
    try:
        dp = DataParallel(0, 1)
        for i in range(300):
            t = torch.rand(1 + i % 7 * 100)
            base = t._use_count()
            dp._all_reduce(t, op=dist.ReduceOp.MAX if i % 2 else dist.ReduceOp.SUM)
            assert t._use_count() == base, f"all-reduce {i} returned while gloo still held the tensor"
    finally:
        dist.destroy_process_group()
