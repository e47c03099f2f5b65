"""BodyModel (SMPL / SMPL-X / FLAME over smplx LBS): golden hand-made models, file lookup, params files."""

from __future__ import annotations

import math
import pickle
import sys
import types

import numpy as np
import pytest
import torch

from _body_fixtures import tiny_flame, tiny_smpl, write_pickle
from meshsplat.drivers.body_models import (
    REGISTER_SITES,
    BodyModel,
    ParametricDriver,
    driver_record,
    find_model_file,
    join_flame_pose15,
    join_smpl_thetas,
    load_driver_params,
    resolve_model_dir,
    save_driver_params,
    split_flame_pose15,
    split_smpl_thetas,
)
from meshsplat.errors import MeshsplatError

L_SHOULDER, L_ELBOW = 16, 18


@pytest.fixture()
def tiny_dir(tmp_path):
    write_pickle(tmp_path / "smpl" / "SMPL_NEUTRAL.pkl", tiny_smpl())
    write_pickle(tmp_path / "flame" / "FLAME_NEUTRAL.pkl", tiny_flame())
    return tmp_path


def _rz(deg):
    return [0.0, 0.0, math.radians(deg)]


def _body_pose(joint, aa):
    bp = torch.zeros(1, 69)
    bp[0, (joint - 1) * 3 : (joint - 1) * 3 + 3] = torch.tensor(aa)
    return bp


def test_elbow_rotation_golden(tiny_dir):
    m = BodyModel("smpl", tiny_dir)
    out = m.forward({"body_pose": _body_pose(L_ELBOW, _rz(90)), "transl": torch.tensor([[1.0, 2.0, 3.0]])})
    # vertex 24 = elbow (0.5,0,0) + Rz(90) (0.3,0,0) = (0.5,0.3,0); plus transl
    assert torch.allclose(out.vertices[0, 24], torch.tensor([1.5, 2.3, 3.0]), atol=1e-5)
    assert torch.allclose(out.vertices[0, 25], torch.tensor([1.8, 2.0, 3.0]), atol=1e-5)  # shoulder-skinned: still
    assert torch.allclose(out.joints[0, L_ELBOW], torch.tensor([1.5, 2.0, 3.0]), atol=1e-5)


def test_shoulder_rotation_carries_child(tiny_dir):
    m = BodyModel("smpl", tiny_dir)
    out = m.forward({"body_pose": _body_pose(L_SHOULDER, _rz(90))})
    # about the shoulder (0.2,0,0): elbow -> (0.2,0.3,0), vertex 24 -> (0.2,0.6,0)
    assert torch.allclose(out.joints[0, L_ELBOW], torch.tensor([0.2, 0.3, 0.0]), atol=1e-5)
    assert torch.allclose(out.vertices[0, 24], torch.tensor([0.2, 0.6, 0.0]), atol=1e-5)


def test_global_orient_and_scale_golden(tiny_dir):
    m = BodyModel("smpl", tiny_dir, scale=4.0)
    out = m.forward({"global_orient": torch.tensor([_rz(-90)]), "transl": torch.tensor([[1.0, 0, 0]])})
    # Rz(-90) about the root at the origin: (0.8,0,0) -> (0,-0.8,0); x4; transl not scaled
    assert torch.allclose(out.vertices[0, 24], torch.tensor([1.0, -3.2, 0.0]), atol=1e-5)
    assert torch.allclose(out.joints[0, L_ELBOW], torch.tensor([1.0, -2.0, 0.0]), atol=1e-5)


def test_posedirs_layout_golden(tmp_path):
    d = tiny_smpl()
    k = (L_ELBOW - 1) * 9 + 0 * 3 + 1  # feature (R - I)[0, 1] of the elbow
    d["posedirs"][24, 1, k] = 0.1
    write_pickle(tmp_path / "smpl" / "SMPL_NEUTRAL.pkl", d)
    m = BodyModel("smpl", tmp_path)
    out = m.forward({"body_pose": _body_pose(L_ELBOW, _rz(90))})
    # Rz(90)[0,1] - 0 = -1 -> rest offset y -0.1: (0.3,-0.1,0) rotated -> (0.1,0.3,0) from the elbow
    assert torch.allclose(out.vertices[0, 24], torch.tensor([0.6, 0.3, 0.0]), atol=1e-5)


def test_betas_move_vertices_and_joints(tiny_dir):
    m = BodyModel("smpl", tiny_dir)
    assert m.num_betas == 10 and m.num_expression == 0 and m.num_joints == 24
    rest = m.rest_vertices({"betas": np.array([0.2], np.float32)})  # shorter betas are zero-padded
    assert torch.allclose(rest[L_ELBOW], torch.tensor([0.6, 0.0, 0.0]), atol=1e-6)
    out = m.forward({"betas": torch.tensor([0.2]), "body_pose": _body_pose(L_ELBOW, _rz(90))})
    assert torch.allclose(out.joints[0, L_ELBOW], torch.tensor([0.6, 0.0, 0.0]), atol=1e-6)
    assert torch.allclose(out.vertices[0, 24], torch.tensor([0.6, 0.2, 0.0]), atol=1e-5)


def test_static_offset_before_posing(tiny_dir):
    m = BodyModel("smpl", tiny_dir)
    off = torch.zeros(m.num_vertices, 3)
    off[24, 0] = 0.1
    out = m.forward({"static_offset": off, "body_pose": _body_pose(L_ELBOW, _rz(90))})
    assert torch.allclose(out.vertices[0, 24], torch.tensor([0.5, 0.4, 0.0]), atol=1e-5)
    assert torch.allclose(m.rest_vertices({"static_offset": off})[24], torch.tensor([0.9, 0.0, 0.0]))


def test_flame_pose15_jaw_eyes_expression_golden(tiny_dir):
    m = BodyModel("flame", tiny_dir)
    assert (m.num_betas, m.num_expression, m.num_joints) == (300, 100, 5)
    pose = torch.zeros(1, 15)
    pose[0, 6:9] = torch.tensor([math.radians(90), 0, 0])  # jaw +90 deg about x
    pose[0, 9:12] = torch.tensor([0, math.radians(90), 0])  # left eye +90 deg about y
    parts = split_flame_pose15(pose)
    assert torch.equal(parts["jaw_pose"], pose[:, 6:9]) and torch.equal(parts["reye_pose"], pose[:, 12:15])
    assert torch.equal(join_flame_pose15(parts), pose)
    out = m.forward(parts)
    # chin (0,0.1,0.15) about jaw (0,0.15,0.05): offset (0,-0.05,0.1) -> Rx(90) -> (0,-0.1,-0.05)
    assert torch.allclose(out.vertices[0, 5], torch.tensor([0.0, 0.05, 0.0]), atol=1e-5)
    # left-eye vertex (0.03,0.2,0.1) about (0.03,0.2,0.05): (0,0,0.05) -> Ry(90) -> (0.05,0,0)
    assert torch.allclose(out.vertices[0, 6], torch.tensor([0.08, 0.2, 0.05]), atol=1e-5)
    e = m.forward({"expression": torch.tensor([[1.0]]), "betas": torch.tensor([1.0])}).vertices[0, 5]
    assert torch.allclose(e, torch.tensor([0.0, 0.12, 0.16]), atol=1e-6)


def test_split_smpl_thetas():
    th = np.arange(2 * 72, dtype=np.float32).reshape(2, 72)
    g, b = split_smpl_thetas(th)
    assert np.array_equal(g, th[:, :3]) and np.array_equal(b, th[:, 3:]) and b.shape == (2, 69)
    assert np.array_equal(join_smpl_thetas(g, b), th)
    with pytest.raises(MeshsplatError, match=r"\[T, 72\]"):
        split_smpl_thetas(np.zeros((2, 69)))


def test_gradients_reach_pose_and_expression(tiny_dir):
    m = BodyModel("flame", tiny_dir)
    jaw = torch.tensor([[0.3, 0.0, 0.0]], requires_grad=True)
    expr = torch.zeros(1, 10, requires_grad=True)
    out = m.forward({"jaw_pose": jaw, "expression": expr})
    out.vertices[0, 5].sum().backward()
    assert jaw.grad is not None and jaw.grad.abs().sum() > 0
    assert expr.grad[0, 0] != 0


def test_batched_equals_per_frame(tiny_dir):
    m = BodyModel("smpl", tiny_dir)
    bp = torch.randn(5, 69) * 0.3
    drv = ParametricDriver(m, {"body_pose": bp, "betas": torch.zeros(10), "transl": torch.randn(5, 3)})
    allv = drv.all_vertices()
    assert allv.shape == (5, m.num_vertices, 3) and drv.num_frames == 5
    for t in (0, 4):
        assert torch.allclose(allv[t], drv.vertices(t), atol=1e-6)
    assert drv.faces.dtype == torch.long and drv.rest_vertices().shape == (m.num_vertices, 3)


def test_check_params_lists_every_problem(tiny_dir):
    m = BodyModel("smpl", tiny_dir)
    bad = {
        "body_pose": np.zeros((3, 63)),
        "transl": np.full((4, 3), np.nan),
        "jaw_pose": np.zeros((3, 3)),
        "betas": np.zeros(11),
    }
    with pytest.raises(MeshsplatError) as e:
        m.check_params(bad)
    msg = str(e.value)
    assert "\n" not in msg
    for part in ("body_pose", "transl: contains NaN", "jaw_pose", "betas"):
        assert part in msg
    with pytest.raises(MeshsplatError, match="disagree"):
        m.check_params({"body_pose": np.zeros((3, 69)), "transl": np.zeros((4, 3))})


def test_missing_file_error_names_file_dirs_and_site(tmp_path):
    (tmp_path / "smpl").mkdir()
    for kind, name in (("smpl", "SMPL_MALE.pkl"), ("smplx", "SMPLX_MALE.npz"), ("flame", "FLAME_MALE.pkl")):
        with pytest.raises(MeshsplatError) as e:
            BodyModel(kind, tmp_path, gender="male")
        msg = str(e.value)
        assert "\n" not in msg and name in msg and str(tmp_path / kind) in msg and REGISTER_SITES[kind] in msg
    with pytest.raises(MeshsplatError, match=r"flame2023.pkl.*flame.is.tue.mpg.de"):
        find_model_file("flame", tmp_path, flame_version="2023")


def test_model_dir_resolution(tmp_path, monkeypatch):
    monkeypatch.delenv("MESHSPLAT_MODEL_DIR", raising=False)
    with pytest.raises(MeshsplatError, match=r"--model-dir.*MESHSPLAT_MODEL_DIR"):
        resolve_model_dir(None)
    with pytest.raises(MeshsplatError, match="does not exist"):
        resolve_model_dir(tmp_path / "nope")
    (tmp_path / "SMPL_NEUTRAL.pkl").write_bytes(b"")
    with pytest.raises(MeshsplatError, match="is a file"):
        resolve_model_dir(tmp_path / "SMPL_NEUTRAL.pkl")
    monkeypatch.setenv("MESHSPLAT_MODEL_DIR", str(tmp_path))
    assert resolve_model_dir(None) == tmp_path


def test_official_flame_names_and_env(tmp_path, monkeypatch):
    write_pickle(tmp_path / "FLAME2020" / "generic_model.pkl", tiny_flame())
    write_pickle(tmp_path / "FLAME2023" / "flame2023.pkl", tiny_flame())
    monkeypatch.setenv("MESHSPLAT_MODEL_DIR", str(tmp_path))
    assert find_model_file("flame", None).name == "generic_model.pkl"
    assert BodyModel("flame", flame_version="2023").path.name == "flame2023.pkl"


def test_unreadable_and_wrong_files(tmp_path):
    p = tmp_path / "smpl" / "SMPL_NEUTRAL.pkl"
    p.parent.mkdir()
    p.write_bytes(b"not a pickle")
    with pytest.raises(MeshsplatError, match=r"cannot read the model file.*smpl.is.tue.mpg.de"):
        BodyModel("smpl", tmp_path)
    d = tiny_smpl()
    d["posedirs"] = np.zeros((26, 3, 36))
    write_pickle(p, d)
    with pytest.raises(MeshsplatError, match=r"posedirs \[26, 3, 36\]"):
        BodyModel("smpl", tmp_path)
    write_pickle(p, {"x": np.zeros(3), "obj": types.SimpleNamespace()})
    with pytest.raises(MeshsplatError, match="refusing to load"):
        BodyModel("smpl", tmp_path)


def test_chumpy_and_sparse_pickles_load_without_chumpy(tmp_path, monkeypatch):
    """Official pickles hold chumpy ``Ch`` leaves and a scipy sparse J_regressor; read them without chumpy."""
    from scipy import sparse

    mod = types.ModuleType("chumpy.ch")

    class Ch:  # the pickled state of a chumpy leaf carries its array under "x"
        def __init__(self, x):
            self.x = x

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    mod.Ch = Ch
    monkeypatch.setitem(sys.modules, "chumpy", types.ModuleType("chumpy"))
    monkeypatch.setitem(sys.modules, "chumpy.ch", mod)
    d = tiny_smpl()
    for k in ("v_template", "shapedirs", "posedirs", "weights"):
        d[k] = Ch(d[k])
    d["J_regressor"] = sparse.csc_matrix(d["J_regressor"])
    path = write_pickle(tmp_path / "smpl" / "SMPL_NEUTRAL.pkl", d)
    path.write_bytes(path.read_bytes().replace(b"numpy._core.multiarray", b"numpy.core.multiarray"))  # numpy 1 files
    monkeypatch.delitem(sys.modules, "chumpy.ch")
    m = BodyModel("smpl", tmp_path)
    out = m.forward({"body_pose": _body_pose(L_ELBOW, _rz(90))})
    assert torch.allclose(out.vertices[0, 24], torch.tensor([0.5, 0.3, 0.0]), atol=1e-5)


def test_params_roundtrip_and_record(tiny_dir, tmp_path):
    m = BodyModel("smpl", tiny_dir, scale=2.0)
    params = {"betas": np.ones(10), "body_pose": np.zeros((3, 69)), "transl": torch.zeros(3, 3)}
    p = save_driver_params(tmp_path / "driver_params.npz", params)
    back = load_driver_params(p)
    assert set(back) == set(params) and back["body_pose"].shape == (3, 69) and back["betas"].dtype == np.float32
    assert driver_record(m) == {
        "type": "smpl",
        "gender": "neutral",
        "flame_version": "2020",
        "scale": 2.0,
        "params": "driver_params.npz",
    }
    np.savez(tmp_path / "bad.npz", body_pose=np.zeros((3, 69)), names=np.array([{"a": 1}], dtype=object))
    with pytest.raises(MeshsplatError, match=r"bad.npz"):
        load_driver_params(tmp_path / "bad.npz")
    with pytest.raises(MeshsplatError, match="unknown key"):
        save_driver_params(tmp_path / "x.npz", {"pose": np.zeros(3)})


# ---------------------------------------------------------------- stand-in model files
STANDIN = {  # kind: (V, J, posedirs P, shapedirs S, faces or None)
    "smpl": (6890, 24, 207, 10, 13776),
    "smplx": (10475, 55, 486, 20, None),
    "flame": (5023, 5, 36, 400, None),
}


@pytest.mark.parametrize("kind", ["smpl", "smplx", "flame"])
def test_standin_files_load_in_smplx_and_match(standin_model_dir, kind):
    smplx = pytest.importorskip("smplx")
    V, J, P, S, F = STANDIN[kind]
    kw = {
        "smplx": dict(use_pca=False, flat_hand_mean=True, num_expression_coeffs=10),
        "flame": dict(num_betas=300, num_expression_coeffs=100),
    }.get(kind, {})
    ref = smplx.create(str(standin_model_dir), model_type=kind, gender="neutral", **kw)
    assert ref.v_template.shape == (V, 3) and ref.posedirs.shape == (P, 3 * V) and ref.J_regressor.shape == (J, V)
    bm = BodyModel(kind, standin_model_dir)
    assert (bm.num_vertices, bm.num_joints) == (V, J)
    assert bm.num_betas + bm.num_expression == (S if kind != "flame" else 400)
    if F is not None:
        assert bm.faces.shape == (F, 3)
    g = torch.Generator().manual_seed(1)
    params = {k: torch.randn(2, w, generator=g) * 0.3 for k, w in bm.param_shapes.items() if k != "betas"}
    params["betas"] = torch.randn(bm.num_betas, generator=g)
    out = bm.forward(params)
    ref_params = {k: (v.expand(2, -1) if v.ndim == 1 else v) for k, v in params.items()}
    assert torch.allclose(out.vertices, ref(**ref_params).vertices, atol=1e-5)
    assert out.joints.shape == (2, J, 3)


def test_standin_file_layout(standin_model_dir):
    from meshsplat.drivers.model_files import read_model_file

    smpl = read_model_file(standin_model_dir / "smpl" / "SMPL_FEMALE.pkl")
    assert smpl["f"].dtype == np.uint32 and smpl["kintree_table"].shape == (2, 24)
    assert all(isinstance(x, np.ndarray) for x in smpl.values())  # plain numpy, no chumpy
    with np.load(standin_model_dir / "smplx" / "SMPLX_NEUTRAL.npz", allow_pickle=False) as z:
        assert z["lmk_faces_idx"].shape == (51,) and z["lmk_bary_coords"].shape == (51, 3)
        assert z["hands_componentsl"].shape == (45, 45) and z["hands_meanr"].shape == (45,)
        assert int(z["lmk_faces_idx"].max()) < len(z["f"])
    with open(standin_model_dir / "flame" / "flame_static_embedding.pkl", "rb") as fh:
        emb = pickle.load(fh)
    assert emb["lmk_face_idx"].shape == (51,) and emb["lmk_b_coords"].shape == (51, 3)
    assert BodyModel("flame", standin_model_dir, flame_version="2023").path.name == "flame2023.pkl"
    smplx = pytest.importorskip("smplx")
    for kind in ("smplx", "flame"):  # the contour landmark files smplx reads with use_face_contour=True
        m = smplx.create(str(standin_model_dir), model_type=kind, use_face_contour=True, use_pca=False)
        assert torch.isfinite(m().joints).all()
    for kind, (V, *_rest) in STANDIN.items():
        with np.load(standin_model_dir / kind / "appearance.npz") as z:
            c = z["vertex_colors"]
        assert c.shape == (V, 3) and c.min() >= 0 and c.max() <= 1 and c.std(0).min() > 0.05


def test_standin_body_is_human_like(standin_model_dir):
    bm = BodyModel("smpl", standin_model_dir)
    rest = bm.rest_vertices()
    J = bm.forward({}).joints[0]
    assert abs(float(rest[:, 1].max() - rest[:, 1].min()) - 1.70) < 0.01
    # left side is +x; arms out along x (T-pose); head above neck above pelvis; knees below hips
    assert 0 < J[16, 0] < J[18, 0] < J[20, 0] < J[22, 0] and 0 > J[17, 0] > J[19, 0] > J[21, 0]
    assert J[15, 1] > J[12, 1] > J[9, 1] > J[6, 1] > J[3, 1] > J[0, 1] > J[1, 1] > J[4, 1] > J[7, 1]
    # +60 degrees about z at the left shoulder lifts the left hand (+x arm), the right hand stays
    lift = bm.forward({"body_pose": _body_pose(L_SHOULDER, _rz(60))}).joints[0]
    assert lift[22, 1] > J[22, 1] + 0.3 and torch.allclose(lift[23], J[23], atol=1e-5)
    male, female = (BodyModel("smpl", standin_model_dir, gender=g).rest_vertices() for g in ("male", "female"))
    height = lambda v: float(v[:, 1].max() - v[:, 1].min())  # noqa: E731
    assert height(male) > height(rest) > height(female)


def test_standin_head_jaw_opens_mouth(standin_model_dir):
    bm = BodyModel("flame", standin_model_dir)
    rest = bm.rest_vertices()
    moved = bm.forward({"jaw_pose": torch.tensor([[0.3, 0.0, 0.0]])}).vertices[0]
    jaw_open = bm.forward({"expression": torch.tensor([[1.0]])}).vertices[0]  # expression 0 = ICT jawOpen
    chin = int((jaw_open - rest).norm(dim=1).argmax())
    assert moved[chin, 1] < rest[chin, 1] - 0.01  # positive jaw pitch drops the chin
    top = int(torch.argmax(rest[:, 1]))
    assert torch.allclose(moved[top], rest[top], atol=1e-6)  # skull stays
    smile = bm.forward({"expression": torch.tensor([[0.0, 1.0]])}).vertices[0]  # mouthSmile_L
    d = (smile - rest).norm(dim=1)
    assert float(d.max()) > 0.003 and float(rest[int(d.argmax()), 0]) > 0  # left corner (+x) moves most
    eye = bm.forward({"leye_pose": torch.tensor([[0.0, 0.5, 0.0]])}).vertices[0]
    moved_ids = ((eye - rest).norm(dim=1) > 1e-6).nonzero().squeeze(1)
    assert len(moved_ids) > 50 and bool((rest[moved_ids, 0] > 0).all())  # only the left eyeball
