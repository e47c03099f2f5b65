"""meshsplat export: PLY in the canonical pose, embedding JSON + OBJ round trip, CLI."""

from __future__ import annotations

import pytest
import torch

from _eval_kit import SIZE, camera, deform, make_avatar, make_run
from meshsplat.camera import Camera
from meshsplat.export import canonical_gaussians, export_avatar, load_exported_avatar
from meshsplat.io import read_gaussian_ply


def _render(av, verts, azimuth):
    K, vm = camera(azimuth)
    with torch.no_grad():
        return av.render(verts, Camera.from_numpy(vm, K, SIZE, SIZE), torch.ones(3), backend="torch")


@pytest.mark.parametrize("sh_degree,clamp", [(0, False), (1, True)])
def test_export_load_renders_identically(tmp_path, sh_degree, clamp):
    """Exact equality is expected, not just closeness: the JSON stores float32 bytes (base64), the OBJ
    writes 9 significant digits (enough to round-trip any float32), and the effective uv (uv + duv,
    clamped when the avatar clamps) is stored as computed, so the loaded avatar (duv = 0, no clamp)
    feeds the renderer the same bits: uv + 0.0 == uv."""
    av = make_avatar(n=200, sh_degree=sh_degree, clamp_to_face=clamp)
    res = export_avatar(av, tmp_path / "exp", source="test")
    for f in (res.ply, res.embedding, res.mesh, res.readme):
        assert f.is_file()
    assert "avatar.ply" in res.readme.read_text()
    back = load_exported_avatar(tmp_path / "exp")
    assert back.num_gaussians == av.num_gaussians and back.sh_degree == sh_degree
    assert back.scale_mode == av.scale_mode
    assert torch.equal(back.mesh.vertices, av.mesh.vertices) and torch.equal(back.mesh.faces, av.mesh.faces)
    for verts, az in ((av.mesh.vertices, 0.0), (deform(av.mesh.vertices, 0.8), 60.0)):
        a, b = _render(av, verts, az), _render(back, verts, az)
        assert float(a.alpha.max()) > 0.5  # something is in view
        assert torch.equal(a.image, b.image) and torch.equal(a.alpha, b.alpha)


def test_ply_holds_the_composed_canonical_gaussians(tmp_path):
    av = make_avatar(n=150, sh_degree=1)
    res = export_avatar(av, tmp_path)
    g, _normals = canonical_gaussians(av)
    ply = read_gaussian_ply(res.ply)
    assert torch.equal(ply["means"], g.means)
    assert torch.equal(ply["quats"], g.quats)
    assert torch.allclose(ply["log_scales"].exp(), g.scales, rtol=1e-6, atol=0)
    assert torch.equal(ply["opacity_logits"], av.params["opacity_logit"].detach())
    assert torch.equal(ply["sh0"], av.params["sh0"].detach())
    assert ply["shN"].shape == (150, 15, 3)  # padded to degree 3 as viewers expect
    assert torch.equal(ply["shN"][:, :3], av.params["shN"].detach()) and not ply["shN"][:, 3:].any()
    assert torch.allclose(ply["normals"].norm(dim=1), torch.ones(150), atol=1e-5)
    # canonical pose: the Gaussians sit on the (displaced) canonical surface, near the unit sphere
    assert (ply["means"].norm(dim=1) - 1).abs().max() < 0.5


def test_cli_export(tmp_path, capsys):
    from meshsplat.cli.main import main

    run = make_run(make_avatar(n=100), tmp_path / "run", None, iteration=3)
    assert main(["export", str(run)]) == 0
    for f in ("avatar.ply", "embedding.json", "canonical_mesh.obj", "README.txt"):
        assert (run / "export" / f).is_file()
    assert "100 Gaussians" in capsys.readouterr().out
    assert main(["export", str(tmp_path / "missing"), "--out", str(tmp_path / "x")]) == 2
    assert "run not found" in capsys.readouterr().err
