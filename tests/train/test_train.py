"""Trainer end to end on a tiny dataset: run layout, learning, bit-exact resume, CLI."""

from __future__ import annotations

import csv
import json
import math
import shutil

import pytest
import torch

from _train_kit import make_tiny_dataset, small_config
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.metrics.lpips_net import get_lpips
from meshsplat.run_folder import load_avatar
from meshsplat.train import LOG_COLUMNS, TrainConfig, Trainer
from meshsplat.train.losses import avatar_loss, subject_crop


def _psnr_on_train(avatar: Avatar, ds) -> float:
    from meshsplat.metrics import psnr

    vals = []
    for i in ds.split("train"):
        fr = ds[i]
        with torch.no_grad():
            out = avatar.render(fr.vertices, fr.camera, background=torch.zeros(3), backend="torch")
        gt = fr.image * fr.mask
        vals.append(float(psnr(out.image.clamp(0, 1), gt)))
    return sum(vals) / len(vals)


@pytest.mark.parametrize("extra", [(), ("optim.lr_color_final=1e-3",)], ids=["constant_colour_lr", "colour_lr_decay"])
def test_kill_and_resume_is_bit_exact(tiny_dataset, tmp_path, extra):
    full = Trainer(small_config(tiny_dataset, tmp_path / "full", 20, extra))
    n0 = full.num_gaussians
    full.train()
    assert full.num_gaussians != n0  # densification really ran
    assert full.num_gaussians <= 500  # within the budget
    # "killed" after the checkpoint at 10: a run dir that holds only that checkpoint
    (tmp_path / "resumed" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000010.pt", tmp_path / "resumed" / "checkpoints")
    res = Trainer(small_config(tiny_dataset, tmp_path / "resumed", 20, extra), resume=True)
    assert res.iteration == 10 and res.resumed_from is not None
    res.train()
    assert res.iteration == 20
    colour_lr = full.optimizers["sh0"].param_groups[0]["lr"]
    assert colour_lr == pytest.approx(1e-3 if extra else 1e-2) == res.optimizers["sh0"].param_groups[0]["lr"]
    assert set(full.params) == set(res.params)
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k
    for k, opt in full.optimizers.items():
        a, b = opt.state[full.params[k]], res.optimizers[k].state[res.params[k]]
        assert torch.equal(a["exp_avg"], b["exp_avg"]) and torch.equal(a["exp_avg_sq"], b["exp_avg_sq"]), k
    assert [r["loss"] for r in full.history[10:]] == [r["loss"] for r in res.history]


def test_resume_keeps_this_machines_fused_adam_choice(tiny_dataset, tmp_path):
    """A checkpoint's optimizer groups carry the saving run's ``fused`` flag (an older meshsplat's: none): the
    resumed optimizers keep the choice this machine made when it built them."""
    from meshsplat.io.checkpoint import load_checkpoint, save_checkpoint

    run = Trainer(small_config(tiny_dataset, tmp_path / "run", 2))
    built = {k: o.param_groups[0]["fused"] for k, o in run.optimizers.items()}
    run.train()
    path = sorted((tmp_path / "run" / "checkpoints").glob("ckpt_*.pt"))[-1]
    st = load_checkpoint(path)
    for opt in st["optimizers"].values():
        for g in opt["param_groups"]:
            g["fused"] = None
    save_checkpoint(path, st)
    res = Trainer(small_config(tiny_dataset, tmp_path / "run", 3), resume=True)
    assert {k: o.param_groups[0]["fused"] for k, o in res.optimizers.items()} == built
    res.train()
    assert res.iteration == 3


def test_resume_on_another_thread_count_says_it_is_not_bit_exact(tiny_dataset, tmp_path):
    """The checkpoint records torch's thread count: a resume on another count (sums split differently) says
    so among the changes on resume, and the same count says nothing."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        Trainer(small_config(tiny_dataset, tmp_path / "run", 2)).train()
        same = Trainer(small_config(tiny_dataset, tmp_path / "run", 3), resume=True)
        assert not any("torch threads" in n for n in same.resume_notes)
        torch.set_num_threads(2)
        other = Trainer(small_config(tiny_dataset, tmp_path / "run", 3), resume=True)
        assert "torch threads: 1 -> 2 (not bit-identical to an uninterrupted run; --threads 1 keeps it so)" in (
            other.resume_notes
        )
    finally:
        torch.set_num_threads(before)


def test_crop_to_subject_trains_and_resumes_bit_exact(tmp_path):
    ds = make_tiny_dataset(tmp_path / "ds96", size=96)
    on = ["loss.crop_to_subject=true", "loss.lpips_every=1", "checkpoint_every=5"]
    full = Trainer(small_config(ds, tmp_path / "full", 10, on))
    _, mask, _, _ = full.frames.frame(full.train_ids[0])
    box = subject_crop(mask, None, full.cfg.loss.crop_margin)
    assert box is not None and box.area_fraction < 0.5  # the crop really is a crop here
    full.train()
    off = Trainer(
        small_config(
            ds, tmp_path / "off", 10, ["loss.crop_to_subject=false", "loss.lpips_every=1", "checkpoint_every=5"]
        )
    )
    off.train()
    assert full.history[0]["l1"] == off.history[0]["l1"]  # same first render: L1 stays full-frame
    assert full.history[0]["lpips"] > 0 and off.history[0]["lpips"] > 0
    assert full.history[0]["lpips"] != off.history[0]["lpips"]  # the perceptual term is on the crop
    (tmp_path / "resumed" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000005.pt", tmp_path / "resumed" / "checkpoints")
    res = Trainer(small_config(ds, tmp_path / "resumed", 10, on), resume=True)
    assert res.iteration == 5
    res.train()
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k
    assert [r["loss"] for r in full.history[5:]] == [r["loss"] for r in res.history]
    with pytest.raises(MeshsplatError, match=r"loss\.crop_to_subject"):  # not a change a resume may make
        Trainer(
            small_config(ds, tmp_path / "resumed", 10, ["loss.crop_to_subject=false", "checkpoint_every=5"]),
            resume=True,
        )


class _Counted:
    """The trainer's own perceptual loss, still doing the work, noting the iteration of each call."""

    def __init__(self, trainer):
        self.trainer, self.inner, self.iterations = trainer, trainer.perceptual, []

    def __call__(self, render, gt):
        self.iterations.append(self.trainer.iteration)
        return self.inner(render, gt)


def test_lpips_every_skips_the_perceptual_net_and_resumes_bit_exact(tmp_path):
    ds = make_tiny_dataset(tmp_path / "ds96", size=96)
    on = ["loss.lpips_every=3", "loss.lambda_ssim=0.2", "checkpoint_every=5"]
    full = Trainer(small_config(ds, tmp_path / "full", 10, on))
    counted = full.perceptual = _Counted(full)
    net_calls: list[int] = []
    hook = None
    if counted.inner.net is not None:  # the LPIPS network itself (installed weights): note its forwards
        net = get_lpips(counted.inner.net, "cpu")
        hook = net.register_forward_hook(lambda *_: net_calls.append(full.iteration))
    try:
        full.train()
    finally:
        if hook is not None:
            hook.remove()
    assert counted.iterations == [3, 6, 9]
    if hook is not None:
        assert sorted(set(net_calls)) == [3, 6, 9]  # no forward of the network on the skipped iterations
    due = [it % 3 == 0 for it in range(1, 11)]
    for r, d in zip(full.history, due, strict=True):
        assert math.isnan(r["lpips"]) != d and math.isnan(r["dssim"]) != d
    assert full.history[2]["lpips"] > 0 and full.history[2]["dssim"] > 0
    for r, d in zip(full.history, due, strict=True):  # 3x the weights when due, the rest alone otherwise
        perceptual = 3 * (0.01 * r["lpips"] + 0.2 * r["dssim"]) if d else 0.0
        albedo = 0.1 * r["albedo"]  # the albedo prior (albedo_prior.weight), every iteration
        mask = 0.1 * r["mask"]  # the mask loss (mask_loss.weight), every iteration
        assert r["loss"] == pytest.approx(r["l1"] + r["scale"] + perceptual + albedo + mask, rel=1e-5)
    with open(tmp_path / "full" / "log.csv", newline="") as fh:
        log = list(csv.DictReader(fh))
    assert [r["lpips"] == "" for r in log] == [it % 3 != 0 for it in range(1, 11)]  # empty: not computed
    assert [r["dssim"] == "" for r in log] == [it % 3 != 0 for it in range(1, 11)]
    # resume from iteration 5 (not a multiple of 3): the cadence follows the iteration counter
    (tmp_path / "resumed" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000005.pt", tmp_path / "resumed" / "checkpoints")
    res = Trainer(small_config(ds, tmp_path / "resumed", 10, on), resume=True)
    res.train()
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k
    assert [r["loss"] for r in full.history[5:]] == [r["loss"] for r in res.history]


def _image_loss_before_lpips_every(self, out, gt, mask):
    """``Trainer._image_loss`` as it was before ``loss.lpips_every`` (the reference of the test below)."""
    L = self.cfg.loss
    crop = subject_crop(mask, out.alpha, L.crop_margin) if L.crop_to_subject else None
    loss, parts = avatar_loss(
        out.image,
        gt,
        self.params["log_scale"].exp(),
        thresh_scale=L.scale_max * self.extent,
        thresh_ratio=L.scale_ratio,
        lambda_l1=L.lambda_l1,
        lambda_lpips=L.lambda_lpips,
        lambda_scale=L.lambda_scale / self.extent,
        lambda_mse=L.lambda_mse,
        lambda_dssim=L.lambda_ssim,
        perceptual=self.perceptual,
        crop=crop,
    )
    if self.cfg.mask_loss.enabled and mask is not None:
        mask_l1 = (out.alpha - mask).abs().mean()
        loss = loss + self.cfg.mask_loss.weight * mask_l1
        parts["mask"] = mask_l1.detach()
    return loss, parts


def test_lpips_every_1_is_bit_identical_to_the_loss_before_it(tmp_path, monkeypatch):
    ds = make_tiny_dataset(tmp_path / "ds96", size=96)
    # the reference predates the albedo prior too: off
    extra = ["loss.lambda_ssim=0.2", "mask_loss.weight=0.1", "loss.lpips_every=1", "albedo_prior.weight=0"]
    now = Trainer(small_config(ds, tmp_path / "now", 8, extra))
    now.train()
    monkeypatch.setattr(Trainer, "_image_loss", _image_loss_before_lpips_every)
    old = Trainer(small_config(ds, tmp_path / "old", 8, extra))
    old.train()
    for k in now.params:
        assert torch.equal(now.params[k].detach(), old.params[k].detach()), k
    drop = lambda rows: [{k: v for k, v in r.items() if k != "time_s"} for r in rows]  # noqa: E731
    assert drop(now.history) == drop(old.history)


@pytest.mark.slow
def test_training_learns_and_writes_run_dir(tiny_dataset, tmp_path):
    from meshsplat.data import open_dataset

    ds = open_dataset(tiny_dataset)
    cfg = small_config(
        tiny_dataset,
        tmp_path / "run",
        60,
        [
            "model.init_color=grey",
            "optim.lr_color=0.03",
            "model.n_init=400",
            "strategy.grow_grad2d=2e-4",
            "strategy.reset_every=1000",
            "strategy.max_gaussians=800",
            "optim.lr_embedding=5e-4",  # the embedding moves enough in 60 iterations to cross edges
        ],
    )
    tr = Trainer(cfg)
    before = _psnr_on_train(tr.avatar(), ds)
    run = tr.train()
    avatar = load_avatar(run)
    after = _psnr_on_train(avatar, ds)
    assert after > before + 3.0, (before, after)
    assert avatar.num_gaussians == tr.num_gaussians
    assert (run / "config.json").is_file()
    assert TrainConfig.from_dict(json.loads((run / "config.json").read_text())) == cfg
    assert (
        sorted(p.name for p in (run / "checkpoints").iterdir())
        == [
            "ckpt_00000010.pt",
            "ckpt_00000020.pt",
            "ckpt_00000030.pt",
            "ckpt_00000040.pt",
            "ckpt_00000050.pt",
            "ckpt_00000060.pt",
        ][-5:]
    )
    assert (run / "previews" / "preview_000060.png").is_file()
    with open(run / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == LOG_COLUMNS and len(rows) == 60
    first = sum(float(r["loss"]) for r in rows[:10]) / 10
    last = sum(float(r["loss"]) for r in rows[-10:]) / 10
    assert last < 0.7 * first
    assert sum(int(r["walked"]) for r in rows) > 0  # embeddings changed face during training


def test_a_run_ending_on_a_refinement_step_saves_what_it_trained(tiny_dataset, tmp_path):
    """The last iteration neither densifies nor resets opacities: the checkpoint holds the Gaussians the
    run trained (refinement on the final step used to save children no iteration had trained)."""
    cfg = small_config(tiny_dataset, tmp_path / "run", 12, ["strategy.grow_grad2d=1e-7", "strategy.reset_every=6"])
    tr = Trainer(cfg)
    run = tr.train()
    with open(run / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    counts = [int(r["n_gaussians"]) for r in rows]
    assert counts[3] != counts[2] and counts[7] != counts[6]  # iterations 4 and 8 refined
    assert load_avatar(run).num_gaussians == tr.num_gaussians == counts[10]  # iteration 12 did not


def test_ablation_switches(tiny_dataset, tmp_path):
    frozen = Trainer(small_config(tiny_dataset, tmp_path / "frozen", 10, ["model.freeze_embedding=true"]))
    frozen.train()
    assert "duv" not in frozen.optimizers and "d" not in frozen.optimizers
    assert torch.all(frozen.params["d"] == 0) and torch.all(frozen.params["duv"] == 0)
    nowalk = Trainer(
        small_config(tiny_dataset, tmp_path / "nowalk", 10, ["walk.enabled=false", "strategy.enabled=false"])
    )
    face0 = nowalk.params["face"].clone()
    nowalk.train()
    assert torch.equal(nowalk.params["face"], face0)
    bary = torch.cat([nowalk.params["uv"], 1 - nowalk.params["uv"].sum(-1, keepdim=True)], -1)
    assert torch.all(bary >= -1e-6)
    assert load_avatar(tmp_path / "nowalk").clamp_to_face


def test_cli_train_and_resume(tiny_dataset, tmp_path, capsys):
    from meshsplat.cli.main import main

    out = tmp_path / "cli"
    args = [
        "train",
        str(tiny_dataset),
        "--out",
        str(out),
        "--iters",
        "6",
        "--device",
        "cpu",
        "--no-progress",
        "--set",
        "model.n_init=100",
        "--set",
        "backend=torch",
        "--set",
        "checkpoint_every=3",
        "--set",
        "log_every=1",
    ]
    assert main(args) == 0
    assert (out / "checkpoints" / "ckpt_00000006.pt").is_file()
    assert main(["train", str(tiny_dataset), "--out", str(out), "--iters", "8", "--resume", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "resuming from" in text and "iteration 8" in text
    with open(out / "log.csv", newline="") as fh:
        assert [int(r["iteration"]) for r in csv.DictReader(fh)] == [1, 2, 3, 4, 5, 6, 7, 8]
    assert main(args[:6] + ["--set", "strategy.bogus=1"]) == 2
    assert "unknown key" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "nothing"), "--out", str(out)]) == 2


def test_training_without_numba_says_it_runs_on_the_torch_path(tiny_dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MESHSPLAT_NO_NUMBA", "1")
    Trainer(small_config(tiny_dataset, tmp_path / "run", 1, ["backend=auto", "loss.lambda_lpips=0"])).train()
    err = capsys.readouterr().err
    assert err.count("training runs on the torch rasterizer") == 1 and "pip install numba" in err
    monkeypatch.delenv("MESHSPLAT_NO_NUMBA")
    Trainer(small_config(tiny_dataset, tmp_path / "run2", 1, ["backend=auto", "loss.lambda_lpips=0"])).train()
    assert "torch rasterizer" not in capsys.readouterr().err
