"""Atomic checkpoints: round trip, crash safety, corrupt files, listing/pruning (which one a run reads:
test_run_folder.py)."""

from __future__ import annotations

import random

import numpy as np
import pytest
import torch

import meshsplat.io.checkpoint as ck
from meshsplat.errors import MeshsplatError
from meshsplat.io import checkpoint_path, list_checkpoints, load_checkpoint, prune_checkpoints, save_checkpoint


def _state(step: int) -> dict:
    return {
        "step": step,
        "params": {"means": torch.randn(5, 3), "face": torch.arange(5)},
        "optim": [{"lr": 1e-3, "betas": (0.9, 0.999)}],
        "rng": {"torch": torch.get_rng_state(), "python": random.getstate()},
        "config": {"name": "run", "scale_mode": "sqrt_area", "missing": None},
    }


def test_round_trip(tmp_path):
    s = _state(7)
    p = save_checkpoint(checkpoint_path(tmp_path, 7), s)
    assert p.name == "ckpt_00000007.pt"
    back = load_checkpoint(p)
    assert back["step"] == 7 and back["config"] == s["config"]
    assert torch.equal(back["params"]["means"], s["params"]["means"])
    assert torch.equal(back["rng"]["torch"], s["rng"]["torch"])
    random.setstate(back["rng"]["python"])  # restorable
    assert back["optim"][0]["betas"] == (0.9, 0.999)


def test_crash_mid_write_keeps_old_checkpoint(tmp_path, monkeypatch):
    p = tmp_path / "ckpt_00000001.pt"
    save_checkpoint(p, _state(1))
    real_save = torch.save

    def crashing_save(obj, fh):
        real_save(obj, fh)
        fh.flush()
        fh.truncate(100)  # partial bytes on disk, then the process "dies"
        raise KeyboardInterrupt("simulated crash")

    monkeypatch.setattr(ck.torch, "save", crashing_save)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(p, _state(2))
    monkeypatch.undo()
    assert load_checkpoint(p)["step"] == 1
    assert sorted(x.name for x in tmp_path.iterdir()) == ["ckpt_00000001.pt"]  # no temp file left


def test_corrupt_truncated_and_foreign_files(tmp_path):
    good = save_checkpoint(tmp_path / "a.pt", _state(3))
    data = good.read_bytes()
    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(MeshsplatError, match="corrupt or truncated"):
        load_checkpoint(trunc)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(MeshsplatError, match="corrupt or truncated"):
        load_checkpoint(junk)
    with pytest.raises(MeshsplatError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt")
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(2)}, foreign)
    with pytest.raises(MeshsplatError, match="not a meshsplat checkpoint"):
        load_checkpoint(foreign)
    future = tmp_path / "future.pt"
    torch.save({"format": ck.FORMAT_TAG, "version": 99, "state": {}}, future)
    with pytest.raises(MeshsplatError, match="version 99"):
        load_checkpoint(future)


def test_unstorable_state_is_named(tmp_path):
    with pytest.raises(MeshsplatError, match=r"state\['rng'\]\['numpy'\].*torch.from_numpy"):
        save_checkpoint(tmp_path / "x.pt", {"rng": {"numpy": np.zeros(3)}})
    assert not any(tmp_path.iterdir())


def test_list_and_prune(tmp_path):
    assert list_checkpoints(tmp_path / "nope") == []
    for step in (100, 200, 300):
        save_checkpoint(checkpoint_path(tmp_path, step), _state(step))
    checkpoint_path(tmp_path, 400).write_bytes(b"garbage")  # listed, not validated
    (tmp_path / "notes.txt").write_text("ignored")
    assert [s for s, _ in list_checkpoints(tmp_path)] == [100, 200, 300, 400]
    save_checkpoint(checkpoint_path(tmp_path, 500), _state(500), keep_last=2)
    assert [s for s, _ in list_checkpoints(tmp_path)] == [400, 500]
    with pytest.raises(MeshsplatError, match="keep_last"):
        prune_checkpoints(tmp_path, 0)
