"""meshsplat.run_folder: names of a run's files, which checkpoint a run is read from, clear one-line errors."""

from __future__ import annotations

import json
import warnings

import pytest
import torch

from _eval_kit import make_avatar, make_run
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.io import checkpoint_path, save_checkpoint
from meshsplat.run_folder import LoadedRun, RunFolder, load_avatar, load_run


def _one_line(exc_info) -> str:
    text = str(exc_info.value)
    assert "\n" not in text
    return text


def test_paths(tmp_path):
    run = RunFolder(tmp_path / "r")
    assert run.config_path == tmp_path / "r" / "config.json"
    assert run.checkpoint_dir == tmp_path / "r" / "checkpoints"
    assert run.log_path == tmp_path / "r" / "log.csv"
    assert run.preview_dir == tmp_path / "r" / "previews"
    assert run.refined_params_path == tmp_path / "r" / "refined_params.npz"
    assert run.source_map_path == tmp_path / "r" / "source_map.npz"
    assert run.eval_dir == tmp_path / "r" / "eval" and run.export_dir == tmp_path / "r" / "export"
    assert run.checkpoint_path(30) == tmp_path / "r" / "checkpoints" / "ckpt_00000030.pt"
    assert run.preview_path(30) == tmp_path / "r" / "previews" / "preview_000030.png"
    assert not (tmp_path / "r").exists()  # naming creates nothing
    assert run.checkpoints() == []


def test_of_a_run_or_a_checkpoint_file(tmp_path):
    run = RunFolder(tmp_path / "r")
    p = save_checkpoint(run.checkpoint_path(5), {"iteration": 5})
    assert RunFolder.of(run.root).root == run.root
    assert RunFolder.of(p).root == run.root  # RUN/checkpoints/ckpt_*.pt -> RUN
    flat = save_checkpoint(checkpoint_path(tmp_path / "old", 5), {"iteration": 5})
    assert RunFolder.of(flat).root == tmp_path / "old"  # older runs kept checkpoints in RUN itself


def test_unreadable_newest_checkpoint_is_refused_unless_allowed(tmp_path):
    run = RunFolder(tmp_path / "r")
    for it in (10, 20, 30):
        save_checkpoint(run.checkpoint_path(it), {"iteration": it})
    run.checkpoint_path(40).write_bytes(b"garbage")  # newest is corrupt
    (run.checkpoint_dir / "notes.txt").write_text("ignored")
    assert [it for it, _ in run.checkpoints()] == [10, 20, 30, 40]
    with pytest.raises(MeshsplatError, match=r"newest checkpoint .*ckpt_00000040.pt is unreadable") as e:
        run.latest_checkpoint()
    text = _one_line(e)
    assert "--allow-older-checkpoint" in text and "3 older" in text
    with pytest.warns(MeshsplatWarning, match=r"skipped .*ckpt_00000040.pt; using ckpt_00000030.pt \(iteration 30\)"):
        path, state = run.latest_checkpoint(allow_older=True)
    assert path == run.checkpoint_path(30) and state["iteration"] == 30
    save_checkpoint(run.checkpoint_path(50), {"iteration": 50}, keep_last=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a readable newest one: no note
        assert run.latest_checkpoint()[0] == run.checkpoint_path(50)


def test_latest_checkpoint_prefers_checkpoints_folder_then_flat(tmp_path):
    save_checkpoint(checkpoint_path(tmp_path / "r", 99), {"iteration": 99})  # an older flat layout
    run = RunFolder(tmp_path / "r")
    assert run.latest_checkpoint()[0].name == "ckpt_00000099.pt"
    save_checkpoint(run.checkpoint_path(1), {"iteration": 1})
    assert run.latest_checkpoint()[0] == run.checkpoint_path(1)


def test_missing_or_unreadable_runs_say_so_in_one_line(tmp_path):
    with pytest.raises(MeshsplatError, match="run not found") as e:
        RunFolder(tmp_path / "missing").latest_checkpoint()
    _one_line(e)
    (tmp_path / "empty").mkdir()
    with pytest.raises(MeshsplatError, match=r"no checkpoint in .*is this a training run folder") as e:
        load_run(tmp_path / "empty")
    _one_line(e)
    bad = RunFolder(tmp_path / "bad")
    bad.checkpoint_dir.mkdir(parents=True)
    bad.checkpoint_path(3).write_bytes(b"PK\x03\x04 truncated")
    bad.checkpoint_path(4).write_bytes(b"")
    with pytest.raises(MeshsplatError, match=r"newest checkpoint .*ckpt_00000004.pt is unreadable") as e:
        load_avatar(bad.root)
    _one_line(e)
    with pytest.raises(MeshsplatError, match=r"all 2 checkpoint\(s\) .* unreadable; newest: .*ckpt_00000004.pt") as e:
        load_avatar(bad.root, allow_older=True)
    _one_line(e)
    save_checkpoint(bad.checkpoint_path(5), {"iteration": 5})
    with pytest.raises(MeshsplatError, match="checkpoint holds no avatar") as e:
        load_run(bad.root)
    _one_line(e)


def test_config(tmp_path):
    run = RunFolder(tmp_path)
    assert run.load_config() is None
    run.config_path.write_text('{"data": "x", "iterations": 3}')
    assert run.load_config() == {"data": "x", "iterations": 3}
    run.config_path.write_text("{nope")
    with pytest.raises(MeshsplatError, match=r"config.json: not valid JSON") as e:
        run.load_config()
    _one_line(e)
    run.config_path.write_text("[1, 2]")
    with pytest.raises(MeshsplatError, match=r"config.json: expected a JSON object, got list"):
        run.load_config()


def test_load_run_and_avatar(tmp_path):
    av = make_avatar(n=40)
    data = tmp_path / "data"
    data.mkdir()
    root = make_run(av, tmp_path / "run", data, iteration=7)
    r = load_run(root)
    assert isinstance(r, LoadedRun) and r.run_dir == root and r.folder.root == root
    assert r.checkpoint == RunFolder(root).checkpoint_path(7) and r.iteration == 7
    assert r.config["data"] == str(data) and r.dataset_path() == data
    assert r.dataset_path(tmp_path / "other") == tmp_path / "other"
    assert torch.equal(r.avatar.params["uv"], av.params["uv"])
    assert torch.equal(load_avatar(r.checkpoint).params["face"], av.params["face"])  # a checkpoint file works too
    assert load_run(r.checkpoint).run_dir == root
    assert r.source_map() is None


def test_config_falls_back_to_the_checkpoint_and_dataset_errors(tmp_path):
    av = make_avatar(n=40)
    run = RunFolder(tmp_path / "run")
    save_checkpoint(
        run.checkpoint_path(2), {"iteration": 2, "avatar": av.state_dict(), "config": {"data": "moved/away"}}
    )
    r = load_run(run.root)
    assert r.config == {"data": "moved/away"}  # no config.json: the checkpoint's copy
    with pytest.raises(MeshsplatError, match=r"dataset moved/away .* is not there.*--dataset PATH") as e:
        r.dataset_path()
    _one_line(e)
    run.config_path.write_text(json.dumps({"out": str(run.root)}))
    with pytest.raises(MeshsplatError, match="names no dataset; pass --dataset PATH"):
        load_run(run.root).dataset_path()
    save_checkpoint(run.checkpoint_path(3), {"iteration": -1, "avatar": av.state_dict()})
    with pytest.raises(MeshsplatError, match="'iteration' must be a non-negative integer"):
        load_run(run.root)
