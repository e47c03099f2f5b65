"""project_to_surface recovers embeddings of points generated on the Phong surface."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from meshsplat.embedding import closest_point_on_triangles, embed, project_to_surface, sample_surface
from meshsplat.errors import MeshsplatError
from meshsplat.mesh import MeshPose, TriMesh


def _points_with_hard_cases(mesh, n, seed, dmax=0.02):
    """Random embeddings incl. points on/near edges and vertices, |d| up to dmax * bbox diagonal."""
    gen = torch.Generator().manual_seed(seed)
    face, uv = sample_surface(mesh.vertices, mesh.faces, n, generator=gen)
    uv = uv.double()
    q = n // 4
    uv[:q, 1] = 1 - uv[:q, 0] - 1e-7 * torch.rand(q, generator=gen, dtype=torch.float64)  # near an edge
    uv[q : 2 * q] = torch.tensor([1.0, 0.0], dtype=torch.float64)  # on a vertex
    uv[2 * q : 2 * q + q // 2] = torch.tensor([0.0, 0.0], dtype=torch.float64) + 1e-6  # near a vertex
    diag = mesh.bbox_diagonal()
    d = (2 * torch.rand(n, generator=gen, dtype=torch.float64) - 1) * dmax * diag
    return face, uv, d, diag


def _recover(mesh, n, seed):
    mesh64 = TriMesh(mesh.vertices.double(), mesh.faces)
    pose = MeshPose.canonical(mesh64)
    face, uv, d, diag = _points_with_hard_cases(mesh64, n, seed)
    x, _ = embed(pose, face, uv, d)
    f2, uv2, d2 = project_to_surface(mesh64, mesh64.vertices, x)
    x2, _ = embed(pose, f2, uv2, d2)
    w = torch.cat([uv2, 1 - uv2.sum(1, keepdim=True)], 1)
    assert bool((w >= 0).all() and (w <= 1).all()) and int(f2.max()) < mesh.num_faces
    return (x2 - x).norm(dim=1) / diag


def test_sphere_recovery():
    s = trimesh.creation.icosphere(subdivisions=3)
    mesh = TriMesh(torch.tensor(s.vertices), torch.tensor(s.faces))
    err = _recover(mesh, 4000, 0)
    assert float((err < 1e-4).double().mean()) >= 0.99


def test_cesium_man_recovery(assets):
    mesh = TriMesh.load(assets / "gltf" / "CesiumMan.glb")
    err = _recover(mesh, 4000, 1)
    assert float((err < 1e-4).double().mean()) >= 0.99


def test_posed_mesh_and_float32():
    s = trimesh.creation.icosphere(subdivisions=2)
    mesh = TriMesh(torch.tensor(s.vertices, dtype=torch.float32), torch.tensor(s.faces))
    posed = mesh.vertices * torch.tensor([1.5, 0.7, 1.0]) + 0.2
    pose = MeshPose.from_vertices(mesh, posed)
    face, uv = sample_surface(mesh.vertices, mesh.faces, 1000, generator=torch.Generator().manual_seed(2))
    d = 0.03 * (torch.rand(1000) - 0.5)
    x, _ = embed(pose, face, uv, d)
    f2, uv2, d2 = project_to_surface(mesh, posed, x)
    assert uv2.dtype == torch.float32 and d2.dtype == torch.float32 and f2.dtype == torch.long
    x2, _ = embed(pose, f2, uv2, d2)
    assert float(((x2 - x).norm(dim=1) < 1e-4).float().mean()) >= 0.99


def test_far_points_no_nan():
    s = trimesh.creation.icosphere(subdivisions=2)
    mesh = TriMesh(torch.tensor(s.vertices), torch.tensor(s.faces))
    x = torch.cat([torch.randn(200, 3, dtype=torch.float64) * 100, torch.zeros(1, 3, dtype=torch.float64)])
    _f, uv, d = project_to_surface(mesh, mesh.vertices, x)
    assert bool(torch.isfinite(uv).all() and torch.isfinite(d).all())
    # far outside: displacement about |x| - 1 (normal direction)
    assert torch.allclose(d[:200], x[:200].norm(dim=1) - 1, rtol=0.01)


def test_closest_point_matches_dense_sampling():
    s = trimesh.creation.icosphere(subdivisions=0)
    rng = np.random.default_rng(0)
    x = torch.as_tensor(rng.normal(size=(200, 3)) * 1.5)
    tri = torch.tensor(s.vertices[s.faces])  # [F,3,3]
    d2, w = closest_point_on_triangles(x[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    # the reported weights reproduce the reported distance
    p = (w[..., None] * tri[None]).sum(-2)
    assert torch.allclose(((p - x[:, None]) ** 2).sum(-1), d2, atol=1e-12)
    # a dense barycentric grid never beats it, and gets within the grid resolution
    g = torch.linspace(0, 1, 81, dtype=torch.float64)
    gu, gv = torch.meshgrid(g, g, indexing="ij")
    keep = (gu + gv) <= 1
    bw = torch.stack([gu[keep], gv[keep], 1 - gu[keep] - gv[keep]], -1)  # [S,3]
    samples = torch.einsum("sk,fkc->fsc", bw, tri).reshape(-1, 3)
    brute = torch.cdist(x, samples).min(1).values
    ours = d2.min(1).values.sqrt()
    assert bool((ours <= brute + 1e-12).all()) and float((brute - ours).max()) < 0.02


def test_bad_points_raise():
    s = trimesh.creation.icosphere(subdivisions=0)
    mesh = TriMesh(torch.tensor(s.vertices), torch.tensor(s.faces))
    with pytest.raises(MeshsplatError, match="points"):
        project_to_surface(mesh, mesh.vertices, torch.full((2, 3), float("nan"), dtype=torch.float64))
