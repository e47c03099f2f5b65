"""The fidelity options (docs/quality.md): pose-dependent shading, SH in the triangle frame, multi-frame colour init, mask loss."""

from __future__ import annotations

import math

import pytest
import torch

from _shading_kit import _lit_from_x, _sphere
from _train_kit import VIEWMAT, H, K, W, small_config
from meshsplat.camera import Camera
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar, compose, init_params, sh0_to_rgb
from meshsplat.gaussians.shading import Shading, sh9_basis, shading_normals
from meshsplat.mesh import MeshPose
from meshsplat.run_folder import load_avatar
from meshsplat.train import Trainer
from meshsplat.train.recipes import recipe_config


def _rot_y(a: float) -> torch.Tensor:
    return torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def test_fresh_shading_is_neutral():
    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    pose = MeshPose.canonical(mesh)
    plain = compose(p, pose)
    shaded = compose(p, pose, shading=Shading())
    assert torch.allclose(plain.colors, shaded.colors, atol=1e-6)


def test_sh9_basis_orthonormal_on_sphere():
    n = torch.nn.functional.normalize(torch.randn(200_000, 3, dtype=torch.float64), dim=-1)
    Y = sh9_basis(n)
    gram = 4 * math.pi * (Y.T @ Y) / n.shape[0]
    assert torch.allclose(gram, torch.eye(9, dtype=torch.float64), atol=0.03)


def test_shading_follows_pose_and_equals_albedo_times_irradiance():
    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    sh = _lit_from_x()
    still = compose(p, MeshPose.canonical(mesh), shading=sh)
    turned = compose(p, MeshPose.from_vertices(mesh, mesh.vertices @ _rot_y(math.pi).T), shading=sh)
    # the same Gaussian turned to the other side gets other light: shading moves with the pose
    assert (still.colors - turned.colors).abs().max() > 0.3
    from meshsplat.embedding import embed

    _, n = embed(MeshPose.canonical(mesh), p["face"], p["uv"] + p["duv"], p["d"])
    e = (sh9_basis(n) @ sh.coeffs).clamp_min(0)
    assert torch.allclose(still.colors, sh0_to_rgb(p["sh0"]).clamp_min(0) * e, atol=1e-5)
    x = n[:, 0]
    c = still.colors.detach()
    assert float(c[x > 0.5].mean()) > float(c[x < -0.5].mean()) + 0.3


def test_shading_gradients_reach_albedo_and_illumination():
    from meshsplat.render import rasterize

    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    sh = Shading(normal="axis")
    sh.coeffs.requires_grad_(True)
    g = compose(p, MeshPose.canonical(mesh), shading=sh)
    out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, VIEWMAT[None], K[None], W, H, backend="torch")
    out.colors.sum().backward()
    assert sh.coeffs.grad is not None and sh.coeffs.grad.abs().sum() > 0
    assert p["sh0"].grad.abs().sum() > 0


def test_axis_normals_are_unit_and_face_the_phong_side():
    mesh = _sphere()
    p = init_params(mesh, 200, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        p["log_scale"][:, 2] -= 2.0  # flat along the local z axis
        p["rotation"].copy_(torch.nn.functional.normalize(torch.randn(200, 4), dim=-1))
    g = compose(p, MeshPose.canonical(mesh))
    from meshsplat.embedding import embed

    _, phong = embed(MeshPose.canonical(mesh), p["face"], p["uv"], p["d"])
    n = shading_normals("axis", phong, g.quats, g.scales)
    assert torch.allclose(n.norm(dim=-1), torch.ones(200), atol=1e-5)
    assert bool(((n * phong).sum(-1) >= 0).all())
    from meshsplat.mesh.quaternion import quat_to_matrix

    z_axis = quat_to_matrix(g.quats)[:, :, 2]
    assert torch.allclose((n * z_axis).sum(-1).abs(), torch.ones(200), atol=1e-5)
    with pytest.raises(MeshsplatError):
        shading_normals("bent", phong, g.quats, g.scales)


def test_sh_in_triangle_frame_turns_with_the_surface():
    mesh = _sphere()
    p = init_params(mesh, 300, sh_degree=1, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        p["shN"].normal_(0, 0.5, generator=torch.Generator().manual_seed(2))
    R = _rot_y(1.1)
    cam = torch.tensor([0.3, 0.2, 4.0])
    for frame, invariant in (("triangle", True), ("world", False)):
        a = compose(p, MeshPose.canonical(mesh), campos=cam, sh_frame=frame).colors
        # turn surface and camera together: the surface sees the camera from the same side
        b = compose(p, MeshPose.from_vertices(mesh, mesh.vertices @ R.T), campos=R @ cam, sh_frame=frame).colors
        assert torch.allclose(a, b, atol=1e-4) == invariant, frame
    # at the canonical pose both frames agree
    a = compose(p, MeshPose.canonical(mesh), campos=cam, sh_frame="triangle").colors
    b = compose(p, MeshPose.canonical(mesh), campos=cam, sh_frame="world").colors
    assert torch.allclose(a, b, atol=1e-5)
    with pytest.raises(MeshsplatError):
        compose(p, MeshPose.canonical(mesh), campos=cam, sh_frame="local")


def test_shading_state_round_trip_and_bad_input():
    mesh = _sphere()
    p = init_params(mesh, 100, generator=torch.Generator().manual_seed(0))
    av = Avatar(mesh, p, shading=_lit_from_x(), sh_frame="triangle")
    back = Avatar.from_state_dict(av.state_dict())
    assert back.sh_frame == "triangle" and torch.equal(back.shading.coeffs, av.shading.coeffs)
    v = mesh.vertices @ _rot_y(0.4).T
    assert torch.equal(av.compose(v).colors, back.compose(v).colors)
    with pytest.raises(MeshsplatError):
        Shading(torch.zeros(4, 3))
    with pytest.raises(MeshsplatError):
        Shading(normal="flat")
    with pytest.raises(MeshsplatError):
        Avatar(mesh, p, sh_frame="camera")


def test_export_ships_illumination_and_bakes_the_ply(tmp_path):
    from meshsplat.export import export_avatar, load_exported_avatar
    from meshsplat.io import read_gaussian_ply

    mesh = _sphere()
    p = init_params(mesh, 150, generator=torch.Generator().manual_seed(0))
    av = Avatar(mesh, p, shading=_lit_from_x())
    export_avatar(av, tmp_path)
    back = load_exported_avatar(tmp_path)
    assert back.shading is not None and back.shading.normal == "phong"
    v = mesh.vertices @ _rot_y(2.0).T
    assert torch.allclose(av.compose(v).colors, back.compose(v).colors, atol=1e-5)
    ply = read_gaussian_ply(tmp_path / "avatar.ply")
    baked = sh0_to_rgb(ply["sh0"])
    assert torch.allclose(baked, av.compose(mesh.vertices).colors, atol=1e-4)
    assert "ALBEDO" in (tmp_path / "README.txt").read_text()


def test_config_switches_validate():
    for bad in (
        "shading.occlusion=phong",
        "shading.normal=face",
        "model.sh_frame=camera",
        "model.init_color_frames=0",
        "mask_loss.weight=-1",
        "offset_bound.max_offset=-0.1",
    ):
        from meshsplat.train import apply_overrides

        with pytest.raises(MeshsplatError):
            apply_overrides(recipe_config("quality"), [bad]).validate()


def test_max_offset_keeps_gaussians_near_their_triangle(tiny_dataset, tmp_path):
    # a fast embedding moves the offsets d along the normal; the bound holds them after every step
    fast = ["optim.lr_embedding=1e-2", "optim.lr_embedding_final=1e-2"]
    free = Trainer(small_config(tiny_dataset, tmp_path / "free", 12, [*fast, "offset_bound.enabled=false"]))
    free.train()
    bound = 2e-3 * free.extent
    assert float(free.params["d"].detach().abs().max()) > bound  # unbounded, some leave the band
    held = Trainer(small_config(tiny_dataset, tmp_path / "held", 12, [*fast, "offset_bound.max_offset=2e-3"]))
    held.train()
    reach = float(held.params["d"].detach().abs().max())
    assert reach <= bound * (1 + 1e-6)  # float32
    assert reach == pytest.approx(bound)  # the bound is reached, not avoided


def test_trainer_with_all_options_learns_illumination_and_resumes_exactly(tiny_dataset, tmp_path):
    import shutil

    opts = [
        "shading.enabled=true",
        "model.init_color_frames=3",
        "model.sh_degree=1",
        "model.sh_frame=triangle",
        "model.antialiased=true",
        "mask_loss.weight=0.1",
    ]
    full = Trainer(small_config(tiny_dataset, tmp_path / "full", 20, opts))
    assert full.shading is not None
    c0 = full.shading.coeffs.detach().clone()
    full.train()
    assert not torch.equal(c0, full.shading.coeffs.detach())  # the illumination is learned
    assert all(r["mask"] > 0 for r in full.history)
    av = load_avatar(tmp_path / "full")
    assert av.shading is not None and av.sh_frame == "triangle" and av.antialiased
    assert torch.equal(av.shading.coeffs, full.shading.coeffs.detach())
    (tmp_path / "res" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000010.pt", tmp_path / "res" / "checkpoints")
    res = Trainer(small_config(tiny_dataset, tmp_path / "res", 20, opts), resume=True)
    res.train()
    assert torch.equal(res.shading.coeffs.detach(), full.shading.coeffs.detach())
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k
    with pytest.raises(MeshsplatError, match="shading"):
        Trainer(small_config(tiny_dataset, tmp_path / "res", 30, ["shading.enabled=false"]), resume=True)


def test_multi_frame_colours_average_visible_frames(tiny_dataset, tmp_path):
    one = Trainer(small_config(tiny_dataset, tmp_path / "a", 1, ["model.init_color_frames=1"]))
    many = Trainer(small_config(tiny_dataset, tmp_path / "b", 1, ["model.init_color_frames=6"]))
    c1, c6 = sh0_to_rgb(one.params["sh0"].detach()), sh0_to_rgb(many.params["sh0"].detach())
    assert torch.equal(one.params["face"], many.params["face"])
    assert bool(((c6 >= 0) & (c6 <= 1)).all())
    # the teacher's colour at each point: the first frame alone also paints the far side with what is in
    # front of it; several frames with the facing test get closer to the truth
    f, uv = one.params["face"], one.params["uv"]
    tri = one.mesh.vertices[one.mesh.faces[f]]
    pos = uv[:, :1] * tri[:, 0] + uv[:, 1:] * tri[:, 1] + (1 - uv.sum(-1, keepdim=True)) * tri[:, 2]
    truth = torch.stack(
        [0.5 + 0.5 * torch.sin(5 * pos[:, 0]), 0.5 + 0.5 * torch.cos(4 * pos[:, 1]), (pos[:, 2] > 0).float()], -1
    )
    seen = (c6 - 0.5).abs().amax(-1) > 1e-6
    assert int(seen.sum()) > 0.8 * len(seen)
    err1 = float((c1 - truth)[seen].abs().mean())
    err6 = float((c6 - truth)[seen].abs().mean())
    assert err6 < 0.8 * err1, (err6, err1)


def test_viewer_bundle_ships_the_shading(tmp_path):
    """The player shades on the GPU (tests/viewer/test_viewer.py checks its screenshots against avatar.render):
    the bundle carries the albedo, not a baked colour, and the learned illumination."""
    from meshsplat.gaussians.params import SH_C0
    from meshsplat.viewer.bundle import read_viewer_bundle, write_viewer_bundle

    mesh = _sphere()
    p = init_params(mesh, 120, generator=torch.Generator().manual_seed(0))
    av = Avatar(mesh, p, shading=_lit_from_x())
    write_viewer_bundle(av, mesh.vertices[None].numpy(), tmp_path)
    header, arrays = read_viewer_bundle(tmp_path)
    albedo = 0.5 + SH_C0 * p["sh0"].detach()[:, 0]
    # the bundle stores colours as half floats (relative error <= 2^-11)
    assert torch.allclose(torch.tensor(arrays["gaussian_rgb"].copy()), albedo, atol=1e-5, rtol=2.0**-11)
    assert torch.equal(torch.tensor(header["shading"]["coeffs"]).float(), av.shading.coeffs.float())
    assert header["shading"]["normal"] == av.shading.normal


def test_antialias_compensation_dims_small_gaussians_only():
    from meshsplat.render.projection import antialias_compensation

    means = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    quats = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    scales = torch.tensor([[0.002, 0.002, 0.002], [0.5, 0.5, 0.5]], requires_grad=True)
    comp = antialias_compensation(means, quats, scales, VIEWMAT[None], K[None], W, H)
    assert comp.shape == (1, 2)
    # 0.002 world units at depth 4 with f=40 is 0.02 px: compensated a lot; a 5 px Gaussian barely
    sigma2 = (0.002 * 40 / 4) ** 2
    assert torch.allclose(comp[0, 0], torch.tensor(sigma2 / (sigma2 + 0.3)), rtol=1e-3)
    assert torch.allclose(comp[0, 1], torch.tensor(25.0 / 25.3), rtol=1e-3)
    comp.sum().backward()
    assert scales.grad[0].abs().sum() > 0


def test_antialiased_avatar_renders_small_splats_fainter(tmp_path):
    mesh = _sphere()
    p = init_params(mesh, 200, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        p["log_scale"].fill_(math.log(0.004))
        p["opacity_logit"].fill_(4.0)
    cam = Camera(VIEWMAT, K, W, H)
    plain = Avatar(mesh, p).render(mesh.vertices, cam, backend="torch")
    aa = Avatar(mesh, p, antialiased=True)
    out = aa.render(mesh.vertices, cam, backend="torch")
    assert float(out.alpha.detach().sum()) < 0.5 * float(plain.alpha.detach().sum())
    back = Avatar.from_state_dict(aa.state_dict())
    assert back.antialiased
    from meshsplat.export import export_avatar, load_exported_avatar

    export_avatar(aa, tmp_path)
    assert load_exported_avatar(tmp_path).antialiased
