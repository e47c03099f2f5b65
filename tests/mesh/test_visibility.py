"""Visibility of far light directions from a posed mesh (meshsplat.mesh.visibility)."""

from __future__ import annotations

import math

import pytest
import torch

from _meshes import box, uv_sphere
from meshsplat._numba import NO_NUMBA_ENV, numba_available
from meshsplat.embedding import sample_surface, surface_points
from meshsplat.errors import MeshsplatError
from meshsplat.mesh import MeshPose, TriMesh
from meshsplat.mesh.visibility import shadow_maps, sphere_directions, surface_samples, visibility


@pytest.fixture(autouse=True, params=["compiled", "torch"])
def path(request, monkeypatch):
    """Every test on both paths: the numba kernels (CPU, when installed) and pure torch (any device)."""
    if request.param == "torch":
        monkeypatch.setenv(NO_NUMBA_ENV, "1")
    elif not numba_available():
        pytest.skip("numba is not installed (pip install numba)")
    return request.param


def test_directions_are_unit_spread_and_deterministic():
    d = sphere_directions(32)
    assert d.shape == (32, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(32), atol=1e-6)
    assert torch.equal(d, sphere_directions(32))
    assert d.mean(0).norm() < 0.05  # no preferred side
    assert (d[:, 1] > 0).sum() == 16  # half above the equator


def test_point_inside_a_closed_box_sees_no_direction():
    v, f = box()
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.5, 0.2]])
    normals = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [1.0, 1.0, 0.0]]), dim=-1)
    vis = visibility(v, f, pts, normals, sphere_directions(32), grid=64)
    assert vis.shape == (2, 32)
    assert vis.sum() == 0


def test_a_sphere_point_sees_the_half_above_its_tangent_plane():
    v, f = uv_sphere()
    dirs = sphere_directions(64)
    pts = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [-0.3, 0.9, 0.1]]), dim=-1)
    vis = visibility(v, f, pts * 0.999, pts, dirs, grid=64)
    cos = pts @ dirs.T
    for i in range(len(pts)):
        assert 24 <= int(vis[i].sum()) <= 40  # about half of 64
        assert bool((vis[i][cos[i] > 0.3] == 1).all())  # well above the tangent plane: lit
        assert bool((vis[i][cos[i] < -0.3] == 0).all())  # well below: the sphere is in the way


def test_a_point_under_an_overhang_is_shadowed_from_above_not_from_below():
    floor, f_floor = box(-1.0, 1.0)
    floor = floor * torch.tensor([2.0, 2.0, 0.05])  # a thin slab around z = 0
    roof = floor + torch.tensor([0.0, 0.0, 1.0])  # the same slab at z = 1: the overhang
    v = torch.cat([floor, roof])
    f = torch.cat([f_floor, f_floor + 8])
    pt = torch.tensor([[0.0, 0.0, 0.05]])  # on the top of the lower slab, under the roof
    up = torch.tensor([[0.0, 0.0, 1.0]])
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.1, 0.0, 0.995]])
    vis = visibility(v, f, pt, up, dirs, grid=32)
    assert vis[0].tolist() == [0.0, 1.0, 0.0]
    # without the roof, the light from above reaches it
    alone = visibility(floor, f_floor, pt, up, dirs, grid=32)
    assert alone[0, 0] == 1.0 and alone[0, 2] == 1.0


def test_visibility_is_deterministic_and_a_pure_function_of_the_pose():
    v, f = uv_sphere(12, 24)
    g = torch.Generator().manual_seed(0)
    pts = torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=-1)
    a = visibility(v, f, pts, pts, sphere_directions(16))
    b = visibility(v.clone(), f.clone(), pts.clone(), pts.clone(), sphere_directions(16))
    assert torch.equal(a, b)
    vg = v.clone().requires_grad_(True)
    c = visibility(vg, f, pts, pts, sphere_directions(16))
    assert torch.equal(a, c) and not c.requires_grad


def test_shadow_maps_answer_for_any_points_and_a_pose_keeps_its_last():
    """Maps built once look up any points as ``visibility`` does; a ``MeshPose`` keeps its last maps for the same
    lights and grid, and builds new ones for others or after its vertices changed in place."""
    v, f = uv_sphere(12, 24)
    g = torch.Generator().manual_seed(1)
    pts = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1)
    dirs = sphere_directions(16)
    maps = shadow_maps(v, f, dirs, 32)
    assert maps.num_directions == 16 and maps.grid == 32
    assert torch.equal(maps.lit(pts, pts), visibility(v, f, pts, pts, dirs, 32))
    assert torch.equal(maps.lit(pts[:40], pts[:40]), visibility(v, f, pts[:40], pts[:40], dirs, 32))
    pose = MeshPose.from_vertices(TriMesh(v, f), v.clone())
    first = pose.shadow_maps(dirs, 32)
    assert torch.equal(first.lit(pts, pts), maps.lit(pts, pts))
    assert pose.shadow_maps(dirs.clone(), 32) is first
    assert pose.shadow_maps(dirs, 48).grid == 48
    other = pose.shadow_maps(dirs[:4], 32)
    assert other.num_directions == 4 and pose.shadow_maps(dirs[:4], 32) is other
    again = pose.shadow_maps(dirs, 32)
    with torch.no_grad():
        pose.verts.mul_(2.0)
    moved = pose.shadow_maps(dirs, 32)
    assert moved is not again and moved.radius == pytest.approx(2 * again.radius, rel=1e-6)


def test_bad_input_is_one_clear_error():
    v, f = box()
    with pytest.raises(MeshsplatError, match="points"):
        visibility(v, f, torch.zeros(3), torch.zeros(3), sphere_directions(4))
    with pytest.raises(MeshsplatError, match="grid"):
        visibility(v, f, torch.zeros(1, 3), torch.zeros(1, 3), sphere_directions(4), grid=1)
    with pytest.raises(MeshsplatError, match="direction count"):
        sphere_directions(0)


def test_surface_samples_leave_no_point_of_the_surface_far_from_a_sample():
    """Every surface point lies within spacing / sqrt(3) of a sample (what keeps the depth grid hole-free)."""
    v, f = box()
    v = v * torch.tensor([1.0, 0.3, 2.0])  # long thin triangles too
    spacing = 0.1
    s = surface_samples(v, f, spacing)
    face, uv = sample_surface(v, f, 3000, generator=torch.Generator().manual_seed(0))
    pts = surface_points(v, f, face, uv)
    assert float(torch.cdist(pts, s).amin(-1).max()) <= spacing / math.sqrt(3) + 1e-6
    area = 2 * (2 * 0.6 + 2 * 4 + 0.6 * 4)
    assert len(s) < 4 * area * 2 / (math.sqrt(3) * spacing**2)  # within 4x of an ideal triangular lattice
