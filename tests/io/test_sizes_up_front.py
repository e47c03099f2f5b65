"""Sizes and cheap checks before the expensive work: the documented frame limit and the memory estimate apply
to every source of frames (a 200,000-frame motion is refused before it is posed, by render and view),
``render --no-png --no-mp4`` says "nothing to write" at once, and ``synth`` refuses a layout that cannot hold
the asset before rendering anything."""

from __future__ import annotations

import json
import resource
import time

import numpy as np
import pytest
import torch

from _eval_kit import make_run
from _peoplesnapshot import make_capture
from meshsplat.cli.main import main
from meshsplat.data.formats import peoplesnapshot as ps
from meshsplat.gaussians import Avatar
from meshsplat.gaussians.params import init_params
from meshsplat.mesh import TriMesh

BIG = 200_000  # frames: 200k x 6890 vertices x 12 bytes would be 16.5 GB once posed


@pytest.fixture(scope="module")
def smpl_run(tmp_path_factory, standin_model_dir):
    tmp = tmp_path_factory.mktemp("sizes")
    cap = make_capture(tmp / "cap")
    ds = ps.read(cap, model_dir=standin_model_dir, check_masks=False)
    mesh = TriMesh(ds.canonical_vertices, ds.faces)
    p = init_params(mesh, 200, generator=torch.Generator().manual_seed(0))
    run = make_run(Avatar(mesh, p, "sqrt_area"), tmp / "run", cap)
    cfg = json.loads((run / "config.json").read_text())
    cfg.update(data_format="peoplesnapshot", model_dir=str(standin_model_dir))
    (run / "config.json").write_text(json.dumps(cfg))
    motion = tmp / "long_motion.npz"  # zeros compress to almost nothing on disk
    np.savez_compressed(motion, poses=np.zeros((BIG, 72), np.float32), trans=np.zeros((BIG, 3), np.float32))
    return run, motion


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _refused_fast(args, capsys, match: str) -> str:
    before, t0 = _peak_rss_mb(), time.perf_counter()
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0], err
    assert _peak_rss_mb() - before < 1500, "the frames were allocated before the refusal"
    assert time.perf_counter() - t0 < 120
    return err[0]


def test_render_refuses_a_200k_frame_motion_before_posing_it(smpl_run, tmp_path, capsys):
    run, motion = smpl_run
    line = _refused_fast(
        [
            "render",
            str(run),
            "--animation",
            "motion",
            str(motion),
            "--out",
            str(tmp_path / "r"),
            "--no-mp4",
            "--no-progress",
        ],
        capsys,
        "200,000 frames",
    )
    assert "--frames N" in line and "limits.md" in line
    assert not (tmp_path / "r" / "frames").exists()


def test_view_refuses_a_200k_frame_motion_before_posing_it(smpl_run, tmp_path, capsys):
    run, motion = smpl_run
    _refused_fast(
        ["view", str(run), "--animation", "motion", str(motion), "--out", str(tmp_path / "v")], capsys, "200,000 frames"
    )
    assert not (tmp_path / "v").exists()


def test_the_first_frames_of_a_long_motion_render_with_frames(smpl_run, tmp_path):
    run, motion = smpl_run
    args = ["render", str(run), "--animation", "motion", str(motion), "--frames", "2", "--size", "32x32", "--no-mp4"]
    assert main([*args, "--out", str(tmp_path / "r"), "--no-progress"]) == 0
    assert len(list((tmp_path / "r" / "frames").glob("*.png"))) == 2


def test_render_with_nothing_to_write_is_refused_at_once(tmp_path, capsys):
    missing = tmp_path / "no-such-run"  # refused before the run is read: its absence is never reported
    args = [
        "render",
        str(missing),
        "--animation",
        "motion",
        "x.npz",
        "--no-png",
        "--no-mp4",
        "--out",
        str(tmp_path / "o"),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "nothing to write" in err and "no-such-run" not in err


@pytest.mark.parametrize(
    "asset, fmt, rig, match",
    [
        ("CesiumMan", "imavatar", "monocular-turn", "stores FLAME parameters"),
        ("smpl", "vhap", "monocular-turn", "stores FLAME parameters"),
        ("flame", "peoplesnapshot", "monocular-turn", "stores SMPL parameters"),
        ("smpl", "peoplesnapshot", "multiview", "one fixed camera"),
    ],
)
def test_synth_refuses_a_layout_that_cannot_hold_the_asset_before_rendering(
    asset, fmt, rig, match, tmp_path, capsys, standin_model_dir
):
    t0 = time.perf_counter()
    args = ["synth", asset, "--out", str(tmp_path / "o"), "--format", fmt, "--rig", rig, "--frames", "2"]
    assert main([*args, "--model-dir", str(standin_model_dir)]) == 2
    assert time.perf_counter() - t0 < 10  # nothing rendered
    assert match in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
