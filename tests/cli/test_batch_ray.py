"""``meshsplat batch`` on a local Ray with 2 workers: three tiny captures and a broken one (which fails
alone), re-running skips finished jobs, and a job whose worker process is killed mid-run is retried from
its checkpoint and ends bit-identical to an uninterrupted run."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import pytest
import torch

from _train_kit import make_tiny_dataset
from meshsplat.fleet.batch import run_batch
from meshsplat.fleet.jobs import job_config, read_jobs
from meshsplat.io import load_checkpoint
from meshsplat.run_folder import RunFolder
from meshsplat.train import Trainer

ray = pytest.importorskip("ray")

SMALL = ["backend=torch", "model.n_init=200", "loss.lambda_lpips=0", "strategy.max_gaussians=400"]
SMALL += ["strategy.refine_start_iter=4", "strategy.refine_every=4", "walk.every=5", "log_every=1"]


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray session (2 CPUs) for the module: Ray's start-up is the slow part."""
    src = str(Path(__file__).resolve().parents[2] / "src")
    os.environ["PYTHONPATH"] = src + os.pathsep + os.environ.get("PYTHONPATH", "")  # the workers import meshsplat
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    first = Path(make_tiny_dataset(root / "a"))
    manifest = json.loads((first / "manifest.json").read_text())
    manifest["splits"]["test_frames"] = [4, 5]  # something to evaluate on
    (first / "manifest.json").write_text(json.dumps(manifest))
    for name in ("b", "c"):
        shutil.copytree(first, root / name)
    (root / "broken").mkdir()
    (root / "broken" / "dataset.json").write_text("{ not json")
    return root


def _jobs(path: Path, jobs: list[dict], iterations: int = 8) -> Path:
    path.write_text(json.dumps({"defaults": {"iterations": iterations, "device": "cpu", "set": SMALL}, "jobs": jobs}))
    return path


@pytest.mark.slow
def test_three_captures_and_a_broken_one(local_ray, captures, tmp_path):
    jobs = _jobs(
        captures / "jobs.json",
        [
            {"data": "a"},
            {"data": "b", "export": ["ply", "splat"]},
            {"data": "c", "set": ["seed=3"]},
            {"data": "broken"},
        ],
    )
    out = tmp_path / "out"
    rows = run_batch(jobs, out, progress=False)
    by = {r["name"]: r for r in rows}
    assert [r["name"] for r in rows] == ["a", "b", "c", "broken"]
    for name in "abc":
        r = by[name]
        assert r["status"] == "ok", r
        assert r["iterations"] == 8 and r["n_gaussians"] > 0 and r["psnr"] > 10 and r["attempts"] == 1
        assert (out / name / "export" / "avatar.ply").is_file()
    assert (out / "b" / "export" / "avatar.splat").is_file()
    broken = by["broken"]
    assert broken["status"] == "failed" and "\n" not in broken["reason"] and "broken" in broken["reason"]
    assert json.loads((out / "results.json").read_text()) == rows
    with open(out / "results.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 4
    assert "1 failed" in (out / "results.html").read_text()
    # the same command again: finished jobs are skipped (no new attempt), the broken one fails again
    before = (out / "a" / "attempts.jsonl").read_text()
    again = run_batch(jobs, out, progress=False)
    assert [r["status"] for r in again] == ["ok", "ok", "ok", "failed"]
    assert (out / "a" / "attempts.jsonl").read_text() == before


def _kill_after_checkpoint(job_dir: Path, stop: threading.Event, killed: list[int]) -> None:
    """SIGKILL the job's worker process once its run holds a checkpoint (as a lost machine would)."""
    while not stop.is_set():
        att = job_dir / "attempts.jsonl"
        if att.exists() and att.read_text().strip() and RunFolder(job_dir / "run").checkpoints():
            pid = json.loads(att.read_text().splitlines()[0])["pid"]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            return
        time.sleep(0.02)


@pytest.mark.slow
def test_killed_worker_is_retried_from_its_checkpoint_bit_exact(local_ray, captures, tmp_path):
    iters = 60
    jobs = _jobs(
        captures / "jobs_kill.json", [{"data": "a", "eval": False, "export": [], "set": ["checkpoint_every=3"]}], iters
    )
    out = tmp_path / "out"
    stop, killed = threading.Event(), []
    killer = threading.Thread(target=_kill_after_checkpoint, args=(out / "a", stop, killed))
    killer.start()
    try:
        rows = run_batch(jobs, out, progress=False)
    finally:
        stop.set()
        killer.join()
    assert killed, "the worker should have been killed mid-run"
    (row,) = rows
    assert row["status"] == "ok" and row["attempts"] == 2, row
    starts = [json.loads(line)["from"] for line in (out / "a" / "attempts.jsonl").read_text().splitlines()]
    assert starts[0] == 0 and 0 < starts[1] < iters  # the retry resumed from a checkpoint
    # the same job, uninterrupted, in this process (one thread, as the job)
    (job,) = read_jobs(jobs)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        Trainer(job_config(job, tmp_path / "reference")).train()
    finally:
        torch.set_num_threads(threads)
    got = load_checkpoint(RunFolder(out / "a" / "run").checkpoints()[-1][1])
    ref = load_checkpoint(RunFolder(tmp_path / "reference").checkpoints()[-1][1])
    assert got["iteration"] == ref["iteration"] == iters
    for k, v in ref["avatar"]["params"].items():
        assert torch.equal(v, got["avatar"]["params"][k]), k
