"""Native dataset format: writer/loader round trip, lazy loading and one test per validation error."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

import meshsplat.data.dataset as dataset_mod
from meshsplat.camera import Camera
from meshsplat.data import DatasetWriter, open_dataset, write_dataset
from meshsplat.errors import MeshsplatError

W, H = 24, 16
VERTS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
FACES = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])


def _camera():
    K = np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    vm = np.eye(4)
    vm[2, 3] = 3.0
    return K, vm


def _make(root, n=3):
    K, vm = _camera()
    rng = np.random.default_rng(0)
    with DatasetWriter(root, VERTS, FACES, meta={"note": "test"}) as w:
        w.add_camera("c0", K, vm, W, H)
        for i in range(n):
            mask = np.zeros((H, W), np.uint8)
            mask[4:10, 5:15] = 255
            w.add_frame(
                rng.random((H, W, 3)).astype(np.float32),
                "c0",
                vertices=VERTS + 0.1 * i,
                mask=mask,
                clip="walk",
                time=i / 10,
            )
        w.set_split("train", [0, 1])
        w.set_split("test_frames", [2])
    return root


@pytest.fixture
def ds_root(tmp_path):
    return _make(tmp_path / "ds")


def _edit_manifest(root, fn):
    p = root / "manifest.json"
    m = json.loads(p.read_text())
    fn(m)
    p.write_text(json.dumps(m))


def test_round_trip(ds_root):
    ds = open_dataset(ds_root)
    assert len(ds) == 3 and ds.split("train") == [0, 1] and "test_frames" in ds.split_names
    fr = ds[2]
    assert fr.image.shape == (H, W, 3) and fr.image.dtype == torch.float32
    assert float(fr.image.min()) >= 0 and float(fr.image.max()) <= 1
    assert fr.mask.shape == (H, W, 1) and float(fr.mask.sum()) == 60
    torch.testing.assert_close(fr.vertices, torch.from_numpy(VERTS + 0.2))
    cam = fr.camera
    assert isinstance(cam, Camera) and cam.K.shape == (3, 3) and cam.viewmat.shape == (4, 4)
    assert cam.viewmat.dtype == torch.float32 and cam.K.dtype == torch.float32
    assert (cam.width, cam.height, fr.index, fr.camera_id, fr.clip) == (W, H, 2, "c0", "walk")
    same = ds.frame_camera(2)  # without decoding the image; a new object, equal values
    assert same is not cam and torch.equal(same.viewmat, cam.viewmat) and torch.equal(same.K, cam.K)
    assert (same.width, same.height) == (W, H) and torch.equal(ds.camera("c0").K, cam.K)
    with pytest.raises(MeshsplatError, match=r"'nope' is not a camera of .*cameras: c0"):
        ds.camera("nope")
    assert ds.faces.dtype == torch.long and ds.canonical_vertices.shape == (4, 3)
    assert ds[-1].name == fr.name
    assert ds.driver().num_frames == 3


def test_images_load_lazily(ds_root, monkeypatch):
    calls = []
    real = dataset_mod.read_image
    monkeypatch.setattr(dataset_mod, "read_image", lambda p, c: calls.append((p.name, c)) or real(p, c))
    ds = open_dataset(ds_root)
    assert all(c == 1 for _, c in calls)  # only masks (emptiness check), no RGB image decoded
    calls.clear()
    open_dataset(ds_root, check_masks=False)
    assert calls == []
    ds[1]
    ds[1]  # cached
    assert [c for _, c in calls].count(3) == 1


def test_write_dataset_one_call(tmp_path):
    K, vm = _camera()
    root = write_dataset(
        tmp_path / "w",
        VERTS,
        FACES,
        {"a": dict(K=K, viewmat=vm, width=W, height=H)},
        [dict(image=np.zeros((H, W, 3), np.uint8), camera_id="a", vertices=VERTS)],
    )
    assert open_dataset(root).split("train") == [0]


def _expect(root, *fragments):
    with pytest.raises(MeshsplatError) as exc:
        open_dataset(root)
    for frag in fragments:
        assert frag in str(exc.value), str(exc.value)


def test_missing_image(ds_root):
    (ds_root / "images" / "000001.png").unlink()
    _expect(ds_root, "frame 1 ('000001')", "image file images/000001.png is missing")


def test_missing_manifest(tmp_path):
    tmp_path.joinpath("empty").mkdir()
    _expect(tmp_path / "empty", "no manifest.json")


def test_bad_version(ds_root):
    _edit_manifest(ds_root, lambda m: m.update(version=99))
    _expect(ds_root, "unsupported format version 99")


def test_image_size_mismatch(ds_root):
    Image.new("RGB", (W + 2, H)).save(ds_root / "images" / "000002.png")
    _expect(ds_root, "frame 2 ('000002')", "image size mismatch", f"{W + 2}x{H}", f"says {W}x{H}")


def test_principal_point_outside_image(ds_root):
    _edit_manifest(ds_root, lambda m: m["cameras"]["c0"]["K"][0].__setitem__(2, 5.0 * W))
    _expect(ds_root, "camera 'c0'", "principal point")


def test_vertex_count_mismatch(ds_root):
    np.save(ds_root / "vertices.npy", np.zeros((3, 5, 3), np.float32))
    _expect(ds_root, "vertices.npy", "vertex count mismatch: 5 posed vertices", "canonical mesh has 4")


def test_nan_vertices(ds_root):
    v = np.load(ds_root / "vertices.npy")
    v[1, 2, 0] = np.nan
    v[1, 3, 1] = np.inf
    np.save(ds_root / "vertices.npy", v)
    _expect(ds_root, "frame 1 ('000001')", "2 NaN/Inf values")


def test_non_rotation_extrinsics(ds_root):
    _edit_manifest(ds_root, lambda m: m["cameras"]["c0"]["viewmat"][0].__setitem__(0, 2.0))
    _expect(ds_root, "camera 'c0'", "not a rotation matrix")


def test_absurd_extrinsics_are_named_without_a_numpy_warning(ds_root):
    """Entries too large to square (the fuzz test found 1e200): the same one line, no overflow warning beside it."""
    _edit_manifest(ds_root, lambda m: m["cameras"]["c0"]["viewmat"][1].__setitem__(2, 1e200))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning would fail here
        _expect(ds_root, "camera 'c0'", "not a rotation matrix")


def test_reflection_extrinsics(ds_root):
    _edit_manifest(ds_root, lambda m: m["cameras"]["c0"]["viewmat"][0].__setitem__(0, -1.0))
    _expect(ds_root, "camera 'c0'", "det(R) != +1")


def test_non_positive_focal(ds_root):
    _edit_manifest(ds_root, lambda m: m["cameras"]["c0"]["K"][1].__setitem__(1, 0.0))
    _expect(ds_root, "camera 'c0'", "non-positive focal length")


def test_empty_mask(ds_root):
    Image.new("L", (W, H)).save(ds_root / "masks" / "000000.png")
    _expect(ds_root, "the subject left the view in 1 of", "(empty masks: 000000.png)", "--drop-bad-frames")


def test_missing_mask_and_bad_split_reported_together(ds_root):
    (ds_root / "masks" / "000002.png").unlink()
    _edit_manifest(ds_root, lambda m: m["splits"].update(test_views=[7]))
    _expect(ds_root, "2 problems", "mask file masks/000002.png is missing", "split 'test_views'")


def test_missing_canonical(ds_root):
    (ds_root / "canonical.npz").unlink()
    _expect(ds_root, "canonical.npz", "canonical mesh file is missing")


def test_writer_rejects_bad_input(tmp_path):
    w = DatasetWriter(tmp_path / "x", VERTS, FACES)
    with pytest.raises(MeshsplatError, match="add_camera"):
        w.add_frame(np.zeros((H, W, 3)), "nope", vertices=VERTS)
    K, vm = _camera()
    w.add_camera(0, K, vm, W, H)
    with pytest.raises(MeshsplatError, match="vertices"):
        w.add_frame(np.zeros((H, W, 3)), 0, vertices=VERTS[:3])
    with pytest.raises(MeshsplatError, match="image"):
        w.add_frame(np.zeros((H + 1, W, 3)), 0, vertices=VERTS)
    with pytest.raises(MeshsplatError, match="no frames"):
        w.close()
