"""Small meshes shared by tests."""

from __future__ import annotations

import math

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


def box(lo: float = -1.0, hi: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A closed axis-aligned cube: 8 vertices, 12 outward-facing triangles."""
    v = torch.tensor([[x, y, z] for x in (lo, hi) for y in (lo, hi) for z in (lo, hi)], dtype=torch.float32)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return v, torch.tensor(faces)


def uv_sphere(rings: int = 24, segments: int = 48) -> tuple[torch.Tensor, torch.Tensor]:
    """A closed unit sphere: poles plus ``rings - 1`` latitude circles."""
    verts = [[0.0, 0.0, 1.0]]
    for i in range(1, rings):
        th = math.pi * i / rings
        for j in range(segments):
            ph = 2 * math.pi * j / segments
            verts.append([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])
    verts.append([0.0, 0.0, -1.0])
    faces = []
    ring = lambda i, j: 1 + (i - 1) * segments + j % segments  # noqa: E731
    for j in range(segments):
        faces.append((0, ring(1, j), ring(1, j + 1)))
        faces.append((len(verts) - 1, ring(rings - 1, j + 1), ring(rings - 1, j)))
    for i in range(1, rings - 1):
        for j in range(segments):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            faces += [(a, c, d), (a, d, b)]
    return torch.tensor(verts), torch.tensor(faces)
