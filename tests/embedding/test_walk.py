"""walk_on_triangles: validity on many mesh kinds, exactness of `unfold` on flat meshes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from meshsplat.embedding import WALK_MODES, walk_on_triangles
from meshsplat.embedding._walk_reference import walk_on_triangles_reference
from meshsplat.errors import MeshsplatError
from meshsplat.mesh import TriMesh

# ----------------------------------------------------------------------------- meshes


def flat_grid(n: int, seed: int, jitter: float = 0.25, holes: int = 0) -> TriMesh:
    """n x n unit-square grid, random diagonal per quad, jittered interior vertices, optional holes."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    interior = (xs.ravel() > 0) & (xs.ravel() < 1) & (ys.ravel() > 0) & (ys.ravel() < 1)
    v[interior, :2] += rng.uniform(-jitter, jitter, (interior.sum(), 2)) / n
    f = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            f += [[a, b, c], [a, c, d]] if rng.random() < 0.5 else [[a, b, d], [b, c, d]]
    f = np.array(f)
    if holes:
        keep = np.ones(len(f), bool)
        keep[rng.choice(len(f), holes, replace=False)] = False
        f = f[keep]
    return TriMesh(torch.tensor(v), torch.tensor(f))


def sphere(sub=2) -> TriMesh:
    s = trimesh.creation.icosphere(subdivisions=sub)
    return TriMesh(torch.tensor(s.vertices), torch.tensor(s.faces))


def open_cylinder() -> TriMesh:
    c = trimesh.creation.cylinder(radius=0.5, height=2.0, sections=24)
    side = np.abs(c.face_normals[:, 2]) < 0.5
    return TriMesh(torch.tensor(c.vertices), torch.tensor(c.faces[side]))


def three_quads() -> TriMesh:
    v = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, -1, 0], [1, -1, 0], [0, 0, 1], [1, 0, 1]], dtype=torch.float64
    )
    f = torch.tensor([[0, 1, 3], [0, 3, 2], [1, 0, 4], [1, 4, 5], [0, 1, 7], [0, 7, 6]])
    return TriMesh(v, f)


def with_degenerate() -> TriMesh:
    m = flat_grid(4, 0, jitter=0.0)
    v = m.vertices.clone()
    f = torch.cat([m.faces, torch.tensor([[0, 1, 2], [5, 5, 6]])])  # collinear boundary sliver + repeated index
    return TriMesh(v, f)


# ----------------------------------------------------------------------------- helpers


def point(mesh, face, uv):
    w = torch.cat([uv, 1 - uv.sum(1, keepdim=True)], 1)
    return (w[:, :, None] * mesh.vertices[mesh.faces[face]]).sum(1)


def step_for(mesh, face, disp):
    """Barycentric (du, dv) in `face` for an in-plane 3D displacement (least squares)."""
    f = mesh.faces[face]
    a, b, c = (mesh.vertices[f[:, i]] for i in range(3))
    m = torch.stack([a - c, b - c], -1)  # [N,3,2]
    return torch.linalg.lstsq(m, disp.unsqueeze(-1)).solution.squeeze(-1)


def random_starts(mesh, n, rng, snap=True):
    face = torch.as_tensor(rng.integers(0, mesh.num_faces, n))
    r = torch.as_tensor(rng.random((n, 2)))
    s = r[:, 0].sqrt()
    uv = torch.stack([1 - s, s * (1 - r[:, 1])], 1)
    if snap:  # some points exactly on vertices and edges
        kind = rng.integers(0, 4, n)
        corners = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]], dtype=uv.dtype)
        uv[kind == 1] = corners[torch.as_tensor(rng.integers(0, 3, int((kind == 1).sum())))]
        on_edge = torch.as_tensor(kind == 2)
        uv[on_edge, 1] = 1 - uv[on_edge, 0]
    return face, uv


def assert_valid(mesh, res, n):
    assert res.face.shape == (n,) and res.uv.shape == (n, 2) and res.changed.dtype == torch.bool
    assert bool(torch.isfinite(res.uv).all())
    assert int(res.face.min()) >= 0 and int(res.face.max()) < mesh.num_faces
    w = torch.cat([res.uv, 1 - res.uv.sum(1, keepdim=True)], 1)
    assert bool((w >= -1e-12).all() and (w <= 1 + 1e-12).all())


# ----------------------------------------------------------------------------- tests


@given(seed=st.integers(0, 10_000), n=st.integers(2, 12), scale=st.sampled_from([0.02, 0.2, 0.9]))
def test_unfold_is_straight_on_flat_grids(seed, n, scale):
    rng = np.random.default_rng(seed)
    mesh = flat_grid(n, seed)
    face, uv = random_starts(mesh, 200, rng)
    p0 = point(mesh, face, uv)
    target = p0.clone()
    target[:, :2] += torch.as_tensor(rng.normal(size=(200, 2))) * scale
    target[:, :2] = target[:, :2].clamp(0.0, 1.0)  # convex domain: segment stays inside
    step = step_for(mesh, face, target - p0)
    res = walk_on_triangles(mesh, mesh.vertices, face, uv, step, mode="unfold", max_crossings=256)
    assert_valid(mesh, res, 200)
    assert torch.allclose(point(mesh, res.face, res.uv), target, atol=1e-7)
    assert torch.equal(res.changed, res.face != face)
    # walking back by the negated 3D step returns to the start
    back = walk_on_triangles(
        mesh, mesh.vertices, res.face, res.uv, step_for(mesh, res.face, p0 - target), mode="unfold", max_crossings=256
    )
    assert torch.allclose(point(mesh, back.face, back.uv), p0, atol=1e-7)
    ref = walk_on_triangles_reference(
        mesh, mesh.vertices, face[:20], uv[:20], step[:20], mode="unfold", max_crossings=256
    )
    assert torch.allclose(point(mesh, ref.face, ref.uv), target[:20], atol=1e-7)


MESH_KINDS = ["sphere", "cylinder", "holes", "nonmanifold", "degenerate", "grid"]


def mesh_of_kind(kind: str, seed: int) -> TriMesh:
    return {
        "sphere": lambda: sphere(1),
        "cylinder": open_cylinder,
        "holes": lambda: flat_grid(6, seed, holes=8),
        "nonmanifold": three_quads,
        "degenerate": with_degenerate,
        "grid": lambda: flat_grid(5, seed),
    }[kind]()


@given(
    seed=st.integers(0, 10_000),
    mode=st.sampled_from(WALK_MODES),
    kind=st.sampled_from(MESH_KINDS),
    scale=st.sampled_from([0.01, 0.3, 3.0, 30.0]),
)
def test_always_valid_output(seed, mode, kind, scale):
    rng = np.random.default_rng(seed)
    mesh = mesh_of_kind(kind, seed)
    face, uv = random_starts(mesh, 300, rng)
    step = torch.as_tensor(rng.normal(size=(300, 2))) * scale
    res = walk_on_triangles(mesh, mesh.vertices, face, uv, step, mode=mode, max_crossings=32)
    assert_valid(mesh, res, 300)
    if kind == "sphere":  # points never leave the surface
        p = point(mesh, res.face, res.uv)
        assert bool((p.norm(dim=1) > 0.9).all() and (p.norm(dim=1) <= 1.0 + 1e-9).all())


def assert_matches_reference(mesh, fast, ref, uv_atol, rel3d):
    """Same face for >= 99% of points; there uv agree, elsewhere (vertex/edge ties) the 3D points agree."""
    same = fast.face == ref.face
    assert float(same.double().mean()) >= 0.99, f"{int((~same).sum())} of {len(same)} end faces differ"
    assert torch.allclose(fast.uv[same].double(), ref.uv[same].double(), atol=uv_atol, rtol=0)
    p_fast, p_ref = point(mesh, fast.face, fast.uv.double()), point(mesh, ref.face, ref.uv.double())
    assert torch.allclose(p_fast, p_ref, atol=rel3d * mesh.bbox_diagonal(), rtol=0)
    assert torch.equal(fast.changed[same], ref.changed[same])


@given(
    seed=st.integers(0, 10_000),
    mode=st.sampled_from(WALK_MODES),
    kind=st.sampled_from(MESH_KINDS),
    scale=st.sampled_from([0.05, 0.5, 3.0, 30.0]),
    max_crossings=st.sampled_from([0, 1, 3, 64]),
)
def test_matches_reference(seed, mode, kind, scale, max_crossings):
    # the per-point reference works from the 3D geometry (edge lookup, Rodrigues unfolding), not the rate maps
    rng = np.random.default_rng(seed)
    mesh = mesh_of_kind(kind, seed)
    face, uv = random_starts(mesh, 150, rng)  # a quarter on vertices, a quarter on edges
    step = torch.as_tensor(rng.normal(size=(150, 2))) * scale
    # a third graze the edge w2 = 0 (rate of corner 2 = du * eps): tests the tolerance rule. Not for unfold on
    # the sphere: a walk along an edge runs exactly through vertices, and round-off picks the side; around a
    # curved vertex the two sides lead to different geodesics (on flat or developable meshes they coincide).
    graze = torch.as_tensor(rng.random(150) < (0.0 if (mode, kind) == ("unfold", "sphere") else 1 / 3))
    eps = torch.as_tensor(rng.choice([0.0, 1e-15, -1e-15, 1e-13, -1e-13, 1e-10, -1e-10, 1e-6, -1e-6], 150))
    step[graze, 1] = -step[graze, 0] * (1 + eps[graze])
    fast = walk_on_triangles(mesh, mesh.vertices, face, uv, step, mode=mode, max_crossings=max_crossings)
    ref = walk_on_triangles_reference(mesh, mesh.vertices, face, uv, step, mode=mode, max_crossings=max_crossings)
    assert_matches_reference(mesh, fast, ref, uv_atol=1e-7, rel3d=1e-7)


@pytest.mark.parametrize("mode", WALK_MODES)
def test_matches_reference_float32(mode):
    mesh = sphere(3)
    rng = np.random.default_rng(7)
    face, uv = random_starts(mesh, 400, rng, snap=False)
    step = torch.as_tensor(rng.normal(size=(400, 2))).float()
    v32 = mesh.vertices.float()
    fast = walk_on_triangles(mesh, v32, face, uv.float(), step, mode=mode)
    ref = walk_on_triangles_reference(mesh, v32, face, uv.float(), step, mode=mode)
    assert fast.uv.dtype == ref.uv.dtype == torch.float32
    assert_matches_reference(mesh, fast, ref, uv_atol=1e-4, rel3d=1e-5)


def test_float32_and_zero_steps():
    mesh = sphere(2)
    rng = np.random.default_rng(0)
    face, uv = random_starts(mesh, 1000, rng)
    v32, uv32 = mesh.vertices.float(), uv.float()
    for mode in WALK_MODES:
        res = walk_on_triangles(mesh, v32, face, uv32, torch.zeros(1000, 2), mode=mode)
        assert torch.equal(res.face, face) and torch.allclose(res.uv, uv32) and not bool(res.changed.any())
        res = walk_on_triangles(mesh, v32, face, uv32, torch.randn(1000, 2) * 2, mode=mode)
        assert res.uv.dtype == torch.float32
        assert_valid(mesh, res, 1000)


def test_inside_steps_are_plain_addition_in_both_modes():
    mesh = flat_grid(3, 1)
    face = torch.arange(mesh.num_faces)
    uv = torch.full((mesh.num_faces, 2), 1 / 3, dtype=torch.float64)
    step = torch.tensor([0.1, -0.05], dtype=torch.float64).expand(mesh.num_faces, 2)
    for mode in WALK_MODES:
        res = walk_on_triangles(mesh, mesh.vertices, face, uv, step, mode=mode)
        assert torch.equal(res.face, face) and torch.allclose(res.uv, uv + step)


def test_paper_equals_unfold_on_a_parallelogram():
    # two triangles forming a parallelogram: the paper's re-expression is then exact
    v = torch.tensor([[0, 0, 0], [2, 0.5, 0], [2.7, 1.5, 0], [0.7, 1.0, 0]], dtype=torch.float64)
    mesh = TriMesh(v, torch.tensor([[0, 1, 2], [0, 2, 3]]))
    rng = np.random.default_rng(3)
    face = torch.zeros(100, dtype=torch.long)
    uv = torch.tensor([[0.2, 0.5]], dtype=torch.float64).expand(100, 2)
    p0 = point(mesh, face, uv)
    target = torch.as_tensor(rng.random((100, 2))) @ torch.stack([v[1, :2] - v[0, :2], v[3, :2] - v[0, :2]])
    target = torch.cat([target, torch.zeros(100, 1, dtype=torch.float64)], 1)
    step = step_for(mesh, face, target - p0)
    a = walk_on_triangles(mesh, v, face, uv, step, mode="paper")
    b = walk_on_triangles(mesh, v, face, uv, step, mode="unfold")
    assert torch.equal(a.face, b.face) and torch.allclose(a.uv, b.uv, atol=1e-12)
    assert torch.allclose(point(mesh, a.face, a.uv), target, atol=1e-12)


def test_paper_mode_follows_algorithm_1_on_a_folded_pair():
    # fold the second triangle up: paper mode is shape-agnostic, so the result is unchanged
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    v_fold = v.clone()
    v_fold[3] = torch.tensor([0.5, 0.5, 0.7071], dtype=torch.float64)
    face = torch.tensor([0])
    uv = torch.tensor([[0.6, 0.3]], dtype=torch.float64)  # weights: v0 0.6, v1 0.3, v2 0.1
    step = torch.tensor([[-0.1, -0.5]], dtype=torch.float64)  # rates (-0.1, -0.5, +0.6): exits via edge (v2, v0)
    for verts, walk in ((v, walk_on_triangles), (v_fold, walk_on_triangles), (v_fold, walk_on_triangles_reference)):
        r = walk(TriMesh(verts, faces), verts, face, uv, step, mode="paper")
        # exit at t=0.6 -> (0.54, 0, 0.46); remaining (-0.04, -0.2, 0.24) re-expressed in face 1 corners
        # (v0, v2, v3): v0 += -0.04 - 0.2, v2 += 0.24 - 0.2, v3 = 0.2  => (0.30, 0.50, 0.20)
        assert int(r.face) == 1 and torch.allclose(r.uv, torch.tensor([[0.30, 0.50]], dtype=torch.float64))


def test_stops_on_boundary_and_nonmanifold_edges():
    mesh = flat_grid(4, 2)
    face = torch.arange(mesh.num_faces)
    uv = torch.full((mesh.num_faces, 2), 1 / 3, dtype=torch.float64)
    p0 = point(mesh, face, uv)
    disp = torch.zeros_like(p0)
    disp[:, 0] = 5.0
    res = walk_on_triangles(mesh, mesh.vertices, face, uv, step_for(mesh, face, disp), mode="unfold")
    p = point(mesh, res.face, res.uv)
    assert torch.allclose(p[:, 0], torch.ones_like(p[:, 0])) and torch.allclose(p[:, 1], p0[:, 1])

    nm = three_quads()
    face = torch.tensor([0, 2, 4])
    uv = torch.full((3, 2), 0.25, dtype=torch.float64)  # heading to edge (0,1), shared by 3 faces
    for mode in WALK_MODES:
        res = walk_on_triangles(
            nm, nm.vertices, face, uv, torch.tensor([[0.6, 0.6]] * 3, dtype=torch.float64), mode=mode
        )
        assert torch.equal(res.face, face)
        w = torch.cat([res.uv, 1 - res.uv.sum(1, keepdim=True)], 1)
        on_01 = torch.stack(
            [
                w[
                    i,
                    next(
                        (j + 2) % 3
                        for j in range(3)
                        if {int(nm.faces[face[i], j]), int(nm.faces[face[i], (j + 1) % 3])} == {0, 1}
                    ),
                ]
                for i in range(3)
            ]
        )
        assert torch.allclose(on_01, torch.zeros(3, dtype=torch.float64), atol=1e-12)


def test_sphere_unfold_walks_geodesic_length():
    # on a fine sphere, a walk of length L along the surface stays at most L away (chord <= arc)
    mesh = sphere(4)
    rng = np.random.default_rng(5)
    face, uv = random_starts(mesh, 500, rng, snap=False)
    p0 = point(mesh, face, uv)
    n = p0 / p0.norm(dim=1, keepdim=True)
    t = torch.linalg.cross(n, torch.as_tensor(rng.normal(size=(500, 3))), dim=1)
    t = 0.5 * t / t.norm(dim=1, keepdim=True)
    res = walk_on_triangles(mesh, mesh.vertices, face, uv, step_for(mesh, face, t), mode="unfold", max_crossings=200)
    chord = (point(mesh, res.face, res.uv) - p0).norm(dim=1)
    assert bool((chord <= 0.5 + 1e-6).all()) and float(chord.median()) > 0.45


def test_bad_inputs_raise():
    mesh = sphere(0)
    face, uv = torch.zeros(3, dtype=torch.long), torch.zeros(3, 2, dtype=torch.float64)
    with pytest.raises(MeshsplatError, match="mode"):
        walk_on_triangles(mesh, mesh.vertices, face, uv, uv, mode="fly")
    with pytest.raises(MeshsplatError, match=r"step: expected shape \[N,2\]"):
        walk_on_triangles(mesh, mesh.vertices, face, uv, torch.zeros(4, 2, dtype=torch.float64))
    with pytest.raises(MeshsplatError, match="NaN"):
        walk_on_triangles(mesh, mesh.vertices, face, uv, torch.full((3, 2), float("nan"), dtype=torch.float64))
    with pytest.raises(MeshsplatError, match="face: indices"):
        walk_on_triangles(mesh, mesh.vertices, face + 99, uv, uv)


@pytest.mark.gpu
def test_cuda_matches_cpu():
    mesh = sphere(3)
    rng = np.random.default_rng(0)
    face, uv = random_starts(mesh, 5000, rng)
    step = torch.as_tensor(rng.normal(size=(5000, 2)))
    for mode in WALK_MODES:
        a = walk_on_triangles(mesh, mesh.vertices, face, uv, step, mode=mode)
        b = walk_on_triangles(mesh, mesh.vertices.cuda(), face.cuda(), uv.cuda(), step.cuda(), mode=mode)
        assert (a.face == b.face.cpu()).float().mean() > 0.999
