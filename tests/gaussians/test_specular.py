"""The additive specular term of the posed normal (shading.specular=sh2; docs/quality.md)."""

from __future__ import annotations

import shutil

import pytest
import torch

from _shading_kit import _lit_from_x, _sphere
from _train_kit import VIEWMAT, H, K, W, small_config
from meshsplat.embedding import embed
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar, compose, init_params, sh0_to_rgb
from meshsplat.gaussians.shading import Shading, sh9_basis
from meshsplat.mesh import MeshPose
from meshsplat.run_folder import load_avatar
from meshsplat.train import Trainer, apply_overrides
from meshsplat.train.recipes import recipe_config

SPEC = ["shading.specular=sh2"]


def _specular(scale: float = 0.0, occlusion: str = "none") -> Shading:
    """The key-lit shading with a specular term: ``scale`` x a fixed white-ish highlight from +x+y."""
    sh = Shading(specular="sh2", occlusion=occlusion, directions=8)
    sh.coeffs.copy_(_lit_from_x().coeffs)
    assert sh.specular is not None
    sh.specular.copy_(scale * _highlight())
    return sh


def _highlight() -> torch.Tensor:
    """``[9,3]``: an added light, brightest towards +x+y, slightly warm."""
    s = torch.zeros(9, 3)
    s[0] = torch.tensor([0.3, 0.28, 0.25])
    s[1] = torch.tensor([0.25, 0.25, 0.2])  # y
    s[3] = torch.tensor([0.3, 0.3, 0.25])  # x
    s[4] = torch.tensor([0.1, 0.1, 0.1])  # xy
    return s


def test_untrained_specular_equals_todays_shading():
    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    pose = MeshPose.from_vertices(mesh, mesh.vertices * torch.tensor([1.0, 1.3, 0.8]))
    for occl in ("none", "directions"):
        today = Shading(occlusion=occl, directions=8)
        today.coeffs.copy_(_lit_from_x().coeffs)
        assert torch.equal(
            compose(p, pose, shading=today).colors, compose(p, pose, shading=_specular(0.0, occl)).colors
        )


def test_colour_is_albedo_times_irradiance_plus_specular():
    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    sh = _specular(1.0)
    pose = MeshPose.canonical(mesh)
    got = compose(p, pose, shading=sh).colors
    _, n = embed(pose, p["face"], p["uv"] + p["duv"], p["d"])
    albedo = sh0_to_rgb(p["sh0"]).clamp_min(0)
    want = albedo * (sh9_basis(n) @ sh.coeffs).clamp_min(0) + sh9_basis(n) @ _highlight()
    assert torch.allclose(got, want, atol=1e-5)
    # added, not multiplied: a black albedo still shows the highlight
    with torch.no_grad():
        p["sh0"].fill_(-0.5 / 0.28209479177387814)
    dark = compose(p, pose, shading=sh).colors
    assert torch.allclose(dark, sh9_basis(n) @ _highlight(), atol=1e-5) and float(dark.detach().max()) > 0.25


def test_gradient_reaches_the_specular():
    from meshsplat.render import rasterize

    mesh = _sphere()
    p = init_params(mesh, 300, generator=torch.Generator().manual_seed(0))
    sh = _specular(0.0)
    assert sh.specular is not None
    sh.specular.requires_grad_(True)
    assert any(t is sh.specular for t in sh.parameters())
    g = compose(p, MeshPose.canonical(mesh), shading=sh)
    out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, VIEWMAT[None], K[None], W, H, backend="torch")
    out.colors.sum().backward()
    assert sh.specular.grad is not None and bool((sh.specular.grad.abs().sum(-1) > 0).all())


def test_state_round_trip_older_states_and_base_rgb():
    mesh = _sphere()
    p = init_params(mesh, 150, generator=torch.Generator().manual_seed(0))
    av = Avatar(mesh, p, shading=_specular(1.0, "directions"))
    v = mesh.vertices * torch.tensor([1.2, 0.9, 1.0])
    back = Avatar.from_state_dict(av.state_dict())
    assert back.shading is not None and back.shading.specular_mode == "sh2" and back.shading.occlusion == "directions"
    assert torch.equal(av.compose(v).colors, back.compose(v).colors)
    moved = Avatar(mesh, p, shading=_specular(1.0).to("cpu"))
    assert moved.shading is not None and torch.equal(moved.shading.specular, _highlight())
    # the static exports' baked colour carries it: base_rgb differs from the same avatar without it
    plain = Avatar(mesh, p, shading=_specular(0.0))
    _, n = embed(MeshPose.canonical(mesh), p["face"], p["uv"] + p["duv"], p["d"])
    assert torch.allclose(moved.base_rgb() - plain.base_rgb(), sh9_basis(n) @ _highlight(), atol=1e-5)
    older = av.state_dict()
    del older["shading"]["specular"]  # a checkpoint written before specular existed
    old = Avatar.from_state_dict(older)
    assert old.shading is not None and old.shading.specular_mode == "none" and old.shading.specular is None
    assert len(old.shading.parameters()) == 2  # coeffs, light
    bad = av.state_dict()
    bad["shading"]["specular"]["coeffs"] = torch.zeros(4, 3)
    with pytest.raises(MeshsplatError, match="specular"):
        Avatar.from_state_dict(bad)
    with pytest.raises(MeshsplatError, match="specular"):
        Shading(specular="phong")


def test_export_round_trip(tmp_path):
    from meshsplat.export import export_avatar, load_exported_avatar

    mesh = _sphere()
    p = init_params(mesh, 150, generator=torch.Generator().manual_seed(0))
    av = Avatar(mesh, p, shading=_specular(1.0))
    export_avatar(av, tmp_path)
    back = load_exported_avatar(tmp_path)
    assert back.shading is not None and back.shading.specular is not None
    v = mesh.vertices * torch.tensor([1.2, 0.9, 1.0])
    assert torch.allclose(av.compose(v).colors, back.compose(v).colors, atol=1e-5)
    assert "specular" in (tmp_path / "README.txt").read_text()


def test_the_bundle_carries_the_specular(tmp_path):
    from meshsplat.viewer.bundle import read_viewer_bundle, write_viewer_bundle

    mesh = _sphere()
    av = Avatar(mesh, init_params(mesh, 50, generator=torch.Generator().manual_seed(0)), shading=_specular(1.0))
    write_viewer_bundle(av, mesh.vertices[None].numpy(), tmp_path / "v")
    h, _ = read_viewer_bundle(tmp_path / "v")
    assert torch.allclose(torch.tensor(h["shading"]["specular"]), _highlight())
    plain = Avatar(mesh, av.params, shading=_lit_from_x())
    write_viewer_bundle(plain, mesh.vertices[None].numpy(), tmp_path / "p")
    assert "specular" not in read_viewer_bundle(tmp_path / "p")[0]["shading"]


def test_config_keys_validate():
    assert apply_overrides(recipe_config("quality"), SPEC).validate().shading.specular == "sh2"
    assert recipe_config("quality").shading.specular == "none"
    for bad in (["shading.specular=phong"],):
        with pytest.raises(MeshsplatError, match="specular"):
            apply_overrides(recipe_config("quality"), bad).validate()


def test_trainer_learns_the_specular_and_resumes_exactly(tiny_dataset, tmp_path):
    full = Trainer(small_config(tiny_dataset, tmp_path / "full", 20, SPEC))
    assert full.shading is not None and isinstance(full.shading.specular, torch.nn.Parameter)
    full.train()
    spec = full.shading.specular.detach()
    assert spec.shape == (9, 3) and float(spec.abs().max()) > 0.0
    av = load_avatar(tmp_path / "full")
    assert av.shading is not None and torch.equal(av.shading.specular, spec)
    (tmp_path / "res" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000010.pt", tmp_path / "res" / "checkpoints")
    res = Trainer(small_config(tiny_dataset, tmp_path / "res", 20, SPEC), resume=True)
    res.train()
    assert res.shading is not None and res.shading.specular is not None
    assert torch.equal(res.shading.specular.detach(), spec)
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k
    with pytest.raises(MeshsplatError, match="specular"):
        Trainer(small_config(tiny_dataset, tmp_path / "res", 30, []), resume=True)
