"""Lifted optimisation: fold the trainable offsets ``duv`` into the embedding (face, uv).

``walk_embeddings`` moves each embedding by its ``duv`` with walking on triangles on the
canonical mesh, writes the resulting (face, uv) IN PLACE, zeroes ``duv`` and its Adam moments,
and resets the Adam moments of ``d`` for the embeddings that changed face. The parameter
objects registered in the optimizers are kept (unlike the published code, which swaps in a new
tensor and thereby freezes ``d``).

With ``walk=False`` (ablation "no walking") ``uv + duv`` is instead projected back onto the
current triangle: no face ever changes.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from meshsplat.embedding import project_uv_to_triangle, walk_on_triangles
from meshsplat.mesh import TriMesh
from meshsplat.train.strategy.ops import zero_moments

__all__ = ["walk_embeddings"]


@torch.no_grad()
def walk_embeddings(
    params: dict[str, torch.Tensor],
    optimizers: Mapping[str, torch.optim.Optimizer],
    mesh: TriMesh,
    *,
    walk: bool = True,
    mode: str = "paper",
    max_crossings: int = 64,
) -> torch.Tensor:
    """Fold ``duv`` into (face, uv); returns ``changed [N] bool`` (faces that changed)."""
    face, uv, duv = params["face"], params["uv"], params["duv"]
    if walk:
        verts = mesh.vertices.to(device=uv.device, dtype=uv.dtype)
        res = walk_on_triangles(mesh, verts, face, uv, duv.detach(), mode=mode, max_crossings=max_crossings)
        changed = res.changed.to(face.device)
        face.copy_(res.face)
        uv.copy_(res.uv.to(uv.dtype))
    else:
        uv.copy_(project_uv_to_triangle(uv + duv.detach()))
        changed = torch.zeros_like(face, dtype=torch.bool)
    duv.zero_()
    zero_moments(optimizers, "duv")
    if bool(changed.any()):
        zero_moments(optimizers, "d", changed)
    return changed
