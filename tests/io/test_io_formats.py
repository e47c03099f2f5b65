"""3DGS .ply, embedding JSON and OBJ: exact round trips and clear errors."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from meshsplat.errors import MeshsplatError
from meshsplat.io import (
    read_embedding_json,
    read_gaussian_ply,
    read_obj,
    write_embedding_json,
    write_gaussian_ply,
    write_obj,
)
from meshsplat.io.ply import gaussian_ply_fields


def _gaussians(n=6, k=3):
    g = torch.Generator().manual_seed(1)
    return dict(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 4,
        opacity_logits=torch.randn(n, generator=g),
        sh0=torch.randn(n, 1, 3, generator=g),
        shN=torch.randn(n, k, 3, generator=g),
    )


def _header(path):
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].decode().splitlines(), raw[end:]


def test_ply_round_trip_with_padding(tmp_path):
    g = _gaussians(n=6, k=3)  # degree 1, padded to degree 3
    p = write_gaussian_ply(tmp_path / "a.ply", **g)
    lines, body = _header(p)
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 6"]
    names = [ln.split()[2] for ln in lines if ln.startswith("property")]
    assert names == gaussian_ply_fields(15) and len(names) == 62
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(body) == 6 * 62 * 4
    rows = np.frombuffer(body, "<f4").reshape(6, 62)
    # f_rest is channel-major: f_rest_0..14 red, 15..29 green, 30..44 blue.
    assert rows[2, 9 + 15 + 1] == g["shN"][2, 1, 1].item()  # green, coefficient 1
    assert rows[2, 9 + 30 + 2] == g["shN"][2, 2, 2].item()  # blue, coefficient 2
    assert np.all(rows[:, 9 + 3 : 9 + 15] == 0)  # red coefficients 3..14 padded
    back = read_gaussian_ply(p)
    for key in ("means", "quats", "log_scales", "opacity_logits", "sh0"):
        assert torch.equal(back[key], g[key]), key
    assert back["shN"].shape == (6, 15, 3)
    assert torch.equal(back["shN"][:, :3], g["shN"]) and not back["shN"][:, 3:].any()


def test_ply_degree0_without_padding_and_flat_sh0(tmp_path):
    g = _gaussians(n=4)
    p = write_gaussian_ply(
        tmp_path / "b.ply",
        g["means"],
        g["quats"],
        g["log_scales"],
        g["opacity_logits"],
        g["sh0"][:, 0],
        None,
        sh_degree_pad=None,
    )
    back = read_gaussian_ply(p)
    assert back["shN"].shape == (4, 0, 3) and torch.equal(back["sh0"], g["sh0"])
    p3 = write_gaussian_ply(tmp_path / "c.ply", g["means"], g["quats"], g["log_scales"], g["opacity_logits"], g["sh0"])
    assert read_gaussian_ply(p3)["shN"].shape == (4, 15, 3)


def test_ply_errors(tmp_path):
    g = _gaussians(n=4)
    with pytest.raises(MeshsplatError, match="quats"):
        write_gaussian_ply(
            tmp_path / "x.ply", g["means"], g["quats"][:3], g["log_scales"], g["opacity_logits"], g["sh0"]
        )
    with pytest.raises(MeshsplatError, match="more than degree 0"):
        write_gaussian_ply(tmp_path / "x.ply", **g, sh_degree_pad=0)
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(MeshsplatError, match="binary_little_endian"):
        read_gaussian_ply(ascii_ply)
    good = write_gaussian_ply(tmp_path / "g.ply", **g)
    trunc = tmp_path / "t.ply"
    trunc.write_bytes(good.read_bytes()[:-10])
    with pytest.raises(MeshsplatError, match="truncated"):
        read_gaussian_ply(trunc)
    mesh = tmp_path / "mesh.ply"
    mesh.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + np.zeros(3, "<f4").tobytes()
    )
    with pytest.raises(MeshsplatError, match="not a Gaussian PLY"):
        read_gaussian_ply(mesh)
    with pytest.raises(MeshsplatError, match="not found"):
        read_gaussian_ply(tmp_path / "none.ply")


def _params(n=5, k=0):
    g = torch.Generator().manual_seed(2)
    p = dict(
        face=torch.randint(0, 100, (n,), generator=g),
        uv=torch.rand(n, 2, generator=g) * 0.5,
        d=torch.randn(n, generator=g) * 1e-3,
        rotation=torch.randn(n, 4, generator=g),
        log_scale=torch.randn(n, 3, generator=g) - 5,
        opacity_logit=torch.randn(n, generator=g),
        sh0=torch.randn(n, 1, 3, generator=g),
    )
    if k:
        p["shN"] = torch.randn(n, k, 3, generator=g)
    return p


@pytest.mark.parametrize("encoding", ["base64", "list"])
def test_embedding_json_round_trip_exact(tmp_path, encoding):
    p = _params(n=7, k=3)
    p["duv"] = torch.randn(7, 2) * 1e-2
    path = write_embedding_json(tmp_path / "e.json", p, meta={"scale_mode": "sqrt_area"}, encoding=encoding)
    back, meta = read_embedding_json(path)
    assert meta == {"scale_mode": "sqrt_area", "sh_degree": 1}
    assert back["face"].dtype == torch.long and torch.equal(back["face"], p["face"])
    assert torch.equal(back["uv"], p["uv"] + p["duv"])  # effective uv, float32-exact
    for key in ("d", "rotation", "log_scale", "opacity_logit", "sh0", "shN"):
        assert back[key].dtype == torch.float32 and torch.equal(back[key], p[key]), key
    doc = json.loads(path.read_text())
    assert doc["format"] == "meshsplat-embedding" and doc["count"] == 7


def test_embedding_json_without_shn_and_errors(tmp_path):
    p = _params(n=3)
    p["sh0"] = p["sh0"][:, 0]  # [N,3] accepted
    back, meta = read_embedding_json(write_embedding_json(tmp_path / "a.json", p))
    assert back["shN"].shape == (3, 0, 3) and back["sh0"].shape == (3, 1, 3) and meta["sh_degree"] == 0
    bad = dict(p)
    del bad["d"]
    with pytest.raises(MeshsplatError, match="missing"):
        write_embedding_json(tmp_path / "b.json", bad)
    bad = dict(p, uv=torch.rand(4, 2))
    with pytest.raises(MeshsplatError, match="uv"):
        write_embedding_json(tmp_path / "b.json", bad)
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(MeshsplatError, match="not valid JSON"):
        read_embedding_json(tmp_path / "c.json")
    doc = json.loads((tmp_path / "a.json").read_text())
    doc["arrays"]["uv"]["data"] = doc["arrays"]["uv"]["data"][:-8]
    (tmp_path / "d.json").write_text(json.dumps(doc))
    with pytest.raises(MeshsplatError, match="uv"):
        read_embedding_json(tmp_path / "d.json")


def test_embedding_json_number_beyond_float32_is_one_error(tmp_path):
    """A list-encoded number beyond float32's range is refused by name, with no numpy warning on the way."""
    path = write_embedding_json(tmp_path / "e.json", _params(n=3), encoding="list")
    doc = json.loads(path.read_text())
    doc["arrays"]["d"]["data"][1] = 1e300
    path.write_text(json.dumps(doc))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(MeshsplatError, match=r"\bd: contains 1 NaN/Inf"):
            read_embedding_json(path)


def test_obj_round_trip(tmp_path):
    v = torch.randn(6, 3)
    f = torch.tensor([[0, 1, 2], [2, 3, 4], [4, 5, 0]])
    m = read_obj(write_obj(tmp_path / "a.obj", v, f))
    assert torch.equal(m.vertices, v) and torch.equal(m.faces, f) and m.uvs is None
    uv = torch.rand(4, 2)
    fuv = torch.tensor([[0, 1, 2], [1, 2, 3], [3, 0, 1]])
    m = read_obj(write_obj(tmp_path / "b.obj", v, f, uv, fuv))
    assert torch.equal(m.uvs, uv) and torch.equal(m.face_uvs, fuv)


@given(st.lists(st.floats(-1e6, 1e6, allow_nan=False, width=32), min_size=9, max_size=9))
def test_obj_vertices_float32_exact(tmp_path_factory, coords):
    v = torch.tensor(coords, dtype=torch.float32).view(3, 3)
    path = tmp_path_factory.mktemp("obj") / "h.obj"
    m = read_obj(write_obj(path, v, torch.tensor([[0, 1, 2]])))
    assert torch.equal(m.vertices, v)


def test_obj_reader_strictness(tmp_path):
    quad = tmp_path / "quad.obj"
    quad.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\ng body\nf 1//1 2//1 3//1 4//1\n")
    with pytest.raises(MeshsplatError, match=r"quad.obj:7: face has 4 vertices"):
        read_obj(quad)
    m = read_obj(quad, triangulate=True)
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    neg = tmp_path / "neg.obj"
    neg.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nf -3 -2 -1\n")
    assert read_obj(neg).faces.tolist() == [[0, 1, 2]]
    oor = tmp_path / "oor.obj"
    oor.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 4\n")
    with pytest.raises(MeshsplatError, match=r"oor.obj:4: vertex index 4 out of range"):
        read_obj(oor)
    junk = tmp_path / "junk.obj"
    junk.write_text("v 0 0 zero\n")
    with pytest.raises(MeshsplatError, match=r"junk.obj:1: bad vertex"):
        read_obj(junk)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(MeshsplatError, match="0 vertices"):
        read_obj(empty)
    with pytest.raises(MeshsplatError, match="faces"):
        write_obj(tmp_path / "bad.obj", torch.zeros(3, 3), torch.tensor([[0, 1, 3]]))
