"""Sizes checked before memory is spent (issue 52): npz arrays from their headers, images from theirs,
numbers in the config that do not fit; each refusal one MeshsplatError line, and what fits still reads
exactly."""

from __future__ import annotations

import io
import json
import re
import struct
import tracemalloc
import zipfile
import zlib

import numpy as np
import pytest

from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npy, read_npz
from meshsplat.io.images import MAX_PIXELS, image_size, read_image
from meshsplat.train.config import apply_overrides
from meshsplat.train.recipes import recipe_config


def _npy_bytes(shape, dtype, payload: bytes) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": tuple(shape)}
    )
    return buf.getvalue() + payload


def test_npz_that_unpacks_past_the_limit_is_refused_from_its_headers(tmp_path):
    path = tmp_path / "zeros.npz"
    np.savez_compressed(path, a=np.zeros(3_000_000, np.float32), b=np.ones(10))  # 12 MB unpacked
    assert path.stat().st_size < 100_000
    tracemalloc.start()
    with pytest.raises(MeshsplatError, match=r"zeros.npz: its arrays would take more than .* \(at most 0.0 GB"):
        read_npz(path, limit=1_000_000)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 2_000_000  # nothing near the 12 MB was allocated
    got = read_npz(path)  # under the default limit: the values, exactly
    assert got["a"].shape == (3_000_000,) and not got["a"].any() and (got["b"] == 1).all()


def test_npz_whose_header_promises_more_than_it_holds_is_refused(tmp_path):
    path = tmp_path / "forged.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("verts.npy", _npy_bytes((10**9, 3), "<f4", b"\0" * 48))
    tracemalloc.start()
    with pytest.raises(MeshsplatError, match=r"array 'verts' claims 12.0 GB but its member holds \d+ bytes"):
        read_npz(path, what="meshes")
    assert tracemalloc.get_traced_memory()[1] < 10_000_000
    tracemalloc.stop()


def test_npy_whose_header_promises_more_than_the_file_is_refused(tmp_path):
    path = tmp_path / "forged.npy"
    path.write_bytes(_npy_bytes((10**9,), "<f8", b"\0" * 64))
    with pytest.raises(MeshsplatError, match=r"forged.npy: its header claims 8.0 GB but the file holds"):
        read_npy(path)
    ok = tmp_path / "ok.npy"
    np.save(ok, np.arange(12.0).reshape(3, 4))
    assert (read_npy(ok) == np.arange(12.0).reshape(3, 4)).all()
    with pytest.raises(MeshsplatError, match=r"would take 0.0 GB of memory"):
        read_npy(ok, limit=8)
    assert (read_npy(ok, mmap=True, limit=8) == np.arange(12.0).reshape(3, 4)).all()  # mapped: not in memory


def _png_header_only(path, width: int, height: int) -> None:
    """A PNG whose IHDR says ``width`` x ``height`` with one empty IDAT (a few dozen bytes)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize("side", [9000, 20000])
def test_huge_image_dimensions_are_refused_before_decoding(tmp_path, side):
    path = tmp_path / "huge.png"
    _png_header_only(path, side, side)
    assert side * side > MAX_PIXELS
    assert image_size(path) == (side, side)  # the header alone answers the size
    for channels in (1, 3, 4):
        tracemalloc.start()
        with pytest.raises(MeshsplatError, match=r"huge.png: .*larger than meshsplat decodes"):
            read_image(path, channels)
        assert tracemalloc.get_traced_memory()[1] < 50_000_000
        tracemalloc.stop()


def test_an_image_at_the_limit_still_decodes_exactly(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (64, 48, 3), dtype=np.uint8)
    Image.fromarray(img).save(tmp_path / "ok.png")
    assert (read_image(tmp_path / "ok.png", 3) == img).all()


@pytest.mark.parametrize(
    "override, message",
    [
        ("iterations=1e999", "iterations expects int, got '1e999'"),
        ("iterations=inf", "iterations expects int"),
        ("iterations=2.5e0", "iterations expects int, got '2.5e0'"),
        ("model.n_init=1e999", "model.n_init expects int"),
        ("seed=99999999999999999999999999", "seed must fit in 63 bits"),
        ("iterations=1e18", "iterations must be <= 10,000,000"),
    ],
)
def test_numbers_that_do_not_fit_are_one_line(override, message):
    with pytest.raises(MeshsplatError, match=re.escape(message)):
        apply_overrides(recipe_config("quality"), [override]).validate()


def test_whole_numbers_written_with_an_exponent_still_read():
    cfg = apply_overrides(recipe_config("quality"), ["iterations=3e4", "seed=12"]).validate()
    assert (cfg.iterations, cfg.seed) == (30000, 12)


def test_synth_poses_again_instead_of_keeping_every_pose_and_writes_the_same_capture(tmp_path, monkeypatch):
    """A long capture (``--frames 20000``) no longer keeps every posed mesh between planning and rendering
    (12 GB at 64 px before): past ``_POSE_CACHE_BYTES`` the poses are computed again, to the same bytes."""
    from meshsplat.synth import generate, synthesize

    opts = {"frames": 5, "resolution": 24, "test_views": 1, "test_frames": 2, "progress": False}
    kept = synthesize("CesiumMan", tmp_path / "kept", **opts)
    monkeypatch.setattr(generate, "_POSE_CACHE_BYTES", 0)
    posed_again = synthesize("CesiumMan", tmp_path / "again", **opts)
    files = sorted(p.relative_to(kept) for p in kept.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(posed_again) for p in posed_again.rglob("*") if p.is_file())
    for rel in files:
        if rel.name == "manifest.json":
            a, b = (json.loads((root / rel).read_text()) for root in (kept, posed_again))
            for m in (a, b):
                m["meta"].pop("seconds", None), m["meta"].pop("seconds_per_frame", None)
            assert a == b
        else:
            assert (kept / rel).read_bytes() == (posed_again / rel).read_bytes(), rel


def test_deeply_nested_json_is_one_line(tmp_path):
    from meshsplat.data import open_dataset
    from meshsplat.io.json_file import read_json_object

    deep = "[" * 200_000 + "]" * 200_000
    (tmp_path / "cameras.json").write_text(deep)
    with pytest.raises(MeshsplatError, match=r"cameras\.json: nested too deeply"):
        read_json_object(tmp_path / "cameras.json")
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "manifest.json").write_text('{"frames": ' + deep + "}")
    with pytest.raises(MeshsplatError, match=r"manifest\.json: nested too deeply"):
        open_dataset(tmp_path / "ds")


def test_the_dataset_writer_streams_meshes_to_the_bytes_np_save_writes(tmp_path):
    from meshsplat.data.writer import DatasetWriter

    rng = np.random.default_rng(3)
    canonical = rng.normal(size=(7, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6]])
    meshes = [canonical + rng.normal(scale=0.1, size=(7, 3)).astype(np.float32) for _ in range(5)]
    w = DatasetWriter(tmp_path / "ds", canonical, faces)
    w.add_camera("c", np.array([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]), np.eye(4), 16, 16)
    for m in meshes:
        w.add_frame(np.zeros((16, 16, 3), np.uint8), "c", vertices=m)
    w.add_frame(np.zeros((16, 16, 3), np.uint8), "c", mesh=2)  # a shared mesh adds no row
    w.close()
    np.save(tmp_path / "ref.npy", np.stack(meshes).astype(np.float32))
    assert (tmp_path / "ds" / "vertices.npy").read_bytes() == (tmp_path / "ref.npy").read_bytes()
    assert not (tmp_path / "ds" / ".vertices.npy.partial").exists()
