"""Nothing lost, nothing silent: resume safety, interruption, full disks, bad manifests, sizes, paths."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from _train_kit import make_tiny_dataset, small_config
from meshsplat.cli.main import main
from meshsplat.data import open_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.io.checkpoint import list_checkpoints, load_checkpoint, save_checkpoint
from meshsplat.run_folder import load_run
from meshsplat.train import Trainer, apply_overrides
from meshsplat.train.config import load_config
from meshsplat.train.recipes import recipe_config

SRC = str(Path(__file__).resolve().parents[2] / "src")


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("robust") / "ds")


@pytest.fixture(scope="module")
def run(ds, tmp_path_factory):
    out = tmp_path_factory.mktemp("robust") / "run"
    Trainer(small_config(ds, out, 4, ["model.n_init=60", "checkpoint_every=2"])).train()
    return out


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


# ---- resume -------------------------------------------------------------------------------
def test_unreadable_checkpoints_are_refused_and_kept(ds, run, tmp_path):
    r = _copy(run, tmp_path / "r")
    ckpts = [p for _, p in list_checkpoints(r / "checkpoints")]
    assert len(ckpts) == 2
    ckpts[-1].write_bytes(b"junk")
    with pytest.raises(MeshsplatError, match=r"ckpt_00000004\.pt.*newest readable one is ckpt_00000002\.pt"):
        Trainer(small_config(ds, r, 8, ["model.n_init=60", "checkpoint_every=2"]), resume=True)
    ckpts[0].write_bytes(b"junk too")
    assert main(["train", str(ds), "--out", str(r), "--resume", "--iters", "8", "--no-progress"]) == 2
    assert [p.read_bytes() for p in ckpts] == [b"junk too", b"junk"]  # nothing deleted or overwritten


def test_fresh_run_refuses_a_folder_with_checkpoints(ds, run, tmp_path, capsys):
    r = _copy(run, tmp_path / "r")
    before = {p.name: p.read_bytes() for _, p in list_checkpoints(r / "checkpoints")}
    assert main(["train", str(ds), "--out", str(r), "--iters", "6", "--no-progress"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for _, p in list_checkpoints(r / "checkpoints")} == before


def test_resume_refuses_model_changes_and_allows_safe_ones(ds, run, tmp_path, capsys):
    r = _copy(run, tmp_path / "r")
    cfg_before = (r / "config.json").read_text()
    rc = main(
        [
            "train",
            str(ds),
            "--out",
            str(r),
            "--resume",
            "--iters",
            "6",
            "--no-progress",
            "--set",
            "model.sh_degree=1",
            "--set",
            "loss.lambda_l1=2",
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "model.sh_degree: 0 -> 1" in err and "loss.lambda_l1" in err and err.count("\n") == 1
    assert (r / "config.json").read_text() == cfg_before
    rc = main(
        [
            "train",
            str(ds),
            "--out",
            str(r),
            "--resume",
            "--iters",
            "6",
            "--no-progress",
            "--set",
            "log_every=2",
            "--device",
            "cpu",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0 and "iterations: 4 -> 6" in out and "log_every: 1 -> 2" in out
    assert load_config(r / "config.json").iterations == 6


def test_run_stores_absolute_paths_and_says_when_the_dataset_moved(ds, tmp_path, monkeypatch, capsys):
    shutil.copytree(ds, tmp_path / "data")
    monkeypatch.chdir(tmp_path)
    Trainer(small_config("data", "runrel", 2, ["model.n_init=40"])).train()
    cfg = json.loads((tmp_path / "runrel" / "config.json").read_text())
    assert Path(cfg["data"]).is_absolute() and Path(cfg["out"]).is_absolute()
    monkeypatch.chdir("/")
    assert main(["export", str(tmp_path / "runrel"), "--out", str(tmp_path / "ex")]) == 0
    (tmp_path / "data").rename(tmp_path / "moved")
    assert main(["eval", str(tmp_path / "runrel"), "--no-lpips", "--no-report", "--no-progress"]) == 2
    assert "moved" in capsys.readouterr().err


@pytest.mark.slow
def test_sigterm_and_sigint_checkpoint_before_stopping(ds, tmp_path):
    for sig in (signal.SIGTERM, signal.SIGINT):
        out = tmp_path / f"s{int(sig)}"
        code = "import sys; from meshsplat.cli.main import main; sys.exit(main(sys.argv[1:]))"
        env = dict(os.environ, PYTHONPATH=SRC, OMP_NUM_THREADS="1")
        p = subprocess.Popen(
            [
                sys.executable,
                "-c",
                code,
                "train",
                str(ds),
                "--out",
                str(out),
                "--iters",
                "100000",
                "--no-progress",
                "--device",
                "cpu",
                "--set",
                "backend=torch",
                "--set",
                "model.n_init=60",
                "--set",
                "log_every=1",
                "--set",
                "loss.lambda_lpips=0",
            ],
            env=env,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        t0 = time.time()
        while time.time() - t0 < 120 and not (
            (out / "log.csv").is_file() and len((out / "log.csv").read_text().splitlines()) > 4
        ):
            time.sleep(0.1)
        p.send_signal(sig)
        _, err = p.communicate(timeout=120)
        assert p.returncode == 128 + int(sig), err
        ((step, path),) = list_checkpoints(out / "checkpoints")
        assert step >= 4 and f"checkpoint {path}" in err and "--resume" in err
        assert load_checkpoint(path)["iteration"] == step


def test_wall_time_checkpoints(ds, tmp_path):
    t = Trainer(
        small_config(ds, tmp_path / "w", 3, ["model.n_init=40", "checkpoint_every=1000", "checkpoint_every_s=1e-9"])
    )
    t.train()
    assert [s for s, _ in list_checkpoints(tmp_path / "w" / "checkpoints")] == [1, 2, 3]


# ---- checkpoint files ---------------------------------------------------------------------
FULL_DISK = """
import resource, signal, sys, torch
from meshsplat.errors import MeshsplatError
from meshsplat.io.checkpoint import save_checkpoint
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)        # a write past the limit fails with EFBIG
resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
try:
    save_checkpoint(sys.argv[1], {"x": torch.zeros(200_000)}, keep_last=1)
except MeshsplatError as exc:
    print(exc)
    sys.exit(2)
"""


def test_checkpoint_write_failure_keeps_previous_and_leaves_no_tmp(tmp_path):
    good = save_checkpoint(tmp_path / "ckpt_00000001.pt", {"x": torch.ones(3)})
    (tmp_path / ".ckpt_00000001.pt.stray.tmp").write_bytes(b"left by a killed writer")
    p = subprocess.run(
        [sys.executable, "-c", FULL_DISK, str(tmp_path / "ckpt_00000002.pt")],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=SRC),
    )
    assert p.returncode == 2, p.stderr
    assert "cannot write checkpoint" in p.stdout and "untouched" in p.stdout
    assert torch.equal(load_checkpoint(good)["x"], torch.ones(3))
    assert sorted(q.name for q in tmp_path.iterdir()) == [".ckpt_00000001.pt.stray.tmp", "ckpt_00000001.pt"]
    save_checkpoint(tmp_path / "ckpt_00000003.pt", {"x": torch.ones(3)})  # a good write clears strays
    assert sorted(q.name for q in tmp_path.iterdir()) == ["ckpt_00000001.pt", "ckpt_00000003.pt"]


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_checkpoint_holding_code_is_refused_plainly(tmp_path):
    p = tmp_path / "ckpt_00000001.pt"
    torch.save({"format": "meshsplat-checkpoint", "version": 1, "state": {"x": _Evil()}}, p)
    with pytest.raises(MeshsplatError) as ei:
        load_checkpoint(p)
    msg = str(ei.value)
    assert "holds Python code" in msg and "not loaded" in msg and "weights_only" not in msg


# ---- config -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "override",
    [
        "loss.lambda_l1=nan",
        "optim.lr_color=inf",
        "loss.lambda_lpips=-1",
        "strategy.grow_grad2d=nan",
        "log_every=0",
        "model.n_init=1e12",
        "strategy.max_gaussians=-1",
        "checkpoint_every_s=0",
        "walk.enabled=2",
    ],
)
def test_config_refuses_non_finite_negative_and_absurd_values(override):
    with pytest.raises(MeshsplatError, match=override.split("=")[0].split(".")[-1]):
        apply_overrides(recipe_config("quality"), [override]).validate()


def test_config_file_with_nan_is_refused(tmp_path):
    (tmp_path / "c.json").write_text('{"loss": {"lambda_scale": NaN}}')
    with pytest.raises(MeshsplatError, match="finite"):
        load_config(tmp_path / "c.json").validate()


# ---- datasets -----------------------------------------------------------------------------
def _edit(ds, dst, fn):
    d = _copy(ds, dst)
    m = json.loads((d / "manifest.json").read_text())
    fn(m)
    (d / "manifest.json").write_text(json.dumps(m))
    return d


def test_manifest_wrong_types_are_all_listed_in_one_error(ds, tmp_path):
    def fn(m):
        m["frames"][0]["mesh"] = "0"
        m["frames"][1]["image"] = 12
        m["frames"][2]["time"] = "soon"
        m["splits"]["test"] = 3
        m["cameras"]["cam0"]["width"] = 32.5
        m["canonical"] = None

    d = _edit(ds, tmp_path / "d", fn)
    with pytest.raises(MeshsplatError) as ei:
        open_dataset(d)
    msg = str(ei.value)
    for part in (
        "mesh must be an integer",
        "image path must be a file path",
        "time must be a number",
        "split 'test'",
        "width and height must be integers",
        "canonical must be a file path",
    ):
        assert part in msg, part
    d2 = _edit(ds, tmp_path / "d2", lambda m: m.__setitem__("cameras", [1]))
    with pytest.raises(MeshsplatError, match="'cameras' must be an object"):
        open_dataset(d2)


def test_manifest_paths_must_stay_inside_the_dataset(ds, tmp_path, monkeypatch):
    shutil.copy(Path(ds) / "images" / "000000.png", tmp_path / "outside.png")
    d = _edit(ds, tmp_path / "d", lambda m: m["frames"][0].__setitem__("image", "../outside.png"))
    with pytest.raises(MeshsplatError, match=r"outside the dataset folder.*MESHSPLAT_ALLOW_OUTSIDE_FILES"):
        open_dataset(d)
    monkeypatch.setenv("MESHSPLAT_ALLOW_OUTSIDE_FILES", "1")
    assert open_dataset(d)[0].image.shape[-1] == 3


def test_16_bit_grey_png_is_scaled_not_clipped(ds, tmp_path):
    from PIL import Image

    d = _copy(ds, tmp_path / "d")
    rec = json.loads((d / "manifest.json").read_text())["frames"][0]
    vals = np.linspace(0, 65535, 32 * 32).reshape(32, 32).astype(np.uint16)
    Image.fromarray(vals).save(d / rec["mask"])  # mode I;16
    assert Image.open(d / rec["mask"]).mode.startswith("I")
    mask = open_dataset(d)[0].mask[..., 0].numpy()
    np.testing.assert_allclose(mask, vals / 65535.0, atol=1e-6)


@pytest.mark.parametrize("what", ["float faces", "single point", "no faces"])
def test_bad_canonical_mesh_is_refused(ds, tmp_path, what):
    d = _copy(ds, tmp_path / "d")
    with np.load(d / "canonical.npz") as z:
        v, f = z["vertices"], z["faces"]
    if what == "float faces":
        f = f.astype(np.float64)
    elif what == "single point":
        v = np.zeros_like(v)
    else:
        f = np.zeros((0, 3), np.int32)
    np.savez(d / "canonical.npz", vertices=v, faces=f)
    with pytest.raises(
        MeshsplatError,
        match={"float faces": "faces must be integers", "single point": "single point", "no faces": "empty"}[what],
    ):
        open_dataset(d)


# ---- command line: sizes, outputs, degenerate inputs -------------------------------------
def test_absurd_sizes_are_refused_before_work(run, tmp_path, capsys):
    cases = [
        (
            [
                "render",
                str(run),
                "--out",
                str(tmp_path / "r"),
                "--animation",
                "dataset",
                "--split",
                "train",
                "--size",
                "16384x16384",
            ],
            "8192",
        ),
        (["synth", "CesiumMan", "--out", str(tmp_path / "s"), "--resolution", "100000"], "16..4096"),
        (["synth", "CesiumMan", "--out", str(tmp_path / "s"), "--frames", "0"], "--frames"),
        (["view", str(run), "--out", str(tmp_path / "v"), "--frames", "0"], "--frames"),
        (
            [
                "render",
                str(run),
                "--out",
                str(tmp_path / "r"),
                "--animation",
                "dataset",
                "--split",
                "train",
                "--fps",
                "1e9",
            ],
            "--fps",
        ),
        (["eval", str(run), "--max-frames", "0"], "--max-frames"),
    ]
    for argv, needle in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1, err
    assert not (tmp_path / "s").exists() and not (tmp_path / "v").exists()


def test_memory_estimate_is_in_the_refusal():
    from meshsplat.cli._guards import check_memory, render_bytes

    with pytest.raises(MeshsplatError, match=r"needs about \d+\.\d GB of memory but only"):
        check_memory("rendering", render_bytes(200_000, 200_000), "lower --size")


def test_output_locations_are_checked_first(run, tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    for argv in (
        ["export", str(run), "--out", str(f)],
        ["view", str(run), "--out", str(f)],
        ["eval", str(run), "--out", str(f / "sub"), "--no-lpips"],
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert str(f) in err and err.count("\n") == 1


def test_os_errors_are_one_line(run, tmp_path, capsys, monkeypatch):
    import meshsplat.export as export

    def full(*a, **k):  # what a write on a full disk raises
        raise OSError(28, "No space left on device", str(tmp_path / "x.ply"))

    monkeypatch.setattr(export, "write_gaussian_ply", full)
    assert main(["export", str(run), "--out", str(tmp_path / "ex")]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "free some space" in err and err.count("\n") == 1


def test_degenerate_vertex_sequences_are_refused(run, tmp_path, capsys):
    n = load_run(run).avatar.mesh.num_vertices
    for name, arr in [
        ("point", np.zeros((2, n, 3), np.float32)),
        ("empty", np.zeros((0, n, 3), np.float32)),
        ("objects", np.array([None, 1], dtype=object)),
    ]:
        np.save(tmp_path / f"{name}.npy", arr, allow_pickle=True)
        assert (
            main(
                [
                    "render",
                    str(run),
                    "--out",
                    str(tmp_path / "r"),
                    "--animation",
                    "vertices",
                    str(tmp_path / f"{name}.npy"),
                    "--no-progress",
                    "--no-mp4",
                ]
            )
            == 2
        ), name
        assert capsys.readouterr().err.count("\n") == 1
