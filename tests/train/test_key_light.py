"""The key light (``shading.occlusion=key``): candidate lights collapse into one shadowed key light."""

from __future__ import annotations

import math
import shutil

import pytest
import torch

from _shading_kit import _sphere
from _train_kit import small_config
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar, compose, init_params
from meshsplat.gaussians.shading import KEY_CONE_DEG, KEY_RING, KEY_RINGS_DEG, KEY_STAGES, Shading, sh9_basis
from meshsplat.mesh import MeshPose, TriMesh
from meshsplat.run_folder import load_avatar
from meshsplat.train import Trainer, apply_overrides
from meshsplat.train.recipes import recipe_config

KEY = ["shading.occlusion=key", "shading.directions=8", "shading.grid=32", "shading.key_iter=4"]


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
    assert sh.visibility(pose, pose.verts[:5], torch.ones(5, 3) / 3**0.5).shape == (5, 1)
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
    cfg = apply_overrides(recipe_config("quality"), KEY).validate()
    assert (cfg.shading.occlusion, cfg.shading.key_iter) == ("key", 4)
    with pytest.raises(MeshsplatError, match=r"shading\.key_iter"):
        apply_overrides(recipe_config("quality"), ["shading.key_iter=0"]).validate()


def test_trainer_aligns_once_and_resumes_exactly_across_it(tiny_dataset, tmp_path):
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


def test_a_short_run_aligns_at_its_last_iteration(tiny_dataset, tmp_path):
    cfg = small_config(tiny_dataset, tmp_path / "short", 6, [*KEY, "shading.key_iter=300"])
    t = Trainer(cfg)
    t.train()
    assert t.shading is not None and t.shading.key_aligned


def test_training_frames_are_posed_once_and_render_as_their_vertices(tiny_dataset, tmp_path):
    """The trainer keeps each training frame's ``MeshPose`` (and with it the key's shadow maps): a frame renders
    bit for bit as the avatar does from its vertices, and the second time from the same pose and maps."""
    t = Trainer(small_config(tiny_dataset, tmp_path / "posed", 13, KEY))
    t.train()
    assert t.shading is not None and t.shading.key_aligned
    bg = torch.tensor([0.3, 0.5, 0.7])
    idx = t.train_ids[0]
    out, _ = t.render_frame(idx, bg)
    pose = t.frames._poses[idx]
    maps = pose._shadows
    again, _ = t.render_frame(idx, bg)
    assert t.frames._poses[idx] is pose and pose._shadows is maps and maps is not None
    _, _, camera, verts = t.frames.frame(idx)
    want = t.avatar().render(verts, camera, bg, backend=t.cfg.backend)
    for got in (out, again):
        assert torch.equal(got.image, want.image) and torch.equal(got.alpha, want.alpha)


def _posed(verts: torch.Tensor, faces: torch.Tensor) -> MeshPose:
    return MeshPose.from_vertices(TriMesh(verts, faces), verts)


def _plate_over_floor(height: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A 4 x 4 floor (y = 0) and a 1 x 1 plate at ``height`` above its centre: vertices ``[V,3]``, faces ``[F,3]``."""

    def grid(n: int, half: float, y: float) -> tuple[torch.Tensor, torch.Tensor]:
        t = torch.linspace(-half, half, n)
        x, z = torch.meshgrid(t, t, indexing="ij")
        v = torch.stack([x.reshape(-1), torch.full((n * n,), y), z.reshape(-1)], -1)
        i = torch.arange(n - 1)[:, None] * n + torch.arange(n - 1)[None]
        i = i.reshape(-1)
        f = torch.cat([torch.stack([i, i + 1, i + n], -1), torch.stack([i + 1, i + n + 1, i + n], -1)])
        return v, f

    vf, ff = grid(41, 2.0, 0.0)
    vp, fp = grid(11, 0.5, height)
    return torch.cat([vf, vp]), torch.cat([ff, fp + len(vf)])


def _soft_key(degrees: float) -> Shading:
    """An aligned key light straight from above, ``degrees`` its angular radius (0: a hard shadow)."""
    return Shading(
        occlusion="key",
        directions=16,
        key=torch.tensor([[0.0, 1.0, 0.0]]),
        key_stage=KEY_STAGES,
        light=torch.ones(1, 3),
        key_soft=degrees,
    )


def test_a_soft_key_averages_the_shadow_maps_of_its_disk():
    from meshsplat.gaussians.shading import KEY_SOFT_SAMPLES
    from meshsplat.mesh.visibility import visibility

    sh = _soft_key(8.0)
    dirs = sh.shadow_directions()
    assert dirs is not None and dirs.shape == (KEY_SOFT_SAMPLES, 3) and dirs.dtype == torch.float64
    cos = dirs @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(KEY_SOFT_SAMPLES, dtype=torch.float64))
    assert float(cos.min()) >= math.cos(math.radians(8.0)) - 1e-12 and float(cos.max()) < 1.0  # spread over the disk
    assert float(torch.nn.functional.normalize(dirs.sum(0), dim=0)[1]) > math.cos(math.radians(1.0))  # centred
    verts, faces = _plate_over_floor(1.0)
    pts = torch.stack([torch.linspace(0.0, 1.2, 121), torch.zeros(121), torch.full((121,), 0.05)], -1)
    up = torch.tensor([[0.0, 1.0, 0.0]]).expand(121, 3)
    v = sh.visibility(_posed(verts, faces), pts, up)
    assert v is not None and v.shape == (121, 1)
    want = visibility(verts.double(), faces, pts.double(), up.double(), dirs, sh.grid).mean(-1, keepdim=True)
    assert torch.equal(v, want.float())
    # a hard key: 0 or 1 only; the same key before alignment ignores key_soft (the candidates' own maps)
    hard = _soft_key(0.0).visibility(_posed(verts, faces), pts, up)
    assert hard is not None and set(hard.unique().tolist()) == {0.0, 1.0}
    early = Shading(occlusion="key", directions=16, key_soft=8.0)
    assert not early.soft_key and torch.equal(early.shadow_directions(), early.directions)


def test_the_soft_penumbra_widens_with_the_occluders_distance():
    """Under a plate, the floor is dark (umbra), far from it lit, and in between partly lit: a penumbra
    about twice height x tan(radius) wide, wider for a plate farther above (at a 64^2 grid's cells of
    0.09, the low plate's penumbra is a fraction of a cell narrower than that)."""
    pts = torch.stack([torch.linspace(0.0, 1.2, 241), torch.zeros(241), torch.full((241,), 0.05)], -1)
    up = torch.tensor([[0.0, 1.0, 0.0]]).expand(241, 3)
    widths = []
    for height in (0.5, 1.5):
        verts, faces = _plate_over_floor(height)
        v = _soft_key(8.0).visibility(_posed(verts, faces), pts, up)
        assert v is not None
        v = v[:, 0]
        assert float(v[0]) == 0.0 and float(v[-1]) == 1.0
        partial = (v > 0) & (v < 1)
        widths.append(float(partial.sum()) * 1.2 / 240)
        assert v[partial].unique().numel() >= 4  # graded, not one step
    assert widths[1] > 2.0 * widths[0] > 0, widths
    assert abs(widths[1] - 2 * 1.5 * math.tan(math.radians(8.0))) < 0.15, widths


def test_a_soft_key_round_trips_and_validates(tmp_path):
    from meshsplat.export import export_avatar, load_exported_avatar

    mesh = _sphere()
    p = init_params(mesh, 150, generator=torch.Generator().manual_seed(0))
    av = Avatar(mesh, p, shading=_soft_key(8.0))
    v = mesh.vertices * torch.tensor([1.2, 0.9, 1.0])
    back = Avatar.from_state_dict(av.state_dict())
    assert back.shading is not None and back.shading.key_soft == 8.0 and back.shading.soft_key
    assert torch.equal(av.compose(v).colors, back.compose(v).colors)
    assert av.shading is not None and av.shading.to("cpu").key_soft == 8.0
    export_avatar(av, tmp_path)
    loaded = load_exported_avatar(tmp_path)
    assert loaded.shading is not None and loaded.shading.key_soft == 8.0
    assert torch.allclose(av.compose(v).colors, loaded.compose(v).colors, atol=1e-5)
    old = av.state_dict()  # written before soft keys existed: a hard key
    del old["shading"]["occlusion"]["soft_deg"]
    assert Avatar.from_state_dict(old).shading.key_soft == 0.0  # type: ignore[union-attr]
    old["shading"]["occlusion"]["soft_deg"] = "wide"
    with pytest.raises(MeshsplatError, match="soft_deg"):
        Avatar.from_state_dict(old)
    for bad, match in ((50.0, "0..45"), (float("nan"), "0..45"), (-1.0, "0..45")):
        with pytest.raises(MeshsplatError, match=match):
            _soft_key(bad)
    with pytest.raises(MeshsplatError, match="needs occlusion='key'"):
        Shading(occlusion="directions", directions=8, key_soft=8.0)
    with pytest.raises(MeshsplatError, match=r"shading\.key_soft"):
        apply_overrides(recipe_config("quality"), ["shading.key_soft=90"]).validate()


def test_the_trainer_builds_a_soft_key_only_for_occlusion_key(tiny_dataset, tmp_path):
    t = Trainer(small_config(tiny_dataset, tmp_path / "soft", 12, [*KEY, "shading.key_soft=6"]))
    t.train()
    assert t.shading is not None and t.shading.soft_key and t.shading.key_soft == 6.0
    av = load_avatar(tmp_path / "soft")
    assert av.shading is not None and av.shading.key_soft == 6.0
    off = Trainer(small_config(tiny_dataset, tmp_path / "none", 2, ["shading.occlusion=none", "shading.key_soft=6"]))
    assert off.shading is not None and off.shading.occlusion == "none"
