"""Topology, TriMesh validation and check() report."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from meshsplat.errors import MeshsplatError
from meshsplat.mesh import MeshTopology, TriMesh


def _grid(n=3):
    xs, ys = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1).astype(np.float32)
    f = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            f += [[a, b, c], [a, c, d]]
    return torch.tensor(v), torch.tensor(f)


def _adjacency_is_symmetric(topo: MeshTopology):
    fa, al = topo.face_adj, topo.adj_local
    has = fa >= 0
    f_idx, j_idx = torch.nonzero(has, as_tuple=True)
    g, k = fa[f_idx, j_idx], al[f_idx, j_idx]
    assert torch.equal(fa[g, k], f_idx) and torch.equal(al[g, k], j_idx)
    # the two local edges are the same vertex pair
    assert torch.equal(topo.face_edges[f_idx, j_idx], topo.face_edges[g, k])


def test_grid_topology():
    v, f = _grid(3)
    topo = TriMesh(v, f).topology
    assert topo.num_edges == 3 * 4 * 2 + 9  # 24 axis edges + 9 diagonals
    assert len(topo.boundary_edges) == 12
    assert len(topo.nonmanifold_edges) == 0 and len(topo.inconsistent_edges) == 0
    assert (topo.face_adj >= 0).sum() == 2 * (topo.num_edges - 12)
    assert torch.all(topo.edges[:, 0] < topo.edges[:, 1])
    e = topo.edges[topo.face_edges]  # [F,3,2]
    start, end = topo.faces, topo.faces[:, [1, 2, 0]]
    assert torch.equal(e[..., 0], torch.minimum(start, end)) and torch.equal(e[..., 1], torch.maximum(start, end))
    _adjacency_is_symmetric(topo)


def test_closed_sphere_every_edge_two_faces():
    s = trimesh.creation.icosphere(subdivisions=2)
    topo = MeshTopology.from_faces(torch.tensor(s.faces))
    assert len(topo.boundary_edges) == 0 and bool((topo.edge_face_count == 2).all())
    assert bool((topo.face_adj >= 0).all())
    _adjacency_is_symmetric(topo)


def test_nonmanifold_edge_has_no_adjacency():
    # three quads (6 triangles) sharing the edge (0, 1)
    v = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, -1, 0], [1, -1, 0], [0, 0, 1], [1, 0, 1]], dtype=torch.float32
    )
    f = torch.tensor([[0, 1, 3], [0, 3, 2], [1, 0, 4], [1, 4, 5], [0, 1, 7], [0, 7, 6]])
    mesh = TriMesh(v, f)
    topo = mesh.topology
    assert len(topo.nonmanifold_edges) == 1
    e = topo.nonmanifold_edges[0]
    assert topo.edges[e].tolist() == [0, 1] and int(topo.edge_face_count[e]) == 3
    on_edge = topo.face_edges == e
    assert bool((topo.face_adj[on_edge] == -1).all()) and bool((topo.adj_local[on_edge] == -1).all())
    report = mesh.check()
    assert report.nonmanifold_edges == 1 and not report.ok
    assert "non-manifold edges:       1" in str(report)
    _adjacency_is_symmetric(topo)


def test_inconsistent_orientation_detected_and_adjacency_kept():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float32)
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    assert len(MeshTopology.from_faces(f).inconsistent_edges) == 0
    f_bad = torch.tensor([[0, 1, 2], [0, 3, 2]])
    topo = TriMesh(v, f_bad).topology
    assert len(topo.inconsistent_edges) == 1
    assert int((topo.face_adj >= 0).sum()) == 2


def test_degenerate_faces_reported_not_fatal():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 0, 0]], dtype=torch.float32)
    f = torch.tensor([[0, 1, 2], [0, 1, 3], [1, 1, 2]])  # collinear face and repeated index
    mesh = TriMesh(v, f)
    assert mesh.degenerate_faces().tolist() == [False, True, True]
    rep = mesh.check()
    assert rep.degenerate_faces == [1, 2] and "degenerate faces:         2" in str(rep)
    assert len(mesh.topology.index_degenerate_faces) == 1
    # a self-loop edge never connects faces
    assert int(mesh.topology.face_adj[2, 0]) == -1


@pytest.mark.parametrize(
    "verts, faces, match",
    [
        (torch.zeros(3, 3), torch.tensor([[0, 1, 3]]), "faces: vertex indices"),
        (torch.zeros(3, 3), torch.tensor([[0, -1, 2]]), "faces: vertex indices"),
        (torch.tensor([[0, 0, 0], [1, 0, 0], [0, float("nan"), 0]]), torch.tensor([[0, 1, 2]]), "NaN"),
        (torch.zeros(3, 2), torch.tensor([[0, 1, 2]]), "vertices: expected shape"),
        (torch.zeros(3, 3), torch.tensor([[0.0, 1.0, 2.0]]), "integer dtype"),
        (torch.zeros(3, 3), torch.zeros(0, 3, dtype=torch.long), "no faces"),
    ],
)
def test_unusable_meshes_raise(verts, faces, match):
    with pytest.raises(MeshsplatError, match=match):
        TriMesh(verts, faces)


def test_summary_and_components():
    v, f = _grid(2)
    v2 = torch.cat([v, v + 10])
    f2 = torch.cat([f, f + v.shape[0]])
    mesh = TriMesh(v2, f2)
    assert mesh.check().num_components == 2
    assert "boundary" in mesh.topology.summary()


def test_load_real_mesh(assets):
    mesh = TriMesh.load(assets / "gltf" / "CesiumMan.glb")
    rep = mesh.check()
    assert rep.num_faces == mesh.num_faces > 1000 and rep.nonmanifold_edges == 0
    with pytest.raises(MeshsplatError, match="not found"):
        TriMesh.load(assets / "nope.obj")
