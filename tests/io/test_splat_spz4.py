"""SPZ version 4 (zstd streams, what the spz library and splat-transform write by default) read by
``read_spz``, and the glTF ``COLOR_0`` fallback in linear RGB (docs/viewer.md, splat export formats)."""

from __future__ import annotations

import gzip
import struct
import subprocess
import sys

import numpy as np
import pytest

from _splat_kit import _align, _gaussians, _node_tool, _pinned, _same_rotation, _sigmoid
from meshsplat.errors import MeshsplatError
from meshsplat.io.ply import read_gaussian_ply, write_gaussian_ply
from meshsplat.io.splat_formats import read_spz, write_gltf_splats, write_spz

zstandard = pytest.importorskip("zstandard")


def _v4_from_v3(v3: bytes, extension: bytes = b"") -> bytes:
    """A version 4 file holding the arrays of a version 3 payload: the layout of the SPZ specification
    (32-byte header, optional extension records, table of contents, one zstd stream per array)."""
    data = gzip.decompress(v3)
    _, _, n, degree, frac, flags, _ = struct.unpack_from("<IIIBBBB", data)
    k = (degree + 1) ** 2 - 1
    sizes, off, streams = [9 * n, n, 3 * n, 3 * n, 4 * n, 3 * k * n], 16, []
    for s in sizes:
        streams.append(data[off : off + s])
        off += s
    packed = [zstandard.ZstdCompressor(level=3).compress(s) for s in streams]
    toc_at = 32 + len(extension)
    head = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, n, degree, frac, flags | (2 if extension else 0), 6, toc_at)
    toc = b"".join(struct.pack("<QQ", len(p), len(s)) for p, s in zip(packed, streams, strict=True))
    return head + extension + toc + b"".join(packed)


@pytest.mark.parametrize("k", [0, 3, 15])
def test_spz_v4_reads_as_the_same_arrays(tmp_path, k):
    g = _gaussians(n=120, k=k)
    v3 = write_spz(tmp_path / "a.spz", g)
    want = read_spz(v3)
    for ext in (b"", struct.pack("<II", 0xADBE0001, 8) + b"\x01" * 8):  # an unknown vendor record is skipped
        (tmp_path / "b.spz").write_bytes(_v4_from_v3(v3.read_bytes(), ext))
        got = read_spz(tmp_path / "b.spz")
        assert set(got) == set(want)
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=key)


def test_spz_v4_damage_is_named(tmp_path, monkeypatch):
    g = _gaussians(n=30, k=3)
    good = _v4_from_v3(write_spz(tmp_path / "a.spz", g).read_bytes())
    for name, raw, words in (
        ("short", good[:20], "header is truncated"),
        ("cut", good[:-10], "truncated"),
        ("toc", good[:16] + struct.pack("<I", 10**6) + good[20:], "table of contents"),
    ):
        (tmp_path / f"{name}.spz").write_bytes(raw)
        with pytest.raises(MeshsplatError, match=words):
            read_spz(tmp_path / f"{name}.spz")
    (tmp_path / "ok.spz").write_bytes(good)
    monkeypatch.setitem(sys.modules, "zstandard", None)  # not installed
    with pytest.raises(MeshsplatError, match=r"pip install 'meshsplat\[spz\]'"):
        read_spz(tmp_path / "ok.spz")


def test_splat_transform_spz_v4_reads_back(tmp_path):
    """The pinned splat-transform writes SPZ version 4; read_spz reads its file: the PLY's values within
    the format's quantization."""
    cli = _node_tool(".bin/splat-transform")
    assert _pinned("@playcanvas/splat-transform") == "3.10.2"
    import torch

    g = _gaussians(n=200, k=8)
    t = {k: torch.from_numpy(v).float() for k, v in g.items()}
    ply = write_gaussian_ply(
        tmp_path / "a.ply", t["means"], t["quats"], t["log_scales"], t["opacity_logits"], t["sh0"], t["shN"]
    )
    out = tmp_path / "st.spz"
    r = subprocess.run([str(cli), "-w", str(ply), str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    raw = out.read_bytes()
    assert raw[:4] == b"NGSP" and struct.unpack_from("<I", raw, 4)[0] == 4  # version 4, not gzip
    back = read_spz(out)
    src = {k: v.double().numpy() for k, v in read_gaussian_ply(ply).items()}
    src["sh0"] = src["sh0"].reshape(-1, 3)
    idx = _align(back, src)
    np.testing.assert_allclose(back["means"], src["means"][idx], atol=2e-3)
    np.testing.assert_allclose(back["log_scales"], src["log_scales"][idx], atol=0.5 / 16 + 1e-6)
    np.testing.assert_allclose(back["sh0"], src["sh0"][idx], atol=0.5 / (0.15 * 255) + 1e-6)
    np.testing.assert_allclose(_sigmoid(back["opacity_logits"]), _sigmoid(src["opacity_logits"][idx]), atol=3e-3)
    np.testing.assert_allclose(back["shN"][:, :8], src["shN"][idx][:, :8], atol=8.5 / 128 + 1e-6)
    _same_rotation(back["quats"], src["quats"][idx] / np.linalg.norm(src["quats"][idx], axis=1, keepdims=True), 0.02)


def test_gltf_color_0_is_linear(tmp_path):
    """glTF vertex colours are linear RGB: the fallback holds the DC colour through the sRGB curve."""
    import pygltflib

    g = _gaussians(n=40, k=0)
    g["sh0"][:3] = (np.array([[0.5, 0.0214, 1.0], [0.0, 0.04, 0.2], [0.8, 0.6, 0.3]]) - 0.5) / 0.28209479177387814
    doc = pygltflib.GLTF2().load(str(write_gltf_splats(tmp_path / "a.glb", g)))
    acc = doc.accessors[doc.meshes[0].primitives[0].attributes.COLOR_0]
    col = np.frombuffer(doc.binary_blob(), "<f4", 4 * acc.count, doc.bufferViews[acc.bufferView].byteOffset)
    col = col.reshape(-1, 4)
    np.testing.assert_allclose(col[0, :3], [0.21404114, 0.0214 / 12.92, 1.0], rtol=1e-5)
    display = np.clip(0.5 + 0.28209479177387814 * g["sh0"], 0, 1)
    back = np.where(col[:, :3] <= 0.0031308, 12.92 * col[:, :3], 1.055 * col[:, :3] ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(back, display, atol=2e-6)  # the inverse curve gives the display colour back
    np.testing.assert_allclose(col[:, 3], _sigmoid(g["opacity_logits"]), atol=1e-7)
