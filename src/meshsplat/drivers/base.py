"""Mesh driver protocol and the per-frame vertex sequence driver."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError

__all__ = ["MeshDriver", "SequenceDriver", "as_faces", "as_vertices"]


@runtime_checkable
class MeshDriver(Protocol):
    """Anything that poses a fixed-topology mesh frame by frame."""

    faces: torch.Tensor  # [F, 3] long

    @property
    def num_frames(self) -> int: ...

    def rest_vertices(self) -> torch.Tensor: ...  # [V, 3] float32

    def vertices(self, frame: int) -> torch.Tensor: ...  # [V, 3] float32


def as_faces(name: str, faces: torch.Tensor | ArrayLike, num_vertices: int | None = None) -> torch.Tensor:
    """Faces as a [F, 3] long tensor with indices checked against ``num_vertices``."""
    f = torch.as_tensor(np.asarray(faces) if not isinstance(faces, torch.Tensor) else faces)
    check_tensor(name, f, "F,3", dtype="int")
    f = f.long()
    if num_vertices is not None and f.numel() and (int(f.min()) < 0 or int(f.max()) >= num_vertices):
        raise MeshsplatError(f"{name}: indices must lie in [0, {num_vertices}), got [{int(f.min())}, {int(f.max())}]")
    return f


def as_vertices(
    name: str, verts: torch.Tensor | ArrayLike, spec: str = "V,3", dims: dict | None = None
) -> torch.Tensor:
    """Vertices as float32 tensor of shape ``spec``, finite."""
    v = verts if isinstance(verts, torch.Tensor) else torch.as_tensor(np.asarray(verts))
    check_tensor(name, v, spec, dims=dims, dtype="float", finite=True)
    return v.float()


class SequenceDriver:
    """Driver over stored per-frame vertices ``[T, V, 3]`` with fixed ``faces [F, 3]``.

    ``rest`` defaults to frame 0. Arrays may be numpy (memory-mapped is fine) or torch.
    """

    def __init__(
        self,
        vertices: np.ndarray | torch.Tensor,
        faces: torch.Tensor | ArrayLike,
        rest: torch.Tensor | ArrayLike | None = None,
    ) -> None:
        if isinstance(vertices, np.ndarray) and vertices.ndim != 3:
            raise MeshsplatError(f"vertices: expected shape [T,V,3], got {list(vertices.shape)}")
        self._seq = vertices
        shape = tuple(vertices.shape)
        if len(shape) != 3 or shape[2] != 3 or shape[0] < 1:
            raise MeshsplatError(f"vertices: expected shape [T,V,3] with T>=1, got {list(shape)}")
        self.faces = as_faces("faces", faces, shape[1])
        self._rest = as_vertices("rest", rest) if rest is not None else None
        if self._rest is not None and self._rest.shape[0] != shape[1]:
            raise MeshsplatError(f"rest: expected {shape[1]} vertices, got {self._rest.shape[0]}")

    @property
    def num_frames(self) -> int:
        return int(self._seq.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self._seq.shape[1])

    def rest_vertices(self) -> torch.Tensor:
        return self._rest.clone() if self._rest is not None else self.vertices(0)

    def vertices(self, frame: int) -> torch.Tensor:
        if not 0 <= frame < self.num_frames:
            raise MeshsplatError(f"frame: expected 0 <= frame < {self.num_frames}, got {frame}")
        v = self._seq[frame]
        v = v.detach().clone() if isinstance(v, torch.Tensor) else torch.from_numpy(np.array(v, dtype=np.float32))
        return v.float()
