"""Standard 3D Gaussian Splatting ``.ply`` (binary little endian), as 3DGS viewers expect.

Vertex properties, all float32, in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3K-1} opacity
    scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

``f_rest`` is channel-major (all K coefficients of red, then green, then blue), padded
with zeros up to ``sh_degree_pad`` (default 3 -> K = 15, 45 values). ``opacity`` is the
logit, ``scale_*`` the log-scale, ``rot_*`` the quaternion wxyz (not normalized).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError

__all__ = ["write_gaussian_ply", "read_gaussian_ply", "gaussian_ply_fields"]

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "uint32": "<u4",
    "float": "<f4",
    "float32": "<f4",
    "double": "<f8",
    "float64": "<f8",
}


def gaussian_ply_fields(num_rest_coeffs: int) -> list[str]:
    """Property names in file order for ``num_rest_coeffs`` = K higher-order SH coefficients."""
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * num_rest_coeffs)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float32).numpy()


def write_gaussian_ply(
    path: str | os.PathLike,
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    sh0: torch.Tensor,
    shN: torch.Tensor | None = None,
    sh_degree_pad: int | None = 3,
    normals: torch.Tensor | None = None,
) -> Path:
    """Write Gaussians to a 3DGS ``.ply``.

    means ``[N,3]``, quats ``[N,4]`` wxyz, log_scales ``[N,3]``, opacity_logits ``[N]``,
    sh0 ``[N,1,3]`` or ``[N,3]``, shN ``[N,K,3]`` or None, normals ``[N,3]`` (zeros if None).
    ``sh_degree_pad``: pad f_rest with zeros to this SH degree (None: write K as given).
    """
    dims: dict[str, int] = {}
    check_tensor("means", means, "N,3", dims, dtype="float", finite=True)
    check_tensor("quats", quats, "N,4", dims, dtype="float", finite=True)
    check_tensor("log_scales", log_scales, "N,3", dims, dtype="float", finite=True)
    check_tensor("opacity_logits", opacity_logits, "N", dims, dtype="float", finite=True)
    if sh0.dim() == 2:
        check_tensor("sh0", sh0, "N,3", dims, dtype="float", finite=True)
    else:
        check_tensor("sh0", sh0, "N,1,3", dims, dtype="float", finite=True)
    n = dims["N"]
    k = 0
    if shN is not None:
        check_tensor("shN", shN, "N,K,3", dims, dtype="float", finite=True)
        k = shN.shape[1]
    if normals is not None:
        check_tensor("normals", normals, "N,3", dims, dtype="float", finite=True)
    k_out = k
    if sh_degree_pad is not None:
        k_pad = (int(sh_degree_pad) + 1) ** 2 - 1
        if k > k_pad:
            raise MeshsplatError(f"shN: has {k} coefficients, more than degree {sh_degree_pad} allows ({k_pad})")
        k_out = k_pad
    rest = np.zeros((n, 3, k_out), np.float32)
    if k:
        assert shN is not None  # k counts its coefficients
        rest[:, :, :k] = _np(shN).transpose(0, 2, 1)  # channel-major as 3DGS
    cols = [
        _np(means),
        np.zeros((n, 3), np.float32) if normals is None else _np(normals),
        _np(sh0).reshape(n, 3),
        rest.reshape(n, 3 * k_out),
        _np(opacity_logits).reshape(n, 1),
        _np(log_scales),
        _np(quats),
    ]
    data = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    names = gaussian_ply_fields(k_out)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names] + ["end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(data.tobytes())
    return path


def _read_header(fh, path: Path) -> tuple[int, list[tuple[str, str]]]:
    """Vertex count and (name, numpy dtype) of its properties; the vertex element must come first."""
    if fh.readline().strip() != b"ply":
        raise MeshsplatError(f"{str(path)!r} is not a PLY file")
    count = None
    props: list[tuple[str, str]] = []
    element = None
    while True:
        line = fh.readline()
        if not line:
            raise MeshsplatError(f"{str(path)!r}: PLY header has no end_header")
        parts = line.decode("ascii", "replace").split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] != "binary_little_endian":
                raise MeshsplatError(
                    f"{str(path)!r}: only binary_little_endian PLY is supported, "
                    f"got {' '.join(parts[1:2]) or 'nothing'}"
                )
        elif parts[0] == "element":
            element = parts[1] if len(parts) > 1 else None
            if count is None:
                if len(parts) != 3 or element != "vertex" or not parts[2].isdigit():
                    raise MeshsplatError(f"{str(path)!r}: expected 'element vertex N' first, got {line.strip()!r}")
                count = int(parts[2])
        elif parts[0] == "property" and element == "vertex":
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                raise MeshsplatError(f"{str(path)!r}: unsupported vertex property {line.strip()!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if count is None or not props:
        raise MeshsplatError(f"{str(path)!r}: PLY has no vertex element")
    return count, props


def read_gaussian_ply(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Read a 3DGS ``.ply`` into float32 tensors.

    Returns ``means [N,3], normals [N,3], quats [N,4], log_scales [N,3],
    opacity_logits [N], sh0 [N,1,3], shN [N,K,3]`` (K = number of f_rest / 3, zero
    padding included, K may be 0).
    """
    path = Path(path)
    if not path.is_file():
        raise MeshsplatError(f"PLY file {str(path)!r} not found")
    with open(path, "rb") as fh:
        n, props = _read_header(fh, path)
        try:
            dtype = np.dtype(props)
        except (ValueError, TypeError) as exc:
            raise MeshsplatError(f"{str(path)!r}: bad vertex properties ({exc})") from None
        raw = fh.read(n * dtype.itemsize)
    if len(raw) < n * dtype.itemsize:
        raise MeshsplatError(f"{str(path)!r}: truncated, expected {n} vertices of {dtype.itemsize} bytes")
    arr = np.frombuffer(raw, dtype=dtype, count=n)
    assert dtype.names is not None  # built from a field list
    names = set(dtype.names)
    required = [
        "x",
        "y",
        "z",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    missing = [r for r in required if r not in names]
    if missing:
        raise MeshsplatError(f"{str(path)!r}: not a Gaussian PLY, missing properties {missing}")
    n_rest = sum(1 for nm in names if nm.startswith("f_rest_"))
    if n_rest % 3 or any(f"f_rest_{i}" not in names for i in range(n_rest)):
        raise MeshsplatError(f"{str(path)!r}: f_rest properties must be f_rest_0..f_rest_(3K-1), found {n_rest}")
    k = n_rest // 3

    def cols(fields):
        return torch.from_numpy(np.stack([arr[f].astype(np.float32) for f in fields], axis=1))

    if k:
        rest = cols([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k).transpose(1, 2).contiguous()
    else:
        rest = torch.zeros(n, 0, 3)
    normals = cols(["nx", "ny", "nz"]) if {"nx", "ny", "nz"} <= names else torch.zeros(n, 3)
    return {
        "means": cols(["x", "y", "z"]),
        "normals": normals,
        "quats": cols(["rot_0", "rot_1", "rot_2", "rot_3"]),
        "log_scales": cols(["scale_0", "scale_1", "scale_2"]),
        "opacity_logits": cols(["opacity"])[:, 0].contiguous(),
        "sh0": cols(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3),
        "shN": rest,
    }
