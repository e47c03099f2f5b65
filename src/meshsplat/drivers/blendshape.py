"""Blendshape driver: neutral + weighted expression deltas + rigid head pose.

``posed = R @ (neutral + sum_i w_i * delta_i - pivot) + pivot + t`` with ``pivot`` the neutral's
bounding-box centre. Loads the ICT FaceKit ARKit npz (keys: neutral, faces, expr_names, expr_deltas).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat._checks import check_tensor
from meshsplat.drivers.base import as_faces, as_vertices
from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npy, read_npz
from meshsplat.paths import resolve_input

__all__ = ["BlendshapeDriver", "axis_angle_to_matrix", "read_weights"]


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues: ``aa [...,3]`` -> ``[...,3,3]``."""
    theta = aa.norm(dim=-1, keepdim=True)
    k = aa / theta.clamp_min(1e-12)
    kx, ky, kz = k.unbind(-1)
    z = torch.zeros_like(kx)
    Kx = torch.stack([z, -kz, ky, kz, z, -kx, -ky, kx, z], -1).reshape(aa.shape[:-1] + (3, 3))
    s, c = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(Kx)
    return eye + s * Kx + (1 - c) * (Kx @ Kx)


_Rows = torch.Tensor | np.ndarray | Sequence  # one row per frame


class BlendshapeDriver:
    """Linear blendshape model with a per-frame rigid pose.

    Args: ``neutral [V,3]``, ``faces [F,3]``, ``deltas [E,V,3]``, ``names`` (E), and a sequence:
    ``weights [T,E]``, ``rotations [T,3]`` (axis-angle, radians), ``translations [T,3]`` (each optional;
    T taken from whichever is given, default 1 neutral frame).
    """

    def __init__(
        self,
        neutral: torch.Tensor | ArrayLike,
        faces: torch.Tensor | ArrayLike,
        deltas: torch.Tensor | ArrayLike,
        names: Sequence[str] | None = None,
        weights: _Rows | None = None,
        rotations: _Rows | None = None,
        translations: _Rows | None = None,
        face_material: torch.Tensor | ArrayLike | None = None,
        material_names: Sequence[str] | None = None,
    ) -> None:
        self.neutral = as_vertices("neutral", neutral)
        dims = {"V": self.neutral.shape[0]}
        d = deltas if isinstance(deltas, torch.Tensor) else torch.from_numpy(np.asarray(deltas, np.float32))
        self.deltas = check_tensor("deltas", d.float(), "E,V,3", dims, finite=True)
        self.faces = as_faces("faces", faces, self.neutral.shape[0])
        self.names = list(names) if names is not None else [f"e{i}" for i in range(self.deltas.shape[0])]
        self.face_material = None if face_material is None else torch.as_tensor(np.asarray(face_material)).long()
        self.material_names = list(material_names) if material_names is not None else []
        self.pivot = (self.neutral.min(0).values + self.neutral.max(0).values) / 2
        self.set_sequence(weights, rotations, translations)

    @classmethod
    def from_npz(cls, path: Path | str | None = None, **sequence: Any) -> BlendshapeDriver:
        """Load a blend-shape npz (a path or a bundled name; default the bundled ICT FaceKit head ``ict``)."""
        p = resolve_input("ict" if path is None else path)
        if not p.is_file():
            raise MeshsplatError(f"blendshape file not found: {p}")
        arrays = read_npz(p, "blend-shape .npz")  # not an npz, object arrays (refused, never unpickled), ...
        missing = [k for k in ("neutral", "faces", "expr_deltas") if k not in arrays]
        if missing:
            raise MeshsplatError(f"{p}: missing keys {missing}")
        if arrays["expr_deltas"].dtype.kind not in "fiu":
            raise MeshsplatError(f"{p}: expr_deltas must be numbers, got {arrays['expr_deltas'].dtype}")
        return cls(
            arrays["neutral"],
            arrays["faces"],
            arrays["expr_deltas"].astype(np.float32),
            names=[str(s) for s in arrays["expr_names"]] if "expr_names" in arrays else None,
            face_material=arrays.get("face_material"),
            material_names=[str(s) for s in arrays["material_names"]] if "material_names" in arrays else None,
            **sequence,
        )

    def set_sequence(
        self, weights: _Rows | None = None, rotations: _Rows | None = None, translations: _Rows | None = None
    ) -> None:
        e = self.deltas.shape[0]
        lens = [len(x) for x in (weights, rotations, translations) if x is not None]
        t = lens[0] if lens else 1
        dims = {"T": t, "E": e}

        def as_t(x: Any) -> torch.Tensor:
            return x.float() if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x, np.float32))

        self.weights = (
            check_tensor("weights", as_t(weights), "T,E", dims, finite=True)
            if weights is not None
            else torch.zeros(t, e)
        )
        self.rotations = (
            check_tensor("rotations", as_t(rotations), "T,3", dims, finite=True)
            if rotations is not None
            else torch.zeros(t, 3)
        )
        self.translations = (
            check_tensor("translations", as_t(translations), "T,3", dims, finite=True)
            if translations is not None
            else torch.zeros(t, 3)
        )

    def derive(
        self, source_index: ArrayLike, faces: torch.Tensor | ArrayLike, rest: torch.Tensor | ArrayLike | None = None
    ) -> BlendshapeDriver:
        """The model on another mesh: vertex ``i`` takes the expression deltas of vertex ``source_index[i]``
        and rest position ``rest[i]`` (default that vertex's); the pivot (head-pose centre) stays, so a
        pose turns the derived mesh as it turns the model's. Used for welded or decimated driving meshes."""
        src = torch.as_tensor(np.asarray(source_index, np.int64)).reshape(-1)
        v = self.neutral.shape[0]
        if src.numel() == 0 or int(src.min()) < 0 or int(src.max()) >= v:
            raise MeshsplatError(f"source_index: expected indices in [0, {v})")
        neutral = self.neutral[src] if rest is None else as_vertices("rest", rest)
        out = BlendshapeDriver(neutral, faces, self.deltas[:, src], names=self.names)
        out.pivot = self.pivot.clone()
        out.set_sequence(self.weights, self.rotations, self.translations)
        return out

    @property
    def num_frames(self) -> int:
        return int(self.weights.shape[0])

    def rest_vertices(self) -> torch.Tensor:
        return self.neutral.clone()

    def pose(
        self,
        weights: torch.Tensor | ArrayLike,
        rotation: torch.Tensor | ArrayLike | None = None,
        translation: torch.Tensor | ArrayLike | None = None,
    ) -> torch.Tensor:
        """Vertices ``[V,3]`` for ``weights [E]``, axis-angle ``rotation [3]``, ``translation [3]``."""
        w = check_tensor("weights", torch.as_tensor(weights, dtype=torch.float32), "E", {"E": self.deltas.shape[0]})
        v = self.neutral + torch.einsum("e,evc->vc", w, self.deltas)
        if rotation is not None:
            R = axis_angle_to_matrix(torch.as_tensor(rotation, dtype=torch.float32).reshape(3))
            v = (v - self.pivot) @ R.T + self.pivot
        if translation is not None:
            v = v + torch.as_tensor(translation, dtype=torch.float32).reshape(3)
        return v

    def vertices(self, frame: int) -> torch.Tensor:
        if not 0 <= frame < self.num_frames:
            raise MeshsplatError(f"frame: expected 0 <= frame < {self.num_frames}, got {frame}")
        return self.pose(self.weights[frame], self.rotations[frame], self.translations[frame])

    def talking_params(self, times: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
        """Deterministic procedural talking curves at ``times [T]`` seconds: ``(weights [T,E], rotations [T,3])``
        (jaw, smile, brow and blink curves; a gentle head sway)."""
        t = np.asarray(times, np.float64).reshape(-1)
        w = np.zeros((len(t), self.deltas.shape[0]), np.float32)
        blink = np.clip(1 - np.abs((t % 3.1) - 1.5) / 0.12, 0, 1)
        curves = {
            "jawOpen": 0.35 * (1 - np.cos(2 * math.pi * 1.3 * t)) / 2,
            "mouthSmile_L": 0.5 * (1 + np.sin(2 * math.pi * 0.4 * t)) / 2,
            "mouthSmile_R": 0.5 * (1 + np.sin(2 * math.pi * 0.4 * t + 0.3)) / 2,
            "browInnerUp_L": 0.4 * np.clip(np.sin(2 * math.pi * 0.3 * t), 0, 1),
            "browInnerUp_R": 0.4 * np.clip(np.sin(2 * math.pi * 0.3 * t), 0, 1),
            "eyeBlink_L": blink,
            "eyeBlink_R": blink,
        }
        for name, c in curves.items():
            if name in self.names:
                w[:, self.names.index(name)] = c
        rot = np.stack(
            [
                0.12 * np.sin(2 * math.pi * 0.25 * t + 0.7),
                0.35 * np.sin(2 * math.pi * 0.15 * t + 1.9),
                0.06 * np.sin(2 * math.pi * 0.2 * t + 4.0),
            ],
            1,
        ).astype(np.float32)
        return torch.from_numpy(w), torch.from_numpy(rot)

    def talking_sequence(self, num_frames: int, fps: float = 25.0) -> None:
        """Set ``num_frames`` frames of :meth:`talking_params` sampled at ``fps``."""
        w, rot = self.talking_params(np.arange(num_frames) / fps)
        self.set_sequence(w, rot, torch.zeros(num_frames, 3))


def read_weights(weights: _Rows | str | Path, names: Sequence[str]) -> np.ndarray:
    """Blend-shape weights ``[T,K]`` (K = ``len(names)``) from an array, a ``.npy``, a ``.json`` holding
    ``[[...], ...]`` or ``{"names": [...], "weights": [[...], ...]}``, or an ``.npz`` with ``weights`` and
    ``names`` (a tracked capture's ``head_fit.npz``, or the capture folder holding it); named columns are
    matched to ``names``, the others 0."""
    names = list(names)
    if isinstance(weights, (str, Path)):
        p = resolve_input(weights)
        if p.is_dir() and (p / "head_fit.npz").is_file():
            p = p / "head_fit.npz"
        if not p.is_file():
            raise MeshsplatError(f"weights file not found: {p}")
        if p.suffix.lower() == ".json":
            w = _weights_json(p, names)
        elif p.suffix.lower() == ".npz":
            d = read_npz(p, "blend-shape weights .npz (weights [T,K], names [K])")
            if "weights" not in d or "names" not in d:
                raise MeshsplatError(f"{p}: expected the keys 'weights' [T,K] and 'names' [K], got {sorted(d)}")
            w = _named_columns(p, np.asarray(d["weights"], np.float32), [str(n) for n in d["names"]], names)
        else:
            a = read_npy(p, "blend-shape weights [T,K]")
            if a.dtype.kind not in "fiub":
                raise MeshsplatError(f"{p}: blend-shape weights must be numbers, got {a.dtype}")
            w = a.astype(np.float32)
    else:
        w = np.asarray(weights.detach().cpu() if isinstance(weights, torch.Tensor) else weights, np.float32)
    if w.ndim == 1:
        w = w[None]
    if w.ndim != 2 or w.shape[1] != len(names) or w.shape[0] < 1:
        raise MeshsplatError(
            f"weights: expected shape [T,{len(names)}] (one column per blend shape), got {list(w.shape)}"
        )
    if not np.isfinite(w).all():
        raise MeshsplatError("weights: contain NaN/Inf values")
    return w


def _weights_json(p: Path, names: list[str]) -> np.ndarray:
    try:
        doc = json.loads(p.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise MeshsplatError(f"{p}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        return np.asarray(doc, np.float32)
    if "weights" not in doc:
        raise MeshsplatError(f"{p}: expected a list [T][K] or an object with 'weights' (and 'names')")
    w = np.asarray(doc["weights"], np.float32)
    if "names" not in doc:
        return w
    return _named_columns(p, w, [str(s) for s in doc["names"]], names)


def _named_columns(p: Path, w: np.ndarray, cols: list[str], names: list[str]) -> np.ndarray:
    """``w [T,len(cols)]`` with columns named ``cols`` -> ``[T,len(names)]`` (unnamed shapes 0)."""
    unknown = [c for c in cols if c not in names]
    if unknown:
        raise MeshsplatError(f"{p}: unknown blend-shape names {unknown[:5]}")
    if w.ndim != 2 or w.shape[1] != len(cols):
        raise MeshsplatError(f"{p}: 'weights' must be [T,{len(cols)}] to match 'names'")
    full = np.zeros((w.shape[0], len(names)), np.float32)
    full[:, [names.index(c) for c in cols]] = w
    return full
