"""Splat file formats other viewers read, besides the 3DGS ``.ply`` (:mod:`meshsplat.io.ply`).

All take and return the same numpy dict of Gaussians in the PLY's raw (pre-activation) terms::

    means [N,3], quats [N,4] (wxyz, unit), log_scales [N,3], opacity_logits [N],
    sh0 [N,3] (DC coefficient), shN [N,K,3] (K = 0, 3, 8 or 15: SH degree 0..3)

Coordinates are written as they are (the avatar's mesh frame), with no axis conversion.

- ``.splat`` (antimatter15): 32 bytes per Gaussian, no header, no SH beyond DC: float32 xyz,
  float32 linear scale, uint8 RGBA (colour 0.5 + C0*sh0, sigmoid opacity), uint8 quaternion
  w x y z as q*128+128; sorted by scale volume x opacity, largest first.
- ``.spz`` (Niantic, version 3, gzip): 16-byte header (magic "NGSP", version, count, SH degree,
  fractional bits, flags), then all positions (24-bit fixed point), alphas (uint8 sigmoid),
  colours (uint8 of sh0*0.15*255 + 127.5), log-scales (uint8 of (s+10)*16), rotations
  ("smallest three" in 32 bits: index of the largest |component| of the xyzw quaternion made
  positive, then the other three as sign + 9-bit magnitude / sqrt(1/2)), SH (uint8 of x*128+128,
  colour innermost; degree-1 coefficients rounded to steps of 8, higher degrees to steps of 16,
  as the reference encoder). Version 2 files (rotation as 3 bytes xyz) are read too, and version 4
  (what the spz library and splat-transform write by default): a 32-byte plain header (magic, version,
  count, SH degree, fractional bits, flags, stream count, table-of-contents offset), optional extension
  records, a table of (compressed, uncompressed) sizes and one zstd stream per array, the arrays as in
  version 3 (needs the ``zstandard`` package: ``pip install meshsplat[spz]``).
- ``.glb`` glTF 2.0 with ``KHR_gaussian_splatting`` (release candidate): one POINTS primitive,
  ``POSITION``, ``KHR_gaussian_splatting:ROTATION`` (xyzw), ``:SCALE`` (linear), ``:OPACITY``
  (linear), ``:SH_DEGREE_l_COEF_n`` (float VEC3 per coefficient and degree) and a ``COLOR_0``
  fallback for viewers without the extension: the DC colour converted to linear RGB (glTF vertex
  colours are linear; the SH stay in the extension's ``srgb_rec709_display`` space) and the opacity.
"""

from __future__ import annotations

import gzip
import json
import os
import struct
from pathlib import Path

import numpy as np

from meshsplat.errors import MeshsplatError

__all__ = ["write_splat", "read_splat", "write_spz", "read_spz", "write_gltf_splats", "read_gltf_splats", "SH_C0"]

SH_C0 = 0.28209479177387814
_K_TO_DEGREE = {0: 0, 3: 1, 8: 2, 15: 3}
_SPZ_MAGIC = 0x5053474E  # "NGSP" little-endian
_SPZ_COLOR_SCALE = 0.15
_KHR = "KHR_gaussian_splatting"


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def _logit(p):
    p = np.clip(np.asarray(p, np.float64), 1e-7, 1 - 1e-7)
    return np.log(p / (1 - p))


def _checked(g: dict) -> dict:
    """float64 copies with shapes checked; quaternions normalized; shN [N,K,3] (K may be 0)."""
    try:
        means = np.asarray(g["means"], np.float64)
        n = means.shape[0]
        out = {
            "means": means.reshape(n, 3),
            "quats": np.asarray(g["quats"], np.float64).reshape(n, 4),
            "log_scales": np.asarray(g["log_scales"], np.float64).reshape(n, 3),
            "opacity_logits": np.asarray(g["opacity_logits"], np.float64).reshape(n),
            "sh0": np.asarray(g["sh0"], np.float64).reshape(n, 3),
        }
        shN = g.get("shN")
        out["shN"] = np.zeros((n, 0, 3)) if shN is None else np.asarray(shN, np.float64).reshape(n, -1, 3)
    except (KeyError, ValueError) as exc:
        raise MeshsplatError(
            f"splats: expected means [N,3], quats [N,4], log_scales [N,3], opacity_logits [N], "
            f"sh0 [N,3], shN [N,K,3] ({exc})"
        ) from None
    if out["shN"].shape[1] not in _K_TO_DEGREE:
        raise MeshsplatError(f"splats: shN has {out['shN'].shape[1]} coefficients; expected 0, 3, 8 or 15")
    if not all(np.isfinite(v).all() for v in out.values()):
        raise MeshsplatError("splats: values must be finite")
    q = out["quats"]
    out["quats"] = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    return out


def _read_bytes(path, what: str) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise MeshsplatError(f"{what} file {str(path)!r} not found")
    return path.read_bytes()


# ------------------------------------------------------------------ .splat
_SPLAT_DTYPE = np.dtype([("xyz", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def write_splat(path: str | os.PathLike, g: dict) -> Path:
    """antimatter15 ``.splat`` (DC colour only; shN is dropped)."""
    g = _checked(g)
    n = len(g["means"])
    rec = np.zeros(n, _SPLAT_DTYPE)
    rec["xyz"] = g["means"]
    rec["scale"] = np.exp(g["log_scales"])
    alpha = _sigmoid(g["opacity_logits"])
    rgb = 0.5 + SH_C0 * g["sh0"]
    rec["rgba"] = np.clip(np.rint(np.concatenate([rgb, alpha[:, None]], 1) * 255), 0, 255)
    rec["rot"] = np.clip(np.rint(g["quats"] * 128 + 128), 0, 255)
    order = np.argsort(-np.exp(g["log_scales"].sum(1)) * alpha, kind="stable")
    path = Path(path)
    path.write_bytes(rec[order].tobytes())
    return path


def read_splat(path: str | os.PathLike) -> dict:
    """Gaussians of a ``.splat`` file (in its stored order; shN empty)."""
    raw = _read_bytes(path, ".splat")
    if len(raw) % _SPLAT_DTYPE.itemsize:
        raise MeshsplatError(f"{str(path)!r}: size {len(raw)} is not a multiple of 32 bytes (not a .splat file)")
    rec = np.frombuffer(raw, _SPLAT_DTYPE)
    n = len(rec)
    q = (rec["rot"].astype(np.float64) - 128) / 128
    return {
        "means": rec["xyz"].astype(np.float64),
        "quats": q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12),
        "log_scales": np.log(np.maximum(rec["scale"].astype(np.float64), 1e-30)),
        "opacity_logits": _logit(rec["rgba"][:, 3] / 255.0),
        "sh0": (rec["rgba"][:, :3] / 255.0 - 0.5) / SH_C0,
        "shN": np.zeros((n, 0, 3)),
    }


# ------------------------------------------------------------------ .spz (version 2)
def _u8(x) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _smallest_three(q_wxyz: np.ndarray) -> np.ndarray:
    """[N] uint32 smallest-three codes of unit quaternions (SPZ v3 layout, components in xyzw order)."""
    q = q_wxyz[:, [1, 2, 3, 0]]
    big = np.abs(q).argmax(1)
    q = q * np.where(q[np.arange(len(q)), big] < 0, -1.0, 1.0)[:, None]
    code = big.astype(np.uint64)
    for i in range(4):
        keep = big != i
        mag = np.minimum(np.floor(511 * np.abs(q[:, i]) / np.sqrt(0.5) + 0.5), 511).astype(np.uint64)
        part = ((q[:, i] < 0).astype(np.uint64) << np.uint64(9)) | mag
        code = np.where(keep, (code << np.uint64(10)) | part, code)
    return code.astype(np.uint32)


def _from_smallest_three(code: np.ndarray) -> np.ndarray:
    code = code.astype(np.uint64)
    big = (code >> np.uint64(30)).astype(np.int64)
    q = np.zeros((len(code), 4))
    for i in range(3, -1, -1):
        rows = big != i
        val = np.sqrt(0.5) * (code & np.uint64(511)).astype(np.float64) / 511
        q[rows, i] = np.where((code >> np.uint64(9)) & np.uint64(1), -val, val)[rows]
        code = np.where(rows, code >> np.uint64(10), code)
    q[np.arange(len(q)), big] = np.sqrt(np.maximum(0.0, 1.0 - (q**2).sum(1)))
    return q[:, [3, 0, 1, 2]]


def write_spz(path: str | os.PathLike, g: dict) -> Path:
    """Niantic ``.spz`` version 3 (gzip). Positions use the most fractional bits (<= 16) that fit."""
    g = _checked(g)
    n, k = len(g["means"]), g["shN"].shape[1]
    extent = float(np.abs(g["means"]).max(initial=0.0))
    if extent >= 2.0**23:
        raise MeshsplatError(f"spz: positions up to {extent:g} do not fit 24-bit fixed point; rescale the scene")
    frac = int(np.clip(np.floor(np.log2((2.0**23 - 1) / max(extent, 1e-30))), 0, 16))
    fixed = np.rint(g["means"] * (1 << frac)).astype(np.int64).reshape(-1) & 0xFFFFFF
    pos = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], 1).astype(np.uint8)
    sh = np.rint(g["shN"] * 128 + 128)
    if k:
        step = np.where(np.arange(k) < 3, 8, 16)[None, :, None]  # degree 1 coefficients: finer steps
        sh = np.floor((sh + step // 2) / step) * step
    header = struct.pack("<IIIBBBB", _SPZ_MAGIC, 3, n, _K_TO_DEGREE[k], frac, 0, 0)
    body = b"".join(
        [
            pos.tobytes(),
            _u8(_sigmoid(g["opacity_logits"]) * 255).tobytes(),
            _u8(g["sh0"] * (_SPZ_COLOR_SCALE * 255) + 127.5).tobytes(),
            _u8((g["log_scales"] + 10) * 16).tobytes(),
            _smallest_three(g["quats"]).astype("<u4").tobytes(),
            _u8(sh).tobytes(),
        ]
    )
    path = Path(path)
    path.write_bytes(gzip.compress(header + body, compresslevel=9, mtime=0))
    return path


def _spz_v4_arrays(path, raw: bytes) -> tuple[int, int, int, int, list[bytes]]:
    """``(version 4, count, SH degree, fractional bits, [the streams' bytes])`` of a version 4 file."""
    if len(raw) < 32:
        raise MeshsplatError(f"{str(path)!r}: .spz header is truncated")
    _, version, n, degree, frac, _flags, streams, toc = struct.unpack_from("<IIIBBBBI", raw)
    if version != 4:
        raise MeshsplatError(f"{str(path)!r}: a plain NGSP header with version {version} (only version 4 has one)")
    if toc < 32 or toc + 16 * streams > len(raw):
        raise MeshsplatError(f"{str(path)!r}: .spz table of contents lies outside the file")
    try:
        import zstandard
    except ImportError:
        raise MeshsplatError(
            f"{str(path)!r}: SPZ version 4 (zstd) needs the zstandard package: pip install 'meshsplat[spz]'"
        ) from None
    sizes = [struct.unpack_from("<QQ", raw, toc + 16 * i) for i in range(streams)]
    off, out = toc + 16 * streams, []
    dec = zstandard.ZstdDecompressor()
    for packed, size in sizes:
        if off + packed > len(raw):
            raise MeshsplatError(f"{str(path)!r}: .spz data is truncated ({n} Gaussians announced)")
        try:
            data = dec.decompress(raw[off : off + packed], max_output_size=size)
        except zstandard.ZstdError as exc:
            raise MeshsplatError(f"{str(path)!r}: a .spz stream does not decompress ({exc})") from None
        if len(data) != size:
            raise MeshsplatError(f"{str(path)!r}: a .spz stream holds {len(data)} bytes, its table says {size}")
        out.append(data)
        off += packed
    return version, n, degree, frac, out


def read_spz(path: str | os.PathLike) -> dict:
    """Gaussians of a version 2, 3 (gzip) or 4 (zstd streams) ``.spz`` file."""
    raw = _read_bytes(path, ".spz")
    if raw[:4] == struct.pack("<I", _SPZ_MAGIC):  # version 4: a plain header, then zstd streams
        version, n, degree, frac, streams = _spz_v4_arrays(path, raw)
        if degree > 3:
            raise MeshsplatError(f"{str(path)!r}: SH degree {degree} (only 0..3 are read)")
        k = (degree + 1) ** 2 - 1
        sizes = [9 * n, n, 3 * n, 3 * n, 4 * n, 3 * k * n]
        if len(streams) < 6 or any(len(a) < s for a, s in zip(streams[:6], sizes, strict=True)):
            raise MeshsplatError(f"{str(path)!r}: .spz streams are shorter than {n} Gaussians need")
        parts = [np.frombuffer(a, np.uint8, s).astype(np.int64) for a, s in zip(streams[:6], sizes, strict=True)]
        return _spz_gaussians(version, n, k, frac, parts)
    try:
        data = gzip.decompress(raw)
    except (OSError, EOFError) as exc:
        raise MeshsplatError(
            f"{str(path)!r}: not a gzip .spz file ({exc}); only gzip SPZ versions 2 and 3 are read"
        ) from None
    if len(data) < 16:
        raise MeshsplatError(f"{str(path)!r}: .spz header is truncated")
    magic, version, n, degree, frac, _flags, _ = struct.unpack_from("<IIIBBBB", data)
    if magic != _SPZ_MAGIC or version not in (2, 3):
        raise MeshsplatError(
            f"{str(path)!r}: expected SPZ magic NGSP version 2 or 3 in gzip (or 4), got {magic:#x} version {version}"
        )
    if degree > 3:
        raise MeshsplatError(f"{str(path)!r}: SH degree {degree} (only 0..3 are read)")
    k = (degree + 1) ** 2 - 1
    sizes = [9 * n, n, 3 * n, 3 * n, (3 if version == 2 else 4) * n, 3 * k * n]
    if len(data) < 16 + sum(sizes):
        raise MeshsplatError(f"{str(path)!r}: .spz data is truncated ({n} Gaussians announced)")
    parts, off = [], 16
    for s in sizes:
        parts.append(np.frombuffer(data, np.uint8, s, off).astype(np.int64))
        off += s
    return _spz_gaussians(version, n, k, frac, parts)


def _spz_gaussians(version: int, n: int, k: int, frac: int, parts: list[np.ndarray]) -> dict:
    """The Gaussians of the six SPZ arrays (positions, alphas, colours, scales, rotations, SH)."""
    pos, alpha, col, scl, rot, sh = parts
    p = pos.reshape(-1, 3)
    fixed = p[:, 0] | (p[:, 1] << 8) | (p[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    if version == 2:
        xyz = rot.reshape(n, 3) / 127.5 - 1.0
        quats = np.concatenate([np.sqrt(np.maximum(0.0, 1.0 - (xyz**2).sum(1)))[:, None], xyz], 1)
    else:
        r = rot.reshape(n, 4)
        quats = _from_smallest_three(r[:, 0] | (r[:, 1] << 8) | (r[:, 2] << 16) | (r[:, 3] << 24))
    return {
        "means": fixed.reshape(n, 3) / float(1 << frac),
        "quats": quats,
        "log_scales": scl.reshape(n, 3) / 16.0 - 10.0,
        "opacity_logits": _logit(alpha / 255.0),
        "sh0": (col.reshape(n, 3) / 255.0 - 0.5) / _SPZ_COLOR_SCALE,
        "shN": (sh.reshape(n, k, 3) - 128) / 128.0,
    }


# ------------------------------------------------------------------ glTF KHR_gaussian_splatting
def _sh_attribute_names(degree: int) -> list[str]:
    return [f"{_KHR}:SH_DEGREE_{lv}_COEF_{c}" for lv in range(1, degree + 1) for c in range(2 * lv + 1)]


def write_gltf_splats(path: str | os.PathLike, g: dict, color_space: str = "srgb_rec709_display") -> Path:
    """Binary glTF (``.glb``) with one ``KHR_gaussian_splatting`` POINTS primitive (float accessors)."""
    g = _checked(g)
    n, k = len(g["means"]), g["shN"].shape[1]
    if n == 0:
        raise MeshsplatError("gltf: no Gaussians to write")
    alpha = _sigmoid(g["opacity_logits"])
    columns = [
        ("POSITION", "VEC3", g["means"]),
        (f"{_KHR}:ROTATION", "VEC4", g["quats"][:, [1, 2, 3, 0]]),  # glTF quaternions are xyzw
        (f"{_KHR}:SCALE", "VEC3", np.exp(g["log_scales"])),
        (f"{_KHR}:OPACITY", "SCALAR", alpha),
        (f"{_KHR}:SH_DEGREE_0_COEF_0", "VEC3", g["sh0"]),
    ]
    columns += [(name, "VEC3", g["shN"][:, i]) for i, name in enumerate(_sh_attribute_names(_K_TO_DEGREE[k]))]
    # glTF vertex colours are linear: the DC colour (a display, sRGB-encoded value) through the sRGB curve
    display = np.clip(0.5 + SH_C0 * g["sh0"], 0, 1)
    linear = np.where(display <= 0.04045, display / 12.92, ((display + 0.055) / 1.055) ** 2.4)
    columns.append(("COLOR_0", "VEC4", np.concatenate([linear, alpha[:, None]], 1)))
    blob, views, accessors, attributes = bytearray(), [], [], {}
    for i, (name, kind, arr) in enumerate(columns):
        data = np.ascontiguousarray(arr, "<f4")
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes, "target": 34962})
        acc = {"bufferView": i, "componentType": 5126, "count": n, "type": kind}
        if name == "POSITION":  # required by glTF for positions
            acc["min"], acc["max"] = data.min(0).tolist(), data.max(0).tolist()
        accessors.append(acc)
        attributes[name] = i
        blob += data.tobytes()
    doc = {
        "asset": {"version": "2.0", "generator": "meshsplat"},
        "extensionsUsed": [_KHR],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "avatar"}],
        "meshes": [
            {
                "primitives": [
                    {
                        "mode": 0,
                        "attributes": attributes,
                        "extensions": {_KHR: {"kernel": "ellipse", "colorSpace": color_space}},
                    }
                ]
            }
        ],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    out = struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js) + 8 + len(blob))
    out += struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob)
    path = Path(path)
    path.write_bytes(out)
    return path


def read_gltf_splats(path: str | os.PathLike) -> dict:
    """Gaussians of the first ``KHR_gaussian_splatting`` primitive of a ``.glb`` (float accessors)."""
    raw = _read_bytes(path, "glTF")
    if len(raw) < 20 or raw[:4] != b"glTF":
        raise MeshsplatError(f"{str(path)!r}: not a binary glTF (.glb) file")
    jlen = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20 : 20 + jlen])
    boff = 20 + jlen
    blen, _ = struct.unpack_from("<II", raw, boff)
    blob = raw[boff + 8 : boff + 8 + blen]
    prim = next((p for m in doc.get("meshes", []) for p in m["primitives"] if _KHR in p.get("extensions", {})), None)
    if prim is None:
        raise MeshsplatError(f"{str(path)!r}: no {_KHR} primitive")
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}

    def attr(name):
        acc = doc["accessors"][prim["attributes"][name]]
        if acc["componentType"] != 5126:
            raise MeshsplatError(f"{str(path)!r}: {name} is not float (quantized accessors are not read)")
        view = doc["bufferViews"][acc["bufferView"]]
        w = width[acc["type"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        return np.frombuffer(blob, "<f4", acc["count"] * w, start).reshape(acc["count"], w).astype(np.float64)

    degree = max((lv for lv in range(1, 4) if f"{_KHR}:SH_DEGREE_{lv}_COEF_0" in prim["attributes"]), default=0)
    n = doc["accessors"][prim["attributes"]["POSITION"]]["count"]
    shN = np.stack([attr(a) for a in _sh_attribute_names(degree)], 1) if degree else np.zeros((n, 0, 3))
    return {
        "means": attr("POSITION"),
        "quats": attr(f"{_KHR}:ROTATION")[:, [3, 0, 1, 2]],
        "log_scales": np.log(np.maximum(attr(f"{_KHR}:SCALE"), 1e-30)),
        "opacity_logits": _logit(attr(f"{_KHR}:OPACITY")[:, 0]),
        "sh0": attr(f"{_KHR}:SH_DEGREE_0_COEF_0"),
        "shN": shN,
    }
