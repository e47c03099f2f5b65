"""The key light (``model.occlusion=key``): candidate lights collapse into one shadowed key light."""

from __future__ import annotations

import math
import shutil

import pytest
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar, compose, init_params
from meshsplat.gaussians.shading import KEY_CONE_DEG, KEY_RING, KEY_RINGS_DEG, KEY_STAGES, Shading, sh9_basis
from meshsplat.mesh import MeshPose
from meshsplat.run_folder import load_avatar
from meshsplat.train import TrainConfig, Trainer, apply_overrides
from test_quality_options import _sphere
from test_train import small_config, tiny_dataset  # noqa: F401  (fixture)

KEY = ["model.occlusion=key", "model.occlusion_directions=8", "model.occlusion_grid=32", "model.occlusion_key_iter=4"]


def _candidates() -> tuple[Shading, int, int, int]:
    """16 candidates: the strongest (1.0), a neighbour within the cone (0.5) and a far light (0.3)."""
    sh = Shading(occlusion="key", directions=16)
    assert sh.directions is not None and sh.light is not None
    d = sh.directions
    a = 0
    cos = d @ d[a]
    inside = math.cos(math.radians(KEY_CONE_DEG))
    b = int(torch.where(cos >= inside, cos, torch.tensor(-2.0)).topk(2).indices[1])  # nearest other
    c = int(cos.argmin())  # the far side
    sh.light.zero_()
    sh.light[a], sh.light[b], sh.light[c] = 1.0, 0.5, 0.3
    return sh, a, b, c


def test_align_key_weights_the_direction_and_folds_the_rest_into_sh2():
    sh, a, b, c = _candidates()
    assert sh.directions is not None
    d = sh.directions.clone()
    coeffs = sh.coeffs.clone()
    sh.align_key()
    assert sh.key_stage == 1 and not sh.key_aligned and sh.light is not None
    assert sh.directions.shape == (1 + KEY_RING, 3)
    want = torch.nn.functional.normalize(1.0**2 * d[a] + 0.5**2 * d[b], dim=0)  # weighted by intensity squared
    assert torch.allclose(sh.directions[0], want, atol=1e-6)
    assert torch.allclose(sh.light, torch.full((1 + KEY_RING, 3), 1.5 / (1 + KEY_RING)))  # shared equally
    ring = sh.directions[1:] @ want  # the new candidates: evenly around the estimate at the first ring's angle
    assert torch.allclose(ring, torch.full((KEY_RING,), math.cos(math.radians(KEY_RINGS_DEG[0]))), atol=1e-6)
    assert torch.allclose(sh.directions.norm(dim=-1), torch.ones(1 + KEY_RING), atol=1e-6)
    # the far light is now part of E_sh2: its clamped cosine's SH2 projection, 1.0625 facing it, 0.0625 opposite
    gain = sh9_basis(torch.stack([d[c], -d[c]])) @ (sh.coeffs - coeffs)
    assert torch.allclose(gain[:, 0], torch.tensor([0.3 * 1.0625, 0.3 * 0.0625]), atol=1e-5)


def test_the_rings_narrow_the_estimate_onto_the_light():
    """A light between the estimate and one ring candidate: the weighted mean moves onto it stage by stage."""
    sh, *_ = _candidates()
    sh.align_key()
    assert sh.directions is not None and sh.light is not None
    for _ in range(KEY_STAGES - 1):
        # pretend training shared the light between the estimate and ring candidate 1 as 1 : 2
        sh.light.zero_()
        sh.light[0], sh.light[1] = 1.0, 2.0
        want = torch.nn.functional.normalize(sh.directions[0] + 2.0**2 * sh.directions[1], dim=0)
        sh.align_key()
        assert torch.allclose(sh.directions[0], want, atol=1e-6)
        assert torch.allclose(sh.light.sum(0), torch.full((3,), 3.0))  # the merged intensity, kept
    assert sh.key_aligned and sh.directions.shape == (1, 3) and sh.light.shape == (1, 3)
    with pytest.raises(MeshsplatError, match="align_key"):
        sh.align_key()


def test_unlit_candidates_align_to_an_unlit_key_and_the_colours_stay():
    mesh = _sphere()
    p = init_params(mesh, 200, generator=torch.Generator().manual_seed(0))
    pose = MeshPose.from_vertices(mesh, mesh.vertices * torch.tensor([1.0, 1.3, 0.8]))
    sh = Shading(occlusion="key", directions=16)
    before = compose(p, pose, shading=sh).colors
    for _ in range(KEY_STAGES):
        sh.align_key()
    assert sh.light is not None and float(sh.light.abs().max()) == 0.0
    assert torch.equal(compose(p, pose, shading=sh).colors, before)
    assert torch.equal(before, compose(p, pose, shading=Shading()).colors)


def test_key_shadows_with_one_map_after_alignment():
    mesh = _sphere()
    p = init_params(mesh, 200, generator=torch.Generator().manual_seed(0))
    pose = MeshPose.canonical(mesh)
    sh, *_ = _candidates()
    for _ in range(KEY_STAGES):
        sh.align_key()
    got = compose(p, pose, shading=sh).colors
    assert sh.directions is not None
    assert sh.visibility(pose.verts, pose.faces, pose.verts[:5], torch.ones(5, 3) / 3**0.5).shape == (5, 1)
    assert torch.isfinite(got).all()


def test_state_round_trip_before_and_after_alignment():
    mesh = _sphere()
    p = init_params(mesh, 150, generator=torch.Generator().manual_seed(0))
    v = mesh.vertices * torch.tensor([1.2, 0.9, 1.0])
    sh, *_ = _candidates()
    for stage in range(KEY_STAGES + 1):
        if stage:
            sh.align_key()
        av = Avatar(mesh, p, shading=sh)
        back = Avatar.from_state_dict(av.state_dict())
        assert back.shading is not None and back.shading.occlusion == "key"
        assert back.shading.key_stage == stage and back.shading.candidates == 16
        assert torch.equal(av.compose(v).colors, back.compose(v).colors)
        moved = back.shading.to("cpu")
        assert moved.key_stage == stage and torch.equal(moved.directions, back.shading.directions)
    bad = Avatar(mesh, p, shading=sh).state_dict()
    bad["shading"]["occlusion"]["directions"] = torch.tensor([[0.0, 2.0, 0.0]])
    with pytest.raises(MeshsplatError, match="unit directions"):
        Avatar.from_state_dict(bad)
    bad["shading"]["occlusion"]["directions"] = torch.eye(3)[:2]
    bad["shading"]["occlusion"]["light"] = torch.zeros(2, 3)
    with pytest.raises(MeshsplatError, match="shape"):
        Avatar.from_state_dict(bad)
    bad["shading"]["occlusion"]["stage"] = 7
    with pytest.raises(MeshsplatError, match="stage"):
        Avatar.from_state_dict(bad)
    with pytest.raises(MeshsplatError, match="key directions given"):
        Shading(key=torch.tensor([0.0, 1.0, 0.0]))


def test_export_keeps_the_key(tmp_path):
    from meshsplat.export import export_avatar, load_exported_avatar

    mesh = _sphere()
    p = init_params(mesh, 150, generator=torch.Generator().manual_seed(0))
    sh, *_ = _candidates()
    for _ in range(KEY_STAGES):
        sh.align_key()
    av = Avatar(mesh, p, shading=sh)
    export_avatar(av, tmp_path)
    back = load_exported_avatar(tmp_path)
    assert back.shading is not None and back.shading.key_aligned
    v = mesh.vertices * torch.tensor([1.2, 0.9, 1.0])
    assert torch.allclose(av.compose(v).colors, back.compose(v).colors, atol=1e-5)


def test_config_validates_the_key_iteration():
    cfg = apply_overrides(TrainConfig(), KEY).validate()
    assert (cfg.model.occlusion, cfg.model.occlusion_key_iter) == ("key", 4)
    with pytest.raises(MeshsplatError, match="occlusion_key_iter"):
        apply_overrides(TrainConfig(), ["model.occlusion_key_iter=0"]).validate()


def test_trainer_aligns_once_and_resumes_exactly_across_it(tiny_dataset, tmp_path):  # noqa: F811
    full = Trainer(small_config(tiny_dataset, tmp_path / "full", 20, KEY))
    assert full.shading is not None and full.shading.directions is not None
    assert full.shading.directions.shape == (8, 3)
    full.train(until=7)
    assert full.shading.key_stage == 1 and full.shading.directions.shape == (1 + KEY_RING, 3)
    full.train()
    sh = full.shading
    assert sh.key_aligned and sh.directions is not None and sh.directions.shape == (1, 3)
    assert sh.light is not None and sh.light.shape == (1, 3)
    av = load_avatar(tmp_path / "full")
    assert av.shading is not None and av.shading.key_aligned
    assert torch.equal(av.shading.directions, sh.directions)
    # resumed from a checkpoint written in the middle of the search (stage 2 began at iteration 8): bit-identical
    (tmp_path / "res" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000010.pt", tmp_path / "res" / "checkpoints")
    res = Trainer(small_config(tiny_dataset, tmp_path / "res", 20, KEY), resume=True)
    assert res.shading is not None and res.shading.key_stage == 2
    res.train()
    assert res.shading.light is not None and sh.light is not None
    assert torch.equal(res.shading.light.detach(), sh.light.detach())
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k


def test_a_short_run_aligns_at_its_last_iteration(tiny_dataset, tmp_path):  # noqa: F811
    cfg = small_config(tiny_dataset, tmp_path / "short", 6, [*KEY, "model.occlusion_key_iter=300"])
    t = Trainer(cfg)
    t.train()
    assert t.shading is not None and t.shading.key_aligned
