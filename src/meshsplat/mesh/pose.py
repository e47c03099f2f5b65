"""One frame's posed mesh quantities used to place embedded Gaussians."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import pose_quantities
from meshsplat.mesh.tri_mesh import TriMesh
from meshsplat.mesh.visibility import ShadowMaps, shadow_maps

__all__ = ["MeshPose"]


@dataclass
class MeshPose:
    """verts [V,3], vertex_normals [V,3], vertex_quats [V,4] (wxyz, canonical -> posed),
    area_ratio [F] (posed / canonical face area), faces [F,3] long on the same device."""

    verts: torch.Tensor
    vertex_normals: torch.Tensor
    vertex_quats: torch.Tensor
    area_ratio: torch.Tensor
    faces: torch.Tensor
    _shadows: tuple | None = field(default=None, repr=False, compare=False)  # (key, ShadowMaps): the last maps

    @classmethod
    def from_vertices(cls, mesh: TriMesh, verts: torch.Tensor, normal_weighting: str = "area") -> MeshPose:
        """Posed quantities for ``verts [V,3]`` (differentiable w.r.t. verts)."""
        if not isinstance(mesh, TriMesh):
            raise MeshsplatError(f"mesh: expected a TriMesh, got {type(mesh).__name__}")
        check_tensor("verts", verts, "V,3", {"V": mesh.num_vertices}, dtype="float", finite=True)
        faces = mesh._on("faces", verts.device)
        v_cano = mesh.vertices.to(device=verts.device, dtype=verts.dtype)
        normals, quats, ratio = pose_quantities(v_cano, verts, faces, normal_weighting)
        return cls(verts=verts, vertex_normals=normals, vertex_quats=quats, area_ratio=ratio, faces=faces)

    @classmethod
    def canonical(cls, mesh: TriMesh) -> MeshPose:
        """The rest pose: identity rotations, unit area ratios."""
        return cls.from_vertices(mesh, mesh.vertices)

    def shadow_maps(self, directions: torch.Tensor, grid: int) -> ShadowMaps:
        """:func:`~meshsplat.mesh.visibility.shadow_maps` of this pose along ``directions [K,3]``; the last maps
        are kept, so a pose rendered again (a training frame, another camera) does not build them again."""
        key = (int(grid), directions.dtype, tuple(directions.detach().flatten().tolist()), self.verts._version)
        if self._shadows is None or self._shadows[0] != key:
            self._shadows = (key, shadow_maps(self.verts, self.faces, directions, grid))
        return self._shadows[1]

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])
