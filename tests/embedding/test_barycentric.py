"""Barycentric helpers (meshsplat.embedding.barycentric) and background compositing (meshsplat.render)."""

import pytest
import torch

from meshsplat.embedding import barycentric_weights, embed, interpolate, surface_points
from meshsplat.errors import MeshsplatError
from meshsplat.mesh import MeshPose, TriMesh
from meshsplat.render import background_color, composite


def _mesh():
    g = torch.Generator().manual_seed(3)
    verts = torch.randn(30, 3, generator=g, dtype=torch.float64)
    faces = torch.stack([torch.randperm(30, generator=g)[:3] for _ in range(40)])
    return verts, faces


def test_weights_sum_to_one_and_pick_corners():
    uv = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0], [0.2, 0.3], [1.5, -0.7]])
    w = barycentric_weights(uv)
    assert torch.allclose(w.sum(-1), torch.ones(5))
    assert torch.equal(w[:3], torch.eye(3))  # u -> corner a, v -> corner b, w -> corner c


def test_surface_points_hit_corners_and_match_embed_at_zero_offset():
    verts, faces = _mesh()
    face = torch.arange(40)
    for j, uv0 in enumerate(([1.0, 0.0], [0.0, 1.0], [0.0, 0.0])):
        uv = torch.tensor(uv0, dtype=torch.float64).expand(40, 2)
        assert torch.allclose(surface_points(verts, faces, face, uv), verts[faces[:, j]])
    uv = torch.rand(40, 2, dtype=torch.float64) * 0.5
    mu, _ = embed(MeshPose.from_vertices(TriMesh(verts, faces), verts), face, uv, torch.zeros(40, dtype=torch.float64))
    assert torch.allclose(surface_points(verts, faces, face, uv), mu)


def test_interpolate_is_linear_in_values():
    _verts, faces = _mesh()
    face = torch.randint(0, 40, (25,))
    w = barycentric_weights(torch.rand(25, 2, dtype=torch.float64) * 0.5)
    a, b = torch.randn(30, 4, dtype=torch.float64), torch.randn(30, 4, dtype=torch.float64)
    lhs = interpolate(2 * a - b, faces, face, w)
    assert torch.allclose(lhs, 2 * interpolate(a, faces, face, w) - interpolate(b, faces, face, w))


def test_composite_and_background_color():
    image = torch.rand(4, 5, 3)
    mask = torch.zeros(4, 5, 1)
    mask[1:3, 1:4] = 1
    bg = background_color("0,0.5,1")
    out = composite(image, mask, bg)
    assert torch.equal(out[1:3, 1:4], image[1:3, 1:4])
    assert torch.equal(out[0, 0], bg)
    assert composite(image, None, bg) is image
    assert torch.equal(background_color("white"), torch.ones(3))
    for bad in ("grey", "1,2,3", [0.5, 0.5]):
        with pytest.raises(MeshsplatError, match="background"):
            background_color(bad)
