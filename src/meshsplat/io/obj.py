"""Triangle-mesh Wavefront OBJ: vertices, faces and optional texture coordinates.

The reader is strict: it accepts ``v``, ``vt``, ``f`` (``a``, ``a/t``, ``a/t/n``, ``a//n``,
negative relative indices) and ignores normals, groups, objects, smoothing, materials
and comments. Polygons are rejected unless ``triangulate=True`` (fan triangulation).
Errors name the file and line.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError

__all__ = ["ObjMesh", "read_obj", "write_obj"]

_IGNORED = {"vn", "vp", "g", "o", "s", "usemtl", "mtllib", "l", "p", "#"}


@dataclass
class ObjMesh:
    """``vertices [V,3] float32``, ``faces [F,3] long``; ``uvs [T,2]`` and ``face_uvs [F,3]`` or None."""

    vertices: torch.Tensor
    faces: torch.Tensor
    uvs: torch.Tensor | None = None
    face_uvs: torch.Tensor | None = None


def write_obj(
    path: str | os.PathLike,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    uvs: torch.Tensor | None = None,
    face_uvs: torch.Tensor | None = None,
) -> Path:
    """Write ``vertices [V,3]``, ``faces [F,3]`` (0-based) and optional ``uvs [T,2]`` with ``face_uvs [F,3]``."""
    dims: dict[str, int] = {}
    check_tensor("vertices", vertices, "V,3", dims, dtype="float", finite=True)
    check_tensor("faces", faces, "F,3", dims, dtype="int")
    if (uvs is None) != (face_uvs is None):
        raise MeshsplatError("uvs and face_uvs: give both or neither")
    v = vertices.detach().cpu().double().numpy()
    f = faces.detach().cpu().long().numpy()
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise MeshsplatError(f"faces: indices must lie in [0, {len(v) - 1}], got [{f.min()}, {f.max()}]")
    lines = [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in v]
    if uvs is not None:
        check_tensor("uvs", uvs, "T,2", dims, dtype="float", finite=True)
        check_tensor("face_uvs", face_uvs, "F,3", dims, dtype="int")
        assert face_uvs is not None  # check_tensor rejects None
        t = uvs.detach().cpu().double().numpy()
        ft = face_uvs.detach().cpu().long().numpy()
        if ft.size and (ft.min() < 0 or ft.max() >= len(t)):
            raise MeshsplatError(f"face_uvs: indices must lie in [0, {len(t) - 1}]")
        lines += [f"vt {a:.9g} {b:.9g}" for a, b in t]
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip(f + 1, ft + 1, strict=True)]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in f + 1]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("# meshsplat\n" + "\n".join(lines) + "\n")
    return path


def _index(tok: str, count: int, kind: str, where: str) -> int:
    try:
        i = int(tok)
    except ValueError:
        raise MeshsplatError(f"{where}: bad {kind} index {tok!r}") from None
    j = i - 1 if i > 0 else count + i
    if i == 0 or not 0 <= j < count:
        raise MeshsplatError(f"{where}: {kind} index {i} out of range (have {count})")
    return j


def read_obj(path: str | os.PathLike, triangulate: bool = False) -> ObjMesh:
    """Read a triangle mesh; see the module docstring for what is accepted."""
    path = Path(path)
    if not path.is_file():
        raise MeshsplatError(f"OBJ file {str(path)!r} not found")
    verts: list[list[float]] = []
    tex: list[list[float]] = []
    faces: list[list[int]] = []
    ftex: list[list[int]] = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, raw in enumerate(fh, 1):
            where = f"{path.name}:{lineno}"
            parts = raw.split("#", 1)[0].split()
            if not parts:
                continue
            key, args = parts[0], parts[1:]
            if key == "v":
                if len(args) not in (3, 4, 6, 7):
                    raise MeshsplatError(f"{where}: vertex needs 3 coordinates, got {raw.strip()!r}")
                try:
                    verts.append([float(a) for a in args[:3]])
                except ValueError:
                    raise MeshsplatError(f"{where}: bad vertex {raw.strip()!r}") from None
            elif key == "vt":
                if len(args) < 2:
                    raise MeshsplatError(f"{where}: texture coordinate needs 2 values, got {raw.strip()!r}")
                try:
                    tex.append([float(a) for a in args[:2]])
                except ValueError:
                    raise MeshsplatError(f"{where}: bad texture coordinate {raw.strip()!r}") from None
            elif key == "f":
                if len(args) < 3:
                    raise MeshsplatError(f"{where}: face needs at least 3 vertices, got {raw.strip()!r}")
                if len(args) > 3 and not triangulate:
                    raise MeshsplatError(
                        f"{where}: face has {len(args)} vertices; only triangles are accepted (pass triangulate=True)"
                    )
                vi, ti = [], []
                for a in args:
                    sub = a.split("/")
                    vi.append(_index(sub[0], len(verts), "vertex", where))
                    if len(sub) > 1 and sub[1]:
                        ti.append(_index(sub[1], len(tex), "texture", where))
                if ti and len(ti) != len(vi):
                    raise MeshsplatError(f"{where}: texture indices on some corners only")
                for j in range(1, len(vi) - 1):
                    faces.append([vi[0], vi[j], vi[j + 1]])
                    ftex.append([ti[0], ti[j], ti[j + 1]] if ti else [])
            elif key not in _IGNORED:
                raise MeshsplatError(f"{where}: unsupported OBJ statement {key!r}")
    if not verts or not faces:
        raise MeshsplatError(
            f"{str(path)!r}: OBJ has {len(verts)} vertices and {len(faces)} faces; need at least one of each"
        )
    vertices = torch.from_numpy(np.asarray(verts, np.float32))
    if not bool(torch.isfinite(vertices).all()):
        raise MeshsplatError(f"{str(path)!r}: vertices contain NaN/Inf")
    faces_t = torch.tensor(faces, dtype=torch.long)
    uvs = face_uvs = None
    with_tex = [bool(t) for t in ftex]
    if any(with_tex):
        if not all(with_tex):
            raise MeshsplatError(f"{str(path)!r}: texture indices on some faces only")
        uvs = torch.from_numpy(np.asarray(tex, np.float32))
        face_uvs = torch.tensor(ftex, dtype=torch.long)
    return ObjMesh(vertices, faces_t, uvs, face_uvs)
