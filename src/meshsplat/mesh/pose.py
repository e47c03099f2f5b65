"""One frame's posed mesh quantities used to place embedded Gaussians."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import face_area_ratio, vertex_normals, vertex_quaternions
from meshsplat.mesh.tri_mesh import TriMesh

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

    @classmethod
    def from_vertices(cls, mesh: TriMesh, verts: torch.Tensor, normal_weighting: str = "area") -> MeshPose:
        """Posed quantities for ``verts [V,3]`` (differentiable w.r.t. verts)."""
        if not isinstance(mesh, TriMesh):
            raise MeshsplatError(f"mesh: expected a TriMesh, got {type(mesh).__name__}")
        check_tensor("verts", verts, "V,3", {"V": mesh.num_vertices}, dtype="float", finite=True)
        faces = mesh._on("faces", verts.device)
        v_cano = mesh.vertices.to(device=verts.device, dtype=verts.dtype)
        return cls(
            verts=verts,
            vertex_normals=vertex_normals(verts, faces, normal_weighting),
            vertex_quats=vertex_quaternions(v_cano, verts, faces),
            area_ratio=face_area_ratio(v_cano, verts, faces),
            faces=faces,
        )

    @classmethod
    def canonical(cls, mesh: TriMesh) -> MeshPose:
        """The rest pose: identity rotations, unit area ratios."""
        return cls.from_vertices(mesh, mesh.vertices)

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])
