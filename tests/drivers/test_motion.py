"""Motion files (SMPL / AMASS / IMavatar / VHAP) and re-enactment."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from _body_fixtures import write_tiny_models
from meshsplat.animation.motion import load_motion, motion_frame_rate, reenact
from meshsplat.drivers.body_models import BodyModel, ParametricDriver, save_driver_params
from meshsplat.errors import MeshsplatError, MeshsplatWarning


@pytest.fixture()
def models(tmp_path):
    root = write_tiny_models(tmp_path / "models")
    return {k: BodyModel(k, root) for k in ("smpl", "smplx", "flame")}


def _ramp(S, W):
    return (np.arange(S * W, dtype=np.float32).reshape(S, W) % 97) / 97.0


def test_aist_motion_layout(assets, models):
    path = assets / "motion" / "aist_demo.npz"
    with np.load(path) as z:
        poses, trans = z["poses"], z["trans"]
    p = load_motion(path, models["smpl"])
    assert p["global_orient"].shape == (320, 3) and p["body_pose"].shape == (320, 69)
    np.testing.assert_array_equal(p["global_orient"], poses[:, :3])
    np.testing.assert_array_equal(p["body_pose"], poses[:, 3:72])
    np.testing.assert_array_equal(p["transl"], trans)
    v = ParametricDriver(models["smpl"], p).all_vertices()
    assert v.shape == (320, models["smpl"].num_vertices, 3) and torch.isfinite(v).all()
    px = load_motion(path, models["smplx"])  # SMPL -> SMPL-X: 21 body joints shared, face and fingers zero
    np.testing.assert_array_equal(px["body_pose"], poses[:, 3:66])
    assert not px["left_hand_pose"].any() and not px["jaw_pose"].any()


def test_amass_smplx_165_layout(tmp_path, models):
    S = 4
    poses = _ramp(S, 165)
    np.savez(tmp_path / "m.npz", poses=poses, trans=_ramp(S, 3), betas=np.ones(16), mocap_framerate=120.0)
    p = load_motion(tmp_path / "m.npz", models["smplx"])
    np.testing.assert_array_equal(p["global_orient"], poses[:, :3])
    np.testing.assert_array_equal(p["body_pose"], poses[:, 3:66])
    np.testing.assert_array_equal(p["jaw_pose"], poses[:, 66:69])
    np.testing.assert_array_equal(p["leye_pose"], poses[:, 69:72])
    np.testing.assert_array_equal(p["reye_pose"], poses[:, 72:75])
    np.testing.assert_array_equal(p["left_hand_pose"], poses[:, 75:120])
    np.testing.assert_array_equal(p["right_hand_pose"], poses[:, 120:165])
    assert p["betas"].shape == (10,)  # the driver's 16 betas cut to the model's 10
    assert motion_frame_rate(tmp_path / "m.npz") == 120.0
    ps = load_motion(tmp_path / "m.npz", models["smpl"])  # SMPL-X -> SMPL: SMPL's hand joints zero
    np.testing.assert_array_equal(ps["body_pose"][:, :63], poses[:, 3:66])
    assert not ps["body_pose"][:, 63:].any()


def test_amass_smplh_156_and_split_keys(tmp_path, models):
    S = 3
    poses = _ramp(S, 156)
    np.savez(tmp_path / "h.npz", poses=poses, trans=np.zeros((S, 3)))
    p = load_motion(tmp_path / "h.npz", models["smplx"])
    np.testing.assert_array_equal(p["left_hand_pose"], poses[:, 66:111])
    np.testing.assert_array_equal(p["right_hand_pose"], poses[:, 111:156])
    assert not p["jaw_pose"].any()
    np.savez(
        tmp_path / "n.npz",
        root_orient=poses[:, :3],
        pose_body=poses[:, 3:66],
        pose_hand=poses[:, 66:156],
        pose_jaw=np.full((S, 3), 0.1),
        pose_eye=np.full((S, 6), 0.2),
        trans=np.zeros((S, 3)),
    )
    q = load_motion(tmp_path / "n.npz", models["smplx"])
    np.testing.assert_array_equal(q["left_hand_pose"], p["left_hand_pose"])
    assert np.allclose(q["jaw_pose"], 0.1) and np.allclose(q["reye_pose"], 0.2)


def test_imavatar_flame_params_json(tmp_path, models):
    S = 3
    pose, expr = _ramp(S, 15), _ramp(S, 50)
    doc = {
        "shape_params": [0.5] * 100,
        "intrinsics": [-1, 1, 0.5, 0.5],
        "frames": [
            {
                "file_path": f"./image/{i + 1}",
                "pose": pose[i].tolist(),
                "expression": expr[i].tolist(),
                "world_mat": np.eye(4)[:3].tolist(),
            }
            for i in range(S)
        ],
    }
    (tmp_path / "flame_params.json").write_text(json.dumps(doc))
    for src in (tmp_path / "flame_params.json", tmp_path):
        p = load_motion(src, models["flame"])
        np.testing.assert_allclose(p["global_orient"], pose[:, :3])
        np.testing.assert_allclose(p["neck_pose"], pose[:, 3:6])
        np.testing.assert_allclose(p["jaw_pose"], pose[:, 6:9])
        np.testing.assert_allclose(p["leye_pose"], pose[:, 9:12])
        np.testing.assert_allclose(p["reye_pose"], pose[:, 12:15])
        assert p["expression"].shape == (S, 50) and not p["transl"].any() and p["betas"].shape == (100,)
    out = models["flame"].forward(p)  # 50 expression columns are zero-padded to the model's 100
    assert out.vertices.shape == (S, models["flame"].num_vertices, 3)


def test_vhap_flame_param_folder(tmp_path, models):
    folder = tmp_path / "flame_param"
    folder.mkdir()
    for t in (10, 2, 1):  # numeric order, not file-name order
        np.savez(
            folder / f"{t:d}.npz",
            translation=np.full((1, 3), t, np.float32),
            rotation=np.full((1, 3), 0.01 * t),
            neck_pose=np.zeros((1, 3)),
            jaw_pose=np.full((1, 3), 0.1),
            eyes_pose=0.01 * (np.arange(6, dtype=np.float32)[None] + t),  # radians: plausible
            shape=np.ones(300),
            expr=np.zeros((1, 100)),
            static_offset=np.zeros((1, 5143, 3)),
        )
    for src in (folder, tmp_path):
        with pytest.warns(MeshsplatWarning, match="frame files jump from 2 to 10: 7 missing"):
            p = load_motion(src, models["flame"])
        assert p["transl"][:, 0].tolist() == [1, 2, 10]
        np.testing.assert_allclose(p["leye_pose"][1], [0.02, 0.03, 0.04], rtol=1e-6)
        np.testing.assert_allclose(p["reye_pose"][1], [0.05, 0.06, 0.07], rtol=1e-6)
        assert "static_offset" not in p and p["betas"].shape == (300,)


def test_driver_params_npz_as_motion(tmp_path, models):
    params = {"global_orient": _ramp(2, 3), "body_pose": _ramp(2, 69), "transl": _ramp(2, 3), "betas": np.ones(10)}
    save_driver_params(tmp_path / "driver_params.npz", params)
    p = load_motion(tmp_path / "driver_params.npz", models["smpl"])
    np.testing.assert_array_equal(p["body_pose"], params["body_pose"])


@pytest.mark.parametrize(
    "keys, kind, match",
    [
        ({"poses": np.zeros((3, 70)), "trans": np.zeros((3, 3))}, "smpl", r"\[S,72\].*AIST"),
        ({"poses": np.zeros((3, 72)), "trans": np.zeros((4, 3))}, "smpl", "disagree"),
        ({"rotation": np.zeros((3, 3)), "expr": np.zeros((3, 100))}, "smpl", "FLAME motion"),
        ({"poses": np.zeros((3, 72)), "trans": np.zeros((3, 3))}, "flame", "missing.*VHAP"),
        ({"trans": np.zeros((3, 3))}, "smplx", "no body poses.*AMASS"),
        ({"poses": np.full((3, 72), np.nan), "trans": np.zeros((3, 3))}, "smpl", "NaN"),
    ],
)
def test_wrong_layouts_are_one_line_errors(tmp_path, models, keys, kind, match):
    np.savez(tmp_path / "bad.npz", **keys)
    with pytest.raises(MeshsplatError, match=match) as e:
        load_motion(tmp_path / "bad.npz", models[kind])
    assert "\n" not in str(e.value)


def test_wrong_files(tmp_path, models):
    with pytest.raises(MeshsplatError, match="not found"):
        load_motion(tmp_path / "nope.npz", models["smpl"])
    (tmp_path / "flame_params.json").write_text('{"frames": [{"pose": [0, 0]}]}')
    with pytest.raises(MeshsplatError, match="IMavatar"):
        load_motion(tmp_path / "flame_params.json", models["flame"])
    np.savez(
        tmp_path / "expr.npz",
        rotation=np.zeros((2, 3)),
        neck_pose=np.zeros((2, 3)),
        jaw_pose=np.zeros((2, 3)),
        eyes_pose=np.zeros((2, 6)),
        expr=np.ones((2, 120)),
    )
    with pytest.raises(MeshsplatError, match="120 components"):
        load_motion(tmp_path / "expr.npz", models["flame"])
    with pytest.raises(MeshsplatError, match="SMPL model takes an npz"):
        load_motion(tmp_path / "flame_params.json", models["smpl"])


def _rz(deg):
    return [0.0, 0.0, math.radians(deg)]


def test_reenact_keeps_subject_shape_and_takes_motion():
    motion = {
        "global_orient": np.array([_rz(90), _rz(90)], np.float32),
        "body_pose": _ramp(2, 69),
        "transl": np.array([[5, 5, 5], [6, 5, 5]], np.float32),
        "betas": np.full(10, 9.0),
    }
    subject = {
        "betas": np.full(10, 0.5),
        "static_offset": np.ones((7, 3)),
        "global_orient": np.zeros((3, 3)),
        "transl": np.array([[0, 1, 2]] * 3, np.float32),
        "body_pose": np.zeros((3, 69)),
    }
    r = reenact(motion, subject, align="none")
    assert np.allclose(r["betas"], 0.5) and r["static_offset"].shape == (7, 3)
    np.testing.assert_array_equal(r["body_pose"], motion["body_pose"])
    np.testing.assert_array_equal(r["transl"], motion["transl"])
    r = reenact(motion, subject)  # translation: the path starts where the subject stands
    np.testing.assert_allclose(r["transl"], [[0, 1, 2], [1, 1, 2]])
    np.testing.assert_allclose(r["global_orient"], motion["global_orient"])
    r = reenact(motion, subject, align="pose")  # first frame turned to the subject's (identity): Rz(-90)
    np.testing.assert_allclose(r["global_orient"], 0, atol=1e-6)
    np.testing.assert_allclose(r["transl"], [[0, 1, 2], [0, 0, 2]], atol=1e-6)  # (1,0,0) -> Rz(-90) -> (0,-1,0)
    with pytest.raises(MeshsplatError, match="align"):
        reenact(motion, subject, align="bogus")


def test_reenact_flame_expression_from_driver(tmp_path, models):
    m = models["flame"]
    subject = {
        "betas": np.full(300, 0.1, np.float32),
        "expression": np.zeros((2, 100), np.float32),
        "global_orient": np.zeros((2, 3), np.float32),
    }
    motion = {
        "global_orient": np.zeros((4, 3), np.float32),
        "jaw_pose": np.full((4, 3), 0.2, np.float32),
        "expression": np.ones((4, 50), np.float32),
        "betas": np.full(100, 3.0, np.float32),
        "transl": np.zeros((4, 3), np.float32),
    }
    r = reenact(motion, subject)
    assert np.allclose(r["betas"], 0.1) and r["expression"].shape == (4, 50) and np.allclose(r["jaw_pose"], 0.2)
    drv = ParametricDriver(m, r)
    assert drv.num_frames == 4 and torch.allclose(drv.rest_vertices(), m.rest_vertices({"betas": subject["betas"]}))
