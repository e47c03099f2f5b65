"""Low-level glTF 2.0 / GLB reading: accessors, images, node transforms, animation sampling.

Everything here is plain numpy in float64; quaternions in glTF files are ``[x, y, z, w]``.
"""

from __future__ import annotations

import base64
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from meshsplat.errors import MeshsplatError

__all__ = [
    "GltfFile",
    "Channel",
    "quat_xyzw_to_matrix",
    "trs_matrix",
    "slerp_xyzw",
    "sample_channel",
]

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_NORM_DIV = {np.int8: 127.0, np.uint8: 255.0, np.int16: 32767.0, np.uint16: 65535.0, np.uint32: 4294967295.0}


class GltfFile:
    """A parsed glTF/GLB file with typed accessor and image access."""

    def __init__(self, path: Path | str) -> None:
        import pygltflib

        self.path = Path(path)
        if not self.path.is_file():
            raise MeshsplatError(f"glTF file not found: {self.path}")
        try:
            self.doc = pygltflib.GLTF2().load(str(self.path))
        except Exception as exc:  # noqa: BLE001 - pygltflib raises assorted errors on bad files
            raise MeshsplatError(f"{self.path}: not a readable glTF/GLB file ({exc})") from None
        if self.doc is None:
            raise MeshsplatError(f"{self.path}: not a readable glTF/GLB file")
        self._buffers: dict[int, bytes] = {}

    def _uri_bytes(self, uri: str) -> bytes:
        if uri.startswith("data:"):
            return base64.b64decode(uri.split(",", 1)[1])
        p = self.path.parent / uri
        if not p.is_file():
            raise MeshsplatError(f"{self.path}: referenced file {uri!r} not found")
        return p.read_bytes()

    def buffer(self, i: int) -> bytes:
        if i not in self._buffers:
            b = self.doc.buffers[i]
            if b.uri is None:
                blob = self.doc.binary_blob()
                if blob is None:
                    raise MeshsplatError(f"{self.path}: buffer {i} has no data")
                self._buffers[i] = bytes(blob)
            else:
                self._buffers[i] = self._uri_bytes(b.uri)
        return self._buffers[i]

    def view_bytes(self, view_index: int) -> bytes:
        bv = self.doc.bufferViews[view_index]
        start = bv.byteOffset or 0
        return self.buffer(bv.buffer)[start : start + bv.byteLength]

    def accessor(self, index: int, as_float: bool = True) -> np.ndarray:
        """Accessor ``index`` as ``[count, ncomp]`` (float64 when ``as_float``; normalized ints scaled)."""
        acc = self.doc.accessors[index]
        dt = np.dtype(_COMPONENT[acc.componentType])
        n = _NCOMP[acc.type]
        if acc.bufferView is not None:
            bv = self.doc.bufferViews[acc.bufferView]
            data = self.buffer(bv.buffer)
            start = (bv.byteOffset or 0) + (acc.byteOffset or 0)
            stride = bv.byteStride or dt.itemsize * n
            out: np.ndarray = np.ndarray(
                (acc.count, n), dt, buffer=data, offset=start, strides=(stride, dt.itemsize)
            ).copy()
        else:
            out = np.zeros((acc.count, n), dt)
        sp = acc.sparse
        if sp is not None and sp.count:
            idt = np.dtype(_COMPONENT[sp.indices.componentType])
            ib = self.doc.bufferViews[sp.indices.bufferView]
            idx = np.frombuffer(
                self.buffer(ib.buffer), idt, sp.count, (ib.byteOffset or 0) + (sp.indices.byteOffset or 0)
            )
            vb = self.doc.bufferViews[sp.values.bufferView]
            vals = np.frombuffer(
                self.buffer(vb.buffer), dt, sp.count * n, (vb.byteOffset or 0) + (sp.values.byteOffset or 0)
            )
            out[idx.astype(np.int64)] = vals.reshape(sp.count, n)
        if not as_float:
            return out
        if acc.normalized and dt.type in _NORM_DIV:
            return np.maximum(out.astype(np.float64) / _NORM_DIV[dt.type], -1.0)
        return out.astype(np.float64)

    def image(self, index: int) -> np.ndarray:
        """Image ``index`` decoded to uint8 ``[H, W, 3|4]``."""
        from PIL import Image

        img = self.doc.images[index]
        raw = self.view_bytes(img.bufferView) if img.bufferView is not None else self._uri_bytes(img.uri or "")
        try:
            pil: Image.Image = Image.open(io.BytesIO(raw))
            pil = pil.convert("RGBA" if "A" in pil.getbands() else "RGB")
        except Exception as exc:  # noqa: BLE001 - PIL raises assorted errors on bad images
            raise MeshsplatError(f"{self.path}: image {index} cannot be decoded ({exc})") from None
        return np.asarray(pil, dtype=np.uint8).copy()


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[..., 4]`` (x, y, z, w) to rotation matrices ``[..., 3, 3]``."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    m = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def trs_matrix(t: ArrayLike, r_xyzw: ArrayLike, s: ArrayLike) -> np.ndarray:
    """4x4 matrix ``T @ R @ S``."""
    m = np.eye(4)
    m[:3, :3] = quat_xyzw_to_matrix(np.asarray(r_xyzw, np.float64)) * np.asarray(s, np.float64)[None, :]
    m[:3, 3] = t
    return m


def slerp_xyzw(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Shortest-arc spherical interpolation between unit quaternions."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + s * (q1 - q0)
    else:
        th = np.arccos(min(d, 1.0))
        q = (np.sin((1 - s) * th) * q0 + np.sin(s * th) * q1) / np.sin(th)
    return q / np.linalg.norm(q)


@dataclass
class Channel:
    """One animation channel: node, path (translation|rotation|scale|weights), keyframes."""

    node: int
    path: str
    times: np.ndarray  # [K]
    values: np.ndarray  # [K, n] or [K, 3, n] for CUBICSPLINE (in-tangent, value, out-tangent)
    interpolation: str


def sample_channel(ch: Channel, t: float) -> np.ndarray:
    """Value of ``ch`` at time ``t`` (clamped to the keyframe range)."""
    times, vals = ch.times, ch.values
    cubic = ch.interpolation == "CUBICSPLINE"
    value = (lambda k: vals[k, 1]) if cubic else (lambda k: vals[k])
    if len(times) == 1 or t <= times[0]:
        return value(0).copy()
    if t >= times[-1]:
        return value(len(times) - 1).copy()
    k = int(np.searchsorted(times, t, side="right") - 1)
    dt = float(times[k + 1] - times[k])
    s = (t - times[k]) / dt if dt > 0 else 0.0
    if ch.interpolation == "STEP":
        return vals[k].copy()
    if cubic:
        p0, m0 = vals[k, 1], dt * vals[k, 2]
        p1, m1 = vals[k + 1, 1], dt * vals[k + 1, 0]
        s2, s3 = s * s, s * s * s
        out = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * m1
        return out / np.linalg.norm(out) if ch.path == "rotation" else out
    if ch.path == "rotation":
        return slerp_xyzw(vals[k], vals[k + 1], s)
    return (1 - s) * vals[k] + s * vals[k + 1]
