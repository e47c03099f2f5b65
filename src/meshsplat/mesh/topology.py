"""Edge/face connectivity of a triangle mesh, built with vectorized sorting.

Local edge ``j`` of a face joins its corners ``j`` and ``(j+1) % 3``. Faces are
adjacent across an edge only when exactly two faces use it (manifold edge);
boundary edges (one face) and non-manifold edges (three or more faces) get
``face_adj == -1``. Faces with a repeated vertex index produce a self-loop
edge ``(a, a)`` and are reported as degenerate by index.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from meshsplat._typing import ArrayLike
from meshsplat.errors import MeshsplatError

__all__ = ["MeshTopology", "as_face_tensor"]


def as_face_tensor(faces: ArrayLike, num_vertices: int | None = None) -> torch.Tensor:
    """Validate ``faces [F,3]`` (array or tensor of ints) and return a CPU long tensor."""
    if isinstance(faces, np.ndarray):
        faces = torch.from_numpy(np.ascontiguousarray(faces))
    if not isinstance(faces, torch.Tensor):
        raise MeshsplatError(f"faces: expected an integer tensor of shape [F,3], got {type(faces).__name__}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshsplatError(f"faces: expected shape [F,3], got {list(faces.shape)}")
    if faces.is_floating_point() or faces.dtype == torch.bool:
        raise MeshsplatError(f"faces: expected an integer dtype, got {faces.dtype}")
    faces = faces.detach().to("cpu", torch.long)
    if faces.shape[0] == 0:
        raise MeshsplatError("faces: mesh has no faces")
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or (num_vertices is not None and hi >= num_vertices):
        n = "?" if num_vertices is None else num_vertices
        raise MeshsplatError(f"faces: vertex indices must lie in [0, {n}), got range [{lo}, {hi}]")
    return faces


@dataclass(frozen=True)
class MeshTopology:
    """Connectivity tables (all CPU long tensors unless noted).

    faces [F,3]; edges [E,2] sorted vertex pairs; face_edges [F,3] edge id of local edge j;
    face_adj [F,3] face across local edge j (-1 at boundary / non-manifold edges);
    adj_local [F,3] local index of that edge in the neighbour (-1 if none);
    edge_face_count [E]; boundary_edges, nonmanifold_edges (edge ids);
    edge_flipped [F,3] bool: local edge j runs from the larger to the smaller vertex id;
    inconsistent_edges: manifold edges whose two faces disagree on orientation.
    """

    faces: torch.Tensor
    num_vertices: int
    edges: torch.Tensor
    face_edges: torch.Tensor
    face_adj: torch.Tensor
    adj_local: torch.Tensor
    edge_face_count: torch.Tensor
    boundary_edges: torch.Tensor
    nonmanifold_edges: torch.Tensor
    edge_flipped: torch.Tensor
    inconsistent_edges: torch.Tensor
    index_degenerate_faces: torch.Tensor

    @classmethod
    def from_faces(cls, faces: ArrayLike, num_vertices: int | None = None) -> MeshTopology:
        faces = as_face_tensor(faces, num_vertices)
        nf = faces.shape[0]
        nv = int(faces.max()) + 1 if num_vertices is None else int(num_vertices)
        start = faces  # [F,3] corner j
        end = faces[:, [1, 2, 0]]  # [F,3] corner j+1
        lo, hi = torch.minimum(start, end), torch.maximum(start, end)
        key = (lo * nv + hi).reshape(-1)  # half-edge h = 3*f + j
        uniq, inverse, counts = torch.unique(key, return_inverse=True, return_counts=True)
        edges = torch.stack([uniq // nv, uniq % nv], dim=1)
        face_edges = inverse.reshape(nf, 3)

        # group half-edges by edge: positions [first[e], first[e] + counts[e])
        order = torch.sort(inverse, stable=True).indices
        first = torch.cumsum(counts, 0) - counts
        face_adj = torch.full((nf * 3,), -1, dtype=torch.long)
        adj_local = torch.full((nf * 3,), -1, dtype=torch.long)
        manifold = torch.nonzero(counts == 2).squeeze(1)
        h0, h1 = order[first[manifold]], order[first[manifold] + 1]
        face_adj[h0], adj_local[h0] = h1 // 3, h1 % 3
        face_adj[h1], adj_local[h1] = h0 // 3, h0 % 3
        # a self-loop edge (a, a) is never a walkable connection
        selfloop = (edges[:, 0] == edges[:, 1])[inverse]
        face_adj[selfloop], adj_local[selfloop] = -1, -1

        flipped = (start > end).reshape(-1)
        incons = manifold[flipped[h0] == flipped[h1]]
        idx_degen = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
        return cls(
            faces=faces,
            num_vertices=nv,
            edges=edges,
            face_edges=face_edges,
            face_adj=face_adj.reshape(nf, 3),
            adj_local=adj_local.reshape(nf, 3),
            edge_face_count=counts,
            boundary_edges=torch.nonzero(counts == 1).squeeze(1),
            nonmanifold_edges=torch.nonzero(counts > 2).squeeze(1),
            edge_flipped=flipped.reshape(nf, 3),
            inconsistent_edges=incons,
            index_degenerate_faces=torch.nonzero(idx_degen).squeeze(1),
        )

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edges.shape[0])

    def unreferenced_vertices(self) -> torch.Tensor:
        used = torch.zeros(self.num_vertices, dtype=torch.bool)
        used[self.faces.reshape(-1)] = True
        return torch.nonzero(~used).squeeze(1)

    def summary(self) -> str:
        return (
            f"{self.num_vertices} vertices, {self.num_faces} faces, {self.num_edges} edges "
            f"({len(self.boundary_edges)} boundary, {len(self.nonmanifold_edges)} non-manifold, "
            f"{len(self.inconsistent_edges)} with inconsistent orientation); "
            f"{len(self.index_degenerate_faces)} faces repeat a vertex, "
            f"{len(self.unreferenced_vertices())} unreferenced vertices"
        )
