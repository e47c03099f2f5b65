"""Small meshes shared by tests."""

from __future__ import annotations

import torch

from meshsplat.mesh import TriMesh


def plane(n: int = 6) -> TriMesh:
    """Unit square in z=0 split into n x n quads, two triangles each (consistent diagonals)."""
    t = torch.linspace(0, 1, n + 1)
    yy, xx = torch.meshgrid(t, t, indexing="ij")
    verts = torch.stack([xx.reshape(-1), yy.reshape(-1), torch.zeros((n + 1) ** 2)], -1)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, i * (n + 1) + j + 1, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1
            faces += [[a, b, d], [a, d, c]]
    return TriMesh(verts, torch.tensor(faces))
