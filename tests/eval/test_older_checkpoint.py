"""An unreadable newest checkpoint: eval, render, export and view refuse it in one line naming the file and
``--allow-older-checkpoint``; with the flag they use the newest readable one and say which (one note line)."""

from __future__ import annotations

import numpy as np
import pytest

from _eval_kit import deform, make_avatar, make_dataset, make_run
from meshsplat.cli.main import main
from meshsplat.run_folder import RunFolder

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("older")
    av = make_avatar(n=60)
    root = make_run(av, tmp / "run", make_dataset(av, tmp / "ds"), iteration=7)
    RunFolder(root).checkpoint_path(9).write_bytes(b"PK\x03\x04 cut short by a full disk")
    np.save(tmp / "verts.npy", np.stack([deform(av.mesh.vertices, t).numpy() for t in (0.0, 0.5)]))
    return root


def _commands(run, out):
    verts = str(run.parent / "verts.npy")
    return {
        "export": ["export", str(run), "--out", str(out / "export")],
        "render": ["render", str(run), "--animation", "vertices", verts, "--out", str(out / "render"), "--size", "32x32",
                   "--no-mp4", "--no-progress"],
        "view": ["view", str(run), "--out", str(out / "view")],
        "eval": ["eval", str(run), "--out", str(out / "eval"), "--no-lpips", "--no-report", "--no-progress",
                 "--max-frames", "1"],
    }  # fmt: skip


@pytest.mark.parametrize("command", ["export", "render", "view", "eval"])
def test_unreadable_newest_checkpoint_is_refused_then_accepted_with_the_flag(run, command, tmp_path, capsys):
    args = _commands(run, tmp_path)[command]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "ckpt_00000009.pt is unreadable" in err[0] and "--allow-older-checkpoint" in err[0]
    assert not any((tmp_path / command).glob("*"))  # nothing written
    assert main([*args, "--allow-older-checkpoint"]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if line.startswith("note:")]
    skipped = [line for line in notes if "ckpt_00000009.pt" in line]
    assert len(skipped) == 1 and "using ckpt_00000007.pt (iteration 7)" in skipped[0], notes
