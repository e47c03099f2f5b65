"""Shading with occlusion from the posed driving mesh (shading.occlusion=directions; docs/quality.md)."""

from __future__ import annotations

import shutil

import pytest
import torch

from _meshes import box
from _shading_kit import _lit_from_x, _sphere
from _train_kit import VIEWMAT, H, K, W, small_config
from meshsplat.embedding import embed, surface_points
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar, compose, init_params, sh0_to_rgb
from meshsplat.gaussians.shading import Shading, sh9_basis
from meshsplat.mesh import MeshPose, TriMesh
from meshsplat.mesh.visibility import visibility
from meshsplat.run_folder import load_avatar
from meshsplat.train import Trainer, apply_overrides
from meshsplat.train.recipes import recipe_config

OCCL = ["shading.occlusion=directions", "shading.directions=8", "shading.grid=32"]


def _occluded(light: float = 0.0, k: int = 16) -> Shading:
    sh = Shading(occlusion="directions", directions=k)
    sh.coeffs.copy_(_lit_from_x().coeffs)
    assert sh.light is not None
    sh.light.fill_(light)
    return sh


def _slabs(gap: float) -> TriMesh:
    """Two thin horizontal slabs (y up): the floor at y = 0 and a roof ``gap`` above it (moved aside when
    ``gap`` is negative: the same vertices, another pose)."""
    v, f = box()
    floor = v * torch.tensor([2.0, 0.05, 2.0])
    roof = floor + (torch.tensor([0.0, gap, 0.0]) if gap > 0 else torch.tensor([6.0, 1.0, 0.0]))
    return TriMesh(torch.cat([floor, roof]), torch.cat([f, f + 8]))


def test_untrained_occlusion_equals_todays_shading():
    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    pose = MeshPose.from_vertices(mesh, mesh.vertices * torch.tensor([1.0, 1.3, 0.8]))
    today = compose(p, pose, shading=_lit_from_x())
    occl = compose(p, pose, shading=_occluded(0.0))
    assert torch.equal(today.colors, occl.colors)


def test_lit_colour_is_albedo_times_ambient_plus_visible_lights():
    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    sh = _occluded(0.0)
    assert sh.light is not None and sh.directions is not None
    sh.light.copy_(torch.rand(16, 3, generator=torch.Generator().manual_seed(1)))
    pose = MeshPose.canonical(mesh)
    got = compose(p, pose, shading=sh).colors
    uv = p["uv"] + p["duv"]
    _, n = embed(pose, p["face"], uv, p["d"])
    vis = visibility(
        mesh.vertices, mesh.faces, surface_points(mesh.vertices, mesh.faces, p["face"], uv), n, sh.directions
    )
    e = (sh9_basis(n) @ sh.coeffs).clamp_min(0) + (vis * (n @ sh.directions.T).clamp_min(0)) @ sh.light
    assert torch.allclose(got, sh0_to_rgb(p["sh0"]).clamp_min(0) * e, atol=1e-5)
    assert 0.3 < float(vis.mean()) < 0.7  # a convex body sees about half of the sky
    assert torch.equal(got, compose(p, pose, shading=sh).colors)  # deterministic


def test_shadows_move_with_the_pose():
    """Gaussians on the floor, a light from straight above: dark under the roof, lit once it moves aside."""
    under, aside = _slabs(1.0), _slabs(-1.0)
    g = torch.Generator().manual_seed(0)
    top = torch.nonzero(under.vertices[under.faces[:12]][:, :, 1].amin(-1) > 0.02)[:, 0]  # the floor's top
    face = top[torch.randint(len(top), (200,), generator=g)]
    uv = torch.full((200, 2), 1 / 3)
    p = init_params(under, 200, generator=g)
    p["face"], p["uv"] = face, uv
    with torch.no_grad():
        p["d"].zero_()
        p["sh0"].fill_(0.0)  # albedo 0.5
    sh = Shading(occlusion="directions", directions=16)
    sh.coeffs.zero_()  # no ambient: only the key light
    assert sh.light is not None and sh.directions is not None
    sh.light[int(sh.directions[:, 1].argmax())] = 1.0  # the most upward direction
    dark = compose(p, MeshPose.canonical(under), shading=sh).colors
    lit = compose(p, MeshPose.from_vertices(under, aside.vertices), shading=sh).colors
    assert float(dark.detach().max()) == 0.0
    assert float(lit.detach().min()) > 0.4


def test_gradient_reaches_the_lights_and_they_stay_non_negative():
    from meshsplat.render import rasterize

    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    sh = _occluded(0.0)
    assert sh.light is not None
    sh.light.requires_grad_(True)
    g = compose(p, MeshPose.canonical(mesh), shading=sh)
    out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, VIEWMAT[None], K[None], W, H, backend="torch")
    out.colors.sum().backward()
    assert sh.light.grad is not None and sh.light.grad.abs().sum() > 0
    with torch.no_grad():
        sh.light.sub_(1.0)
    sh.project()
    assert float(sh.light.detach().min()) == 0.0


def test_state_round_trip_and_older_states():
    mesh = _sphere()
    p = init_params(mesh, 150, generator=torch.Generator().manual_seed(0))
    sh = _occluded(0.3, k=8)
    av = Avatar(mesh, p, shading=sh)
    v = mesh.vertices * torch.tensor([1.2, 0.9, 1.0])
    back = Avatar.from_state_dict(av.state_dict())
    assert back.shading is not None and back.shading.occlusion == "directions" and back.shading.grid == 64
    assert torch.equal(av.compose(v).colors, back.compose(v).colors)
    older = av.state_dict()
    del older["shading"]["occlusion"]  # a checkpoint written before occlusion existed
    old = Avatar.from_state_dict(older)
    assert old.shading is not None and old.shading.occlusion == "none" and old.shading.light is None
    bad = av.state_dict()
    bad["shading"]["occlusion"]["light"] = torch.zeros(5, 3)
    with pytest.raises(MeshsplatError, match="occlusion"):
        Avatar.from_state_dict(bad)


def test_export_round_trip(tmp_path):
    from meshsplat.export import export_avatar, load_exported_avatar

    mesh = _sphere()
    p = init_params(mesh, 150, generator=torch.Generator().manual_seed(0))
    av = Avatar(mesh, p, shading=_occluded(0.4, k=8))
    export_avatar(av, tmp_path)
    back = load_exported_avatar(tmp_path)
    assert back.shading is not None and back.shading.occlusion == "directions"
    v = mesh.vertices * torch.tensor([1.2, 0.9, 1.0])
    assert torch.allclose(av.compose(v).colors, back.compose(v).colors, atol=1e-5)
    assert "occlusion" in (tmp_path / "README.txt").read_text()


def test_the_player_refuses_an_occluded_avatar(tmp_path):
    """Lights from fixed directions: refused in one line (the player shades one aligned key light,
    shading.occlusion=key; tests/test_viewer.py)."""
    from meshsplat.viewer.bundle import write_viewer_bundle

    mesh = _sphere()
    av = Avatar(mesh, init_params(mesh, 50, generator=torch.Generator().manual_seed(0)), shading=_occluded(0.1))
    with pytest.raises(MeshsplatError, match=r"shading\.occlusion=directions.*shades shading\.occlusion=key"):
        write_viewer_bundle(av, mesh.vertices[None].numpy(), tmp_path / "v")
    assert not (tmp_path / "v").exists()


def test_config_keys_validate():
    cfg = apply_overrides(recipe_config("quality"), OCCL).validate()
    assert (cfg.shading.occlusion, cfg.shading.directions, cfg.shading.grid) == ("directions", 8, 32)
    assert recipe_config("quality").shading.occlusion == "key"  # the quality preset's
    for bad in (
        ["shading.occlusion=rays"],
        ["shading.directions=0"],
        ["shading.grid=4"],
    ):
        with pytest.raises(MeshsplatError, match="shading"):
            apply_overrides(recipe_config("quality"), bad).validate()


def test_trainer_learns_the_lights_and_resumes_exactly(tiny_dataset, tmp_path):
    full = Trainer(small_config(tiny_dataset, tmp_path / "full", 20, OCCL))
    assert full.shading is not None and full.shading.light is not None
    full.train()
    light = full.shading.light.detach()
    assert light.shape == (8, 3) and float(light.min()) >= 0.0 and float(light.max()) > 0.0
    av = load_avatar(tmp_path / "full")
    assert av.shading is not None and av.shading.grid == 32 and torch.equal(av.shading.light, light)
    (tmp_path / "res" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000010.pt", tmp_path / "res" / "checkpoints")
    res = Trainer(small_config(tiny_dataset, tmp_path / "res", 20, OCCL), resume=True)
    res.train()
    assert res.shading is not None and res.shading.light is not None
    assert torch.equal(res.shading.light.detach(), light)
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k
    with pytest.raises(MeshsplatError, match="occlusion"):
        Trainer(small_config(tiny_dataset, tmp_path / "res", 30, []), resume=True)
