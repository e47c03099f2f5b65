"""Mesh-embedded Gaussians as JSON (for the web viewer and other engines).

Layout::

    {"format": "meshsplat-embedding", "version": 1, "count": N, "encoding": "base64",
     "meta": {"scale_mode": "sqrt_area", "sh_degree": 0, ...},
     "arrays": {"face": {"dtype": "int32", "shape": [N], "data": "<base64>"},
                "uv": {"dtype": "float32", "shape": [N, 2], "data": ...},
                "d": [N], "rotation": [N, 4] (wxyz, canonical, unnormalized),
                "log_scale": [N, 3], "opacity_logit": [N], "sh0": [N, 1, 3],
                "shN": [N, K, 3] (only when K > 0)}}

``encoding="base64"`` stores each array as little-endian bytes (row-major) in base64:
compact and exact (decode in JS with ``new Float32Array(bytes.buffer)``).
``encoding="list"`` stores nested JSON numbers written at full float32 precision; it
also round-trips exactly, at about 3x the size. ``uv`` is the effective barycentric
coordinate the renderer uses: ``uv + duv`` when the parameters hold a ``duv``.
"""

from __future__ import annotations

import base64
import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError
from meshsplat.io.json_file import read_json_object

__all__ = ["write_embedding_json", "read_embedding_json", "EMBEDDING_FORMAT", "EMBEDDING_VERSION"]

EMBEDDING_FORMAT = "meshsplat-embedding"
EMBEDDING_VERSION = 1
_SPECS = {
    "face": ("N", "int32"),
    "uv": ("N,2", "float32"),
    "d": ("N", "float32"),
    "rotation": ("N,4", "float32"),
    "log_scale": ("N,3", "float32"),
    "opacity_logit": ("N", "float32"),
    "sh0": ("N,1,3", "float32"),
    "shN": ("N,K,3", "float32"),
}


def _encode(arr: np.ndarray, encoding: str) -> dict:
    out = {"dtype": str(arr.dtype), "shape": list(arr.shape)}
    if encoding == "base64":
        out["data"] = base64.b64encode(arr.astype(arr.dtype.newbyteorder("<")).tobytes()).decode("ascii")
    else:
        # float(np.float32) is the exact double of the float32; repr round-trips it.
        out["data"] = arr.tolist()
    return out


def _decode(name: str, entry, encoding: str, path: Path) -> np.ndarray:
    try:
        dtype = np.dtype(entry["dtype"]).newbyteorder("<")
        if dtype.kind not in "fiu":
            raise ValueError(f"dtype {entry['dtype']!r} is not a number type")
        shape = tuple(int(s) for s in entry["shape"])
        with np.errstate(over="ignore", invalid="ignore"):  # a number beyond the dtype: inf, refused by the caller
            if encoding == "base64":
                arr = np.frombuffer(base64.b64decode(entry["data"], validate=True), dtype=dtype)
            else:
                arr = np.asarray(entry["data"], dtype=dtype)
            return arr.reshape(shape).astype(dtype.newbyteorder("="))
    except (KeyError, TypeError, ValueError, OverflowError, IndexError) as exc:
        raise MeshsplatError(f"{str(path)!r}: array {name!r} is malformed ({exc})") from None


def write_embedding_json(
    path: str | os.PathLike, params: Mapping[str, torch.Tensor], meta: Mapping | None = None, encoding: str = "base64"
) -> Path:
    """Write the embedding and Gaussian parameters of ``params`` to JSON.

    params needs ``face [N], uv [N,2], d [N], rotation [N,4], log_scale [N,3],
    opacity_logit [N], sh0 [N,1,3] or [N,3]``; optional ``duv [N,2]`` (added to uv) and
    ``shN [N,K,3]``. ``meta`` (JSON-serialisable, e.g. ``scale_mode``) is stored as is,
    plus ``sh_degree``.
    """
    if encoding not in ("base64", "list"):
        raise MeshsplatError(f"encoding: expected 'base64' or 'list', got {encoding!r}")
    missing = [k for k in _SPECS if k != "shN" and k not in params]
    if missing:
        raise MeshsplatError(f"params: missing {missing}")
    p = dict(params)
    if p["sh0"].dim() == 2:
        p["sh0"] = p["sh0"].unsqueeze(1)
    dims: dict[str, int] = {}
    arrays = {}
    for name, (spec, dt) in _SPECS.items():
        if name not in p or p[name] is None:
            continue
        t = p[name]
        check_tensor(name, t, spec, dims, dtype="int" if dt == "int32" else "float", finite=dt != "int32")
        if name == "uv" and p.get("duv") is not None:
            check_tensor("duv", p["duv"], "N,2", dims, dtype="float", finite=True)
            t = t + p["duv"].to(t)
        if name == "shN" and t.shape[1] == 0:
            continue
        arrays[name] = _encode(t.detach().cpu().numpy().astype(dt), encoding)
    k = p["shN"].shape[1] if p.get("shN") is not None else 0
    sh_degree = round((k + 1) ** 0.5) - 1
    if (sh_degree + 1) ** 2 - 1 != k:
        raise MeshsplatError(f"shN: {k} coefficients is not (degree+1)^2-1 for any degree")
    meta_out = dict(meta or {})
    meta_out.setdefault("sh_degree", sh_degree)
    doc = {
        "format": EMBEDDING_FORMAT,
        "version": EMBEDDING_VERSION,
        "count": dims["N"],
        "encoding": encoding,
        "meta": meta_out,
        "arrays": arrays,
    }
    try:
        text = json.dumps(doc, separators=(",", ":"))
    except (TypeError, ValueError) as exc:
        raise MeshsplatError(f"meta: not JSON-serialisable ({exc})") from None
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def read_embedding_json(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor], dict]:
    """Read a file of :func:`write_embedding_json`: ``(params, meta)``.

    params: ``face [N] long, uv [N,2], d [N], rotation [N,4], log_scale [N,3],
    opacity_logit [N], sh0 [N,1,3], shN [N,K,3]`` (K = 0 when absent), float32.
    """
    path = Path(path)
    doc = read_json_object(path, "a meshsplat embedding file (a JSON object)")
    if doc.get("format") != EMBEDDING_FORMAT:
        raise MeshsplatError(f"{str(path)!r}: not a meshsplat embedding file")
    if doc.get("version") != EMBEDDING_VERSION:
        raise MeshsplatError(f"{str(path)!r}: format version {doc.get('version')!r}, expected {EMBEDDING_VERSION}")
    encoding = doc.get("encoding")
    if encoding not in ("base64", "list"):
        raise MeshsplatError(f"{str(path)!r}: unknown encoding {encoding!r}")
    arrays = doc.get("arrays", {})
    if not isinstance(arrays, dict):
        raise MeshsplatError(f"{str(path)!r}: 'arrays' must be an object, got {type(arrays).__name__}")
    if not isinstance(doc.get("meta") or {}, dict):
        raise MeshsplatError(f"{str(path)!r}: 'meta' must be an object")
    n = doc.get("count")
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise MeshsplatError(f"{str(path)!r}: 'count' must be a non-negative integer, got {n!r}")
    out: dict[str, torch.Tensor] = {}
    dims: dict[str, int] = {"N": n} if isinstance(n, int) else {}
    for name, (spec, _) in _SPECS.items():
        if name not in arrays:
            if name == "shN":
                out[name] = torch.zeros(dims.get("N", 0), 0, 3)
                continue
            raise MeshsplatError(f"{str(path)!r}: missing array {name!r}")
        t = torch.from_numpy(_decode(name, arrays[name], encoding, path))
        t = t.long() if name == "face" else t.float()  # float64 beyond float32's range becomes inf: caught below
        try:
            check_tensor(name, t, spec, dims, finite=True)
        except MeshsplatError as exc:
            raise MeshsplatError(f"{str(path)!r}: {exc}") from None
        if name == "face" and t.numel() and int(t.min()) < 0:
            raise MeshsplatError(f"{str(path)!r}: array 'face' holds negative face indices")
        out[name] = t
    return out, dict(doc.get("meta") or {})
