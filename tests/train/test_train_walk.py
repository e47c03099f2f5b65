"""Lifted optimisation: Gaussians must slide across triangles to match a target image."""

from __future__ import annotations

import torch

from _meshes import plane
from meshsplat.gaussians import compose, make_params, rgb_to_sh0
from meshsplat.mesh import MeshPose, TriMesh
from meshsplat.render import rasterize
from meshsplat.train.optim import build_optimizers
from meshsplat.train.strategy import walk_embeddings

W = H = 32


def top_camera():
    """Looks down -z at the unit square from z = 2 (OpenCV axes)."""
    viewmat = torch.tensor([[1.0, 0, 0, -0.5], [0, -1, 0, 0.5], [0, 0, -1, 2], [0, 0, 0, 1]])
    K = torch.tensor([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]])
    return viewmat, K


def locate(mesh: TriMesh, pts: torch.Tensor):
    """(face, uv) of points on the flat plane mesh (exact barycentrics of the containing face)."""
    v = mesh.vertices[mesh.faces]  # [F,3,3]
    a, b, c = v[:, 0, :2], v[:, 1, :2], v[:, 2, :2]
    p = pts[:, None, :2]
    m = torch.stack([a - c, b - c], -1)  # [F,2,2]
    uv = torch.linalg.solve(m[None].expand(len(pts), -1, -1, -1), (p - c[None])[..., None])[..., 0]
    inside = (uv >= -1e-6).all(-1) & (uv.sum(-1) <= 1 + 1e-6)
    face = inside.float().argmax(-1)
    return face, uv[torch.arange(len(pts)), face]


def render(mesh, params, viewmat, K):
    g = compose(params, MeshPose.canonical(mesh), "none")
    out = rasterize(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.colors,
        viewmat[None],
        K[None],
        W,
        H,
        backgrounds=torch.zeros(1, 3),
        backend="torch",
    )
    return out.colors[0], g


def test_embeddings_slide_across_faces_to_fit_target():
    torch.manual_seed(0)
    mesh = plane(8)  # faces 0.125 wide
    viewmat, K = top_camera()
    xs = torch.linspace(0.55, 0.8, 4)
    ys = torch.linspace(0.25, 0.75, 4)
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    start = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.zeros(16)], -1)
    shift = torch.tensor([-0.15, 0.0, 0.0])

    def make(pts):
        face, uv = locate(mesh, pts)
        n = len(pts)
        return make_params(
            face,
            uv,
            log_scale=torch.log(torch.tensor([0.04, 0.04, 0.01])).expand(n, 3),
            opacity_logit=torch.full((n,), 2.0),
            sh0=rgb_to_sh0(torch.ones(n, 3)),
        )

    with torch.no_grad():
        target, _ = render(mesh, make(start + shift), viewmat, K)
    params = make(start)
    face0 = params["face"].clone()
    opts = build_optimizers(params, {"duv": 0.03, "d": 1e-3})
    assert set(opts) == {"duv", "d"}
    duv_obj, d_obj = params["duv"], params["d"]
    losses, walked = [], 0
    for it in range(1, 161):
        img, _ = render(mesh, params, viewmat, K)
        loss = (img - target).abs().mean()
        loss.backward()
        for o in opts.values():
            o.step()
            o.zero_grad(set_to_none=True)
        losses.append(float(loss.detach()))
        if it % 10 == 0:
            walked += int(walk_embeddings(params, opts, mesh, mode="paper").sum())
            assert params["duv"] is duv_obj and params["d"] is d_obj  # same registered tensors
            assert torch.all(params["duv"] == 0)
    _, g = render(mesh, params, viewmat, K)
    moved = g.means.detach()[:, 0].mean() - start[:, 0].mean()
    assert losses[-1] < 0.35 * losses[0], (losses[0], losses[-1])
    assert float(moved) < -0.1, float(moved)  # slid about 0.15 to the left
    assert walked >= 8
    assert (params["face"] != face0).float().mean() >= 0.5
    bary = torch.cat([params["uv"], 1 - params["uv"].sum(-1, keepdim=True)], -1)
    assert torch.all(bary >= -1e-6)
