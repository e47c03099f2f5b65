"""Triangle-mesh PLY reader (ascii, binary little/big endian): positions, optional colours and uvs.

Reads the ``vertex`` element (``x y z``; optional ``red green blue`` and ``s t`` / ``u v`` /
``texture_u texture_v``) and the ``face`` element's index list (polygons fan-triangulated).
Other elements and properties are skipped. Errors name the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from meshsplat.errors import MeshsplatError

__all__ = ["PlyMesh", "read_ply_mesh"]

_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass
class PlyMesh:
    """``vertices [V,3] float32``, ``faces [F,3] int64``; ``colors [V,3]`` in [0,1] and ``uvs [V,2]`` or None."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    uvs: np.ndarray | None = None


def _header(fh, path: Path):
    if fh.readline().strip() != b"ply":
        raise MeshsplatError(f"{path}: not a PLY file (no 'ply' magic line)")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str, Any, Any]]]] = []
    while True:
        line = fh.readline()
        if not line:
            raise MeshsplatError(f"{path}: PLY header has no 'end_header'")
        tok = line.decode("ascii", "replace").split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise MeshsplatError(f"{path}: PLY property before any element")
            if tok[1] == "list":
                elements[-1][2].append((tok[4], "list", tok[2], tok[3]))
            else:
                elements[-1][2].append((tok[2], tok[1], None, None))
        elif tok[0] == "end_header":
            break
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshsplatError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements


def _dtype(t: str, path: Path, order: str) -> np.dtype:
    if t not in _TYPES:
        raise MeshsplatError(f"{path}: unsupported PLY property type {t!r}")
    return np.dtype(order + _TYPES[t])


def read_ply_mesh(path: Path | str) -> PlyMesh:
    """Read a triangle (or polygon) mesh from a PLY file; see the module docstring."""
    path = Path(path)
    if not path.is_file():
        raise MeshsplatError(f"PLY file not found: {path}")
    with open(path, "rb") as fh:
        fmt, elements = _header(fh, path)
        order = ">" if fmt == "binary_big_endian" else "<"
        data: dict[str, dict] = {}
        tokens = iter(fh.read().split()) if fmt == "ascii" else None
        body = None if fmt == "ascii" else fh
        for name, count, props in elements:
            cols: dict[str, list] = {p[0]: [] for p in props}
            scalar = all(p[1] != "list" for p in props)
            if body is not None and scalar:  # fast path: one structured read
                dt = np.dtype([(p[0], _dtype(p[1], path, order)) for p in props])
                arr = np.frombuffer(body.read(dt.itemsize * count), dt, count=count)
                data[name] = {p[0]: arr[p[0]] for p in props}
                continue
            try:
                for _ in range(count):
                    for pname, ptype, ctype, itype in props:
                        if ptype == "list":
                            if tokens is not None:
                                n = int(next(tokens))
                                cols[pname].append([float(next(tokens)) for _ in range(n)])
                            else:
                                assert body is not None  # binary formats read from the file handle
                                cd, idt = _dtype(ctype, path, order), _dtype(itype, path, order)
                                n = int(np.frombuffer(body.read(cd.itemsize), cd)[0])
                                cols[pname].append(np.frombuffer(body.read(idt.itemsize * n), idt).tolist())
                        elif tokens is not None:
                            cols[pname].append(float(next(tokens)))
                        else:
                            assert body is not None  # binary formats read from the file handle
                            d = _dtype(ptype, path, order)
                            cols[pname].append(np.frombuffer(body.read(d.itemsize), d)[0])
            except (StopIteration, ValueError, IndexError):
                raise MeshsplatError(f"{path}: PLY data ends early or is malformed in element {name!r}") from None
            data[name] = cols
    v = data.get("vertex")
    f = data.get("face")
    if v is None or not all(k in v for k in "xyz") or f is None:
        raise MeshsplatError(f"{path}: PLY needs a 'vertex' element with x, y, z and a 'face' element")
    verts = np.stack([np.asarray(v[k], np.float64) for k in "xyz"], 1).astype(np.float32)
    lists = f.get("vertex_indices", f.get("vertex_index"))
    if lists is None:
        raise MeshsplatError(f"{path}: PLY 'face' element has no vertex_indices list")
    tris = []
    for poly in lists:
        poly = [int(i) for i in poly]
        tris += [[poly[0], poly[j], poly[j + 1]] for j in range(1, len(poly) - 1)]
    faces = np.asarray(tris, np.int64).reshape(-1, 3)
    if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(verts):
        raise MeshsplatError(f"{path}: PLY faces are empty or index past the {len(verts)} vertices")
    if not np.isfinite(verts).all():
        raise MeshsplatError(f"{path}: PLY vertices contain NaN/Inf")
    colors = None
    if all(k in v for k in ("red", "green", "blue")):
        c = np.stack([np.asarray(v[k], np.float64) for k in ("red", "green", "blue")], 1)
        colors = (c / 255.0 if c.max() > 1.0 else c).astype(np.float32)
    uvs = None
    for a, b in (("s", "t"), ("u", "v"), ("texture_u", "texture_v")):
        if a in v and b in v:
            uvs = np.stack([np.asarray(v[a], np.float64), np.asarray(v[b], np.float64)], 1).astype(np.float32)
            break
    return PlyMesh(verts, faces, colors, uvs)
