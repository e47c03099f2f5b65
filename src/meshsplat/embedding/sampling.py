"""Area-weighted uniform sampling of embeddings on a mesh surface."""

from __future__ import annotations

import torch

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import degenerate_faces, face_areas

__all__ = ["sample_surface"]


def sample_surface(
    verts: torch.Tensor, faces: torch.Tensor, n: int, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points uniform over the surface: ``face [n]`` long and ``uv [n,2]`` (verts' dtype/device).

    Faces are drawn with probability proportional to area, then a uniform point in the
    triangle (square-root warp), so the density per unit area is constant.
    """
    check_tensor("verts", verts, "V,3", dtype="float", finite=True)
    check_tensor("faces", faces, "F,3", dtype="int")
    if n < 0:
        raise MeshsplatError(f"n: expected a non-negative count, got {n}")
    faces = faces.to(verts.device)
    areas = face_areas(verts.detach(), faces).masked_fill(degenerate_faces(verts, faces), 0.0)
    if not bool(areas.sum() > 0):
        raise MeshsplatError("verts/faces: the mesh has zero total area, cannot sample its surface")
    dev = verts.device
    gen_dev = generator.device if generator is not None else dev
    face = torch.multinomial(areas.to(gen_dev, torch.float64), n, replacement=True, generator=generator).to(dev)
    r = torch.rand(n, 2, generator=generator, device=gen_dev, dtype=torch.float64).to(dev)
    s = r[:, 0].sqrt()
    u = 1.0 - s
    v = s * (1.0 - r[:, 1])
    uv = torch.stack([u, v], dim=-1).to(verts.dtype)
    return face, uv
