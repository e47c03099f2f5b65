"""Gaussian parameters, composition in a pose, Avatar persistence."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from meshsplat.camera import Camera
from meshsplat.embedding import project_uv_to_triangle
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import (
    SH_C0,
    Avatar,
    check_params,
    compose,
    eval_sh,
    init_params,
    knn_scales,
    make_params,
    sh_degree_of,
)
from meshsplat.mesh import MeshPose, TriMesh
from meshsplat.mesh.quaternion import quat_multiply, quat_normalize


def icosphere(subdiv: int = 2, dtype=torch.float32) -> TriMesh:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdiv)
    return TriMesh(torch.tensor(m.vertices, dtype=dtype), torch.tensor(m.faces, dtype=torch.long))


def test_init_matches_paper():
    mesh = icosphere()
    gen = torch.Generator().manual_seed(0)
    p = init_params(mesh, 500, generator=gen)
    check_params(p)
    assert p["face"].dtype == torch.long and p["face"].shape == (500,)
    assert torch.all(p["d"] == 0) and torch.all(p["duv"] == 0)
    assert torch.allclose(p["rotation"], torch.tensor([1.0, 0, 0, 0]).expand(500, 4))
    assert torch.allclose(torch.sigmoid(p["opacity_logit"]), torch.full((500,), 0.1))
    assert torch.allclose(p["sh0"][:, 0] * SH_C0 + 0.5, torch.full((500, 3), 0.5))
    assert (p["uv"] >= 0).all() and (p["uv"].sum(-1) <= 1 + 1e-6).all()
    # isotropic scale ~ neighbour spacing: for N points on a unit sphere ~ sqrt(4π/N)
    s = p["log_scale"].detach().exp()
    assert torch.allclose(s[:, 0], s[:, 1]) and torch.allclose(s[:, 0], s[:, 2])
    spacing = math.sqrt(4 * math.pi / 500)
    assert 0.2 * spacing < float(s.median()) < 2 * spacing
    assert "shN" not in p and sh_degree_of(p) == 0
    assert "shN" in init_params(mesh, 50, sh_degree=2) and init_params(mesh, 50, sh_degree=2)["shN"].shape == (50, 8, 3)
    # the points lie on the canonical mesh: composed means are at d=0
    g = compose(p, MeshPose.canonical(mesh))
    assert torch.allclose(g.means.norm(dim=-1), torch.ones(500), atol=0.05)


def test_knn_scales_regular_grid():
    xs = torch.arange(5, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    pts = torch.cat([grid, torch.zeros(25, 1, dtype=torch.float64)], 1) * 0.1
    s = knn_scales(pts, 3)
    assert torch.allclose(s[12], torch.tensor(0.1, dtype=torch.float64))  # centre: 4 neighbours at 0.1


def test_compose_gradients_reach_duv_and_d():
    mesh = icosphere(1)
    p = init_params(mesh, 64, generator=torch.Generator().manual_seed(1))
    verts = mesh.vertices * torch.tensor([1.2, 0.9, 1.0])  # a non-trivial pose
    g = compose(p, MeshPose.from_vertices(mesh, verts))
    (g.means * torch.randn_like(g.means)).sum().backward()
    assert p["duv"].grad is not None and p["duv"].grad.abs().min() > 0
    assert p["d"].grad is not None and p["d"].grad.abs().min() > 0


def test_compose_position_uses_uv_plus_duv():
    mesh = icosphere(1)
    p = init_params(mesh, 32, generator=torch.Generator().manual_seed(2))
    pose = MeshPose.canonical(mesh)
    with torch.no_grad():
        p["duv"].copy_(torch.rand(32, 2) * 0.1 - 0.05)
        p["d"].copy_(torch.rand(32) * 0.01)
    g = compose(p, pose)
    q = make_params(
        p["face"],
        p["uv"] + p["duv"],
        d=p["d"],
        log_scale=p["log_scale"],
        opacity_logit=p["opacity_logit"],
        sh0=p["sh0"],
    )
    g2 = compose(q, pose)
    assert torch.allclose(g.means, g2.means, atol=1e-6)
    assert not torch.allclose(g.means, compose({**p, "duv": torch.zeros(32, 2)}, pose).means)


def test_compose_rotation_and_scale_follow_pose():
    mesh = icosphere(1)
    p = init_params(mesh, 40, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        p["rotation"].copy_(quat_normalize(torch.randn(40, 4)))
    # rigid rotation about z by 90 degrees and uniform scaling by 2
    R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    verts = 2.0 * mesh.vertices @ R.T
    g0 = compose(p, MeshPose.canonical(mesh))
    for mode, factor in (("sqrt_area", 2.0), ("area", 4.0), ("none", 1.0)):
        g = compose(p, MeshPose.from_vertices(mesh, verts), mode)
        assert torch.allclose(g.means, 2.0 * g0.means @ R.T, atol=1e-5)
        assert torch.allclose(g.scales, factor * g0.scales, rtol=1e-4)
        qz = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
        expect = quat_multiply(qz.expand(40, 4), g0.quats)
        assert torch.allclose((g.quats * expect).sum(-1).abs(), torch.ones(40), atol=1e-5)


@given(st.lists(st.floats(-2, 2), min_size=2, max_size=2))
def test_project_uv_to_triangle_is_projection(uv):
    x = torch.tensor([uv], dtype=torch.float64)
    y = project_uv_to_triangle(x)
    b = torch.cat([y, 1 - y.sum(-1, keepdim=True)], -1)
    assert (b >= -1e-12).all() and abs(float(b.sum()) - 1) < 1e-12
    # optimality: no point of a fine grid on the simplex is closer (in (u,v,w) space)
    t = torch.linspace(0, 1, 41, dtype=torch.float64)
    uu, vv = torch.meshgrid(t, t, indexing="ij")
    keep = (uu + vv) <= 1
    grid = torch.stack([uu[keep], vv[keep], 1 - uu[keep] - vv[keep]], -1)
    bx = torch.cat([x, 1 - x.sum(-1, keepdim=True)], -1)
    d_best = ((grid - bx) ** 2).sum(-1).min()
    assert float(((b - bx) ** 2).sum()) <= float(d_best) + 1e-12
    inside = (x >= 0).all() and float(x.sum()) <= 1
    if inside:
        assert torch.allclose(y, x)


def test_clamp_to_face_keeps_points_on_their_triangle():
    mesh = icosphere(1)
    p = init_params(mesh, 50, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        p["duv"].copy_(torch.randn(50, 2))
    g = compose(p, MeshPose.canonical(mesh), clamp_to_face=True)
    tri = mesh.vertices[mesh.faces[p["face"]]]
    # each mean is a convex combination of its triangle's corners
    uvc = project_uv_to_triangle(p["uv"] + p["duv"])
    w = torch.cat([uvc, 1 - uvc.sum(-1, keepdim=True)], -1)
    assert torch.allclose(g.means, (w[..., None] * tri).sum(1), atol=1e-5)


def test_eval_sh_degree_zero_and_view_dependence():
    sh0 = torch.randn(10, 1, 3)
    assert torch.allclose(eval_sh(sh0, None, None), (SH_C0 * sh0[:, 0] + 0.5).clamp_min(0))
    shN = torch.zeros(10, 3, 3)
    shN[:, 1] = 1.0  # the z band
    up = eval_sh(sh0 * 0, shN, torch.tensor([[0, 0, 1.0]]).expand(10, 3))
    down = eval_sh(sh0 * 0, shN, torch.tensor([[0, 0, -1.0]]).expand(10, 3))
    assert (up > down).all()
    assert torch.allclose(eval_sh(sh0, shN, None), eval_sh(sh0, None, None))  # DC only without a view


def test_check_params_errors_are_clear():
    mesh = icosphere(1)
    p = init_params(mesh, 10)
    bad = dict(p)
    bad["uv"] = torch.zeros(9, 2)
    with pytest.raises(MeshsplatError, match=r"params\['uv'\]"):
        check_params(bad)
    with pytest.raises(MeshsplatError, match="missing"):
        check_params({k: v for k, v in p.items() if k != "d"})


def test_avatar_state_roundtrip_and_compose():
    mesh = icosphere(1)
    p = init_params(mesh, 30, sh_degree=1)
    av = Avatar(mesh, p, "area")
    sd = av.state_dict()
    av2 = Avatar.from_state_dict(sd)
    assert av2.num_gaussians == 30 and av2.sh_degree == 1 and av2.scale_mode == "area"
    for k in p:
        assert torch.equal(av2.params[k], p[k].detach())
    verts = mesh.vertices * 1.1
    a = av.compose(verts, campos=torch.tensor([0, 0, 5.0]))
    b = av2.compose(verts, campos=torch.tensor([0, 0, 5.0]))
    assert torch.equal(a.means, b.means) and torch.equal(a.colors, b.colors)
    with pytest.raises(MeshsplatError, match="verts_posed"):
        av.compose(verts[:-1])


def _turned_camera(width: int = 40, height: int = 30) -> Camera:
    c, s = math.cos(0.4), math.sin(0.4)
    viewmat = torch.tensor([[c, 0, -s, 0.1], [0, -1, 0, 0.05], [-s, 0, -c, 4.0], [0, 0, 0, 1]])
    K = torch.tensor([[45.0, 0, width / 2 + 0.3], [0, 47.0, height / 2 - 0.2], [0, 0, 1]])
    return Camera(viewmat, K, width, height)


@pytest.mark.parametrize("antialiased", [False, True])
def test_avatar_render_through_a_camera_is_the_rasterizer_on_the_same_tensors(antialiased):
    from meshsplat.render import rasterize
    from meshsplat.render.projection import antialias_compensation

    mesh = icosphere(2)
    av = Avatar(
        mesh, init_params(mesh, 300, sh_degree=1, generator=torch.Generator().manual_seed(3)), antialiased=antialiased
    )
    verts = mesh.vertices * torch.tensor([1.0, 1.2, 0.9])
    cam = _turned_camera()
    bg = torch.tensor([0.2, 0.3, 0.4])
    with torch.no_grad():
        out = av.render(verts, cam, bg, backend="torch")
        g = av.compose(verts, campos=torch.linalg.inv(cam.viewmat)[:3, 3], compiled=False)  # torch throughout
        opacities = g.opacities
        if antialiased:
            opacities = (
                opacities
                * antialias_compensation(
                    g.means, g.quats, g.scales, cam.viewmat[None], cam.K[None], cam.width, cam.height
                )[0]
            )
        ref = rasterize(
            g.means,
            g.quats,
            g.scales,
            opacities,
            g.colors,
            cam.viewmat[None],
            cam.K[None],
            cam.width,
            cam.height,
            backgrounds=bg[None],
            backend="torch",
        )
        # the camera's tensors are moved to the avatar's dtype, as before
        as64 = av.render(verts, cam.to(dtype=torch.float64), bg, backend="torch")
    assert out.image.shape == (30, 40, 3) and float(out.alpha.max()) > 0.5
    assert torch.equal(out.image, ref.colors[0]) and torch.equal(out.alpha, ref.alphas[0])
    assert torch.equal(as64.image, out.image)


def test_avatar_render_takes_one_camera():
    mesh = icosphere(1)
    av = Avatar(mesh, init_params(mesh, 20))
    cam = _turned_camera()
    with pytest.raises(
        MeshsplatError,
        match=r"camera: expected a meshsplat.Camera, got Tensor .*"
        r"Avatar.render\(vertices, camera, background=None",
    ):
        av.render(mesh.vertices, cam.viewmat)
    with pytest.raises(TypeError):  # the four loose arguments of old
        av.render(mesh.vertices, cam.viewmat, cam.K, 40, 30)  # type: ignore[call-arg]
    bad = _turned_camera()
    bad.K = bad.K.clone()
    bad.K[0, 0] = float("nan")
    with pytest.raises(MeshsplatError, match="camera K: contains"):
        av.render(mesh.vertices, bad)


def test_camera_checks_its_fields():
    cam = _turned_camera()
    with pytest.raises(MeshsplatError, match=r"camera viewmat: expected shape \[4,4\]"):
        Camera(cam.viewmat[:3], cam.K, 40, 30)
    with pytest.raises(MeshsplatError, match=r"camera K: expected a torch.Tensor"):
        Camera(cam.viewmat, cam.K.numpy(), 40, 30)  # type: ignore[arg-type]
    with pytest.raises(MeshsplatError, match="camera width: expected a positive integer, got 0"):
        Camera(cam.viewmat, cam.K, 0, 30)
    with pytest.raises(MeshsplatError, match=r"camera height: expected a positive integer, got 30.0"):
        Camera(cam.viewmat, cam.K, 40, 30.0)  # type: ignore[arg-type]
    moved = cam.to(dtype=torch.float64)
    assert moved.viewmat.dtype == moved.K.dtype == torch.float64 and (moved.width, moved.height) == (40, 30)
    assert cam.viewmat.dtype == torch.float32  # the original is unchanged


def test_avatar_renders_a_shared_mesh_pose_as_its_vertices():
    """A ``MeshPose`` from ``avatar.pose`` renders exactly what its vertices do (the trainer poses each training
    frame once); one of another mesh or dtype is refused with a clear message."""
    mesh = icosphere(2)
    av = Avatar(mesh, init_params(mesh, 300, sh_degree=1, generator=torch.Generator().manual_seed(3)))
    verts = mesh.vertices * torch.tensor([1.0, 1.2, 0.9])
    cam, bg = _turned_camera(), torch.tensor([0.2, 0.3, 0.4])
    pose = av.pose(verts)
    assert av.pose(pose) is pose
    with torch.no_grad():
        want = av.render(verts, cam, bg, backend="torch")
        got = av.render(pose, cam, bg, backend="torch")
    assert torch.equal(got.image, want.image) and torch.equal(got.alpha, want.alpha)
    other = icosphere(1)
    with pytest.raises(MeshsplatError, match="pose: a MeshPose of 42 vertices and 80 faces, the avatar's mesh has 162"):
        av.render(MeshPose.canonical(other), cam)
    with pytest.raises(MeshsplatError, match=r"pose: a MeshPose on cpu in torch\.float64"):
        av.render(MeshPose.from_vertices(TriMesh(mesh.vertices.double(), mesh.faces), verts.double()), cam)
