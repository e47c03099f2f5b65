"""What the commands say: meshsplat's warnings as one plain `note:` line once per command (no file:line,
no 'UserWarning'), and the training progress PSNR labelled for what it is (not eval's metric)."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np

from _peoplesnapshot import make_capture
from meshsplat.cli.main import main
from meshsplat.data.formats import peoplesnapshot
from meshsplat.errors import MeshsplatWarning

NOTE = "so the split-relative poses/anim_nerf_*.npz cannot be placed"


def _capture_that_warns(root: Path) -> Path:
    """A PeopleSnapshot folder without config.json (read with a gender) but with a split-relative
    refinement (one warning)."""
    root = make_capture(root, n=6)
    (root / "config.json").unlink()
    (root / "poses").mkdir()
    np.savez(
        root / "poses" / "anim_nerf_train.npz",
        betas=np.zeros((1, 10)),
        global_orient=np.zeros((3, 3)),
        body_pose=np.zeros((3, 69)),
        transl=np.ones((3, 3)),
    )
    return root


def _note_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if NOTE in line]


def test_library_warnings_are_meshsplat_warnings(tmp_path, standin_model_dir):
    root = _capture_that_warns(tmp_path / "ps")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        peoplesnapshot.read(root, model_dir=standin_model_dir, gender="neutral")
    assert [w.category for w in caught if NOTE in str(w.message)] == [MeshsplatWarning]


def test_a_warning_raised_twice_in_one_command_prints_once_as_one_plain_line(tmp_path, standin_model_dir, capsys):
    root = _capture_that_warns(tmp_path / "ps")
    # a time budget: the probe opens the capture, then training opens it again, so the reader warns twice
    # within this one command
    args = ["train", str(root), "--out", str(tmp_path / "run"), "--minutes", "5", "--threads", "1"]
    args += ["--model-dir", str(standin_model_dir), "--gender", "neutral", "--device", "cpu", "--no-progress"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main([*args, "--set", "iterations=2", "model.n_init=100", "loss.lambda_lpips=0"]) == 0
    err = capsys.readouterr().err
    lines = _note_lines(err)
    assert len(lines) == 1, err
    assert lines[0].startswith("note: ") and "Warning" not in lines[0] and ".py:" not in lines[0]
    assert "warnings.warn" not in err and not [w for w in caught if NOTE in str(w.message)]


def test_a_real_process_prints_the_note_as_one_line(tmp_path, standin_model_dir):
    root = _capture_that_warns(tmp_path / "ps")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    cmd = [sys.executable, "-m", "meshsplat.cli.main", "import", str(root), "--out", str(tmp_path / "nat")]
    res = subprocess.run(
        [*cmd, "--model-dir", str(standin_model_dir), "--gender", "neutral"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    assert _note_lines(res.stderr) == [
        f"note: {root}: no config.json and no known subject name, {NOTE}; using poses.npz"
    ], res.stderr
    assert "UserWarning" not in res.stderr and "peoplesnapshot.py" not in res.stderr


def test_progress_and_done_line_say_what_their_psnr_is(tmp_path, capsys):
    from _capture_kit import _capture

    root = _capture(tmp_path / "cap")
    run = tmp_path / "run"
    args = ["train", str(root), "--out", str(run), "--iters", "3", "--device", "cpu"]
    assert main([*args, "--set", "model.n_init=100", "loss.lambda_lpips=0"]) == 0
    cap = capsys.readouterr()
    label = "train PSNR (random bg, mean of last 10 iters)"
    assert label in cap.err  # the progress bar
    kernels = ("first step: loading the compiled CPU kernels", "compiling the CPU kernels")  # numba's first use
    done = next(line for line in cap.out.splitlines() if line.startswith("done:"))
    assert label in done and done.endswith(" dB")
    assert f"held-out metrics (test frames, one background; docs/quality.md): meshsplat eval {run}" in cap.out
    white = ["train", str(root), "--out", str(tmp_path / "w"), "--iters", "2", "--device", "cpu", "--no-progress"]
    assert main([*white, "--set", "model.n_init=100", "loss.lambda_lpips=0", "background=white"]) == 0
    assert "train PSNR (white bg, mean of last 10 iters)" in capsys.readouterr().out
    plain = ["train", str(root), "--out", str(tmp_path / "t"), "--iters", "2", "--device", "cpu"]
    assert main([*plain, "--set", "model.n_init=100", "loss.lambda_lpips=0", "backend=torch"]) == 0
    assert not any(k in capsys.readouterr().err for k in kernels)  # the torch path: no compiled kernels
