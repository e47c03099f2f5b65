"""Generator sources for per-frame mesh sequences, and the up-axis change for any source.

``SequenceSource`` plays a :class:`~meshsplat.drivers.mesh_sequence.MeshSequence` (linear
interpolation between frames at its ``fps``). A derived (welded, smoothed, decimated) driving mesh
follows source vertex ``src[i]``; a rest offset from that vertex (smoothing, decimation) turns with
the vertex's rotation between rest and pose. ``UpAxisSource`` turns a z-up source into the
project's y-up world.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat.drivers.mesh_sequence import MeshSequence
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import vertex_quaternions
from meshsplat.mesh.quaternion import quat_to_matrix

__all__ = ["SequenceSource", "UpAxisSource", "up_rotation", "with_up"]


class SequenceSource:
    """A mesh sequence as a generator source (see :mod:`meshsplat.synth.sources`)."""

    def __init__(self, seq: MeshSequence, name: str = "sequence") -> None:
        self.seq = seq
        self.name = name
        v = seq.vertices.shape[1]
        self._frames = torch.from_numpy(np.ascontiguousarray(seq.vertices, np.float32))
        self._rest = torch.from_numpy(seq.rest) if seq.rest is not None else self._frames[0].clone()
        self._base_faces = torch.from_numpy(seq.faces).long()
        self.faces = self._base_faces
        self.uvs = torch.from_numpy(seq.uvs) if seq.uvs is not None else torch.zeros(v, 2)
        self.vertex_colors = torch.from_numpy(seq.colors) if seq.colors is not None else torch.ones(v, 3)
        self.face_material = torch.zeros(len(seq.faces), dtype=torch.long)
        tex = None if seq.texture is None else torch.from_numpy(seq.texture).float() / 255.0
        if tex is not None and seq.uvs is None:
            raise MeshsplatError(f"{name}: has a texture but no uvs; add uvs [V,2] (or OBJ vt) or drop the texture")
        self.materials = [(torch.ones(3), tex)]
        self.clips = list(seq.clips)
        self.attribution = seq.attribution
        self.up = seq.up
        self._src: torch.Tensor | None = None
        self._offset: torch.Tensor | None = None

    def time_range(self, clip: str | None) -> tuple[float, float]:
        a, b = self.seq.clips[clip if clip is not None else self.clips[0]]
        return a / self.seq.fps, b / self.seq.fps

    def _frame_at(self, clip, time) -> torch.Tensor:
        a, b = self.seq.clips[clip if clip is not None else self.clips[0]]
        f = min(max(float(time) * self.seq.fps, a), b)
        i0 = int(np.floor(f))
        i1 = min(i0 + 1, b)
        w = f - i0
        return self._frames[i0] if w < 1e-9 else (1 - w) * self._frames[i0] + w * self._frames[i1]

    def _drive(self, v: torch.Tensor) -> torch.Tensor:
        if self._src is None:
            return v.clone()
        out = v[self._src]
        if self._offset is not None:
            q = vertex_quaternions(self._rest, v, self._base_faces)[self._src]
            out = out + (quat_to_matrix(q) @ self._offset[..., None])[..., 0]
        return out

    def pose(self, clip: str | None, time: float) -> torch.Tensor:
        return self._drive(self._frame_at(clip, time))

    def rest(self) -> torch.Tensor:
        return self._drive(self._rest)

    def frame(self, i: int) -> torch.Tensor:
        """Stored frame ``i`` (on the derived mesh when derived)."""
        return self._drive(self._frames[int(i)])

    def derive(self, src: ArrayLike, faces: ArrayLike, rest: ArrayLike | None = None) -> SequenceSource:
        out = object.__new__(SequenceSource)
        out.__dict__.update(self.__dict__)
        s = torch.as_tensor(np.asarray(src), dtype=torch.long)
        out._src = s
        out.faces = torch.as_tensor(np.asarray(faces), dtype=torch.long)
        out.uvs, out.vertex_colors = self.uvs[s], self.vertex_colors[s]
        out._offset = None
        if rest is not None:
            r = torch.as_tensor(np.asarray(rest), dtype=torch.float32)
            out._offset = r - self._rest[s]
        return out


def up_rotation(up: str) -> np.ndarray:
    """Rotation ``[3,3]`` taking the asset's ``up`` axis to world +y (identity for ``"y"``)."""
    if up == "y":
        return np.eye(3)
    if up == "z":
        return np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # (x, y, z) -> (x, z, -y)
    raise MeshsplatError(f"up: expected 'y' or 'z', got {up!r}")


class UpAxisSource:
    """``source`` seen in the y-up world: every pose is rotated by ``R [3,3]``."""

    def __init__(self, source: Any, R: np.ndarray) -> None:
        self.inner = source
        self.R = torch.as_tensor(R, dtype=torch.float32)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def pose(self, clip: str | None, time: float) -> torch.Tensor:
        return self.inner.pose(clip, time) @ self.R.T

    def rest(self) -> torch.Tensor:
        return self.inner.rest() @ self.R.T

    def derive(self, src: ArrayLike, faces: ArrayLike, rest: ArrayLike | None = None) -> UpAxisSource:
        r = None if rest is None else torch.as_tensor(np.asarray(rest), dtype=torch.float32) @ self.R
        return UpAxisSource(self.inner.derive(src, faces, r), self.R.numpy())


def with_up(source: Any, up: str | None) -> tuple[Any, str, str]:
    """``(source in the y-up world, up used, how it was chosen)``: ``up`` given, else the asset's own
    (glTF is y-up by specification; a mesh sequence may say ``up``), else y."""
    own = getattr(source, "up", None)
    if up is not None:
        used, how = str(up).lower(), "--up"
    elif own is not None:
        used, how = own, "from the asset"
    elif hasattr(source, "driver") and type(source).__name__ == "GltfSource":
        used, how = "y", "glTF is y-up"
    else:
        used, how = "y", "default; pass --up z for a z-up asset"
    R = up_rotation(used)
    return (source if used == "y" else UpAxisSource(source, R)), used, how
