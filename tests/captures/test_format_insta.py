"""INSTA layout: golden OpenCV camera->world cameras, stored per-frame meshes, validation, write -> read."""

from __future__ import annotations

import json

import numpy as np
import pytest

from _head_captures import assert_vertices_close, native_flame_dataset, project, same_cameras, write_tiny_flame
from meshsplat.data import open_dataset
from meshsplat.data.formats import detect_format, insta, open_capture
from meshsplat.data.formats._files import obj_vertices
from meshsplat.errors import MeshsplatError
from meshsplat.io.images import write_png

W, H, F = 16, 12, 24.0
# OpenCV camera->world: camera at (0,0,1), x right, y down (-y world), looking down -z (as metrical-tracker's)
C2W_FRONT = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]]
# at (1,0,0) looking down -x: camera x = world -z, y = world -y, z = world -x
C2W_SIDE = [[0, 0, -1, 1.0], [0, -1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]]
TETRA = np.array([[0.0, 0.1, 0.0], [-0.1, -0.05, 0.05], [0.1, -0.05, 0.05], [0.0, -0.05, -0.1]])
TETRA_F = [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]


def _obj(path, v, faces=TETRA_F, colours=False):
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# https://github.com/mikedh/trimesh"]
    lines += [f"v {a:.9g} {b:.9g} {c:.9g}" + (" 0.5 0.5 0.5" if colours else "") for a, b, c in v]
    lines += ["vn 0 0 1"] + [f"f {a + 1}//1 {b + 1}//1 {c + 1}//1" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def _capture(root, splits, masks="folder", canonical=True):
    """``splits``: INSTA file name -> list of (frame id, c2w, mesh id); meshes are TETRA moved by +0.01 * id."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    if canonical:
        _obj(root / "canonical.obj", TETRA)
    for name, frames in splits.items():
        recs = []
        for fid, c2w, mid in frames:
            img = np.full((H, W, 4 if masks == "alpha" else 3), 70, np.uint8)
            if masks == "alpha":
                img[..., 3] = 0
                img[2:9, 3:12, 3] = 255
            write_png(root / "images" / f"{fid}.png", img)
            if not (root / "meshes" / f"{mid}.obj").exists():
                _obj(root / "meshes" / f"{mid}.obj", TETRA + 0.01 * int(mid))
            if masks == "folder":
                m = np.zeros((H, W), np.uint8)
                m[2:9, 3:12] = 255
                (root / "masks").mkdir(exist_ok=True)
                write_png(root / "masks" / f"{fid}.png", m)
            recs.append(
                {
                    "transform_matrix": c2w,
                    "file_path": f"images/{fid}.png",
                    "mesh_path": f"meshes/{mid}.obj",
                    "exp_path": f"flame/exp/{fid}.txt",
                    "seg_mask_path": f"seg_mask/{fid}.png",
                }
            )
        data = {"w": W, "h": H, "cx": 8.0, "cy": 6.0, "fl_x": F, "fl_y": F, "frames": recs}
        (root / f"transforms_{name}.json").write_text(json.dumps(data))
    return root


def test_camera_golden_opencv_c2w(tmp_path):
    root = _capture(tmp_path / "cap", {"train": [("00001", C2W_FRONT, "00001"), ("00002", C2W_SIDE, "00001")]})
    ds = insta.read(root)
    assert len(ds.camera_ids) == 2 and ds.meta["camera_convention"] == "opencv"
    c0 = ds.manifest["cameras"][ds.frame_info(0)["camera"]]
    c1 = ds.manifest["cameras"][ds.frame_info(1)["camera"]]
    np.testing.assert_allclose(c0["K"], [[F, 0, 8], [0, F, 6], [0, 0, 1]])
    # (0.05, 0.02, 0) one unit in front of the camera at (0,0,1): right of and above the centre
    np.testing.assert_allclose(project(c0["K"], c0["viewmat"], [0.05, 0.02, 0.0]), [8 + F * 0.05, 6 - F * 0.02])
    np.testing.assert_allclose(project(c1["K"], c1["viewmat"], [0.0, 0.02, 0.05]), [8 - F * 0.05, 6 - F * 0.02])
    # read as OpenGL, the same file puts the head behind the camera: one line naming the option
    with pytest.raises(MeshsplatError, match="camera_convention='opencv'"):
        insta.read(root, camera_convention="opengl")


def test_vhap_mesh_export_is_opengl(tmp_path):
    # VHAP's mesh export writes this layout with OpenGL camera->world and timestep_index per frame
    root = _capture(tmp_path / "cap", {"train": [("00000", np.diag([1.0, 1, 1, 1]).tolist(), "00000")]})
    data = json.loads((root / "transforms_train.json").read_text())
    data["frames"][0]["transform_matrix"][2][3] = 1.0
    data["frames"][0]["timestep_index"] = 0
    (root / "transforms_train.json").write_text(json.dumps(data))
    ds = insta.read(root)
    assert ds.meta["camera_convention"] == "opengl"
    cam = ds.manifest["cameras"][ds.frame_info(0)["camera"]]
    np.testing.assert_allclose(project(cam["K"], cam["viewmat"], [0.05, 0.02, 0.0]), [8 + F * 0.05, 6 - F * 0.02])


def test_meshes_rows_masks_and_splits(tmp_path):
    root = _capture(
        tmp_path / "cap",
        {
            "train": [("00010", C2W_FRONT, "00010"), ("00002", C2W_FRONT, "00002"), ("00003", C2W_FRONT, "00002")],
            "test": [("00011", C2W_FRONT, "00011"), ("00012", C2W_FRONT, "00012")],
            "val": [("00012", C2W_FRONT, "00012")],
        },
    )
    ds = insta.read(root)
    names = [ds.frame_info(i)["name"] for i in range(len(ds))]
    assert names == ["00002", "00003", "00010", "00011", "00012"]  # capture (natural) order
    assert ds.split("train") == [0, 1, 2] and ds.split("test_frames") == [3, 4] and ds.split("val") == [4]
    assert ds.frame_info(0)["mesh"] == ds.frame_info(1)["mesh"]  # frames sharing an OBJ share a row
    for i, mid in enumerate([2, 2, 10, 11, 12]):
        np.testing.assert_allclose(ds.vertices(i).numpy(), TETRA + 0.01 * mid, atol=1e-7)
    np.testing.assert_allclose(ds.canonical_vertices.numpy(), TETRA, atol=1e-7)
    assert ds.faces.tolist() == TETRA_F and ds.driver_info is None
    assert ds.frame_info(0)["mask"] == "masks/00002.png" and ds[0].mask.numpy()[5, 5, 0] == 1.0
    assert detect_format(root) == "insta" and open_capture(root).format_name == "insta"
    # RGBA images: the alpha is the matte
    ds = insta.read(_capture(tmp_path / "rgba", {"train": [("1", C2W_FRONT, "1")]}, masks="alpha"))
    assert ds.frame_info(0)["mask_kind"] == "alpha" and ds[0].mask.numpy()[0, 0, 0] == 0.0
    # transforms.json only: the tail rule; no canonical.obj: the first frame's mesh
    root = _capture(
        tmp_path / "one",
        {"train": [(f"{k:03d}", C2W_FRONT, f"{k:03d}") for k in range(5)]},
        masks="none",
        canonical=False,
    )
    (root / "transforms_train.json").rename(root / "transforms.json")
    ds = insta.read(root, test_frames=2)
    assert ds.split("test_frames") == [3, 4] and ds[0].mask is None
    assert ds.meta["canonical"] == "first frame's mesh"


def test_obj_vertices_fast_reader(tmp_path):
    _obj(tmp_path / "a.obj", TETRA, colours=True)
    v, nf = obj_vertices(tmp_path / "a.obj")
    np.testing.assert_allclose(v, TETRA)
    assert nf == 4


def test_every_problem_in_one_error(tmp_path):
    root = _capture(tmp_path / "bad", {"train": [(f"{k}", C2W_FRONT, f"{k}") for k in range(5)]})
    data = json.loads((root / "transforms_train.json").read_text())
    data["frames"][0]["transform_matrix"] = [[1, 0], [0, 1]]
    (root / "transforms_train.json").write_text(json.dumps(data))
    _obj(root / "meshes" / "1.obj", TETRA[:3], faces=[[0, 1, 2]])
    (root / "meshes" / "2.obj").unlink()
    (root / "images" / "3.png").unlink()
    (root / "masks" / "4.png").unlink()
    with pytest.raises(MeshsplatError) as e:
        insta.read(root)
    msg = str(e.value)
    for part in (
        "frame 0 ('images/0.png')",
        "transform_matrix",
        "frame 1",
        "meshes/1.obj has 3 vertices",
        "frame 2",
        "meshes/2.obj is missing",
        "3.png is missing",
        "masks/4.png is missing",
    ):
        assert part in msg, part


def test_write_read_round_trip(tmp_path):
    model_dir = write_tiny_flame(tmp_path / "models")
    src = open_dataset(native_flame_dataset(tmp_path / "native", model_dir, rows=3, views=3, shared_K=False))
    out = insta.write(src, tmp_path / "insta")
    assert (out / "canonical.obj").is_file() and len(list((out / "meshes").glob("*.obj"))) == 3
    back = insta.read(out)
    assert len(back) == len(src)
    for name in src.split_names:
        assert back.split(name) == src.split(name)
    for i in range(len(src)):
        same_cameras(src, back, i)
        assert_vertices_close(src.vertices(i).numpy(), back.vertices(i).numpy())
        assert np.array_equal(src[i].image.numpy(), back[i].image.numpy())
        assert np.array_equal(src[i].mask.numpy(), back[i].mask.numpy())
    assert back.driver().num_frames == 3
    np.testing.assert_allclose(back.canonical_vertices.numpy(), src.canonical_vertices.numpy(), atol=1e-6)
    assert back.faces.tolist() == src.faces.tolist()
    # written with OpenGL axes, read back with the matching option
    back = insta.read(insta.write(src, tmp_path / "gl", camera_convention="opengl"), camera_convention="opengl")
    same_cameras(src, back, 0)


def test_standin_flame_meshes_round_trip(tmp_path, standin_model_dir):
    src = open_dataset(native_flame_dataset(tmp_path / "native", standin_model_dir, rows=4, views=1))
    back = insta.read(insta.write(src, tmp_path / "insta"))
    assert back.num_vertices == 5023 and back.faces.tolist() == src.faces.tolist()
    for i in range(len(src)):
        same_cameras(src, back, i)
        assert_vertices_close(src.vertices(i).numpy(), back.vertices(i).numpy())
