"""PeopleSnapshot (InstantAvatar / Anim-NeRF layout): golden hand-made folders, validation, masks,
anim_nerf precedence, default splits, and synth -> write -> read parity."""

from __future__ import annotations

import json
import math
import pickle
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from _peoplesnapshot import EXTRINSIC, H, K, W, make_capture
from meshsplat.camera import Camera
from meshsplat.data import DatasetWriter, open_dataset
from meshsplat.data.formats import peoplesnapshot as ps
from meshsplat.errors import MeshsplatError


def _rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _smpl_file(model_dir: Path) -> dict:
    with open(model_dir / "smpl" / "SMPL_NEUTRAL.pkl", "rb") as fh:
        return pickle.load(fh, encoding="latin1")


def test_detect(tmp_path):
    root = make_capture(tmp_path / "cap", n=3)
    assert ps.detect(root)
    assert not ps.detect(tmp_path)
    (root / "poses.npz").unlink()
    assert not ps.detect(root)


def test_golden_camera_and_smpl_pose(tmp_path, standin_model_dir):
    """Known camera position, known pixel of a known joint: global orient + transl + betas of a
    hand-made folder against SMPL evaluated by hand from the model file."""
    m = _smpl_file(standin_model_dir)
    betas = np.array([0.8, -0.5, 0.3, 0, 0, 0, 0, 0, 0, 0.2])
    v_shaped = m["v_template"] + m["shapedirs"][:, :, :10] @ betas
    J = np.asarray(m["J_regressor"]) @ v_shaped
    assert np.allclose(np.asarray(m["J_regressor"]).sum(1), 1.0, atol=1e-6)  # convex: the pelvis regresses exactly
    X = np.array([0.3, -0.6, 0.0])  # wanted pelvis position in the world
    n = 4
    thetas = np.zeros((n, 72))
    thetas[:, 1] = math.pi / 2  # global orient: 90 degrees about +y
    transl = np.tile(X - J[0], (n, 1))
    root = make_capture(tmp_path / "cap", n=n, betas=betas[None], thetas=thetas, transl=transl)
    ds = ps.read(root, model_dir=standin_model_dir)

    cam = ds.camera("0")
    assert isinstance(cam, Camera) and (cam.width, cam.height) == (W, H)
    assert torch.allclose(cam.center, torch.tensor([0.0, 0.0, -3.0]))
    assert np.allclose(ds.canonical_vertices.numpy(), v_shaped, atol=1e-5)
    expected = (v_shaped - J[0]) @ _rot_y(math.pi / 2).T + X
    verts = ds.vertices(0).double().numpy()
    assert np.abs(verts - expected).max() < 1e-5
    pelvis = np.asarray(m["J_regressor"])[0] @ verts
    assert np.allclose(pelvis, X, atol=1e-5)
    p_cam = cam.viewmat.double().numpy() @ np.append(pelvis, 1.0)
    pix = (cam.K.double().numpy() @ p_cam[:3])[:2] / p_cam[2]
    # InstantAvatar's K puts pixel centres at integers: its K sends the pelvis to (42, 4), the centre of
    # pixel column 42, row 4, which is (42.5, 4.5) in meshsplat's convention (centres at +0.5)
    assert np.allclose(pix, [32 + 100 * 0.3 / 3 + 0.5, 24 - 100 * 0.6 / 3 + 0.5], atol=1e-3)
    assert ds.driver_info["type"] == "smpl" and ds.driver_info["gender"] == "neutral"
    fp = ds.frame_params(1)
    assert fp["global_orient"].shape == (1, 3) and np.allclose(fp["global_orient"], [[0, math.pi / 2, 0]])
    assert np.allclose(fp["betas"], betas)


def test_body_pose_and_splits(tmp_path, standin_model_dir):
    from meshsplat.drivers.body_models import BodyModel

    n = 6
    thetas = np.zeros((n, 72))
    thetas[:, 3 * 16] = np.linspace(0, 1.2, n)  # left shoulder (joint 16) and elbow (joint 18) bend
    thetas[:, 3 * 18 + 2] = np.linspace(0, 1.2, n)
    root = make_capture(
        tmp_path / "cap",
        n=n,
        thetas=thetas,
        config={
            "gender": "female",
            "train": {"start": 0, "end": 4, "skip": 2},
            "val": {"start": 5, "end": 5, "skip": 1},
            "test": {"start": 5, "end": 5, "skip": 1},
        },
    )
    ds = ps.read(root, model_dir=standin_model_dir)
    assert [ds.frame_info(i)["frame_index"] for i in range(len(ds))] == [0, 2, 4, 5]
    assert ds.split("train") == [0, 1, 2] and ds.split("val") == [3] and ds.split("test_frames") == [3]
    assert ds.driver_info["gender"] == "female"
    model = BodyModel("smpl", standin_model_dir, gender="female")
    with torch.no_grad():
        ref = model.forward({"betas": np.zeros(10), "global_orient": thetas[[4], :3], "body_pose": thetas[[4], 3:]})
    assert torch.allclose(ds.vertices(2), ref.vertices[0], atol=1e-6)
    assert not torch.allclose(ds.vertices(2), ds.vertices(0), atol=1e-3)


def test_every_problem_in_one_error(tmp_path, standin_model_dir):
    n = 8
    transl = np.zeros((n, 3))
    transl[2, 1] = np.nan  # a used row
    transl[3, 1] = np.inf  # an unused row (train skips it): not a problem
    root = make_capture(
        tmp_path / "cap",
        n=n,
        transl=transl,
        config={
            "gender": "robot",
            "train": {"start": 0, "end": 4, "skip": 2},
            "test": {"start": 5, "end": 9, "skip": 1},
        },
    )
    (root / "images" / "image_0002.png").unlink()
    (root / "masks" / "mask_0006.png").unlink()
    Image.fromarray(np.zeros((H + 2, W, 3), np.uint8)).save(root / "images" / "image_0004.png")
    (root / "poses").mkdir()
    np.savez(
        root / "poses" / "anim_nerf_test.npz",
        betas=np.zeros((1, 10)),
        global_orient=np.zeros((3, 3)),
        body_pose=np.zeros((3, 69)),
        transl=np.zeros((3, 3)),
    )
    with pytest.raises(MeshsplatError) as e:
        ps.read(root, model_dir=standin_model_dir)
    msg = str(e.value)
    for part in (
        "unknown gender 'robot'",
        "anim_nerf_test.npz: rows",
        "do not match the 5 frames",
        "poses.npz: NaN/Inf parameters in rows 2",
        "no mask_%04d.png or .npy for frames 6, 8, 9",
        "image_0002.png is missing",
        "image_0008.png is missing",
        "image size mismatch: images/image_0004.png",
    ):
        assert part in msg, (part, msg)
    assert "rows 2, 3" not in msg
    assert msg.count("\n  - ") >= 7


def test_broken_files_reported_together(tmp_path, standin_model_dir):
    root = make_capture(tmp_path / "cap", n=4)
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=np.eye(3), height=np.array(H))
    np.savez(root / "poses.npz", betas=np.zeros(10), thetas=np.zeros((4, 70)), transl=np.zeros((5, 3)))
    (root / "images" / "image_0001.png").unlink()
    with pytest.raises(MeshsplatError) as e:
        ps.read(root, model_dir=standin_model_dir)
    msg = str(e.value)
    assert "cameras.npz: missing keys ['width']" in msg
    assert "thetas must be [N,72], got [4, 70]" in msg
    assert "missing image_%04d.png for frames 1" in msg
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=EXTRINSIC, height=np.array(H), width=np.array(W))
    np.savez(root / "poses.npz", betas=np.zeros(10), thetas=np.zeros((4, 72)), transl=np.zeros((5, 3)))
    with pytest.raises(MeshsplatError, match="thetas has 4 rows but transl has 5"):
        ps.read(root, model_dir=standin_model_dir)


def test_missing_model_file_is_one_of_the_problems(tmp_path):
    root = make_capture(tmp_path / "cap", n=3)
    (root / "masks" / "mask_0001.png").unlink()
    (tmp_path / "models").mkdir()
    with pytest.raises(MeshsplatError) as e:
        ps.read(root, model_dir=tmp_path / "models")
    assert "SMPL model file not found" in str(e.value) and "smpl.is.tue.mpg.de" in str(e.value)
    assert "frames 1" in str(e.value)


@pytest.mark.parametrize("kind", ["png", "npy"])
def test_masks_png_and_npy(tmp_path, standin_model_dir, kind):
    root = make_capture(tmp_path / "cap", n=3, masks=kind)
    if kind == "png":  # soft edge values survive
        m = np.zeros((H, W), np.uint8)
        m[10:, 5:] = 255  # the stand-in body covers the middle of the frame
        m[10:, 25] = 128
        Image.fromarray(m).save(root / "masks" / "mask_0000.png")
    ds = ps.read(root, model_dir=standin_model_dir)
    assert ds.frame_info(0)["mask_kind"] == kind
    mask = ds[0].mask
    assert mask.shape == (H, W, 1)
    assert float(mask[20, 10, 0]) == 1.0 and float(mask[0, 0, 0]) == 0.0
    if kind == "png":
        assert abs(float(mask[20, 25, 0]) - 128 / 255) < 1e-6
    assert ds[2].image.shape == (H, W, 3) and abs(float(ds[2].image[0, 0, 0]) - 20 / 255) < 1e-6
    # an empty mask is a problem
    if kind == "npy":
        np.save(root / "masks" / "mask_0001.npy", np.zeros((H, W), np.uint8))
        with pytest.raises(MeshsplatError, match=r"left the view in 1 of \d+ frames \(empty masks: image_0001.png\)"):
            ps.read(root, model_dir=standin_model_dir)


def test_anim_nerf_precedence(tmp_path, standin_model_dir):
    """Refined files win for their split and are indexed by position inside the split."""
    n = 10
    transl = np.zeros((n, 3))
    transl[:, 0] = 0.01 * np.arange(n)  # poses.npz: x = absolute index / 100
    cfg = {
        "gender": "neutral",
        "train": {"start": 0, "end": 6, "skip": 2},
        "val": {"start": 7, "end": 8, "skip": 1},
        "test": {"start": 7, "end": 8, "skip": 1},
    }
    root = make_capture(tmp_path / "cap", n=n, transl=transl, config=cfg)
    (root / "poses").mkdir()
    for split, base, rows in (("train", 0.1, 4), ("test", 0.2, 2)):
        t = np.zeros((rows, 3), np.float32)
        t[:, 0] = base + 0.01 * np.arange(rows)  # x = base + position in split / 100 (the body stays in view)
        np.savez(
            root / "poses" / f"anim_nerf_{split}.npz",
            betas=np.zeros((1, 10), np.float32),
            global_orient=np.zeros((rows, 3), np.float32),
            body_pose=np.zeros((rows, 69), np.float32),
            transl=t,
        )
    ds = ps.read(root, model_dir=standin_model_dir)
    x = {ds.frame_info(i)["frame_index"]: float(ds.frame_params(i)["transl"][0, 0]) for i in range(len(ds))}
    assert x == pytest.approx({0: 0.1, 2: 0.11, 4: 0.12, 6: 0.13, 7: 0.2, 8: 0.21})
    i4 = next(i for i in range(len(ds)) if ds.frame_info(i)["frame_index"] == 4)
    rest = ds.canonical_vertices
    assert torch.allclose(ds.vertices(i4) - rest, torch.tensor([0.12, 0, 0]).expand_as(rest), atol=1e-4)
    assert ds.split("val") == ds.split("test_frames")
    assert ds.meta["params_source"] == {
        "train": "poses/anim_nerf_train.npz",
        "val": "poses.npz",
        "test_frames": "poses/anim_nerf_test.npz",
    }
    # without the refined files the absolute rows of poses.npz are used
    for f in (root / "poses").iterdir():
        f.unlink()
    ds = ps.read(root, model_dir=standin_model_dir)
    x = [float(ds.frame_params(i)["transl"][0, 0]) for i in range(len(ds))]
    assert x == pytest.approx([0, 0.02, 0.04, 0.06, 0.07, 0.08])


def test_default_split_without_config(tmp_path, standin_model_dir):
    root = make_capture(tmp_path / "cap", n=10)
    (root / "config.json").unlink()
    (root / "poses").mkdir()
    np.savez(
        root / "poses" / "anim_nerf_train.npz",
        betas=np.zeros((1, 10)),
        global_orient=np.zeros((3, 3)),
        body_pose=np.zeros((3, 69)),
        transl=np.ones((3, 3)),
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = ps.read(root, model_dir=standin_model_dir, gender="male")
    assert any("no config.json" in str(w.message) for w in caught)
    assert ds.split("train") == list(range(8)) and ds.split("test_frames") == [8, 9]
    assert ds.driver_info["gender"] == "male"
    assert float(np.abs(ds.driver_params["transl"]).max()) == 0.0  # poses.npz, not the unplaceable refinement


def _tiny_native(root: Path, cameras=("0",)) -> Path:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    w = DatasetWriter(root, v, np.array([[0, 1, 2]]))
    for c in cameras:
        w.add_camera(c, K, EXTRINSIC, W, H)
    img = np.zeros((H, W, 3), np.uint8)
    for k, c in enumerate(cameras):
        w.add_frame(img, c, vertices=v + 0.1 * k)
    return w.close()


def test_write_needs_smpl_and_one_training_camera(tmp_path):
    ds = open_dataset(_tiny_native(tmp_path / "a"))
    with pytest.raises(MeshsplatError, match="needs SMPL driver parameters, this dataset has no model"):
        ps.write(ds, tmp_path / "out")
    root = _tiny_native(tmp_path / "b", cameras=("0", "1"))
    with pytest.raises(MeshsplatError, match="training frames use 2 cameras"):
        ps.plan_frames(open_dataset(root))
    with pytest.raises(MeshsplatError, match="masks: expected 'png' or 'npy'"):
        ps.write(ds, tmp_path / "out", masks="jpg")


@pytest.mark.parametrize("masks", ["png", "npy"])
def test_synth_write_read_parity(tmp_path, standin_model_dir, masks):
    """synth smpl (native) -> write peoplesnapshot -> read: same cameras, vertices, images, masks, params."""
    from meshsplat.synth.capture import synth_capture

    out = synth_capture(
        "smpl",
        tmp_path / "ps",
        format="peoplesnapshot",
        native_dir=tmp_path / "native",
        write_options={"masks": masks},
        frames=4,
        resolution=64,
        test_frames=2,
        test_views=1,
        model_dir=standin_model_dir,
    )
    nat = open_dataset(tmp_path / "native")
    assert nat.driver_info["type"] == "smpl" and "test_views" in nat.split_names
    assert ps.detect(out)
    back = ps.read(out, model_dir=standin_model_dir)
    plan = ps.plan_frames(nat)
    written = plan["train"] + plan["test"]
    assert len(back) == len(written) == 6
    assert back.split("train") == [0, 1, 2, 3] and back.split("test_frames") == [4, 5]
    a, b = nat.camera("0"), back.camera("0")
    assert (
        torch.allclose(a.K, b.K) and torch.allclose(a.viewmat, b.viewmat) and (a.width, a.height) == (b.width, b.height)
    )
    assert torch.allclose(nat.canonical_vertices, back.canonical_vertices, atol=1e-6)
    assert torch.equal(nat.faces, back.faces)
    for k, i in enumerate(written):
        assert (nat.vertices(i) - back.vertices(k)).abs().max() < 1e-5
        # the native capture gives the subject's colour at its soft edge (its backdrop taken out); the
        # written layout stores that colour in 8 bits, so it composites exactly too
        assert float((nat[i].image - back[k].image).abs().max()) <= 0.5 / 255 + 1e-6
        if masks == "png":
            assert torch.equal(nat[i].mask, back[k].mask)
        else:
            assert torch.equal((nat[i].mask >= 0.5).float(), back[k].mask)
        for key in ps.PER_FRAME:
            assert np.allclose(nat.frame_params(i)[key], back.frame_params(k)[key], atol=1e-6)
    assert sorted(p.suffix for p in (out / "masks").iterdir())[0] == f".{masks}"


def test_config_problems(tmp_path, standin_model_dir):
    root = make_capture(tmp_path / "cap", n=4, config={"gender": "male", "test": {"start": 3, "end": 1}})
    with pytest.raises(MeshsplatError) as e:
        ps.read(root, model_dir=standin_model_dir)
    assert "has no 'train' range" in str(e.value) and "'test': need 0 <= start <= end" in str(e.value)
    (root / "config.json").write_text("{not json")
    with pytest.raises(MeshsplatError, match=r"config.json: invalid JSON"):
        ps.read(root, model_dir=standin_model_dir)
    for spec in ({"start": 0.5, "end": 3}, {"start": True, "end": 3}, {"start": 0, "end": 3, "skip": 1.5}):
        (root / "config.json").write_text(json.dumps({"gender": "male", "train": spec}))
        with pytest.raises(MeshsplatError, match=r"'train' needs integer start, end"):  # not rounded
            ps.read(root, model_dir=standin_model_dir)
    (root / "config.json").write_text(json.dumps({"gender": "male", "train": {"start": 0.0, "end": 3.0}}))
    assert len(ps.read(root, model_dir=standin_model_dir)) == 4  # whole floats read
