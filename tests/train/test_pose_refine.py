"""Pose refinement: the trained offsets, the refined poses a run hands to eval, and their refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.eval import evaluate_run
from meshsplat.io import load_checkpoint
from meshsplat.run_folder import TRACKED_POSES_FLAG, RunFolder, load_run
from meshsplat.synth import synthesize
from meshsplat.train import Trainer, apply_overrides
from meshsplat.train.recipes import recipe_config


@pytest.fixture(scope="module")
def noisy_smpl(tmp_path_factory, standin_model_dir):
    """The stand-in SMPL body, 6 training frames at 48 px whose tracked poses are off by 0.05 rad, two
    held-out frames and held-out views of 2 training frames."""
    root = tmp_path_factory.mktemp("smpl") / "noisy"
    synthesize(
        "smpl",
        root,
        frames=6,
        resolution=48,
        test_frames=2,
        test_views=1,
        test_view_frames=2,
        model_dir=standin_model_dir,
        pose_noise=0.05,
        threads=None,
    )
    return root


@pytest.fixture(scope="module")
def refined_run(tmp_path_factory, noisy_smpl, standin_model_dir):
    out = tmp_path_factory.mktemp("runs") / "refined"
    cfg = recipe_config("quality", data=str(noisy_smpl), out=str(out), iterations=12, device="cpu", backend="torch")
    cfg = apply_overrides(
        cfg,
        [
            "progress=false",
            "model.n_init=300",
            "loss.lambda_lpips=0",
            "checkpoint_every=12",
            "preview_every=100",
            "pose_refine.enabled=true",
            "pose_refine.required=true",
            "pose_refine.lr=1e-2",
            f"model_dir={standin_model_dir}",
        ],
    )
    trainer = Trainer(cfg)
    trainer.train()
    return out, trainer


def _rows(ds, split):
    return {int(ds.frame_info(i)["mesh"]) for i in ds.split(split)}


def test_training_moves_the_poses_and_saves_them(refined_run, noisy_smpl):
    out, trainer = refined_run
    assert all(v > 0 for v in trainer.component("pose_refine").refiner.offset_norms().values())
    with np.load(out / "refined_params.npz", allow_pickle=False) as z:
        rows = set(z["mesh_rows"].tolist())
    assert rows == _rows(trainer.dataset, "train")


def test_a_run_hands_eval_its_refined_training_poses(refined_run):
    """Held-out views of training frames come in the refined pose (the one training rendered); held-out
    frames keep the tracker's; ``refined_poses=False`` gives the tracker's everywhere."""
    out, trainer = refined_run
    run = load_run(out)
    tracked, refined = run.open_dataset(refined_poses=False), run.open_dataset()
    train_rows = _rows(tracked, "train")
    assert refined.replaced_meshes == train_rows and not tracked.replaced_meshes
    assert _rows(tracked, "test_views") <= train_rows and not _rows(tracked, "test_frames") & train_rows
    for i in tracked.split("test_views"):
        row = int(tracked.frame_info(i)["mesh"])
        with torch.no_grad():
            want = trainer.component("pose_refine").refiner.vertices(row).float()
        torch.testing.assert_close(refined.vertices(i), want, atol=1e-5, rtol=0)
        assert float((refined.vertices(i) - tracked.vertices(i)).abs().max()) > 1e-4
    for i in tracked.split("test_frames"):
        assert torch.equal(refined.vertices(i), tracked.vertices(i))


def test_eval_says_which_frames_used_refined_poses(refined_run, tmp_path):
    out, _ = refined_run
    m = evaluate_run(out, out_dir=tmp_path / "a", lpips_net=None, report=False, device="cpu")
    views = m["splits"]["test_views"]["frames"]
    assert m["refined_pose_frames"] == len(views) == 2 and all(f["refined_pose"] for f in views)
    assert not any(f["refined_pose"] for f in m["splits"]["test_frames"]["frames"])
    t = evaluate_run(out, out_dir=tmp_path / "b", lpips_net=None, report=False, device="cpu", refined_poses=False)
    assert t["refined_pose_frames"] == 0
    assert t["splits"]["test_frames"]["psnr"] == pytest.approx(m["splits"]["test_frames"]["psnr"])
    assert json.loads((tmp_path / "a" / "metrics.json").read_text())["refined_pose_frames"] == 2


def test_another_capture_gets_no_refined_poses(refined_run, noisy_smpl, tmp_path):
    import shutil

    out, _ = refined_run
    copy = tmp_path / "copy"
    shutil.copytree(noisy_smpl, copy)
    assert not load_run(out).open_dataset(copy).replaced_meshes


@pytest.mark.parametrize(
    "damage",
    [
        lambda p: p.write_bytes(b"not an npz"),
        lambda p: np.savez(p, mesh_rows=np.array([0, 0])),
        lambda p: np.savez(p, mesh_rows=np.array([10_000])),
        lambda p: np.savez(p, mesh_rows=np.array([0]), body_pose=np.zeros((1, 5), np.float32)),
        lambda p: np.savez(p, mesh_rows=np.array([0]), body_pose=np.full((1, 69), np.nan, np.float32)),
        lambda p: np.savez(p, mesh_rows=np.array([0]), shoe_size=np.zeros((1, 1), np.float32)),
    ],
    ids=["not_npz", "repeated_rows", "row_out_of_range", "wrong_width", "nan", "unknown_key"],
)
def test_broken_refined_poses_are_refused_in_one_line(refined_run, tmp_path, damage):
    import shutil

    out, _ = refined_run
    run_dir = tmp_path / "run"
    shutil.copytree(out, run_dir)
    damage(run_dir / "refined_params.npz")
    with pytest.raises(MeshsplatError) as err:
        load_run(run_dir).open_dataset()
    msg = str(err.value)
    assert "\n" not in msg and "refined_params.npz" in msg and TRACKED_POSES_FLAG in msg
    assert not load_run(run_dir).open_dataset(refined_poses=False).replaced_meshes


def test_refined_poses_without_the_model_files_name_the_way_out(refined_run, tmp_path, monkeypatch):
    out, _ = refined_run
    monkeypatch.delenv("MESHSPLAT_MODEL_DIR", raising=False)
    run = load_run(out)
    with pytest.raises(MeshsplatError) as err:
        run.open_dataset(model_dir=tmp_path / "no_models")
    msg = str(err.value)
    assert "\n" not in msg and "refined poses need the body model" in msg and TRACKED_POSES_FLAG in msg
    assert not run.open_dataset(model_dir=tmp_path / "no_models", refined_poses=False).replaced_meshes


def test_with_meshes_checks_rows_and_shapes(noisy_smpl):
    from meshsplat.data import open_dataset

    ds = open_dataset(noisy_smpl)
    v = np.zeros((ds.num_vertices, 3), np.float32)
    other = ds.with_meshes({0: v})
    i = next(j for j in range(len(ds)) if int(ds.frame_info(j)["mesh"]) == 0)
    assert float(other.vertices(i).abs().max()) == 0 and float(ds.vertices(i).abs().max()) > 0
    for bad in ({0: v[:5]}, {-1: v}, {10_000: v}):
        with pytest.raises(MeshsplatError, match="with_meshes"):
            ds.with_meshes(bad)


def test_eval_command_names_refined_frames_and_takes_tracked_poses(refined_run, tmp_path, capsys):
    from meshsplat.cli.main import main

    out, _ = refined_run
    assert main(["eval", str(out), "--out", str(tmp_path / "a"), "--no-lpips", "--no-report"]) == 0
    assert "2 frames in the poses training refined" in capsys.readouterr().out
    assert main(["eval", str(out), "--out", str(tmp_path / "b"), "--no-lpips", "--no-report", TRACKED_POSES_FLAG]) == 0
    assert "poses training refined" not in capsys.readouterr().out
    assert json.loads((tmp_path / "b" / "metrics.json").read_text())["refined_pose_frames"] == 0


def _short(data, out, *extra):
    cfg = recipe_config("quality", data=str(data), out=str(out), iterations=2, device="cpu", backend="torch")
    return apply_overrides(
        cfg,
        [
            "progress=false",
            "model.n_init=100",
            "loss.lambda_lpips=0",
            "checkpoint_every=2",
            "pose_refine.polish_steps=0",  # the recipe's polish where a test asks for it
            *extra,
        ],
    )


def test_the_default_refines_a_body_model_capture_when_it_finds_the_model_files(
    noisy_smpl, standin_model_dir, tmp_path, monkeypatch
):
    monkeypatch.delenv("MESHSPLAT_MODEL_DIR", raising=False)
    on = Trainer(_short(noisy_smpl, tmp_path / "on", f"model_dir={standin_model_dir}"))
    assert on.component("pose_refine") is not None and on.notes[0].startswith("pose refinement on: ")
    assert "SMPL" in on.notes[0] and "of 6 training meshes" in on.notes[0]
    off = Trainer(_short(noisy_smpl, tmp_path / "off", f"model_dir={tmp_path / 'nothing'}"))
    assert off.component("pose_refine") is None and off.notes[0].startswith("pose refinement off, ")
    assert "--model-dir" in off.notes[0] and "\n" not in off.notes[0]
    # asked for explicitly, missing model files are an error, as before
    with pytest.raises(MeshsplatError):
        Trainer(
            _short(
                noisy_smpl,
                tmp_path / "on2",
                "pose_refine.enabled=true",
                "pose_refine.required=true",
                f"model_dir={tmp_path / 'none'}",
            )
        )
    assert Trainer(_short(noisy_smpl, tmp_path / "no", "pose_refine.enabled=false")).component("pose_refine") is None


def test_a_mesh_capture_trains_without_refinement_and_without_a_note(noisy_smpl, tmp_path):
    import shutil

    plain = tmp_path / "plain"
    shutil.copytree(noisy_smpl, plain)
    doc = json.loads((plain / "manifest.json").read_text())
    doc.pop("driver", None)
    (plain / "manifest.json").write_text(json.dumps(doc))
    t = Trainer(_short(plain, tmp_path / "run"))
    assert t.component("pose_refine") is None and t.notes == []
    with pytest.raises(MeshsplatError, match="no body/head model parameters"):
        Trainer(_short(plain, tmp_path / "run2", "pose_refine.enabled=true", "pose_refine.required=true"))


def test_resuming_a_refined_run_without_the_model_files_is_refused(noisy_smpl, standin_model_dir, tmp_path):
    out = tmp_path / "run"
    Trainer(_short(noisy_smpl, out, f"model_dir={standin_model_dir}")).train()
    cfg = _short(noisy_smpl, out, f"model_dir={tmp_path / 'gone'}")
    with pytest.raises(MeshsplatError) as err:
        Trainer(cfg, resume=True)
    assert "trained with pose_refine" in str(err.value) and "\n" not in str(err.value)


def test_train_command_says_what_it_decided(noisy_smpl, standin_model_dir, tmp_path, capsys):
    from meshsplat.cli.main import main

    args = ["train", str(noisy_smpl), "--iters", "2", "--set", "model.n_init=100", "loss.lambda_lpips=0"]
    assert main([*args, "--out", str(tmp_path / "a"), "--model-dir", str(standin_model_dir)]) == 0
    assert "pose refinement on: " in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "b"), "--model-dir", str(standin_model_dir), "--no-refine-pose"]) == 0
    assert "pose refinement" not in capsys.readouterr().out
    assert not json.loads((tmp_path / "b" / "config.json").read_text())["pose_refine"]["enabled"]


@pytest.mark.parametrize(
    "polish,mid", [(0, 0), (3, 0), (3, 0.5)], ids=["refined", "polished_at_the_end", "polished_at_the_checkpoint"]
)
def test_resume_with_refinement_is_bit_exact(noisy_smpl, standin_model_dir, tmp_path, polish, mid):
    """A run "killed" after its checkpoint at 3 of 6 iterations resumes to the same avatar, pose offsets and
    refined poses as the run that went through (the offsets and their Adam state travel in the checkpoint);
    with ``pose_refine.polish_steps`` the resumed run fits its poses at the end as the other did, and a polish at
    the checkpoint's iteration (``polish_mid``) is in that checkpoint, not done again."""
    import shutil

    def cfg(out):
        sets = [f"model_dir={standin_model_dir}", "checkpoint_every=3", "pose_refine.lr=1e-2"]
        c = _short(noisy_smpl, out, *sets, f"pose_refine.polish_steps={polish}", f"pose_refine.polish_mid={mid}")
        c.iterations = 6
        return c

    full = Trainer(cfg(tmp_path / "full"))
    full.train()
    (tmp_path / "resumed" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000003.pt", tmp_path / "resumed" / "checkpoints")
    resumed = Trainer(cfg(tmp_path / "resumed"), resume=True)
    assert resumed.iteration == 3 and not resumed.component("pose_refine").refiner.polished
    resumed.train()
    assert (
        resumed.component("pose_refine").refiner.polished
        == full.component("pose_refine").refiner.polished
        == bool(polish)
    )
    for k in full.params:
        assert torch.equal(full.params[k].detach(), resumed.params[k].detach()), k
    for k, v in full.component("pose_refine").refiner.offsets.items():
        assert torch.equal(v.detach(), resumed.component("pose_refine").refiner.offsets[k].detach()), k
    assert float(sum(v.detach().abs().sum() for v in full.component("pose_refine").refiner.offsets.values())) > 0
    with (
        np.load(tmp_path / "full" / "refined_params.npz") as a,
        np.load(tmp_path / "resumed" / "refined_params.npz") as b,
    ):
        assert all(np.array_equal(a[k], b[k]) for k in a.files)


def test_with_meshes_holds_only_the_replaced_rows_and_drives_with_them(noisy_smpl):
    from meshsplat.data import open_dataset

    ds = open_dataset(noisy_smpl)
    v = np.full((ds.num_vertices, 3), 0.25, np.float32)
    other = ds.with_meshes({1: v})
    assert other._verts is ds._verts  # the stored meshes are shared, not copied
    again = other.with_meshes({2: v})
    assert again.replaced_meshes == {1, 2} and other.replaced_meshes == {1}
    drv = again.driver()
    assert torch.equal(drv.vertices(1), torch.from_numpy(v)) and torch.equal(drv.vertices(0), ds.driver().vertices(0))


def _training_error(trainer) -> float:
    """Sum over training frames of the L1 error in their refined poses (what the polish minimises)."""
    white = torch.ones(3)
    with torch.no_grad():
        return sum(
            float((o.image - g).abs().mean()) for o, g in (trainer.render_frame(i, white) for i in trainer.train_ids)
        )


def test_polishing_fits_the_training_poses_once_at_the_end(noisy_smpl, standin_model_dir, tmp_path):
    """``pose_refine.polish_steps``: after the last iteration the refined poses alone are fitted to the
    training images (the avatar unchanged), saved with the run, and not fitted again on a resume."""
    sets = [f"model_dir={standin_model_dir}", "pose_refine.lr=1e-2", "checkpoint_every=100", "pose_refine.polish_mid=0"]
    plain = Trainer(_short(noisy_smpl, tmp_path / "plain", *sets))
    plain.train()
    polished = Trainer(_short(noisy_smpl, tmp_path / "polished", *sets, "pose_refine.polish_steps=8"))
    polished.train()
    for k in plain.params:  # the same avatar: the polish changes the poses only
        assert torch.equal(plain.params[k].detach(), polished.params[k].detach()), k
    assert polished.component("pose_refine").refiner.polished and not plain.component("pose_refine").refiner.polished
    moved = sum(
        float((a - plain.component("pose_refine").refiner.offsets[k]).detach().abs().sum())
        for k, a in polished.component("pose_refine").refiner.offsets.items()
    )
    assert moved > 0
    assert _training_error(polished) < _training_error(plain)
    state = load_checkpoint(RunFolder(tmp_path / "polished").checkpoints()[-1][1])
    assert state["components"]["pose_refine"]["polished"] and state["iteration"] == 2
    with np.load(tmp_path / "polished" / "refined_params.npz") as z:
        np.testing.assert_allclose(
            z["body_pose"], polished.component("pose_refine").refiner.refined_params()["body_pose"]
        )
    again = Trainer(_short(noisy_smpl, tmp_path / "polished", *sets, "pose_refine.polish_steps=8"), resume=True)
    assert not again.finishing
    again.train()
    for k, v in again.component("pose_refine").refiner.offsets.items():
        assert torch.equal(v.detach(), polished.component("pose_refine").refiner.offsets[k].detach()), k


def test_polish_settings_are_checked():
    for bad in ("pose_refine.polish_steps=-1", "pose_refine.polish_lr=0"):
        with pytest.raises(MeshsplatError, match="polish"):
            apply_overrides(recipe_config("quality"), [bad]).validate()


# ---- the lazy per-frame Adam (issue 44) -----------------------------------------------------------------


@pytest.fixture(scope="module")
def noisy_flame(tmp_path_factory, standin_model_dir):
    """The stand-in FLAME head, 4 training frames at 32 px (jaw pose and expressions per frame)."""
    root = tmp_path_factory.mktemp("flame") / "noisy"
    synthesize(
        "flame", root, frames=4, resolution=32, test_views=0, model_dir=standin_model_dir, pose_noise=0.05, threads=None
    )
    return root


def _refiner(data, model_dir, names="global_orient,body_pose,transl,neck_pose,jaw_pose,expression"):
    from meshsplat.data import open_dataset
    from meshsplat.train.pose_refine import PoseRefiner

    ds = open_dataset(data)
    return PoseRefiner(ds, list(ds.split("train")), names, 1e-2, str(model_dir), torch.device("cpu"))


def _target_loss(verts: torch.Tensor) -> torch.Tensor:
    """A smooth loss with its minimum away from the tracked pose (every offset gets a gradient)."""
    return ((verts - torch.tensor([0.01, -0.02, 0.03])) ** 2).sum() + verts[:, 1].sin().sum()


@pytest.mark.parametrize("capture", ["noisy_smpl", "noisy_flame"])
def test_a_step_moves_only_the_batch_rows_and_equals_adam_on_that_frame_alone(capture, request, standin_model_dir):
    """Rows drawn in interleaved batches (of one and two frames) follow exactly the trajectory of a plain
    ``torch.optim.Adam`` over that row's offsets alone; a row outside the batch, and its Adam state, do not
    change at all. SMPL poses and FLAME jaw/expressions alike."""
    ref = _refiner(request.getfixturevalue(capture), standin_model_dir)
    rows = sorted(ref.row_of)
    a, b, idle = rows[0], rows[1], rows[-1]
    assert len(rows) >= 3
    ja = ref.row_of[a]
    alone = {k: torch.nn.Parameter(torch.zeros_like(v[ja : ja + 1])) for k, v in ref.offsets.items()}
    adam = torch.optim.Adam(list(alone.values()), lr=ref.lr, eps=1e-15, foreach=False)
    schedule = [[a], [b], [b], [a, b], [b], [a], [a, a], [b, a]]
    for batch in schedule:
        before = {k: v.detach().clone() for k, v in ref.offsets.items()}
        state = {k: v.clone() for k, v in ref.exp_avg.items()}
        sum(_target_loss(ref.vertices(r)) for r in batch).backward()
        ref.step(batch)
        j_idle = ref.row_of[idle]
        for k, v in ref.offsets.items():
            assert torch.equal(v.detach()[j_idle], before[k][j_idle]), k
            assert torch.equal(ref.exp_avg[k][j_idle], state[k][j_idle]), k
            if b not in batch:
                assert torch.equal(v.detach()[ref.row_of[b]], before[k][ref.row_of[b]]), k
        if a in batch:
            params = dict(ref.shared)
            params.update({k: v[ja : ja + 1] for k, v in ref.rows.items()})
            for k, off in alone.items():
                params[k] = params[k] + off
            (batch.count(a) * _target_loss(ref.model.forward(params).vertices[0])).backward()
            adam.step()
            adam.zero_grad()
        for k, off in alone.items():
            assert torch.equal(ref.offsets[k].detach()[ja], off.detach()[0]), k
    assert ref.steps[ja] == sum(a in s for s in schedule) and ref.steps[ref.row_of[idle]] == 0
    assert all(float(v.detach()[ja].abs().max()) > 0 for v in ref.offsets.values())
    assert all(float(v.detach()[ref.row_of[idle]].abs().max()) == 0 for v in ref.offsets.values())


def test_the_refiner_state_round_trips_and_continues_the_same(noisy_smpl, standin_model_dir):
    one, two = _refiner(noisy_smpl, standin_model_dir), _refiner(noisy_smpl, standin_model_dir)
    r0, r1 = sorted(one.row_of)[:2]
    for batch in ([r0], [r1], [r0]):
        sum(_target_loss(one.vertices(r)) for r in batch).backward()
        one.step(batch)
    two.load_state_dict(one.state_dict())
    for ref in (one, two):
        _target_loss(ref.vertices(r1)).backward()
        ref.step([r1])
    assert one.steps == two.steps
    for k in one.offsets:
        assert torch.equal(one.offsets[k].detach(), two.offsets[k].detach()), k
        assert torch.equal(one.exp_avg_sq[k], two.exp_avg_sq[k]), k


def test_an_older_refiner_checkpoint_is_refused_in_one_line(noisy_smpl, standin_model_dir):
    ref = _refiner(noisy_smpl, standin_model_dir)
    st = ref.state_dict()
    old = {"offsets": st["offsets"], "optimizer": {"state": {}, "param_groups": []}, "polished": False}
    with pytest.raises(MeshsplatError, match="older meshsplat") as err:
        ref.load_state_dict(old)
    assert "\n" not in str(err.value)


def test_training_moves_only_the_frames_it_drew(noisy_smpl, standin_model_dir, tmp_path):
    """Batch of one, 3 iterations over 6 training frames: the frames never drawn keep the tracker's pose
    exactly; every step stepped the row it drew."""
    t = Trainer(_short(noisy_smpl, tmp_path / "run", f"model_dir={standin_model_dir}", "pose_refine.lr=1e-2"))
    t.cfg.iterations = 3
    t.train()
    steps = t.component("pose_refine").refiner.steps
    assert sum(steps) == 3 and 0 in steps
    for k, v in t.component("pose_refine").refiner.offsets.items():
        for j, n in enumerate(steps):
            assert (float(v.detach()[j].abs().max()) == 0) == (n == 0), (k, j)


def test_poses_stay_tracked_until_the_start_fraction_then_move(noisy_smpl, standin_model_dir, tmp_path):
    """``pose_refine.start=0.5`` of 6 iterations: iterations 1-3 train on the tracker's poses (no row steps,
    no gradient reaches the offsets), 4-6 step the rows they draw."""
    cfg = _short(
        noisy_smpl, tmp_path / "run", f"model_dir={standin_model_dir}", "pose_refine.lr=1e-2", "pose_refine.start=0.5"
    )
    cfg.iterations = 6
    t = Trainer(cfg)
    comp = t.component("pose_refine")
    seen = []
    step = comp.after_step

    def spy(it, rows):
        seen.append((it, comp.started, sum(comp.refiner.steps)))
        step(it, rows)

    comp.after_step = spy
    t.train()
    assert [s for _, s, _ in seen] == [False, False, False, True, True, True]
    assert [n for _, _, n in seen[:4]] == [0, 0, 0, 0] and sum(comp.refiner.steps) == 3
    assert any(float(v.detach().abs().max()) > 0 for v in comp.refiner.offsets.values())


def test_keep_depth_moves_no_translation_along_the_training_camera(noisy_smpl, standin_model_dir, tmp_path):
    """``pose_refine.keep_depth``: every training frame of the monocular capture has one camera, so each row's
    translation offset ends perpendicular to that camera's line of sight to the subject; without it the
    offsets have a component along it."""
    offsets = {}
    for keep in (True, False):
        cfg = _short(
            noisy_smpl,
            tmp_path / f"run{keep}",
            f"model_dir={standin_model_dir}",
            "pose_refine.lr=1e-2",
            f"pose_refine.keep_depth={str(keep).lower()}",
        )
        cfg.iterations = 6
        t = Trainer(cfg)
        comp = t.component("pose_refine")
        t.train()
        offsets[keep] = comp.refiner.offsets["transl"].detach()
        if keep:
            dirs = comp.depth_dirs
            assert len(dirs) == len(comp.refiner.row_of)
            along = [float(offsets[keep][comp.refiner.row_of[r]] @ d) for r, d in dirs.items()]
            moved = [float(offsets[keep][comp.refiner.row_of[r]].norm()) for r in dirs]
            assert max(moved) > 1e-4 and max(abs(a) for a in along) < 1e-5 * max(moved)
    # the same draws without the rule move along the line of sight too
    assert float((offsets[False] - offsets[True]).abs().max()) > 1e-5


def test_the_start_fraction_is_checked():
    for bad in ("1", "-0.1"):
        with pytest.raises(MeshsplatError, match=r"pose_refine.start must be in \[0, 1\)"):
            apply_overrides(recipe_config("quality"), [f"pose_refine.start={bad}"]).validate()


@pytest.mark.slow
def test_two_processes_refine_as_one_process_with_the_same_batch(noisy_smpl, standin_model_dir, tmp_path, monkeypatch):
    """Data-parallel (``--nproc 2``, batch 2): every rank steps the rows of the whole batch with the
    all-reduced gradients, so the offsets and step counts equal one process's with batch 2."""
    import os
    from pathlib import Path

    from meshsplat.train.launch import launch

    src = str(Path(__file__).resolve().parents[2] / "src")
    monkeypatch.setenv("PYTHONPATH", src + os.pathsep + os.environ.get("PYTHONPATH", ""))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")

    def cfg(out):
        c = _short(noisy_smpl, out, f"model_dir={standin_model_dir}", "pose_refine.lr=1e-2", "batch_size=2")
        c.iterations, c.checkpoint_every = 3, 3
        return c

    one = Trainer(cfg(tmp_path / "one"))
    one.train()
    launch(cfg(tmp_path / "two"), nproc=2)
    a = load_checkpoint(RunFolder(tmp_path / "one").checkpoints()[-1][1])["components"]["pose_refine"]
    b = load_checkpoint(RunFolder(tmp_path / "two").checkpoints()[-1][1])["components"]["pose_refine"]
    assert torch.equal(a["steps"], b["steps"]) and 0 < int(a["steps"].sum()) <= 6
    for k, v in a["offsets"].items():
        assert float(v.abs().max()) > 0
        torch.testing.assert_close(b["offsets"][k], v, atol=1e-7, rtol=1e-5)


def test_the_prior_pulls_an_offset_its_images_do_not_hold_back_to_the_tracked_pose(noisy_smpl, standin_model_dir):
    """``pose_refine.prior``: with no image gradient, an offset shrinks step by step; rows not drawn stay."""
    from meshsplat.data import open_dataset
    from meshsplat.train.pose_refine import PoseRefiner

    ds = open_dataset(noisy_smpl)
    ref = PoseRefiner(ds, list(ds.split("train")), "body_pose", 1e-2, str(standin_model_dir), torch.device("cpu"), 1.0)
    a, b = sorted(ref.row_of)[:2]
    with torch.no_grad():
        ref.offsets["body_pose"].fill_(0.05)
    sizes = []
    for _ in range(3):
        (0 * ref.vertices(a).sum()).backward()
        ref.step([a])
        sizes.append(float(ref.offsets["body_pose"].detach()[ref.row_of[a]].abs().max()))
    assert 0.05 > sizes[0] > sizes[1] > sizes[2]
    assert bool((ref.offsets["body_pose"].detach()[ref.row_of[b]] == torch.tensor(0.05)).all())
    with pytest.raises(MeshsplatError, match="prior"):
        apply_overrides(recipe_config("quality"), ["pose_refine.prior=-1"]).validate()


def test_evidence_slows_a_number_whose_gradient_flips_and_not_one_that_keeps_its_sign(noisy_smpl, standin_model_dir):
    """``pose_refine.evidence``: each number's Adam step times ``(|m| / sqrt(v))^evidence``. Gradients of one sign
    get Adam's full step (the ratio is 1); gradients whose sign alternates (noise about a right pose) move the
    offset much less than plain Adam does; evidence 0 is plain Adam, bit for bit."""
    from meshsplat.data import open_dataset
    from meshsplat.train.pose_refine import PoseRefiner

    ds = open_dataset(noisy_smpl)
    ids = list(ds.split("train"))

    def walk(evidence: float, signs: list[float]) -> torch.Tensor:
        ref = PoseRefiner(ds, ids, "body_pose", 1e-2, str(standin_model_dir), torch.device("cpu"), evidence=evidence)
        a = sorted(ref.row_of)[0]
        for s in signs:
            ref.offsets["body_pose"].grad = torch.zeros_like(ref.offsets["body_pose"])
            ref.offsets["body_pose"].grad[ref.row_of[a]] = s
            ref.step([a])
        return ref.offsets["body_pose"].detach()[ref.row_of[a]]

    steady, flipping = [1.0] * 8, [1.0, -1.0] * 4
    assert torch.allclose(walk(4.0, steady), walk(0.0, steady))  # one sign: full steps
    first = walk(0.0, flipping[:1]).abs().max()  # Adam's first step is the rate, gated or not (the ratio is 1)
    assert torch.allclose(walk(4.0, flipping[:1]), walk(0.0, flipping[:1])) and float(first) == pytest.approx(1e-2)
    plain = (walk(0.0, flipping).abs().max() - first).abs()  # how far the flipping steps after it carried on
    gated = (walk(4.0, flipping).abs().max() - first).abs()
    assert gated < 0.2 * plain, (gated, plain)
    with pytest.raises(MeshsplatError, match="evidence"):
        apply_overrides(recipe_config("quality"), ["pose_refine.evidence=-1"]).validate()


def test_a_guarded_fit_keeps_a_right_pose_and_moves_a_wrong_one(noisy_smpl, standin_model_dir):
    """``PoseRefiner.fit_guarded`` (the polish): a row whose error any step raises ends exactly where it began (plain
    Adam moves it); a row whose error its steps lower moves most of the way."""
    ref = _refiner(noisy_smpl, standin_model_dir, "global_orient,body_pose")
    right, wrong = sorted(ref.row_of)[:2]
    with torch.no_grad():
        truth = {right: ref.vertices(right).clone()}
        ref.offsets["body_pose"][ref.row_of[wrong], :9] = 0.05  # the images show this pose of the wrong row
        truth[wrong] = ref.vertices(wrong).clone()
        ref.offsets["body_pose"].zero_()

    def row_error(row: int) -> torch.Tensor:
        v = ref.vertices(row)
        if row == right:  # a gradient at the tracked pose, but its minimum closer than any step the rate takes
            return 1e3 * ((v - truth[row]) ** 2).sum() + 1e-4 * v[:, 0].sum()
        return (v - truth[row]).abs().mean() if row in truth else v.sum() * 0

    before = float(row_error(wrong).detach())
    counts = ref.fit_guarded(row_error, steps=30, lr=1e-2, min_gain=1e-3)
    for k, off in ref.offsets.items():
        assert bool((off.detach()[ref.row_of[right]] == 0).all()), k  # undone, bit for bit
    assert float(row_error(wrong).detach()) < 0.3 * before
    assert counts["moved"] == 1 and counts["kept"] > 0 and counts["undone"] >= ref.GIVE_UP
    ref.fit(row_error, steps=1, lr=1e-2)
    assert float(ref.offsets["body_pose"].detach()[ref.row_of[right]].abs().max()) > 0


def test_a_finished_run_resumed_with_a_polish_fits_its_poses_as_a_run_that_had_it_from_the_start(
    noisy_smpl, standin_model_dir, tmp_path
):
    """``pose_refine.polish_*`` may change on a resume (they act after the last iteration): the resumed run ends
    with the poses, bit for bit, of a run polished at its end."""
    sets = [f"model_dir={standin_model_dir}", "pose_refine.lr=1e-2", "checkpoint_every=100", "pose_refine.start=0"]
    sets.append("pose_refine.polish_mid=0")
    polish = ["pose_refine.polish_steps=4", "pose_refine.polish_lr=3e-3"]
    whole = Trainer(_short(noisy_smpl, tmp_path / "whole", *sets, *polish))
    whole.train()
    Trainer(_short(noisy_smpl, tmp_path / "later", *sets)).train()
    later = Trainer(_short(noisy_smpl, tmp_path / "later", *sets, *polish), resume=True)
    assert later.finishing
    later.train()
    a, b = whole.component("pose_refine").refiner, later.component("pose_refine").refiner
    assert b.polished and whole.component("pose_refine").polish_counts["kept"] > 0
    for k, v in a.offsets.items():
        assert torch.equal(v.detach(), b.offsets[k].detach()), k


def test_a_polish_at_mid_run_fits_the_poses_and_the_avatar_trains_on_in_them(noisy_smpl, standin_model_dir, tmp_path):
    """``pose_refine.polish_mid``: at that fraction of the run the poses are polished (the avatar frozen for it),
    then the avatar trains on in the polished poses: the run differs from one without it from then on only."""
    sets = [f"model_dir={standin_model_dir}", "pose_refine.lr=1e-2", "checkpoint_every=100", "pose_refine.start=0"]
    sets += ["pose_refine.polish_steps=4", "pose_refine.polish_lr=3e-3"]
    runs = {}
    for mid in (0, 0.5):
        c = _short(noisy_smpl, tmp_path / f"mid{mid}", *sets, f"pose_refine.polish_mid={mid}")
        c.iterations = 4
        t = Trainer(c)
        t.train(until=2)
        runs[mid] = (t, {k: v.detach().clone() for k, v in t.params.items()}, t.component("pose_refine").polish_counts)
        t.train()
    (a, a_at2, a_counts), (b, b_at2, b_counts) = runs[0], runs[0.5]
    assert a_counts is None and b_counts is not None and b_counts["kept"] > 0  # polished at iteration 2 only
    for k in a_at2:
        assert torch.equal(a_at2[k], b_at2[k]), k  # the avatar frozen during the polish
    assert any(not torch.equal(a.params[k].detach(), b.params[k].detach()) for k in a.params)  # then trained on


def test_a_polish_makes_at_most_the_renders_it_declares(noisy_smpl, standin_model_dir, tmp_path):
    """``extra_renders`` (what ``train --minutes`` plans for the polish) bounds the frame renders a polish makes:
    at the end, and once more with ``polish_mid``; none once the run is polished."""
    sets = [f"model_dir={standin_model_dir}", "pose_refine.lr=1e-2", "checkpoint_every=100"]
    end_only = Trainer(
        _short(noisy_smpl, tmp_path / "a", *sets, "pose_refine.polish_steps=3", "pose_refine.polish_mid=0")
    )
    comp = end_only.component("pose_refine")
    assert comp.extra_renders() == 4 * len(end_only.train_ids)  # 3 steps and the last measure, every frame
    calls = []
    real = end_only.training_error
    end_only.training_error = lambda idx: calls.append(idx) or real(idx)  # type: ignore[method-assign]
    end_only.train()
    assert 0 < len(calls) <= 4 * len(end_only.train_ids)
    assert comp.extra_renders() == 0  # polished: nothing left
    both = Trainer(
        _short(noisy_smpl, tmp_path / "b", *sets, "pose_refine.polish_steps=3", "pose_refine.polish_mid=0.5")
    )
    assert both.component("pose_refine").extra_renders() == 2 * 4 * len(both.train_ids)
    assert Trainer(_short(noisy_smpl, tmp_path / "c", *sets)).component("pose_refine").extra_renders() == 0
