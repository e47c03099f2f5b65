"""Kill -9 at random moments (and inside checkpoint writes), resume, and end bit for bit equal to
an uninterrupted run with the default loss (LPIPS on). Each training run is a real subprocess."""

from __future__ import annotations

import csv
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from _train_kit import make_tiny_dataset
from meshsplat.metrics.lpips_net import lpips_available

ITERS = 16
ARGS = [
    "--iters",
    str(ITERS),
    "--no-progress",
    "--device",
    "cpu",
    "--set",
    "backend=torch",
    "--set",
    "model.n_init=200",
    "--set",
    "checkpoint_every=2",
    "--set",
    "keep_checkpoints=3",
    "--set",
    "log_every=1",
    "--set",
    "preview_every=1000",
    "--set",
    "strategy.refine_start_iter=2",
    "--set",
    "strategy.refine_every=2",
    "--set",
    "strategy.reset_every=9",
    "--set",
    "strategy.grow_grad2d=1e-6",
    "--set",
    "strategy.max_gaussians=3000",
    "--set",
    "walk.every=3",
]

# Runs the CLI; with KILL_AT_FSYNC=k the process SIGKILLs itself at the k-th fsync of a file written
# atomically (during training: the checkpoints; fsyncs of the folder after the rename do not count):
# the temporary file is fully written but not yet moved into place.
DRIVER = """
import os, signal, stat, sys
import meshsplat.io.atomic as atomic
k = int(os.environ.get("KILL_AT_FSYNC", "0"))
if k:
    real, n = os.fsync, [0]
    def fsync(fd):
        real(fd)
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            return
        n[0] += 1
        if n[0] == k:
            os.kill(os.getpid(), signal.SIGKILL)
    atomic.os = type("os_with_kill", (), {"__getattr__": lambda self, a: getattr(os, a)})()
    atomic.os.fsync = fsync
from meshsplat.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def _env(**extra):
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    src = str(Path(__file__).resolve().parents[2] / "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    env.update(extra)
    return env


def _train(ds, out, resume=False, kill_after=None, kill_at_fsync=0):
    argv = [sys.executable, "-c", DRIVER, "train", str(ds), "--out", str(out), *ARGS] + (["--resume"] if resume else [])
    p = subprocess.Popen(
        argv, env=_env(KILL_AT_FSYNC=str(kill_at_fsync)), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    if kill_after is not None:
        try:
            p.wait(timeout=kill_after)
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGKILL)
    _, err = p.communicate(timeout=300)
    return p.returncode, err


def _final(out):
    st = torch.load(Path(out) / "checkpoints" / f"ckpt_{ITERS:08d}.pt", weights_only=True)["state"]
    with open(Path(out) / "log.csv", newline="") as fh:
        losses = [(r["iteration"], r["loss"], r["n_gaussians"]) for r in csv.DictReader(fh)]
    return st, losses


@pytest.mark.slow
@pytest.mark.skipif(not lpips_available("alex"), reason="LPIPS weights not installed (default loss needs them)")
def test_kill_at_random_moments_then_resume_is_bit_exact(tmp_path):
    ds = make_tiny_dataset(tmp_path / "ds")
    rc, err = _train(ds, tmp_path / "ref")
    assert rc == 0, err
    ref, ref_log = _final(tmp_path / "ref")

    out = tmp_path / "killed"
    rng = random.Random(1234)
    t0 = time.perf_counter()
    rc, err = _train(ds, out, kill_at_fsync=3)  # killed inside its 3rd checkpoint write
    assert rc == -signal.SIGKILL, err
    assert any(p.name.endswith(".tmp") for p in (out / "checkpoints").iterdir())  # the interrupted write
    startup = time.perf_counter() - t0
    for _kill in range(3):
        rc, err = _train(ds, out, resume=True, kill_after=rng.uniform(0.3, 1.5) * startup)
        if rc == 0:  # finished before the kill: start the killed phase again from a checkpoint
            break
        assert rc == -signal.SIGKILL, err
    rc, err = _train(ds, out, resume=True, kill_at_fsync=2)  # one more kill inside a write
    if rc != 0:
        assert rc == -signal.SIGKILL, err
        rc, err = _train(ds, out, resume=True)
    assert rc == 0, err
    assert not [p for p in (out / "checkpoints").iterdir() if p.name.endswith(".tmp")]  # cleaned up

    got, got_log = _final(out)
    a, b = ref["avatar"]["params"], got["avatar"]["params"]
    assert a["sh0"].shape[0] != 200  # densification changed the count
    assert set(a) == set(b)
    for k in a:
        assert a[k].shape == b[k].shape and torch.equal(a[k], b[k]), k
    for k, opt in ref["optimizers"].items():
        for slot, st in opt["state"].items():
            for name, t in st.items():
                assert torch.equal(t, got["optimizers"][k]["state"][slot][name]), (k, name)
    assert got_log == ref_log
