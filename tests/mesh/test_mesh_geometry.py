"""Differentiable geometry: normals, areas, frames, rotations, vertex quaternions."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from meshsplat.mesh import (
    MeshPose,
    TriMesh,
    degenerate_faces,
    face_area_ratio,
    face_areas,
    face_frames,
    face_normals,
    face_rotations,
    matrix_to_quat,
    quat_to_matrix,
    vertex_normals,
    vertex_quaternions,
)
from meshsplat.mesh.geometry import pose_quantities


def _sphere(sub=2, dtype=torch.float64):
    s = trimesh.creation.icosphere(subdivisions=sub)
    return torch.tensor(s.vertices, dtype=dtype), torch.tensor(s.faces)


def _rot(axis, angle, dtype=torch.float64):
    axis = torch.tensor(axis, dtype=dtype)
    axis = axis / axis.norm()
    q = torch.cat([torch.tensor([math.cos(angle / 2)], dtype=dtype), math.sin(angle / 2) * axis])
    return q, quat_to_matrix(q)


def test_sphere_normals_point_outward_and_areas_sum():
    v, f = _sphere(3)
    n = vertex_normals(v, f)
    assert torch.allclose(n, v / v.norm(dim=1, keepdim=True), atol=2e-2)
    na = vertex_normals(v, f, weighting="angle")
    assert torch.allclose(na, n, atol=2e-2)
    tm = trimesh.Trimesh(v.numpy(), f.numpy(), process=False)
    assert torch.allclose(face_areas(v, f), torch.tensor(tm.area_faces), rtol=1e-10)
    fn = face_normals(v, f)
    cent = v[f].mean(1)
    assert bool(((fn * cent).sum(-1) > 0).all())


def test_frames_orthonormal_and_batched():
    v, f = _sphere(1)
    batch = torch.stack([v, 2 * v, v + 1])
    fr = face_frames(batch, f)
    assert fr.shape == (3, f.shape[0], 3, 3)
    eye = torch.eye(3, dtype=v.dtype)
    assert torch.allclose(fr.transpose(-1, -2) @ fr, eye.expand_as(fr), atol=1e-10)
    assert torch.allclose(torch.linalg.det(fr), torch.ones(3, f.shape[0], dtype=v.dtype))
    t = fr[..., 0]
    e0 = batch[:, f[:, 1]] - batch[:, f[:, 0]]
    assert torch.allclose(t, e0 / e0.norm(dim=-1, keepdim=True))
    assert vertex_quaternions(v, batch, f).shape == (3, v.shape[0], 4)
    assert face_area_ratio(v, batch, f).shape == (3, f.shape[0])


@given(
    axis=st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda a: sum(x * x for x in a) > 0.01),
    angle=st.floats(0.0, math.pi),
    scale=st.floats(0.3, 3.0),
)
def test_rigid_motion_gives_its_rotation_everywhere(axis, angle, scale):
    v, f = _sphere(1)
    q, r = _rot(axis, angle)
    posed = scale * v @ r.T + torch.tensor([0.3, -1.0, 2.0], dtype=v.dtype)
    rots = face_rotations(v, posed, f)
    assert torch.allclose(rots, r.expand_as(rots), atol=1e-9)
    vq = vertex_quaternions(v, posed, f)
    # near 180 degrees face quaternions have w ~ 0 and arbitrary signs: alignment must fix them
    aligned = torch.where((vq @ q)[:, None] < 0, -vq, vq)
    assert torch.allclose(aligned, q.expand_as(vq), atol=1e-8)
    assert torch.allclose(face_area_ratio(v, posed, f), torch.full((f.shape[0],), scale**2, dtype=v.dtype))


def test_sign_alignment_near_half_turn():
    # a vertex whose faces rotate by slightly less / more than 180 degrees about nearly the same axis
    v, f = _sphere(2)
    _, r = _rot([0, 0, 1], math.pi)
    posed = v @ r.T
    # bend: small extra rotation on the upper half
    _, r2 = _rot([1, 0, 0], 0.02)
    up = posed[:, 2] > 0
    posed[up] = posed[up] @ r2.T
    vq = vertex_quaternions(v, posed, f)
    assert torch.allclose(vq.norm(dim=1), torch.ones(v.shape[0], dtype=v.dtype))
    # every vertex rotation stays close to a half turn about z (no cancellation to garbage)
    assert bool((vq[:, 3].abs() > 0.99).all())


def test_degenerate_faces_finite_values_and_gradients():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0]], dtype=torch.float64, requires_grad=True)
    f = torch.tensor([[0, 1, 2], [1, 3, 4], [0, 0, 2]])  # face 1 collinear, face 2 repeats a vertex
    posed = v * 1.5
    outs = [
        face_normals(v, f),
        face_areas(v, f),
        vertex_normals(v, f),
        vertex_normals(v, f, "angle"),
        face_frames(v, f),
        face_rotations(v, posed, f),
        vertex_quaternions(v, posed, f),
        face_area_ratio(v, posed, f),
    ]
    total = sum(o.sum() for o in outs)
    (g,) = torch.autograd.grad(total, v)
    assert all(bool(torch.isfinite(o).all()) for o in outs) and bool(torch.isfinite(g).all())
    assert degenerate_faces(v, f).tolist() == [False, True, True]
    assert torch.equal(face_frames(v, f)[1], torch.eye(3, dtype=v.dtype))
    assert float(face_area_ratio(v, posed, f)[1].detach()) == 1.0


def test_matrix_quat_roundtrip():
    q = torch.nn.functional.normalize(torch.randn(100, 4, dtype=torch.float64), dim=1)
    q2 = matrix_to_quat(quat_to_matrix(q))
    assert torch.allclose(torch.where((q * q2).sum(1, keepdim=True) < 0, -q2, q2), q, atol=1e-10)


def test_mesh_pose_rest_is_identity():
    v, f = _sphere(1, torch.float32)
    pose = MeshPose.canonical(TriMesh(v, f))
    assert torch.allclose(pose.vertex_quats, torch.tensor([1.0, 0, 0, 0]).expand_as(pose.vertex_quats), atol=1e-6)
    assert torch.allclose(pose.area_ratio, torch.ones_like(pose.area_ratio))


def test_vertex_sums_match_a_loop_over_faces_batched():
    """Area-weighted vertex normals and the area ratio of a batch of poses against a plain loop over the
    faces of each pose (the flat per-corner scatter and its batch offsets); ``pose_quantities`` gives the same."""
    v, f = _sphere(1)
    g = torch.Generator().manual_seed(0)
    posed = v * torch.tensor([1.0, 1.3, 0.8], dtype=v.dtype) + 0.05 * torch.randn(
        3, *v.shape, generator=g, dtype=v.dtype
    )
    n = vertex_normals(posed, f)
    for b in range(posed.shape[0]):
        acc = torch.zeros_like(v)
        for a, c, d in f.tolist():
            cross = torch.linalg.cross(posed[b, c] - posed[b, a], posed[b, d] - posed[b, a], dim=0)
            for i in (a, c, d):
                acc[i] += cross
        assert torch.allclose(n[b], torch.nn.functional.normalize(acc, dim=-1), atol=1e-12)
    want = face_areas(posed, f) / face_areas(v, f)
    assert torch.allclose(face_area_ratio(v, posed, f), want, atol=1e-12)
    normals, quats, ratio = pose_quantities(v, posed, f)
    assert torch.equal(normals, n) and torch.equal(ratio, face_area_ratio(v, posed, f))
    assert torch.equal(quats, vertex_quaternions(v, posed, f))


@pytest.mark.gradcheck
def test_geometry_gradcheck():
    v, f = _sphere(0)
    v = (v + 0.05 * torch.randn_like(v)).requires_grad_(True)
    posed = v.detach() * 1.2 + 0.1 * torch.randn_like(v)
    assert torch.autograd.gradcheck(
        lambda x: vertex_quaternions(v.detach(), x, f), (posed.clone().requires_grad_(True),)
    )
    assert torch.autograd.gradcheck(lambda x: vertex_normals(x, f, "angle"), (v,))
    assert torch.autograd.gradcheck(lambda x: face_area_ratio(v.detach(), x, f), (posed.clone().requires_grad_(True),))
