"""GaussianAvatars / VHAP layout: golden OpenGL cameras and FLAME npz poses, validation, write -> read."""

from __future__ import annotations

import json

import numpy as np
import pytest

from _head_captures import (
    JAW_VERTS,
    JOINTS,
    SHIFT_2023,
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
from meshsplat.data.formats import detect_format, open_capture, vhap
from meshsplat.errors import MeshsplatError
from meshsplat.io.images import write_png

W, H, F = 16, 12, 24.0
C2W_FRONT = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.0], [0, 0, 0, 1]]  # VHAP's monocular camera at (0,0,1)
C2W_SIDE = [[0, 0, 1, 1.0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]]  # at (1,0,0) looking down -x


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    return write_tiny_flame(tmp_path_factory.mktemp("models"))


def _npz(path, **kw):
    p = {
        "translation": np.zeros((1, 3)),
        "rotation": np.zeros((1, 3)),
        "neck_pose": np.zeros((1, 3)),
        "jaw_pose": np.zeros((1, 3)),
        "eyes_pose": np.zeros((1, 6)),
        "shape": np.zeros(300),
        "expr": np.zeros((1, 100)),
    }
    p.update(kw)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: np.asarray(v, np.float32) for k, v in p.items()})


def _capture(root, splits, params=None, masks=True, top_level=True):
    """``splits``: VHAP file name -> list of (timestep, camera, c2w); ``params``: timestep -> npz keys."""
    steps = sorted({t for fr in splits.values() for t, _, _ in fr})
    for t in steps:
        _npz(root / "flame_param" / f"{t:05d}.npz", **(params or {}).get(t, {}))
    intr = {"fl_x": F, "fl_y": F, "cx": 8.0, "cy": 6.0, "w": W, "h": H}
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "fg_masks").mkdir(exist_ok=True)
    for name, frames in splits.items():
        recs = []
        for t, c, c2w in frames:
            stem = f"{t:05d}_{c:02d}"
            write_png(root / "images" / f"{stem}.png", np.full((H, W, 3), 60 + c, np.uint8))
            rec = {
                "timestep_index": t,
                "camera_index": c,
                "transform_matrix": c2w,
                "file_path": f"images/{stem}.png",
                "flame_param_path": f"flame_param/{t:05d}.npz",
            }
            if not top_level:
                rec.update(intr)
            if masks:
                m = np.zeros((H, W), np.uint8)
                m[2:9, 3:12] = 255
                write_png(root / "fg_masks" / f"{stem}.png", m)
                rec["fg_mask_path"] = f"fg_masks/{stem}.png"
            recs.append(rec)
        (root / f"transforms_{name}.json").write_text(json.dumps({**(intr if top_level else {}), "frames": recs}))
    return root


def test_camera_golden_opengl_c2w(tmp_path, model_dir):
    root = _capture(tmp_path / "cap", {"train": [(0, 0, C2W_FRONT), (0, 1, C2W_SIDE)]})
    ds = vhap.read(root, model_dir=model_dir)
    assert len(ds.camera_ids) == 2 and len(ds) == 2
    cam0 = ds.manifest["cameras"][ds.frame_info(0)["camera"]]
    cam1 = ds.manifest["cameras"][ds.frame_info(1)["camera"]]
    np.testing.assert_allclose(cam0["K"], [[F, 0, 8], [0, F, 6], [0, 0, 1]])
    # front camera at (0,0,1) looking down -z: (0.05, 0.02, 0) is 1 unit ahead, right and up of centre
    np.testing.assert_allclose(project(cam0["K"], cam0["viewmat"], [0.05, 0.02, 0.0]), [8 + F * 0.05, 6 - F * 0.02])
    np.testing.assert_allclose(np.linalg.inv(cam0["viewmat"])[:3, 3], [0, 0, 1], atol=1e-12)
    # side camera at (1,0,0) looking down -x: world +z appears on the image's left
    np.testing.assert_allclose(project(cam1["K"], cam1["viewmat"], [0.0, 0.02, 0.05]), [8 - F * 0.05, 6 - F * 0.02])
    # both frames share timestep 0's mesh row
    assert ds.frame_info(0)["mesh"] == ds.frame_info(1)["mesh"] == 0


def test_flame_npz_golden(tmp_path, model_dir):
    offset = np.zeros((1, V + vhap.TEETH_VERTICES, 3))
    offset[0, 5, 1] = 0.005  # lifts the forehead 5 mm before posing
    offset[0, V:] = 1e3  # VHAP's teeth rows: must be ignored
    shape = np.zeros(300)
    shape[299] = 1.0  # the 300th shape coefficient is used (widens the left cheek by 1 cm)
    expr = np.zeros((1, 100))
    expr[0, 99] = 1.0  # the 100th expression lowers the lip by 1 cm
    tr = np.array([[0.1, -0.05, 0.02]])
    params = {
        0: {"shape": shape, "static_offset": offset},
        1: {"shape": shape, "static_offset": offset, "translation": tr, "jaw_pose": [[0.3, 0, 0]]},
        2: {"shape": shape, "static_offset": offset, "eyes_pose": [[0, 0.4, 0, 0, 0, 0]], "expr": expr},
        3: {"shape": shape, "static_offset": offset, "rotation": [[0, 0.5, 0]]},
    }
    root = _capture(tmp_path / "cap", {"train": [(t, 0, C2W_FRONT) for t in range(4)]}, params)
    ds = vhap.read(root, model_dir=model_dir)  # FLAME 2023 by default: the template shifted +1 cm in x
    rest = np.concatenate([JOINTS, SURFACE]) + SHIFT_2023
    rest[5, 1] += 0.005
    rest[6, 0] += 0.01
    v0, vjaw, veye, vrot = (ds.vertices(i).numpy().astype(np.float64) for i in range(4))
    np.testing.assert_allclose(v0, rest, atol=1e-6)
    np.testing.assert_allclose(ds.canonical_vertices.numpy(), rest, atol=1e-6)
    jaw = rest[2]
    for i in range(V):
        want = (jaw + rx(0.3) @ (rest[i] - jaw) if i in JAW_VERTS else rest[i]) + tr[0]
        np.testing.assert_allclose(vjaw[i], want, atol=1e-6, err_msg=f"vertex {i}")
    moved = np.nonzero(np.abs(veye - v0).max(1) > 1e-7)[0].tolist()
    assert moved == [9, 12]  # the lip (expression 99) and the left eye (eyes_pose[:3] = FLAME joint 3)
    np.testing.assert_allclose(veye[12], rest[3] + ry(0.4) @ (rest[12] - rest[3]), atol=1e-6)
    np.testing.assert_allclose(veye[9], rest[9] + [0, -0.01, 0], atol=1e-6)
    # global rotation turns about the root joint; the neck joint (vertex 1) lands at J0 + R (J1 - J0)
    np.testing.assert_allclose(vrot[1], rest[0] + ry(0.5) @ (rest[1] - rest[0]), atol=1e-6)
    # FLAME 2020 on request: no shift
    v2020 = vhap.read(root, model_dir=model_dir, flame_version="2020").vertices(0).numpy()
    np.testing.assert_allclose(v2020 + SHIFT_2023, v0, atol=1e-6)
    assert ds.driver_info["flame_version"] == "2023"
    assert ds.frame_params(1)["transl"][0].tolist() == pytest.approx(tr[0])


def test_splits_views_and_timesteps(tmp_path, model_dir):
    root = _capture(
        tmp_path / "cap",
        {
            "train": [(0, 0, C2W_FRONT), (1, 0, C2W_FRONT)],
            "val": [(0, 1, C2W_SIDE), (1, 1, C2W_SIDE)],
            "test": [(2, 0, C2W_FRONT), (2, 1, C2W_SIDE)],
        },
        top_level=False,
    )
    ds = vhap.read(root, model_dir=model_dir)
    assert len(ds) == 6 and len(ds.camera_ids) == 2 and ds.driver().num_frames == 3
    assert ds.split("train") == [0, 1] and ds.split("test_views") == [2, 3] and ds.split("test_frames") == [4, 5]
    rows = [ds.frame_info(i)["mesh"] for i in range(6)]
    assert rows == [0, 1, 0, 1, 2, 2]
    assert ds[0].mask is not None and ds.frame_info(0)["mask"] == "fg_masks/00000_00.png"
    assert detect_format(root) == "vhap" and open_capture(root, model_dir=model_dir).format_name == "vhap"


def test_every_problem_in_one_error(tmp_path, model_dir):
    root = _capture(tmp_path / "bad", {"train": [(t, 0, C2W_FRONT) for t in range(4)]})
    data = json.loads((root / "transforms_train.json").read_text())
    data["frames"][0]["transform_matrix"] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    (root / "transforms_train.json").write_text(json.dumps(data))
    (root / "flame_param" / "00001.npz").unlink()
    _npz(root / "flame_param" / "00002.npz", eyes_pose=np.zeros((1, 5)))
    (root / "images" / "00003_00.png").unlink()
    with pytest.raises(MeshsplatError) as e:
        vhap.read(root, model_dir=model_dir)
    msg = str(e.value)
    for part in ("frame 0", "transform_matrix", "00001.npz is missing", "eyes_pose has 5", "00003_00.png is missing"):
        assert part in msg, part
    # a camera convention flipped to OpenCV puts the head behind the camera
    root = _capture(tmp_path / "cv", {"train": [(0, 0, np.diag([1.0, -1, -1, 1]).tolist())]})
    data = json.loads((root / "transforms_train.json").read_text())
    data["frames"][0]["transform_matrix"][2][3] = 1.0
    (root / "transforms_train.json").write_text(json.dumps(data))
    with pytest.raises(MeshsplatError, match="behind its camera"):
        vhap.read(root, model_dir=model_dir)
    # per-frame dynamic offsets cannot be posed: say so, and how to go on
    root = _capture(
        tmp_path / "dyn", {"train": [(0, 0, C2W_FRONT)]}, {0: {"dynamic_offset": np.full((1, V + 120, 3), 0.001)}}
    )
    with pytest.raises(MeshsplatError, match="ignore_dynamic_offset"):
        vhap.read(root, model_dir=model_dir)
    assert len(vhap.read(root, model_dir=model_dir, ignore_dynamic_offset=True)) == 1


def test_write_read_round_trip(tmp_path, model_dir):
    src = open_dataset(
        native_flame_dataset(
            tmp_path / "native", model_dir, rows=3, views=3, flame_version="2023", static_offset=True, shared_K=False
        )
    )
    out = vhap.write(src, tmp_path / "vhap")
    with np.load(out / "flame_param" / "00000.npz") as z:
        assert z["static_offset"].shape == (1, V + 120, 3) and z["expr"].shape == (1, 100)
        assert z["shape"].shape == (300,) and z["eyes_pose"].shape == (1, 6)
    with pytest.raises(MeshsplatError, match="overwrite"):
        vhap.write(src, out)
    (out / "transforms_stale.json").write_text('{"frames": []}')
    assert vhap.write(src, out, overwrite=True) == out and not (out / "transforms_stale.json").exists()
    back = vhap.read(out, model_dir=model_dir)
    assert len(back) == len(src)
    for name in src.split_names:
        assert back.split(name) == src.split(name)
    for i in range(len(src)):
        same_cameras(src, back, i)
        assert_vertices_close(src.vertices(i).numpy(), back.vertices(i).numpy())
        assert np.array_equal(src[i].image.numpy(), back[i].image.numpy())
        assert np.array_equal(src[i].mask.numpy(), back[i].mask.numpy())
    assert back.driver().num_frames == 3  # one mesh row per timestep, shared by its cameras
    np.testing.assert_allclose(back.canonical_vertices.numpy(), src.canonical_vertices.numpy(), atol=1e-5)


def test_write_scales_world_to_flame_units(tmp_path, model_dir):
    src = open_dataset(native_flame_dataset(tmp_path / "native", model_dir, rows=2, views=2, scale=4.0))
    back = vhap.read(vhap.write(src, tmp_path / "vhap"), model_dir=model_dir, flame_version="2020")
    for i in range(len(src)):
        va, vb = src.vertices(i).numpy().astype(np.float64), back.vertices(i).numpy().astype(np.float64)
        assert_vertices_close(va / 4.0, vb)
        ca = src.manifest["cameras"][src.frame_info(i)["camera"]]
        cb = back.manifest["cameras"][back.frame_info(i)["camera"]]
        for p, q in zip(va, vb, strict=True):
            np.testing.assert_allclose(
                project(ca["K"], ca["viewmat"], p), project(cb["K"], cb["viewmat"], q), atol=1e-3
            )


def test_standin_flame_round_trip_with_teeth_rows(tmp_path, standin_model_dir):
    src = open_dataset(
        native_flame_dataset(
            tmp_path / "native", standin_model_dir, rows=3, views=2, flame_version="2023", static_offset=True
        )
    )
    out = vhap.write(src, tmp_path / "vhap")
    with np.load(out / "flame_param" / "00001.npz") as z:
        assert z["static_offset"].shape == (1, 5143, 3)  # FLAME's 5023 + VHAP's 120 teeth rows
    back = vhap.read(out, model_dir=standin_model_dir)
    assert back.num_vertices == 5023
    for i in range(len(src)):
        same_cameras(src, back, i)
        assert_vertices_close(src.vertices(i).numpy(), back.vertices(i).numpy())
