"""The small helpers with one home each: output folder rule, float image -> uint8, bbox diagonal, JSON object."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.io.images import float_to_uint8, read_image, write_png
from meshsplat.io.json_file import read_json_object
from meshsplat.io.out_folder import empty_or_new_folder
from meshsplat.mesh import TriMesh, bbox_diagonal


def test_output_folder_new_empty_or_overwrite(tmp_path):
    assert empty_or_new_folder(tmp_path / "new") == tmp_path / "new"
    assert not (tmp_path / "new").exists()  # nothing is created
    (tmp_path / "empty").mkdir()
    assert empty_or_new_folder(str(tmp_path / "empty")) == tmp_path / "empty"
    full = tmp_path / "full"
    full.mkdir()
    (full / "x.txt").write_text("keep me")
    with pytest.raises(MeshsplatError, match=r"exists and is not empty.*--overwrite") as e:
        empty_or_new_folder(full)
    assert "\n" not in str(e.value)
    assert empty_or_new_folder(full, overwrite=True) == full
    assert (full / "x.txt").read_text() == "keep me"
    (tmp_path / "file").write_text("")
    for overwrite in (False, True):
        with pytest.raises(MeshsplatError, match="is a file, not a folder"):
            empty_or_new_folder(tmp_path / "file", overwrite)


def test_float_to_uint8_rounds_half_to_even_and_clamps():
    x = np.array([-0.5, 0.0, 0.5 / 255, 1.5 / 255, 2.5 / 255, 0.5, 1.0, 1.7], np.float32)
    expected = np.rint(np.clip(x, 0, 1) * np.float32(255)).astype(np.uint8)
    got = float_to_uint8(x)
    assert got.dtype == np.uint8 and got.shape == x.shape
    np.testing.assert_array_equal(got, expected)
    assert got[0] == 0 and got[-1] == 255 and got[-2] == 255
    # exact ties in float32: k + 0.5 goes to the even neighbour
    ties = (np.arange(0, 254, dtype=np.float32) + 0.5) / np.float32(255)
    scaled = ties * np.float32(255)
    exact = scaled == np.arange(0, 254, dtype=np.float32) + 0.5
    assert exact.any()
    np.testing.assert_array_equal(float_to_uint8(ties)[exact], np.rint(scaled[exact]).astype(np.uint8))
    # tensors (with grad, any device) and arrays agree; uint8 passes through untouched
    t = torch.rand(5, 7, 3, requires_grad=True)
    np.testing.assert_array_equal(float_to_uint8(t), float_to_uint8(t.detach().numpy()))
    u = np.arange(256, dtype=np.uint8)
    assert float_to_uint8(u) is u


def test_float_to_uint8_round_trips_an_8bit_image(tmp_path):
    u = np.random.default_rng(0).integers(0, 256, (9, 11, 3), dtype=np.uint8)
    write_png(tmp_path / "a.png", u)
    back = read_image(tmp_path / "a.png", 3).astype(np.float32) / 255.0
    np.testing.assert_array_equal(float_to_uint8(back), u)


def test_float_to_uint8_refuses_nan_and_non_images():
    with pytest.raises(MeshsplatError, match="NaN/Inf"):
        float_to_uint8(np.array([0.5, np.nan], np.float32))
    with pytest.raises(MeshsplatError, match="expected float in \\[0, 1\\] or uint8, got int64"):
        float_to_uint8(np.array([1, 2]))


def test_bbox_diagonal_torch_numpy_and_trimesh():
    v = torch.tensor([[0.0, 0.0, 0.0], [3.0, -4.0, 0.0], [1.0, 1.0, 12.0]])
    # box 3 x 5 x 12 -> diagonal sqrt(9 + 25 + 144)
    assert bbox_diagonal(v) == pytest.approx(float(np.sqrt(178.0)))
    assert bbox_diagonal(v.numpy().astype(np.float64)) == pytest.approx(float(np.sqrt(178.0)), rel=1e-15)
    mesh = TriMesh(v, torch.tensor([[0, 1, 2]]))
    assert mesh.bbox_diagonal() == bbox_diagonal(v)
    # each path keeps its caller's precision: float32 torch equals the inline float32 formula bit for bit
    r = torch.randn(1000, 3)
    assert bbox_diagonal(r) == float((r.amax(0) - r.amin(0)).norm())
    a = r.numpy().astype(np.float64)
    assert bbox_diagonal(a) == float(np.linalg.norm(a.max(0) - a.min(0)))
    assert bbox_diagonal(torch.zeros(4, 3)) == 0.0


def test_read_json_object(tmp_path):
    p = tmp_path / "a.json"
    p.write_text('{"x": 1}')
    assert read_json_object(p) == {"x": 1}
    with pytest.raises(MeshsplatError, match=r"missing\.json: file not found"):
        read_json_object(tmp_path / "missing.json")
    p.write_text('{"x": ')
    with pytest.raises(MeshsplatError, match=r"a\.json: not valid JSON") as e:
        read_json_object(p)
    assert "\n" not in str(e.value)
    p.write_bytes(b"\xff\xfe{")
    with pytest.raises(MeshsplatError, match="not valid JSON"):
        read_json_object(p)
    p.write_text("[1, 2]")
    with pytest.raises(MeshsplatError, match=r"a\.json: expected a run config, got list"):
        read_json_object(p, "a run config")


def test_check_finite_finds_every_nan_and_inf_and_passes_sums_that_overflow():
    from meshsplat._checks import check_finite

    big = torch.full((4, 3), 3e38)  # finite, but their sum overflows to inf: the exact check clears it
    assert check_finite("big", big) is big
    for bad, count in ((float("nan"), 1), (float("inf"), 1), (-float("inf"), 1)):
        x = torch.zeros(5, 3)
        x[2, 1] = bad
        with pytest.raises(MeshsplatError, match=f"x: contains {count} NaN/Inf values"):
            check_finite("x", x)
    both = torch.tensor([float("inf"), -float("inf"), 1.0])  # inf - inf sums to nan: still found, both counted
    with pytest.raises(MeshsplatError, match="contains 2 NaN/Inf"):
        check_finite("both", both)
    assert check_finite("ints", torch.arange(3)) is not None and check_finite("empty", torch.zeros(0, 3)).numel() == 0
