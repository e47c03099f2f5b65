"""The published protocol: each PeopleSnapshot split posed with its own parameter file (betas included),
InstantAvatar folders without config.json, the betas note, and every layout's pixel-centre convention
(golden captures written by hand, a known 3D point on a known pixel centre)."""

from __future__ import annotations

import json
import os
import pickle
import warnings

import numpy as np
import pytest
import torch

from _peoplesnapshot import H, K, W, make_capture
from meshsplat.animation import AnimationSource, load_animation
from meshsplat.camera import Camera
from meshsplat.cli.main import main as cli_main
from meshsplat.data.formats import open_capture
from meshsplat.data.formats import peoplesnapshot as ps
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.gaussians.params import init_params
from meshsplat.mesh import TriMesh


def _project(cam: Camera, X) -> np.ndarray:
    p = cam.viewmat.double().numpy() @ np.append(np.asarray(X, np.float64), 1.0)
    return (cam.K.double().numpy() @ p[:3])[:2] / p[2]


def _smpl(model_dir):
    with open(model_dir / "smpl" / "SMPL_NEUTRAL.pkl", "rb") as fh:
        return pickle.load(fh, encoding="latin1")


def _anim_nerf(root, split, betas, n, transl=None):
    (root / "poses").mkdir(exist_ok=True)
    np.savez(
        root / "poses" / f"anim_nerf_{split}.npz",
        betas=np.asarray(betas, np.float32).reshape(1, 10),
        global_orient=np.zeros((n, 3), np.float32),
        body_pose=np.zeros((n, 69), np.float32),
        transl=np.zeros((n, 3), np.float32) if transl is None else transl,
    )


# ---------------------------------------------------------------- finding 1: each split its own betas
def _split_capture(tmp_path):
    cfg = {
        "gender": "neutral",
        "train": {"start": 0, "end": 5, "skip": 1},
        "val": {"start": 6, "end": 6, "skip": 1},
        "test": {"start": 6, "end": 7, "skip": 1},
    }
    root = make_capture(tmp_path / "cap", n=8, config=cfg)
    b_train, b_test, b_val = np.zeros(10), np.zeros(10), np.zeros(10)
    b_train[0], b_test[0], b_val[0] = 0.1, 0.41, 0.2  # test differs from train by 0.31
    _anim_nerf(root, "train", b_train, 6)
    _anim_nerf(root, "test", b_test, 2)
    _anim_nerf(root, "val", b_val, 1)
    return root, b_train, b_test


def test_each_split_posed_with_its_own_betas(tmp_path, standin_model_dir):
    """Golden: every vertex of a test frame is SMPL evaluated by hand with the test file's betas."""
    root, b_train, b_test = _split_capture(tmp_path)
    m = _smpl(standin_model_dir)
    shaped = lambda b: m["v_template"] + m["shapedirs"][:, :, :10] @ b  # noqa: E731  (zero pose, zero transl)
    ds = ps.read(root, model_dir=standin_model_dir)
    assert ds.meta["betas"]["mode"] == "per_split"
    t0 = ds.split("test_frames")[0]
    assert np.abs(ds.vertices(t0).double().numpy() - shaped(b_test)).max() < 1e-5
    assert np.abs(ds.vertices(0).double().numpy() - shaped(b_train)).max() < 1e-5
    assert np.abs(ds.canonical_vertices.double().numpy() - shaped(b_train)).max() < 1e-5  # the avatar's shape
    assert np.allclose(ds.frame_params(t0)["betas"], b_test[None], atol=1e-7)
    assert "betas" in ds.per_frame_param_names
    # the shared-shape option poses the same frame with the train betas
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        shared = ps.read(root, model_dir=standin_model_dir, shape="train")
    assert np.abs(shared.vertices(t0).double().numpy() - shaped(b_train)).max() < 1e-5
    assert shared.driver_params["betas"].shape == (10,)
    with pytest.raises(MeshsplatError, match="shape: expected one of"):
        ps.read(root, model_dir=standin_model_dir, shape="first")


def test_betas_note_says_how_large_and_what_it_means(tmp_path, standin_model_dir):
    root, b_train, b_test = _split_capture(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = ps.read(root, model_dir=standin_model_dir)  # the protocol: nothing to warn about
    assert not [w for w in caught if "betas" in str(w.message)]
    note = ds.meta["betas"]
    m = _smpl(standin_model_dir)
    sd = m["shapedirs"][:, :, :10]
    shift = lambda a, b: 1000 * np.linalg.norm(sd @ (a - b), axis=1).mean()  # noqa: E731  (mm, zero pose)
    # frame 6 is in val and test and takes the test file (precedence train, test, val): 2 frames move
    expected_mm = shift(b_test, b_train)
    assert note["max_abs_diff"] == pytest.approx(0.31, abs=1e-6)
    assert note["mean_vertex_shift_mm"] == pytest.approx(expected_mm, rel=1e-3)
    assert note["splits"] == ["test_frames"] and note["frames"] == 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ps.read(root, model_dir=standin_model_dir, shape="train")
    msgs = [str(w.message) for w in caught if "betas" in str(w.message)]
    assert len(msgs) == 1
    text = msgs[0]
    assert "max |delta betas| 0.31" in text and f"{expected_mm:.2f} mm" in text
    assert "not on the published protocol" in text and "per_split" in text
    assert caught[0].filename == __file__  # points at the caller, not at meshsplat's internals


def test_writer_round_trips_per_split_betas(tmp_path, standin_model_dir):
    root, _, b_test = _split_capture(tmp_path)
    ds = ps.read(root, model_dir=standin_model_dir)
    out = ps.write(ds, tmp_path / "out")
    with np.load(out / "poses" / "anim_nerf_test.npz") as z:
        assert np.allclose(z["betas"], b_test[None], atol=1e-7)
    back = ps.read(out, model_dir=standin_model_dir)
    for name in ds.split_names:
        for i, j in zip(back.split(name), ds.split(name), strict=True):
            assert np.allclose(back.frame_params(i)["betas"], ds.frame_params(j)["betas"], atol=1e-7)
            assert torch.allclose(back.vertices(i), ds.vertices(j), atol=1e-6)
    assert torch.allclose(back.canonical_vertices, ds.canonical_vertices, atol=1e-6)


# ---------------------------------------------------------------- finding 4: InstantAvatar folders as they are
def _instant_avatar_folder(root, n):
    """InstantAvatar's preprocessing output: no config.json, masks as .npy, images from 0 (one image and
    one mask hard-linked n times: the frame count matters here, not the pixels)."""
    make_capture(root, n=1, masks="npy")
    (root / "config.json").unlink()
    for i in range(1, n):
        os.link(root / "images" / "image_0000.png", root / "images" / f"image_{i:04d}.png")
        os.link(root / "masks" / "mask_0000.npy", root / "masks" / f"mask_{i:04d}.npy")
    np.savez(root / "poses.npz", betas=np.zeros((1, 10)), thetas=np.zeros((n, 72)), transl=np.zeros((n, 3)))
    return root


def test_known_subject_without_config(tmp_path, standin_model_dir):
    root = _instant_avatar_folder(tmp_path / "female-4-casual", 524)
    spec = ps.KNOWN_SUBJECTS["female-4-casual"]  # InstantAvatar: train 0..335 /4, val 335, test 335..523 /4
    _anim_nerf(root, "test", np.full(10, 0.05), len(range(335, 524, 4)))
    ds = ps.read(root, model_dir=standin_model_dir, check_masks=False)
    assert ds.driver_info["gender"] == "female" == spec["gender"]
    idx = lambda split: [ds.frame_info(i)["frame_index"] for i in ds.split(split)]  # noqa: E731
    assert idx("train") == list(range(0, 336, 4)) and idx("test_frames") == list(range(335, 524, 4))
    assert idx("val") == [335]
    assert "InstantAvatar" in ds.meta["split_rule"] and "female-4-casual" in ds.meta["split_rule"]
    assert ds.meta["params_source"]["test_frames"] == "poses/anim_nerf_test.npz"  # the refined file is used
    assert np.allclose(ds.frame_params(ds.split("test_frames")[0])["betas"], 0.05)


def test_unknown_folder_without_config_asks_for_gender(tmp_path, standin_model_dir):
    root = _instant_avatar_folder(tmp_path / "my-subject", 10)
    with pytest.raises(MeshsplatError) as e:
        ps.read(root, model_dir=standin_model_dir)
    msg = str(e.value)
    assert "\n" not in msg and "--gender" in msg and "my-subject" in msg and "last 20%" in msg
    ds = ps.read(root, model_dir=standin_model_dir, gender="female")
    assert ds.driver_info["gender"] == "female"
    assert ds.meta["split_rule"].startswith("no config.json: the last 20%")
    assert len(ds.split("test_frames")) == 2


def test_cli_gender_and_shape_reach_the_reader(tmp_path, standin_model_dir, capsys):
    root = _instant_avatar_folder(tmp_path / "my-subject", 4)
    out = tmp_path / "native"
    assert cli_main(["import", str(root), "--out", str(out), "--model-dir", str(standin_model_dir)]) == 2
    err = capsys.readouterr().err
    assert "--gender" in err and len(err.strip().splitlines()) == 1
    args = ["import", str(root), "--out", str(out), "--model-dir", str(standin_model_dir), "--gender", "male"]
    assert cli_main([*args, "--shape", "train"]) == 0
    assert "splits from no config.json" in capsys.readouterr().out
    assert json.loads((out / "manifest.json").read_text())["driver"]["gender"] == "male"
    with pytest.raises(MeshsplatError, match="has no reader option 'gender'"):
        open_capture(out, gender="male")


# ---------------------------------------------------------------- finding 6: pixel centres, every layout
# A point straight ahead of the camera at depth 2, offset (0.25, -0.125): with f = 80 it lands 10 px right
# of and 5 px above the principal point. Each capture below is written by hand in its own convention.
F_PX, WID, HEI = 80.0, 64, 48
X_CAM = np.array([0.25, -0.125, 2.0])  # OpenCV camera coordinates


def test_golden_pixel_centre_peoplesnapshot(tmp_path, standin_model_dir):
    """InstantAvatar casts rays through integer pixel coordinates: its K with cx = 20 sends the point to
    x = 30, the centre of column 30, which meshsplat calls 30.5."""
    root = make_capture(tmp_path / "cap", n=3)
    with np.load(root / "cameras.npz") as z:
        extrinsic = z["extrinsic"].astype(np.float64)  # the fixture's, which sees the subject (camera check)
    np.savez(
        root / "cameras.npz",
        intrinsic=np.array([[F_PX, 0, 20.0], [0, F_PX, 30.0], [0, 0, 1]]),
        extrinsic=extrinsic,
        height=np.array(H),
        width=np.array(W),
    )
    cam = ps.read(root, model_dir=standin_model_dir).camera("0")
    x_world = (np.linalg.inv(extrinsic) @ np.append(X_CAM, 1.0))[:3]
    assert np.allclose(_project(cam, x_world), [30.5, 25.5], atol=1e-9)
    assert K[0, 2] == 32  # the shared fixture's K is InstantAvatar's too


def test_motion_keeps_the_train_shape_with_per_split_betas(tmp_path, standin_model_dir):
    """An avatar of a capture whose splits carry their own betas is driven with its train shape."""
    root, _, _ = _split_capture(tmp_path)
    ds = ps.read(root, model_dir=standin_model_dir)
    mesh = TriMesh(ds.canonical_vertices, ds.faces)
    avatar = Avatar(mesh, init_params(mesh, 8))
    motion = tmp_path / "motion.npz"
    np.savez(motion, poses=np.zeros((2, 72), np.float32), trans=np.zeros((2, 3), np.float32))
    frames = load_animation(
        AnimationSource("motion", motion, model_dir=standin_model_dir, align="none"), avatar, dataset=ds
    ).frames
    assert len(frames) == 2
    assert torch.allclose(frames[0], ds.canonical_vertices, atol=1e-5)  # rest pose with the train betas
