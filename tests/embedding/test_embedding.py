"""embed / pose_frame / sample_surface: geometry, pose rotation and scale, gradients."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from meshsplat.embedding import embed, pose_frame, sample_surface
from meshsplat.errors import MeshsplatError
from meshsplat.mesh import MeshPose, TriMesh, face_areas, quat_multiply, quat_to_matrix


def _sphere_mesh(sub=2, dtype=torch.float64):
    s = trimesh.creation.icosphere(subdivisions=sub)
    return TriMesh(torch.tensor(s.vertices, dtype=dtype), torch.tensor(s.faces))


def _rigid(mesh, angle=2.5, scale=1.0):
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=mesh.vertices.dtype)
    axis = axis / axis.norm()
    q = torch.cat([torch.tensor([math.cos(angle / 2)], dtype=axis.dtype), math.sin(angle / 2) * axis])
    r = quat_to_matrix(q)
    return q, r, scale * mesh.vertices @ r.T + torch.tensor([1.0, 2.0, 3.0], dtype=axis.dtype)


def test_embed_on_surface_and_displacement():
    mesh = _sphere_mesh()
    pose = MeshPose.canonical(mesh)
    face, uv = sample_surface(mesh.vertices, mesh.faces, 500)
    d = torch.rand(500, dtype=torch.float64) * 0.1
    mu0, n = embed(pose, face, uv, torch.zeros_like(d))
    f = mesh.faces[face]
    w = torch.cat([uv, 1 - uv.sum(1, keepdim=True)], 1)
    expect = (w[:, :, None] * mesh.vertices[f]).sum(1)
    assert torch.allclose(mu0, expect)
    mu, n2 = embed(pose, face, uv, d)
    assert torch.allclose(mu, mu0 + d[:, None] * n) and torch.allclose(n, n2)
    assert torch.allclose(n.norm(dim=1), torch.ones(500, dtype=torch.float64))
    assert bool(((n * mu0).sum(1) > 0.98 * mu0.norm(dim=1)).all())  # outward on a sphere


def test_rigid_pose_moves_and_rotates_points():
    mesh = _sphere_mesh()
    q, r, posed = _rigid(mesh)
    pose0, pose = MeshPose.canonical(mesh), MeshPose.from_vertices(mesh, posed)
    face, uv = sample_surface(mesh.vertices, mesh.faces, 300)
    d = torch.randn(300, dtype=torch.float64) * 0.05
    mu0, _n0 = embed(pose0, face, uv, d)
    mu, _n = embed(pose, face, uv, d)
    assert torch.allclose(mu, mu0 @ r.T + torch.tensor([1.0, 2.0, 3.0], dtype=r.dtype), atol=1e-10)
    dq, s = pose_frame(pose, face, uv)
    aligned = torch.where((dq @ q)[:, None] < 0, -dq, dq)
    assert torch.allclose(aligned, q.expand_as(dq), atol=1e-9)
    # composition q = dq ⊗ q_cano rotates the canonical frame
    q_cano = torch.nn.functional.normalize(torch.randn(300, 4, dtype=r.dtype), dim=1)
    rot = quat_to_matrix(quat_multiply(dq, q_cano))
    assert torch.allclose(rot, r @ quat_to_matrix(q_cano), atol=1e-9)
    assert torch.allclose(s, torch.ones_like(s))


@pytest.mark.parametrize("mode, expect", [("area", 4.0), ("sqrt_area", 2.0), ("none", 1.0)])
def test_scale_modes(mode, expect):
    mesh = _sphere_mesh(1)
    pose = MeshPose.from_vertices(mesh, 2.0 * mesh.vertices)
    face, uv = sample_surface(mesh.vertices, mesh.faces, 50)
    _, s = pose_frame(pose, face, uv, scale_mode=mode)
    assert s.shape == (50, 1) and torch.allclose(s, torch.full_like(s, expect))


def test_pose_frame_rejects_bad_mode_and_shapes():
    mesh = _sphere_mesh(0)
    pose = MeshPose.canonical(mesh)
    face = torch.zeros(4, dtype=torch.long)
    with pytest.raises(MeshsplatError, match="scale_mode"):
        pose_frame(pose, face, torch.zeros(4, 2, dtype=torch.float64), scale_mode="cube")
    with pytest.raises(MeshsplatError, match=r"uv: expected shape \[N,2\]"):
        embed(pose, face, torch.zeros(3, 2, dtype=torch.float64), torch.zeros(4, dtype=torch.float64))
    with pytest.raises(MeshsplatError, match="face: indices"):
        embed(pose, face + 1000, torch.zeros(4, 2, dtype=torch.float64), torch.zeros(4, dtype=torch.float64))


def test_sample_surface_area_weighted_and_inside():
    # two triangles, areas 1:3
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 2, 0], [3, 0, 1], [6, 0, 1], [3, 2, 1]], dtype=torch.float32)
    f = torch.tensor([[0, 1, 2], [3, 4, 5]])
    gen = torch.Generator().manual_seed(1)
    face, uv = sample_surface(v, f, 40000, generator=gen)
    frac = float((face == 1).float().mean())
    assert abs(frac - 0.75) < 0.01
    w = torch.cat([uv, 1 - uv.sum(1, keepdim=True)], 1)
    assert bool((w >= 0).all() and (w <= 1).all())
    # uniform inside a triangle: mean barycentric is (1/3, 1/3, 1/3), mass in the sub-triangle near a corner
    assert torch.allclose(w.mean(0), torch.full((3,), 1 / 3), atol=0.01)
    assert abs(float((w[:, 0] > 0.5).float().mean()) - 0.25) < 0.01
    face2, _uv2 = sample_surface(v, f, 100, generator=torch.Generator().manual_seed(1))
    assert torch.equal(face2, face[:100])


def test_sample_surface_zero_area_raises():
    v = torch.zeros(3, 3)
    with pytest.raises(MeshsplatError, match="zero total area"):
        sample_surface(v, torch.tensor([[0, 1, 2]]), 10)


@pytest.mark.gradcheck
def test_gradients_reach_offsets_and_displacement():
    """Trainable (δu, δv) and d must receive gradients through embed and pose_frame."""
    mesh = _sphere_mesh(1)
    _, _, posed = _rigid(mesh, angle=0.7, scale=1.3)
    posed = posed + 0.02 * torch.randn_like(posed)
    pose = MeshPose.from_vertices(mesh, posed)
    face, uv = sample_surface(mesh.vertices, mesh.faces, 6)
    uv = uv * 0.8 + 0.05
    duv = (0.01 * torch.randn(6, 2, dtype=torch.float64)).requires_grad_(True)
    d = (0.05 * torch.randn(6, dtype=torch.float64)).requires_grad_(True)

    def f_embed(duv, d):
        return embed(pose, face, uv + duv, d)

    def f_frame(duv):
        return pose_frame(pose, face, uv + duv, scale_mode="sqrt_area")[0]

    assert torch.autograd.gradcheck(f_embed, (duv, d))
    assert torch.autograd.gradcheck(f_frame, (duv,))
    mu, _ = f_embed(duv, d)
    gu, gd = torch.autograd.grad(mu.sum(), (duv, d))
    assert bool((gu.abs().sum(1) > 0).all()) and bool((gd.abs() > 0).all())
    # and through the posed vertices (the mesh drives the Gaussians)
    vv = posed.clone().requires_grad_(True)

    def f_verts(vv):
        p = MeshPose.from_vertices(mesh, vv)
        mu, _ = embed(p, face, uv, d.detach())
        dq, s = pose_frame(p, face, uv, scale_mode="area")
        return mu, dq, s

    assert torch.autograd.gradcheck(f_verts, (vv,))


def test_face_areas_match_sampling_density(assets):
    mesh = TriMesh.load(assets / "gltf" / "CesiumMan.glb")
    face, uv = sample_surface(mesh.vertices, mesh.faces, 20000, generator=torch.Generator().manual_seed(0))
    pose = MeshPose.canonical(mesh)
    mu, n = embed(pose, face, uv, torch.zeros(20000))
    assert bool(torch.isfinite(mu).all() and torch.isfinite(n).all())
    big = face_areas(mesh.vertices, mesh.faces).argmax()
    assert int((face == big).sum()) > 0


def test_gradients_to_the_posed_vertices_repeat_bit_for_bit_on_several_threads():
    """Pose refinement sends gradients through embed and pose_frame to the posed vertices. A gather whose
    backward scatters with atomics (``values[faces[face]]``) sums in another order on every call with 2
    threads, so two trainings of one capture drifted apart; the gathers must sum in a fixed order."""
    m = trimesh.creation.icosphere(subdivisions=4)
    mesh = TriMesh(torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces))
    g = torch.Generator().manual_seed(0)
    n = 40_000
    face = torch.randint(0, mesh.num_faces, (n,), generator=g)
    uv, weights = torch.rand(n, 2, generator=g) * 0.5, torch.rand(n, 3, generator=g)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        grads = []
        for _ in range(5):
            verts = (mesh.vertices * 1.1).requires_grad_(True)
            pose = MeshPose.from_vertices(mesh, verts)
            means, normals = embed(pose, face, uv, torch.zeros(n))
            delta_q, factor = pose_frame(pose, face, uv)
            loss = ((means + normals + delta_q[:, :3]) * weights).sum() + factor.sum()
            grads.append(torch.autograd.grad(loss, verts)[0])
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(grads[0], gr) for gr in grads[1:])
