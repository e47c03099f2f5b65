"""Per-frame mesh sequences in the documented layouts (docs/bring-your-own-mesh.md).

* ``npz`` layout: one ``.npz`` with ``faces [F,3]`` int and ``vertices [T,V,3]`` float, optional
  ``rest [V,3]``, ``uvs [V,2]``, ``colors [V,3]`` (float in [0,1] or uint8), ``texture [H,W,3|4]``
  uint8, ``fps`` (default 30), ``up`` (``"y"`` or ``"z"``), ``attribution`` (text),
  ``clip_names [K]`` + ``clip_ranges [K,2]`` (first and last frame of each clip; default one clip
  ``"sequence"``). Read with ``allow_pickle=False``.
* ``frames`` layout: a folder of ``.obj`` or ``.ply`` files, one per frame in name order, all
  with the same faces; optional ``texture.png``/``texture.jpg`` and ``sequence.json`` with
  ``fps``, ``up``, ``attribution`` and ``clips`` (``{"name": [first, last]}``). OBJ texture
  coordinates are kept by splitting vertices along UV seams (``vertex_of``: sequence vertex ->
  file vertex).

Every error names the layout and what it expects.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

import numpy as np
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import npz_keys, read_npz
from meshsplat.io.images import open_image
from meshsplat.io.json_file import read_json_object
from meshsplat.io.obj import read_obj
from meshsplat.io.ply_mesh import read_ply_mesh

__all__ = ["MeshSequence", "read_mesh_sequence", "is_mesh_sequence", "NPZ_LAYOUT", "FRAMES_LAYOUT"]

NPZ_LAYOUT = "npz mesh sequence (faces [F,3], vertices [T,V,3], optional uvs/colors/texture/fps/up)"
FRAMES_LAYOUT = "folder of OBJ/PLY frames (one file per frame, same faces, optional texture.png, sequence.json)"


@dataclass
class MeshSequence:
    """``faces [F,3] int64``, ``vertices [T,V,3] float32`` and surface colour data; ``clips`` name ->
    (first, last) frame; ``vertex_of [V]`` maps to the file's vertices when seams were split."""

    faces: np.ndarray
    vertices: np.ndarray
    layout: str
    rest: np.ndarray | None = None
    uvs: np.ndarray | None = None
    colors: np.ndarray | None = None
    texture: np.ndarray | None = None
    fps: float = 30.0
    up: str | None = None
    attribution: str = ""
    clips: dict = field(default_factory=dict)
    vertex_of: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])


def is_mesh_sequence(path: Path | str) -> bool:
    """True when ``path`` is an ``.npz`` with ``faces`` and ``vertices`` or a folder of OBJ/PLY frames."""
    p = Path(path)
    if p.is_dir():
        return any(q.suffix.lower() in (".obj", ".ply") for q in p.iterdir())
    if p.suffix.lower() == ".npz" and p.is_file():
        try:
            keys = npz_keys(p)
        except MeshsplatError:
            return False
        return "faces" in keys and "vertices" in keys
    return False


def _natural(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _text(z, key: str) -> str | None:
    if key not in z:
        return None
    a = np.asarray(z[key])
    return str(a.reshape(-1)[0]) if a.size else ""


def _colors(c, n: int, layout: str, where) -> np.ndarray:
    c = np.asarray(c)
    if c.ndim != 2 or c.shape[0] != n or c.shape[1] not in (3, 4):
        raise MeshsplatError(f"{where}: colors must be [V,3] with V={n} ({layout}), got {list(c.shape)}")
    c = c[:, :3].astype(np.float32) / (255.0 if c.dtype == np.uint8 else 1.0)
    return np.clip(c, 0.0, 1.0)


def _texture(t, layout: str, where) -> np.ndarray:
    t = np.asarray(t)
    if t.ndim != 3 or t.shape[2] not in (3, 4) or t.dtype != np.uint8:
        raise MeshsplatError(f"{where}: texture must be uint8 [H,W,3] ({layout}), got {t.dtype} {list(t.shape)}")
    return np.ascontiguousarray(t[..., :3])


def _clips(names, ranges, t: int, layout: str, where) -> dict:
    if names is None:
        return {"sequence": (0, t - 1)}
    r = np.asarray(ranges, np.int64).reshape(-1, 2)
    if len(names) != len(r):
        raise MeshsplatError(f"{where}: {len(names)} clip names but {len(r)} clip ranges ({layout})")
    out = {}
    for n, (a, b) in zip(names, r, strict=True):
        if not 0 <= a <= b < t:
            raise MeshsplatError(f"{where}: clip {n!r} frames [{a}, {b}] outside [0, {t - 1}] ({layout})")
        out[str(n)] = (int(a), int(b))
    return out


def _check_up(up, layout: str, where) -> str | None:
    if up is None:
        return None
    up = str(up).lower()
    if up not in ("y", "z"):
        raise MeshsplatError(f"{where}: up must be 'y' or 'z' ({layout}), got {up!r}")
    return up


def _read_npz(p: Path) -> MeshSequence:
    L = NPZ_LAYOUT
    try:
        z = read_npz(p)
    except MeshsplatError as exc:
        raise MeshsplatError(f"{exc} (expected an {L})") from None
    missing = [k for k in ("faces", "vertices") if k not in z]
    if missing:
        raise MeshsplatError(f"{p}: missing keys {missing} for the {L}; found {sorted(z)}")
    faces, verts = np.asarray(z["faces"]), np.asarray(z["vertices"])
    if verts.ndim == 2:
        verts = verts[None]
    if verts.dtype.kind not in "fiu" or faces.dtype.kind not in "iu":
        raise MeshsplatError(f"{p}: vertices and faces must be numbers ({L}), got {verts.dtype} and {faces.dtype}")
    if verts.ndim != 3 or verts.shape[2] != 3 or verts.shape[0] < 1:
        raise MeshsplatError(f"{p}: vertices must be [T,V,3] ({L}), got {list(verts.shape)}")
    v = verts.shape[1]
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer) or len(faces) == 0:
        raise MeshsplatError(f"{p}: faces must be integer [F,3] ({L}), got {faces.dtype} {list(faces.shape)}")
    if faces.min() < 0 or faces.max() >= v:
        raise MeshsplatError(f"{p}: face indices must lie in [0, {v}) ({L}), got [{faces.min()}, {faces.max()}]")
    if not np.isfinite(verts).all():
        raise MeshsplatError(f"{p}: vertices contain NaN/Inf ({L})")
    seq = MeshSequence(faces.astype(np.int64), verts.astype(np.float32), "npz")
    if "rest" in z:
        rest = np.asarray(z["rest"], np.float32)
        if rest.shape != (v, 3) or not np.isfinite(rest).all():
            raise MeshsplatError(f"{p}: rest must be finite [V,3] with V={v} ({L}), got {list(rest.shape)}")
        seq.rest = rest
    if "uvs" in z:
        uvs = np.asarray(z["uvs"], np.float32)
        if uvs.shape != (v, 2):
            raise MeshsplatError(f"{p}: uvs must be [V,2] with V={v} ({L}), got {list(uvs.shape)}")
        seq.uvs = uvs
    if "colors" in z:
        seq.colors = _colors(z["colors"], v, L, p)
    if "texture" in z:
        seq.texture = _texture(z["texture"], L, p)
    if "fps" in z:
        seq.fps = float(np.asarray(z["fps"]).reshape(-1)[0])
    seq.up = _check_up(_text(z, "up"), L, p)
    seq.attribution = _text(z, "attribution") or ""
    names = [str(s) for s in np.asarray(z["clip_names"]).reshape(-1)] if "clip_names" in z else None
    seq.clips = _clips(names, z.get("clip_ranges", []), seq.num_frames, L, p)
    if seq.fps <= 0 or not np.isfinite(seq.fps):
        raise MeshsplatError(f"{p}: fps must be > 0 ({L}), got {seq.fps}")
    return seq


def _read_frame(q: Path, with_uvs: bool):
    if q.suffix.lower() == ".obj":
        m = read_obj(q, triangulate=True)
        fuv = m.face_uvs.numpy() if (with_uvs and m.face_uvs is not None) else None
        uvs = cast(torch.Tensor, m.uvs).numpy() if fuv is not None else None  # face uvs come with uvs
        return (m.vertices.numpy(), m.faces.numpy(), None, uvs, fuv)
    pm = read_ply_mesh(q)
    return pm.vertices, pm.faces, pm.colors, pm.uvs if with_uvs else None, None


def _read_texture(path: Path) -> np.ndarray:
    try:
        with open_image(path) as im:  # the size checked before decoding
            return np.array(im.convert("RGB"), dtype=np.uint8)
    except (OSError, ValueError) as exc:
        raise MeshsplatError(f"{path}: cannot decode the texture ({exc}) ({FRAMES_LAYOUT})") from None


def _read_folder(p: Path, with_uvs: bool = True) -> MeshSequence:
    L = FRAMES_LAYOUT
    files = sorted((q for q in p.iterdir() if q.suffix.lower() in (".obj", ".ply")), key=lambda q: _natural(q.name))
    if not files:
        raise MeshsplatError(f"{p}: no .obj or .ply frames found ({L})")
    if len({q.suffix.lower() for q in files}) > 1:
        raise MeshsplatError(f"{p}: mixes .obj and .ply frames; use one kind ({L})")
    v0, f0, colors, uv0, fuv = _read_frame(files[0], with_uvs)
    frames = [v0]
    for q in files[1:]:
        v, f, _, _, _ = _read_frame(q, False)
        if v.shape != v0.shape or f.shape != f0.shape or not np.array_equal(f, f0):
            raise MeshsplatError(
                f"{q}: {len(v)} vertices / {len(f)} faces differ from {files[0].name} "
                f"({len(v0)} / {len(f0)}): every frame needs the same mesh ({L})"
            )
        frames.append(v)
    verts = np.stack(frames).astype(np.float32)
    faces = f0.astype(np.int64)
    seq = MeshSequence(faces, verts, "frames", colors=colors)
    if fuv is not None:  # split vertices along UV seams: one sequence vertex per (vertex, uv) pair
        pairs, inv = np.unique(np.stack([faces.reshape(-1), fuv.reshape(-1)], 1), axis=0, return_inverse=True)
        seq.faces = inv.reshape(-1, 3).astype(np.int64)
        seq.vertex_of = pairs[:, 0]
        seq.vertices = verts[:, pairs[:, 0]]
        seq.uvs = uv0[pairs[:, 1]].astype(np.float32)
        seq.colors = None if colors is None else colors[pairs[:, 0]]
    elif uv0 is not None:
        seq.uvs = uv0
    for name in ("texture.png", "texture.jpg", "texture.jpeg"):
        if (p / name).is_file():
            seq.texture = _read_texture(p / name)
            break
    meta_path = p / "sequence.json"
    names, ranges = None, []
    if meta_path.is_file():
        meta = read_json_object(meta_path, f"an object with fps, up, attribution, clips ({L})")
        seq.fps = float(meta.get("fps", seq.fps))
        seq.up = _check_up(meta.get("up"), L, meta_path)
        seq.attribution = str(meta.get("attribution", ""))
        if isinstance(meta.get("clips"), dict):
            names, ranges = list(meta["clips"]), list(meta["clips"].values())
        if seq.fps <= 0:
            raise MeshsplatError(f"{meta_path}: fps must be > 0 ({L}), got {seq.fps}")
    seq.clips = _clips(names, ranges, seq.num_frames, L, meta_path)
    return seq


def read_mesh_sequence(path: Path | str, with_uvs: bool = True) -> MeshSequence:
    """Read a mesh sequence in the ``npz`` or ``frames`` layout (see the module docstring)."""
    p = Path(path)
    if p.is_dir():
        return _read_folder(p, with_uvs)
    if not p.is_file():
        raise MeshsplatError(f"mesh sequence not found: {p} (expected an {NPZ_LAYOUT} or a {FRAMES_LAYOUT})")
    if p.suffix.lower() == ".npz":
        return _read_npz(p)
    if p.suffix.lower() == ".npy":
        raise MeshsplatError(
            f"{p}: a .npy vertex array has no faces; save faces and vertices together as an {NPZ_LAYOUT}"
        )
    raise MeshsplatError(f"{p}: expected an {NPZ_LAYOUT} or a {FRAMES_LAYOUT}")
