"""`meshsplat import`: any capture layout -> native (PNG images and masks, meshes, splits, driver parameters),
and `meshsplat synth SOURCE --format NAME`."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _peoplesnapshot import EXTRINSIC, H, K, W, make_capture
from meshsplat.cli.main import main
from meshsplat.data import DatasetWriter, open_dataset
from meshsplat.data.convert import write_native
from meshsplat.data.formats import open_capture
from meshsplat.drivers.body_models import BodyModel
from meshsplat.errors import MeshsplatError


def _assert_same(a, b, mask_equal=True):
    assert len(a) == len(b)
    assert a.split_names == b.split_names
    for s in a.split_names:
        assert a.split(s) == b.split(s)
    assert a.camera_ids == b.camera_ids
    for cid in a.camera_ids:
        x, y = a.camera(cid), b.camera(cid)
        assert torch.allclose(x.K, y.K) and torch.allclose(x.viewmat, y.viewmat)
        assert (x.width, x.height) == (y.width, y.height)
    assert torch.equal(a.canonical_vertices, b.canonical_vertices) and torch.equal(a.faces, b.faces)
    for i in range(len(a)):
        fa, fb = a[i], b[i]
        assert torch.equal(fa.vertices, fb.vertices)
        assert torch.equal(fa.image, fb.image)
        assert (fa.mask is None) == (fb.mask is None)
        if fa.mask is not None and mask_equal:
            assert torch.equal(fa.mask, fb.mask)


def test_import_peoplesnapshot_keeps_everything(tmp_path, standin_model_dir, capsys):
    n = 6
    rng = np.random.default_rng(0)
    thetas = rng.normal(0, 0.2, (n, 72))
    transl = rng.normal(0, 0.1, (n, 3))
    root = make_capture(
        tmp_path / "cap",
        n=n,
        masks="npy",
        thetas=thetas,
        transl=transl,
        gender="female",
        betas=rng.normal(0, 0.5, (1, 10)),
    )
    out = tmp_path / "native"
    assert main(["import", str(root), "--out", str(out), "--model-dir", str(standin_model_dir)]) == 0
    printed = capsys.readouterr().out
    assert "format: peoplesnapshot (detected)" in printed and "driver: smpl" in printed
    src = open_capture(root, model_dir=standin_model_dir)
    nat = open_dataset(out)
    _assert_same(src, nat)
    assert nat.format_name == "native" and nat.meta["source_format"] == "peoplesnapshot"
    assert all(nat.frame_info(i)["mask"].endswith(".png") for i in range(len(nat)))  # npy masks became PNG
    assert set(np.unique(np.asarray(nat[0].mask))) == {0.0, 1.0}
    assert nat.driver_info["type"] == "smpl" and nat.driver_info["gender"] == "female"
    assert sorted(nat.driver_info["per_frame"]) == ["body_pose", "global_orient", "transl"]
    for i in range(len(nat)):
        for k, v in src.frame_params(i).items():
            assert np.allclose(v, nat.frame_params(i)[k])
    assert nat.frame_info(2)["frame_index"] == 2  # extra record keys are kept
    # the stored parameters reproduce the stored meshes
    model = BodyModel("smpl", standin_model_dir, gender="female")
    with torch.no_grad():
        v = model.forward(nat.frame_params(3)).vertices[0]
    assert torch.allclose(v, nat.vertices(3), atol=1e-5)


def test_import_native_round_trip_and_alpha_masks(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    w = DatasetWriter(tmp_path / "a", v, np.array([[0, 1, 2]]), meta={"note": "x"})
    w.add_camera("cam/0", K, EXTRINSIC, W, H)
    rng = np.random.default_rng(1)
    for k in range(3):
        m = np.zeros((H, W), np.uint8)
        m[5:20, 5 + k : 30] = 200
        w.add_frame(
            rng.integers(0, 255, (H, W, 3), dtype=np.uint8),
            "cam/0",
            vertices=v + 0.1 * k,
            mask=m,
            name=f"f:{k}",
            clip="c",
            time=0.5 * k,
        )
    w.set_split("test_frames", [2])
    src = open_dataset(w.close())
    out = write_native(src, tmp_path / "b")
    back = open_dataset(out)
    _assert_same(src, back)
    assert back.frame_info(1)["name"] == "f_1" and back[1].time == 0.5 and back[1].clip == "c"
    with pytest.raises(MeshsplatError, match="exists and is not empty"):
        write_native(src, out)
    with pytest.raises(MeshsplatError, match="capture folder itself"):
        write_native(src, src.root, overwrite=True)


def test_import_cli_errors(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["import", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a capture layout meshsplat reads" in err[0]
    root = make_capture(tmp_path / "cap", n=3)
    assert (
        main(
            [
                "import",
                str(root),
                "--format",
                "peoplesnapshot",
                "--out",
                str(tmp_path / "o"),
                "--model-dir",
                str(tmp_path / "nowhere"),
            ]
        )
        == 2
    )
    assert "model directory" in capsys.readouterr().err


def test_synth_cli_peoplesnapshot_then_import(tmp_path, standin_model_dir, capsys):
    ps_dir, nat_dir = tmp_path / "ps", tmp_path / "nat"
    assert (
        main(
            [
                "synth",
                "smpl",
                "--format",
                "peoplesnapshot",
                "--out",
                str(ps_dir),
                "--model-dir",
                str(standin_model_dir),
                "--gender",
                "male",
                "--frames",
                "3",
                "--resolution",
                "48",
                "--test-frames",
                "2",
                "--test-views",
                "0",
                "--masks",
                "npy",
                "--native-out",
                str(tmp_path / "n0"),
            ]
        )
        == 0
    )
    assert "peoplesnapshot capture written" in capsys.readouterr().out
    assert sorted(p.name for p in (ps_dir / "masks").iterdir())[0] == "mask_0000.npy"
    assert main(["import", str(ps_dir), "--out", str(nat_dir), "--model-dir", str(standin_model_dir)]) == 0
    nat, n0 = open_dataset(nat_dir), open_dataset(tmp_path / "n0")
    assert nat.driver_info["gender"] == "male" and len(nat) == 5
    for i in range(len(nat)):
        assert (nat.vertices(i) - n0.vertices(i)).abs().max() < 1e-5
    assert main(["synth", "smpl", "--format", "native", "--masks", "npy", "--out", str(tmp_path / "x")]) == 2


def test_a_file_given_for_the_capture_folder_is_named_as_a_file(tmp_path):
    """A file where the capture folder should be is not "not found" (it is there): one line saying what it is."""
    f = tmp_path / "capture.zip"
    f.write_bytes(b"PK")
    with pytest.raises(MeshsplatError, match=r"capture\.zip is a file, not a capture folder") as err:
        open_capture(f)
    assert "\n" not in str(err.value)
    with pytest.raises(MeshsplatError, match=r"capture folder not found: .*nothing_here"):
        open_capture(tmp_path / "nothing_here")
