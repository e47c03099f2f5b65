"""A lit sphere capture for the shading tests."""

from __future__ import annotations

import torch

from meshsplat.gaussians.shading import Shading
from meshsplat.mesh import TriMesh


def _sphere() -> TriMesh:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    return TriMesh(torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces))


def _lit_from_x() -> Shading:
    sh = Shading()
    sh.coeffs[3] = 1.5  # linear term in x: brighter on the +x side
    return sh
