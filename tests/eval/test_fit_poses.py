"""Test-time pose fitting (``meshsplat eval --fit-poses``): held-out frames' poses fitted to their own
images with the avatar frozen move towards the true pose and score better; training rows are left alone;
captures without body-model parameters are refused in one line."""

from __future__ import annotations

import json

import pytest
import torch

from meshsplat.cli.main import main
from meshsplat.data import open_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.eval import evaluate_run
from meshsplat.eval.fit_poses import fit_test_poses, rows_to_fit
from meshsplat.render.background import composite
from meshsplat.run_folder import load_run
from meshsplat.synth import synthesize
from meshsplat.train import Trainer, apply_overrides
from meshsplat.train.recipes import recipe_config

SHOTS = dict(frames=6, resolution=48, test_frames=2, test_views=1, test_view_frames=2, threads=None)


@pytest.fixture(scope="module")
def captures(tmp_path_factory, standin_model_dir):
    """The stand-in SMPL body twice, the same shots: tracked poses off by 0.1 rad, and exact."""
    root = tmp_path_factory.mktemp("fit")
    synthesize("smpl", root / "noisy", model_dir=standin_model_dir, pose_noise=0.1, **SHOTS)
    synthesize("smpl", root / "exact", model_dir=standin_model_dir, **SHOTS)
    return root / "noisy", root / "exact"


@pytest.fixture(scope="module")
def run(tmp_path_factory, captures, standin_model_dir):
    out = tmp_path_factory.mktemp("runs") / "run"
    cfg = recipe_config("quality", data=str(captures[1]), out=str(out), iterations=60, device="cpu", backend="torch")
    sets = ["progress=false", "model.n_init=1500", "loss.lambda_lpips=0", "checkpoint_every=60"]
    sets += ["preview_every=1000", "pose_refine.enabled=false", f"model_dir={standin_model_dir}"]
    Trainer(apply_overrides(cfg, sets)).train()
    return out


def _image_error(avatar, ds, i, verts) -> float:
    fr = ds[i]
    gt = composite(fr.image, fr.mask, torch.ones(3))
    with torch.no_grad():
        return float((avatar.render(verts, fr.camera, torch.ones(3), backend="torch").image - gt).abs().mean())


def test_fitting_lowers_the_held_out_frames_image_error_and_leaves_the_avatar(run, captures, standin_model_dir):
    """The fit lowers what it optimises, the image error of each held-out frame's own images; only rows
    that no training frame shows are fitted; the avatar's parameters end as they started."""
    noisy = open_dataset(captures[0])
    avatar = load_run(run).avatar
    before = {k: v.detach().clone() for k, v in avatar.params.items()}
    grads = {k: v.requires_grad for k, v in avatar.params.items()}
    ids = noisy.split("test_frames") + noisy.split("test_views")
    groups = rows_to_fit(noisy, ids)
    assert sorted(i for f in groups.values() for i in f) == sorted(noisy.split("test_frames"))  # views: trained rows
    fitted = fit_test_poses(avatar, noisy, ids, steps=40, lr=3e-3, model_dir=str(standin_model_dir), backend="torch")
    assert set(fitted) == set(groups)
    for row, frames in groups.items():
        i = frames[0]
        tracked = _image_error(avatar, noisy, i, noisy.vertices(i))
        assert _image_error(avatar, noisy, i, torch.as_tensor(fitted[row])) < 0.8 * tracked, row
    for k, v in avatar.params.items():
        assert torch.equal(v.detach(), before[k]) and v.grad is None and v.requires_grad == grads[k], k


def test_eval_with_fitted_poses_scores_better_and_says_so(run, captures, standin_model_dir, tmp_path, capsys):
    common = dict(dataset=captures[0], lpips_net=None, report=False, device="cpu", backend="torch")
    tracked = evaluate_run(run, out_dir=tmp_path / "t", **common)
    fitted = evaluate_run(run, out_dir=tmp_path / "f", fit_poses=40, fit_poses_lr=3e-3, **common)
    assert tracked["fitted_pose_frames"] == 0 and tracked["fit_poses"] is None
    assert fitted["fitted_pose_frames"] == 2 and fitted["fit_poses"] == {"steps": 40, "lr": 3e-3}
    assert all(f["fitted_pose"] for f in fitted["splits"]["test_frames"]["frames"])
    assert not any(f["fitted_pose"] for f in fitted["splits"]["test_views"]["frames"])
    gain = fitted["splits"]["test_frames"]["psnr_mask"] - tracked["splits"]["test_frames"]["psnr_mask"]
    assert gain > 1.0, gain
    assert fitted["splits"]["test_views"]["psnr"] == pytest.approx(tracked["splits"]["test_views"]["psnr"])
    argv = ["eval", str(run), "--dataset", str(captures[0]), "--out", str(tmp_path / "c"), "--no-lpips"]
    assert main([*argv, "--no-report", "--fit-poses", "3", "--backend", "torch"]) == 0
    assert "2 held-out frames in poses fitted to their own images (3 steps)" in capsys.readouterr().out
    assert json.loads((tmp_path / "c" / "metrics.json").read_text())["fit_poses"]["steps"] == 3


def test_fitting_is_refused_in_one_line_without_pose_parameters(run, captures, tmp_path, capsys):
    import shutil

    plain = tmp_path / "plain"
    shutil.copytree(captures[0], plain)
    doc = json.loads((plain / "manifest.json").read_text())
    doc.pop("driver", None)
    (plain / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(MeshsplatError) as err:
        evaluate_run(run, dataset=plain, out_dir=tmp_path / "e", lpips_net=None, report=False, fit_poses=5)
    assert "\n" not in str(err.value) and "no body/head model parameters" in str(err.value)
    for bad in (["--fit-poses", "-1"], ["--fit-poses", "5", "--fit-poses-lr", "0"]):
        assert main(["eval", str(run), "--out", str(tmp_path / "x"), *bad]) == 2
        assert "--fit-poses" in capsys.readouterr().err
