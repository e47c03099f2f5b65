"""IMavatar / DECA layout: golden cameras and FLAME x4 poses written by hand, validation, write -> read."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from _head_captures import (
    JAW_VERTS,
    JOINTS,
    SURFACE,
    V,
    assert_vertices_close,
    native_flame_dataset,
    project,
    rx,
    ry,
    same_cameras,
    write_tiny_flame,
)
from meshsplat.data import open_dataset
from meshsplat.data.formats import detect_format, imavatar, open_capture
from meshsplat.data.formats._files import tail_split
from meshsplat.errors import MeshsplatError
from meshsplat.io.images import write_png

W, H = 16, 12
INTR = [-1.5, 2.0, 0.5, 0.5]  # fx = 24 (stored negative), fy = 24, cx = 8, cy = 6


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    return write_tiny_flame(tmp_path_factory.mktemp("models"))


def _gl_world_mat(R, t):
    return np.hstack([np.asarray(R, float), np.asarray(t, float)[:, None]]).tolist()


def _rgba(alpha=True):
    img = np.full((H, W, 4 if alpha else 3), 90, np.uint8)
    if alpha:
        img[..., 3] = 0
        img[3:9, 4:12, 3] = 255
    return img


def _capture(root, frames, alpha=True, shape=None, extra=None):
    """flame_params.json + image/<k>.png for ``frames`` = list of (world_mat, pose15, expression50)."""
    (root / "image").mkdir(parents=True)
    items = []
    for k, (wm, pose, expr) in enumerate(frames, start=1):
        write_png(root / "image" / f"{k}.png", _rgba(alpha))
        items.append(
            {
                "file_path": f"./image/{k}",
                "world_mat": wm,
                "pose": list(pose),
                "expression": list(expr),
                "bbox": [-1, -1, 1, 1],
            }
        )
    data = {"intrinsics": INTR, "shape_params": list(shape if shape is not None else np.zeros(100)), "frames": items}
    data.update(extra or {})
    (root / "flame_params.json").write_text(json.dumps(data))
    return root


def _zeros():
    return np.zeros(15), np.zeros(50)


def test_camera_golden_in_imavatars_own_convention(tmp_path, model_dir):
    # DECA's default camera: R = I, T = (0, 0, -4): OpenGL-like, the head at the origin 4 units in front
    R2 = ry(math.radians(30)) @ rx(math.radians(10))
    t2 = np.array([0.1, -0.2, -4.5])
    root = _capture(
        tmp_path / "cap", [(_gl_world_mat(np.eye(3), [0, 0, -4]), *_zeros()), (_gl_world_mat(R2, t2), *_zeros())]
    )
    ds = imavatar.read(root, model_dir=model_dir)
    cam0 = ds.frame_camera(0)
    K, vm = cam0.K.double().numpy(), cam0.viewmat.double().numpy()
    assert (cam0.width, cam0.height) == (W, H)
    # IMavatar casts rays through integer pixel coordinates (real_dataset.py: uv = np.mgrid[...]): its
    # principal point (8, 6) is the centre of pixel (8, 6), (8.5, 6.5) in meshsplat's convention
    np.testing.assert_allclose(K, [[24, 0, 8.5], [0, 24, 6.5], [0, 0, 1]], atol=1e-6)
    # hand-computed: (0.5, 0.25, 0) -> camera (0.5, 0.25, -4); u = W(i0 X/Z + i2) = 11, v = H(i1 Y/Z + i3) = 4.5
    # in IMavatar's terms, so the centre of pixel (11, 4.5) + 0.5 in meshsplat's
    np.testing.assert_allclose(project(K, vm, [0.5, 0.25, 0.0]), [11.5, 5.0], atol=1e-4)
    assert vm[2, 3] == pytest.approx(4.0)  # the origin is 4 units in front (+z in OpenCV)
    # a rotated world_mat: the reader's camera equals IMavatar's own projection with the signed intrinsics
    cam = ds.manifest["cameras"][ds.frame_info(1)["camera"]]
    for p in ([0.1, 0.2, 0.05], [-0.3, 0.1, 0.2], [0.0, -0.25, -0.1]):
        X = R2 @ np.asarray(p) + t2
        expect = [W * (INTR[0] * X[0] / X[2] + INTR[2]) + 0.5, H * (INTR[1] * X[1] / X[2] + INTR[3]) + 0.5]
        np.testing.assert_allclose(project(cam["K"], cam["viewmat"], p), expect, atol=1e-6)
    # the head (FLAME x4 near the origin) lies in the image
    uv = np.array([project(cam["K"], cam["viewmat"], v) for v in ds.vertices(1).numpy()])
    assert (uv[:, 0] > 0).all() and (uv[:, 0] < W).all() and (uv[:, 1] > 0).all() and (uv[:, 1] < H).all()


def test_flame_pose15_golden(tmp_path, model_dir):
    wm = _gl_world_mat(np.eye(3), [0, 0, -4])
    pose_jaw, pose_glob, pose_neck, pose_eye = (np.zeros(15) for _ in range(4))
    pose_jaw[6] = 0.3  # jaw: indices 6..8
    pose_glob[1] = 0.5  # global: indices 0..2
    pose_neck[3] = 0.2  # neck: indices 3..5
    pose_eye[10] = 0.4  # left eye: indices 9..11
    expr = np.zeros(50)
    expr[0] = 1.0
    shape = np.zeros(100)
    shape[0] = 1.0
    root = _capture(
        tmp_path / "cap",
        [
            (wm, np.zeros(15), np.zeros(50)),
            (wm, pose_jaw, np.zeros(50)),
            (wm, pose_glob, np.zeros(50)),
            (wm, pose_neck, np.zeros(50)),
            (wm, pose_eye, np.zeros(50)),
            (wm, np.zeros(15), expr),
        ],
        shape=shape,
    )
    ds = imavatar.read(root, model_dir=model_dir, test_frames=1)
    rest = np.concatenate([JOINTS, SURFACE])
    rest[5, 1] += 0.01  # shape_params[0] lifts the forehead by 1 cm (before the x4)
    v0, vjaw, vglob, vneck, veye, vexpr = (ds.vertices(i).numpy().astype(np.float64) for i in range(6))
    np.testing.assert_allclose(v0, 4 * rest, atol=1e-5)  # DECA's x4, no translation
    np.testing.assert_allclose(ds.canonical_vertices.numpy(), 4 * rest, atol=1e-5)
    # jaw open: chin and lip rotate about the jaw joint (0,-0.02,0) by Rx(0.3); nothing else moves
    jaw = JOINTS[2]
    for i in range(V):
        want = 4 * (jaw + rx(0.3) @ (rest[i] - jaw)) if i in JAW_VERTS else 4 * rest[i]
        np.testing.assert_allclose(vjaw[i], want, atol=1e-5, err_msg=f"vertex {i}")
    assert vjaw[8, 1] < v0[8, 1]  # the chin drops: the mouth opens
    # global rotation about the root joint: the neck joint (vertex 1) lands at J0 + Ry(0.5)(J1 - J0)
    np.testing.assert_allclose(vglob[1], 4 * (JOINTS[0] + ry(0.5) @ (JOINTS[1] - JOINTS[0])), atol=1e-5)
    # neck rotation: root-skinned vertices stay, head vertices turn about the neck joint
    np.testing.assert_allclose(vneck[[0, 1, 11]], v0[[0, 1, 11]], atol=1e-6)
    np.testing.assert_allclose(vneck[5], 4 * (JOINTS[1] + rx(0.2) @ (rest[5] - JOINTS[1])), atol=1e-5)
    # left eye (pose 9..11 = FLAME joint 3 at +x): only vertex 12 moves
    moved = np.nonzero(np.abs(veye - v0).max(1) > 1e-6)[0].tolist()
    assert moved == [12]
    np.testing.assert_allclose(veye[12], 4 * (JOINTS[3] + ry(0.4) @ (rest[12] - JOINTS[3])), atol=1e-5)
    # expression 0 pushes the chin forward by 1 cm (x4)
    np.testing.assert_allclose(vexpr - v0, np.eye(V)[:, [8]] * [0, 0, 0.04], atol=1e-6)
    # driver parameters: IMavatar's pose15 split into FLAME's named joints
    p = ds.frame_params(1)
    assert p["jaw_pose"][0].tolist() == pytest.approx([0.3, 0, 0])
    assert ds.driver_info["type"] == "flame" and ds.driver_info["scale"] == 4.0


def test_masks_alpha_or_folder(tmp_path, model_dir):
    wm = _gl_world_mat(np.eye(3), [0, 0, -4])
    ds = imavatar.read(_capture(tmp_path / "a", [(wm, *_zeros())]), model_dir=model_dir)
    assert ds.frame_info(0)["mask_kind"] == "alpha"
    m = ds[0].mask.numpy()[..., 0]
    assert m[5, 6] == 1.0 and m[0, 0] == 0.0
    root = _capture(tmp_path / "b", [(wm, *_zeros())], alpha=False)
    (root / "mask").mkdir()
    mask = np.zeros((H, W), np.uint8)
    mask[2:5, 2:5] = 255
    write_png(root / "mask" / "1.png", mask)
    ds = imavatar.read(root, model_dir=model_dir)
    assert ds.frame_info(0)["mask"] == "mask/1.png"
    assert ds[0].mask.numpy()[3, 3, 0] == 1.0
    assert imavatar.read(root, model_dir=model_dir, mask="none")[0].mask is None
    # images/ instead of image/ (IMavatar's fallback)
    (root / "image").rename(root / "images")
    assert imavatar.read(root, model_dir=model_dir).frame_info(0)["image"] == "images/1.png"


def test_test_split_rule(tmp_path, model_dir):
    assert tail_split(400, None) == (list(range(50)), list(range(50, 400)))
    assert tail_split(351, None)[1] == list(range(1, 351))
    assert tail_split(350, None)[1] == list(range(280, 350))  # <= 350 frames: the last 20%
    assert tail_split(1, None) == ([0], [])
    with pytest.raises(MeshsplatError, match="test_frames"):
        tail_split(5, 5)
    wm = _gl_world_mat(np.eye(3), [0, 0, -4])
    ds = imavatar.read(_capture(tmp_path / "c", [(wm, *_zeros())] * 5), model_dir=model_dir, test_frames=2)
    assert ds.split("train") == [0, 1, 2] and ds.split("test_frames") == [3, 4]


@pytest.mark.parametrize("intr", ["../other/images/0.png", {"fx": 1}, [[1, 2], [3]]])
def test_intrinsics_that_are_not_numbers_are_one_line(tmp_path, model_dir, intr):
    """Found by the readers' property test: a string in ``intrinsics`` was a ValueError traceback."""
    root = _capture(tmp_path / "c", [(_gl_world_mat(np.eye(3), [0, 0, -4]), *_zeros())] * 3)
    data = json.loads((root / "flame_params.json").read_text())
    data["intrinsics"] = intr
    (root / "flame_params.json").write_text(json.dumps(data))
    with pytest.raises(MeshsplatError, match="intrinsics: expected 4 finite numbers"):
        imavatar.read(root, model_dir=model_dir)


def test_every_problem_in_one_error(tmp_path, model_dir):
    wm = _gl_world_mat(np.eye(3), [0, 0, -4])
    root = _capture(tmp_path / "bad", [(wm, *_zeros())] * 4)
    data = json.loads((root / "flame_params.json").read_text())
    data["frames"][0]["world_mat"] = [[1, 0, 0], [0, 1, 0]]
    data["frames"][1]["pose"] = [0.0] * 12
    data["frames"][2]["expression"] = [float("nan")] * 50
    (root / "flame_params.json").write_text(json.dumps(data))
    (root / "image" / "4.png").unlink()
    with pytest.raises(MeshsplatError) as e:
        imavatar.read(root, model_dir=model_dir)
    msg = str(e.value)
    for part in ("frame 0", "world_mat", "frame 1", "pose must have 15", "frame 2", "NaN", "4.png is missing"):
        assert part in msg, part
    # a camera looking away from the head (the sign error the OpenGL flip guards against)
    root = _capture(tmp_path / "behind", [(_gl_world_mat(np.eye(3), [0, 0, 4]), *_zeros())])
    with pytest.raises(MeshsplatError, match="behind its camera"):
        imavatar.read(root, model_dir=model_dir)
    # no model directory: one line naming what to pass
    with pytest.raises(MeshsplatError, match="model"):
        imavatar.read(root, model_dir=tmp_path / "nowhere")


def test_detect(tmp_path, model_dir):
    root = _capture(tmp_path / "d", [(_gl_world_mat(np.eye(3), [0, 0, -4]), *_zeros())])
    assert imavatar.detect(root) and not imavatar.detect(tmp_path) and detect_format(root) == "imavatar"
    assert open_capture(root, model_dir=model_dir).format_name == "imavatar"


def test_write_read_round_trip_exact(tmp_path, model_dir):
    # a native dataset already in DECA's units (FLAME x4, no translation) comes back identical
    src = open_dataset(
        native_flame_dataset(tmp_path / "native", model_dir, scale=4.0, transl=False, n_betas=100, n_expr=50)
    )
    out = imavatar.write(src, tmp_path / "ima")
    data = json.loads((out / "flame_params.json").read_text())
    assert data["intrinsics"][0] < 0 and len(data["shape_params"]) == 100
    assert len(data["frames"][0]["pose"]) == 15 and len(data["frames"][0]["expression"]) == 50
    back = imavatar.read(out, model_dir=model_dir)
    assert len(back) == len(src)
    for i in range(len(src)):
        same_cameras(src, back, i)
        assert_vertices_close(src.vertices(i).numpy(), back.vertices(i).numpy())
        a, b = src[i], back[i]
        assert np.array_equal(a.image.numpy(), b.image.numpy())
        assert np.array_equal(a.mask.numpy(), b.mask.numpy())
    assert back.frame_info(0)["mask_kind"] == "alpha"
    np.testing.assert_allclose(back.canonical_vertices.numpy(), src.canonical_vertices.numpy(), atol=1e-5)


def test_write_moves_translation_into_the_camera(tmp_path, model_dir):
    # metres + per-frame translation -> DECA x4 units without translation; every pixel stays put
    src = open_dataset(
        native_flame_dataset(tmp_path / "native", model_dir, scale=1.0, transl=True, n_betas=100, n_expr=50)
    )
    back = imavatar.read(imavatar.write(src, tmp_path / "ima"), model_dir=model_dir)
    transl = src.driver_params["transl"]
    for i in range(len(src)):
        row = src.frame_info(i)["mesh"]
        va, vb = src.vertices(i).numpy().astype(np.float64), back.vertices(i).numpy().astype(np.float64)
        assert_vertices_close(4.0 * (va - transl[row]), vb)
        ca = src.manifest["cameras"][src.frame_info(i)["camera"]]
        cb = back.manifest["cameras"][back.frame_info(i)["camera"]]
        for p, q in zip(va, vb, strict=True):
            np.testing.assert_allclose(
                project(ca["K"], ca["viewmat"], p), project(cb["K"], cb["viewmat"], q), atol=1e-3
            )


def test_writer_refuses_what_the_layout_cannot_hold(tmp_path, model_dir):
    src = open_dataset(native_flame_dataset(tmp_path / "n1", model_dir, n_betas=300, n_expr=50))
    with pytest.raises(MeshsplatError, match="betas"):
        imavatar.write(src, tmp_path / "o1")
    src = open_dataset(native_flame_dataset(tmp_path / "n2", model_dir, n_betas=100, n_expr=50, shared_K=False))
    with pytest.raises(MeshsplatError, match="one camera intrinsics"):
        imavatar.write(src, tmp_path / "o2")


def test_standin_flame_jaw_and_round_trip(tmp_path, standin_model_dir):
    """The 5023-vertex stand-in FLAME: opening the jaw moves only jaw-skinned vertices below the eyes;
    write -> read keeps cameras and vertices."""
    from meshsplat.drivers.model_files import read_model_file

    m = read_model_file(standin_model_dir / "flame" / "FLAME_NEUTRAL.pkl")
    jaw_skinned = m["weights"][:, 2] > 0
    eye_y = (m["J_regressor"] @ m["v_template"])[3, 1]
    wm = _gl_world_mat(np.eye(3), [0, 0, -4])
    pose = np.zeros(15)
    pose[6] = 0.3
    ds = imavatar.read(
        _capture(tmp_path / "cap", [(wm, *_zeros()), (wm, pose, np.zeros(50))]), model_dir=standin_model_dir
    )
    v0, v1 = ds.vertices(0).numpy(), ds.vertices(1).numpy()
    moved = np.abs(v1 - v0).max(1) > 1e-5
    assert ds.num_vertices == 5023 and moved.sum() > 50
    assert not (moved & ~jaw_skinned).any()
    low = np.median(v0[moved, 1])
    assert low < 4 * eye_y and low < np.median(v0[~moved, 1]) - 0.1  # the lower face
    np.testing.assert_allclose(v0, 4 * m["v_template"], atol=1e-5)
    src = open_dataset(
        native_flame_dataset(
            tmp_path / "native", standin_model_dir, rows=3, views=2, scale=4.0, transl=False, n_betas=100, n_expr=50
        )
    )
    back = imavatar.read(imavatar.write(src, tmp_path / "ima"), model_dir=standin_model_dir)
    for i in range(len(src)):
        same_cameras(src, back, i)
        assert_vertices_close(src.vertices(i).numpy(), back.vertices(i).numpy())
