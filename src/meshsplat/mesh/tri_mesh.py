"""Canonical triangle mesh: validated vertices/faces, cached topology, a readable check()."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat._typing import ArrayLike
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import bbox_diagonal, degenerate_faces, face_areas
from meshsplat.mesh.topology import MeshTopology, as_face_tensor

__all__ = ["TriMesh", "MeshReport", "validate_mesh"]


def validate_mesh(vertices: ArrayLike, faces: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Return ``(vertices [V,3] float, faces [F,3] long)``; raise MeshsplatError if unusable.

    Unusable: wrong shapes or dtypes, NaN/Inf vertices, no faces, out-of-range indices.
    """
    if isinstance(vertices, np.ndarray):
        vertices = torch.from_numpy(np.ascontiguousarray(vertices))
    if not isinstance(vertices, torch.Tensor):
        raise MeshsplatError(f"vertices: expected a float tensor of shape [V,3], got {type(vertices).__name__}")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
        raise MeshsplatError(f"vertices: expected shape [V,3] with V > 0, got {list(vertices.shape)}")
    if not vertices.is_floating_point():
        vertices = vertices.float()
    bad = ~torch.isfinite(vertices).all(1)
    if bool(bad.any()):
        raise MeshsplatError(f"vertices: {int(bad.sum())} vertices contain NaN/Inf (first: {int(bad.nonzero()[0])})")
    faces = as_face_tensor(faces, vertices.shape[0]).to(vertices.device)
    return vertices, faces


@dataclass
class MeshReport:
    """Result of :meth:`TriMesh.check`; ``str(report)`` is human readable."""

    num_vertices: int
    num_faces: int
    num_edges: int
    boundary_edges: int
    nonmanifold_edges: int
    inconsistent_edges: int
    degenerate_faces: list[int] = field(default_factory=list)
    unreferenced_vertices: int = 0
    num_components: int = 1

    @property
    def ok(self) -> bool:
        """True when walking and embedding work everywhere (no degenerate / non-manifold parts)."""
        return not self.degenerate_faces and self.nonmanifold_edges == 0

    def __str__(self) -> str:
        lines = [
            f"mesh: {self.num_vertices} vertices, {self.num_faces} faces, {self.num_edges} edges, "
            f"{self.num_components} connected component(s)",
            f"  boundary edges:           {self.boundary_edges}" + ("  (closed)" if self.boundary_edges == 0 else ""),
            f"  non-manifold edges:       {self.nonmanifold_edges}"
            + ("  (no walking across them)" if self.nonmanifold_edges else ""),
            f"  inconsistently oriented:  {self.inconsistent_edges}",
            f"  degenerate faces:         {len(self.degenerate_faces)}"
            + (f"  e.g. {self.degenerate_faces[:5]}" if self.degenerate_faces else ""),
            f"  unreferenced vertices:    {self.unreferenced_vertices}",
            f"  status: {'ok' if self.ok else 'usable with caveats'}",
        ]
        return "\n".join(lines)


class TriMesh:
    """Canonical mesh ``vertices [V,3]`` (float) and ``faces [F,3]`` (long), validated on construction."""

    def __init__(self, vertices: ArrayLike, faces: ArrayLike) -> None:
        self.vertices, self.faces = validate_mesh(vertices, faces)

    @classmethod
    def load(cls, path: str | Path) -> TriMesh:
        """Load any format trimesh reads (OBJ, PLY, GLB, ...), scene flattened into one mesh."""
        import trimesh as _trimesh

        path = Path(path)
        if not path.exists():
            raise MeshsplatError(f"mesh file not found: {path}")
        try:
            m: Any = _trimesh.load(str(path), force="mesh", process=False)  # a Trimesh (force="mesh")
        except Exception as exc:  # noqa: BLE001 - reported as one clear message
            raise MeshsplatError(f"cannot read mesh {path}: {exc}") from None
        return cls(
            torch.as_tensor(np.asarray(m.vertices), dtype=torch.float32),
            torch.as_tensor(np.asarray(m.faces), dtype=torch.long),
        )

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @cached_property
    def topology(self) -> MeshTopology:
        return MeshTopology.from_faces(self.faces, self.num_vertices)

    def _on(self, name: str, device: torch.device) -> torch.Tensor:
        """Per-device cache of topology tables (e.g. ``face_adj`` on CUDA)."""
        cache = self.__dict__.setdefault("_device_cache", {})
        key = (name, str(device))
        if key not in cache:
            cache[key] = getattr(self.topology, name).to(device)
        return cache[key]

    def degenerate_faces(self) -> torch.Tensor:
        """[F] bool, zero-area or repeated-index faces of the canonical mesh."""
        return degenerate_faces(self.vertices, self.faces).cpu()

    def face_areas(self) -> torch.Tensor:
        return face_areas(self.vertices, self.faces)

    def bbox_diagonal(self) -> float:
        return bbox_diagonal(self.vertices)

    def check(self) -> MeshReport:
        """Inspect the mesh without raising; see :class:`MeshReport`."""
        topo = self.topology
        return MeshReport(
            num_vertices=self.num_vertices,
            num_faces=self.num_faces,
            num_edges=topo.num_edges,
            boundary_edges=len(topo.boundary_edges),
            nonmanifold_edges=len(topo.nonmanifold_edges),
            inconsistent_edges=len(topo.inconsistent_edges),
            degenerate_faces=torch.nonzero(self.degenerate_faces()).squeeze(1).tolist(),
            unreferenced_vertices=len(topo.unreferenced_vertices()),
            num_components=_count_components(topo),
        )

    def __repr__(self) -> str:
        return f"TriMesh(V={self.num_vertices}, F={self.num_faces})"


def _count_components(topo: MeshTopology) -> int:
    """Connected components over faces sharing vertices (scipy sparse graph)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = topo.faces.numpy()
    nf = f.shape[0]
    rows = np.repeat(np.arange(nf), 3)
    g = coo_matrix((np.ones(nf * 3), (rows, f.reshape(-1) + nf)), shape=(nf + topo.num_vertices,) * 2)
    _n, labels = connected_components(g, directed=False)
    used = np.unique(labels[:nf])
    return len(used)
