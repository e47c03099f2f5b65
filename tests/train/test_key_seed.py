"""The key light's seeded search (``shading.key_seed``) and its checks (``shading.key_agree_deg``,
``shading.key_check_frames``): the search starts from the learned irradiance's own direction, and a key far from
that direction, or whose shadow does not lower the training error, is folded into the SH2 irradiance
(``Shading.drop_key``)."""

from __future__ import annotations

import math
import shutil
from types import SimpleNamespace

import pytest
import torch

from _train_kit import small_config
from meshsplat.errors import MeshsplatError
from meshsplat.export import export_avatar, load_exported_avatar
from meshsplat.gaussians.shading import (
    _CLAMPED_COS_BANDS,
    KEY_RING,
    KEY_RINGS_DEG,
    KEY_STAGES,
    Shading,
    irradiance_direction,
    sh9_basis,
)
from meshsplat.run_folder import load_avatar
from meshsplat.train import Trainer
from meshsplat.train.components.shading import ShadingComponent, ShadingConfig
from meshsplat.viewer import read_viewer_bundle, write_viewer_bundle

KEY = ["shading.occlusion=key", "shading.directions=8", "shading.grid=32", "shading.key_iter=4"]
SEEDED = [*KEY, "shading.key_seed=true", "shading.key_check_frames=3"]


def _lobe(d: torch.Tensor) -> torch.Tensor:
    """SH2 projection [9] of max(0, n . d)."""
    return sh9_basis(d[None])[0] * torch.tensor(_CLAMPED_COS_BANDS)


def _angle(a: torch.Tensor, b: torch.Tensor) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b) / float(a.norm() * b.norm())))))


def _random_directions(n: int, seed: int) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(seed)), dim=-1)


def test_irradiance_direction_finds_a_light_anywhere_on_the_sphere():
    """Ambient, a coloured directional light and a dimmer second one at 120 degrees: the fit points at the
    strong light, wherever it is."""
    for d in _random_directions(20, 1):
        other = torch.nn.functional.normalize(torch.linalg.cross(d, torch.tensor([0.3, 0.5, 0.8])), dim=0)
        other = math.cos(math.radians(120)) * d + math.sin(math.radians(120)) * other
        coeffs = torch.zeros(9, 3)
        coeffs[0] = 0.35 / 0.28209479177387814
        coeffs += _lobe(d)[:, None] * torch.tensor([0.9, 0.8, 0.6])
        coeffs += _lobe(other)[:, None] * 0.2
        assert _angle(irradiance_direction(coeffs), d) < 10.0  # the dim light pulls it a few degrees
        assert _angle(irradiance_direction(_lobe(d)[:, None].expand(9, 3)), d) < 0.5  # alone: exact


def test_key_seed_reads_the_light_spread_over_the_candidates():
    """Candidate lights that each took a share of one light (and SH2 that took some): the seed is the light's
    direction within 20 degrees, from any of 20 directions; the strongest candidate is up to tens of degrees off."""
    for d in _random_directions(20, 2):
        sh = Shading(occlusion="key", directions=16)
        assert sh.directions is not None and sh.light is not None
        with torch.no_grad():
            sh.light.copy_((sh.directions @ d).clamp_min(0.0)[:, None].pow(3) * 0.5)
            sh.coeffs += 0.3 * _lobe(d)[:, None]
        assert _angle(sh.key_seed(), d) < 20.0


def test_a_seeded_first_stage_keeps_the_unshadowed_irradiance():
    sh = Shading(occlusion="key", directions=16)
    assert sh.light is not None
    with torch.no_grad():
        sh.light.uniform_(0.0, 1.0, generator=torch.Generator().manual_seed(3))
    before = sh.unshadowed_coeffs()
    start = torch.nn.functional.normalize(torch.tensor([0.2, -0.4, -0.9]), dim=0)
    sh.align_key(start=start)
    assert sh.key_stage == 1 and sh.directions is not None and sh.directions.shape == (1 + KEY_RING, 3)
    assert torch.allclose(sh.directions[0], start, atol=1e-6)
    ring = sh.directions[1:] @ start
    assert torch.allclose(ring, torch.full((KEY_RING,), math.cos(math.radians(KEY_RINGS_DEG[0]))), atol=1e-5)
    assert torch.allclose(sh.unshadowed_coeffs(), before, atol=1e-5)  # only the shadows moved
    with pytest.raises(MeshsplatError, match="first stage"):
        sh.align_key(start=start)


def test_drop_key_folds_the_key_into_sh2_and_round_trips(tmp_path):
    sh = Shading(occlusion="key", directions=16, key_soft=8.0)
    assert sh.light is not None
    with torch.no_grad():
        sh.light[3] = 0.7
    for _ in range(KEY_STAGES):
        sh.align_key()
    assert sh.key_aligned and sh.directions is not None
    key, before = sh.directions[0].clone(), sh.unshadowed_coeffs()
    sh.drop_key()
    assert sh.occlusion == "none" and sh.directions is None and sh.light is None and sh.key_soft == 0.0
    assert sh.dropped_key is not None and torch.allclose(sh.dropped_key, key)
    assert torch.allclose(sh.coeffs, before)
    assert sh.visibility(None, torch.zeros(1, 3), torch.zeros(1, 3)) is None  # type: ignore[arg-type]
    for state in (sh.state_dict(), sh.json_state()):
        back = Shading.from_state_dict(state)
        assert back is not None and back.occlusion == "none" and back.light is None
        assert back.dropped_key is not None and torch.allclose(back.dropped_key, key)
        assert torch.equal(back.coeffs, sh.coeffs)
    assert "key dropped" in repr(sh)
    with pytest.raises(MeshsplatError, match="drop_key"):
        sh.drop_key()
    with pytest.raises(MeshsplatError, match="dropped_key"):
        Shading.from_state_dict({**sh.state_dict(), "dropped_key": {"direction": [1.0, 2.0]}})


class _StubState(SimpleNamespace):
    """What the shading component reads of the trainer, with a training error that is lower with a key light
    (``key_helps``) or higher."""

    def training_error(self, idx: int) -> torch.Tensor:
        sh = self.component.shading
        keyed = sh.occlusion == "key"
        return torch.tensor(0.1 + (0.0 if keyed == self.key_helps else 0.01) + 1e-4 * idx)


def _key_component(iterations: int = 100, **cfg) -> tuple[ShadingComponent, torch.Tensor]:
    """A started shading component with a key light (stages of 2 iterations) over a stub trainer, its third
    candidate light lit (0.5): the component and that candidate's direction ``[3]``."""
    state = _StubState(
        device=torch.device("cpu"), lr_factor=1.0, eps=1e-15, iterations=iterations, train_ids=list(range(10))
    )
    comp = ShadingComponent(ShadingConfig(enabled=True, occlusion="key", key_iter=2, **cfg), state)
    state.component = comp
    comp.start()
    assert comp.shading is not None and comp.shading.light is not None and comp.shading.directions is not None
    with torch.no_grad():
        comp.shading.light[2] = 0.5
    return comp, comp.shading.directions[2].clone()


@pytest.mark.parametrize("key_helps", [True, False])
def test_the_check_keeps_a_key_that_lowers_the_error_and_drops_one_that_does_not(key_helps):
    comp, _ = _key_component(key_seed=True, key_check_frames=3)
    comp.state.key_helps = key_helps
    assert comp._check_frames() == [1, 5, 8]
    for it in range(1, 7):
        comp.after_step(it, [])
    sh = comp.shading
    assert comp.key_log["kept"] is key_helps and set(comp.key_log["check_errors"]) == {"key", "off"}
    assert set(comp.key_log) >= {"seed", "strongest"}  # the start, and the one without key_seed
    if key_helps:
        assert sh.key_aligned and sh.occlusion == "key"
    else:
        assert sh.occlusion == "none" and sh.dropped_key is not None
        assert comp.optimizer is not None and len(comp.optimizer.param_groups[0]["params"]) == 1
        comp.after_step(7, [])  # nothing more to align


@pytest.mark.parametrize("agrees", [True, False])
def test_a_key_far_from_the_learned_irradiance_is_dropped(agrees):
    """``key_agree_deg``: the aligned key stays when the learned irradiance points its way, and is folded into
    the SH2 irradiance when the irradiance points elsewhere (its shadows fit frames from a light not there)."""
    comp, d = _key_component(key_agree_deg=20.0)
    if not agrees:  # most of the learned light comes from the other side
        with torch.no_grad():
            comp.shading.coeffs += 1.5 * _lobe(-d)[:, None]
    for it in range(1, 7):
        comp.after_step(it, [])
    sh = comp.shading
    test = comp.key_log["agree_aligned"]
    assert test["agrees"] is agrees and "check_errors" not in comp.key_log and "agree_end" not in comp.key_log
    if agrees:
        assert sh.key_aligned and sh.occlusion == "key" and test["angle_deg"] <= 20.0
        assert sh.directions is not None and _angle(sh.directions[0], d) < 20.0
    else:
        assert test["angle_deg"] > 90.0 and sh.occlusion == "none" and sh.dropped_key is not None
        assert _angle(sh.dropped_key, d) < 20.0
        assert comp.optimizer is not None and len(comp.optimizer.param_groups[0]["params"]) == 1


def test_the_key_is_tested_again_at_the_end():
    """A key that agreed with the irradiance when aligned is dropped at the last iteration if the irradiance
    learned since points elsewhere; before the last iteration nothing is tested."""
    comp, d = _key_component(iterations=20, key_agree_deg=20.0)
    for it in range(1, 7):
        comp.after_step(it, [])
    assert comp.key_log["agree_aligned"]["agrees"] and comp.shading.occlusion == "key"
    with torch.no_grad():  # the irradiance learned after the alignment: most light from the other side
        comp.shading.coeffs += 1.5 * _lobe(-d)[:, None]
    for it in range(7, 20):
        comp.after_step(it, [])
    assert comp.shading.occlusion == "key" and "agree_end" not in comp.key_log
    comp.after_step(20, [])
    sh = comp.shading
    assert comp.key_log["agree_end"]["agrees"] is False and sh.occlusion == "none" and sh.dropped_key is not None
    assert comp.optimizer is not None and len(comp.optimizer.param_groups[0]["params"]) == 1


def _turned(d: torch.Tensor, degrees: float) -> torch.Tensor:
    """``d [3]`` turned by ``degrees`` about an axis perpendicular to it."""
    side = torch.nn.functional.normalize(torch.linalg.cross(d, torch.tensor([0.3, 0.5, 0.8])), dim=0)
    return math.cos(math.radians(degrees)) * d + math.sin(math.radians(degrees)) * side


def test_move_key_moves_the_shadow_and_keeps_the_unshadowed_irradiance():
    """``Shading.move_key``: the key's direction changes, its intensity does not, and every normal unshadowed
    is lit as before; only where the key is shadowed does the light change. Only an aligned key moves."""
    sh = Shading(normal="phong", occlusion="key", directions=8, grid=16)
    with pytest.raises(MeshsplatError, match="aligned"):
        sh.move_key(torch.tensor([0.0, 1.0, 0.0]))
    with torch.no_grad():
        sh.light[3] = torch.tensor([0.6, 0.5, 0.4])
        sh.coeffs[0] += 0.3
    while not sh.key_aligned:
        sh.align_key()
    old_dir, light, unshadowed = sh.directions[0].clone(), sh.light.clone(), sh.unshadowed_coeffs()
    normals = _random_directions(200, 4)
    lit_before = sh.irradiance(normals, torch.ones(200, 1))
    shadowed_before = sh.irradiance(normals, torch.zeros(200, 1))
    target = _turned(old_dir, 25.0)
    sh.move_key(3.0 * target)  # any length: the direction is what counts
    assert _angle(sh.directions[0], target) < 1e-4 and sh.directions.shape == (1, 3)
    assert torch.equal(sh.light, light.clamp_min(0.0))
    assert torch.allclose(sh.unshadowed_coeffs(), unshadowed, atol=1e-6)
    # lit: the same but for the clamped cosine's part above SH2 (a few % of the key), which the SH2 fold cannot
    # hold; in shadow: the lobe the SH2 irradiance now lacks is another one
    lit_change = (sh.irradiance(normals, torch.ones(200, 1)) - lit_before).abs().max()
    shadow_change = (sh.irradiance(normals, torch.zeros(200, 1)) - shadowed_before).abs().max()
    assert lit_change < 0.15 * light.max() and shadow_change > 2 * lit_change
    for bad in (torch.zeros(3), torch.tensor([float("nan"), 0.0, 1.0]), torch.ones(2)):
        with pytest.raises(MeshsplatError, match="direction"):
            sh.move_key(bad)


@pytest.mark.parametrize("snap", [0.0, 10.0, 30.0])
def test_a_key_that_half_agrees_with_the_irradiance_moves_to_it(snap):
    """``key_snap_deg``: an aligned key 10-30 degrees from the learned irradiance's direction (within
    ``key_agree_deg``) moves to that direction when farther than ``key_snap_deg``, and stays where the search
    put it otherwise (0: off, or 30: closer than that); the moved key is the optimizer's new leaf."""
    comp, d = _key_component(key_agree_deg=45.0, key_snap_deg=snap)
    with torch.no_grad():  # the irradiance pulled away from the key's side
        comp.shading.coeffs += 1.0 * _lobe(_turned(d, 40.0))[:, None]
    for it in range(1, 7):
        comp.after_step(it, [])
    sh = comp.shading
    test = comp.key_log["agree_aligned"]
    assert sh.key_aligned and sh.occlusion == "key" and sh.directions is not None
    assert 10.0 < test["angle_deg"] < 30.0
    if snap and test["angle_deg"] > snap:
        assert test["fate"] == "moved" and _angle(torch.tensor(test["from"]), d) < 20.0
        assert _angle(sh.directions[0], sh.key_seed()) < 1.0  # now where the irradiance points
        assert comp.optimizer is not None and comp.optimizer.param_groups[0]["params"][1] is sh.light
    else:
        assert test["fate"] == "kept" and "from" not in test
        assert _angle(sh.directions[0], sh.key_seed()) > 10.0


def test_without_key_agree_deg_a_far_key_moves_instead_of_being_dropped():
    """``key_snap_deg`` alone (``key_agree_deg`` 0): the test still runs, and a key on the far side of the learned
    irradiance moves to it; nothing is dropped."""
    comp, d = _key_component(key_snap_deg=15.0)
    with torch.no_grad():
        comp.shading.coeffs += 1.5 * _lobe(-d)[:, None]
    for it in range(1, 7):
        comp.after_step(it, [])
    sh, test = comp.shading, comp.key_log["agree_aligned"]
    assert test["angle_deg"] > 90.0 and test["agrees"] and test["fate"] == "moved"
    assert sh.occlusion == "key" and sh.directions is not None and _angle(sh.directions[0], sh.key_seed()) < 1.0


def test_the_key_moves_at_the_end_when_the_irradiance_moved_since():
    """``key_snap_deg`` at the last iteration: a key that was kept when aligned moves to the irradiance's
    direction if the irradiance learned since turned 10-30 degrees away, and the optimizer holds the new key."""
    comp, d = _key_component(iterations=20, key_agree_deg=45.0, key_snap_deg=10.0)
    for it in range(1, 7):
        comp.after_step(it, [])
    assert comp.key_log["agree_aligned"]["fate"] == "kept"
    key = comp.shading.directions[0].clone()
    with torch.no_grad():
        comp.shading.coeffs += 1.0 * _lobe(_turned(d, 40.0))[:, None]
    for it in range(7, 21):
        comp.after_step(it, [])
    sh, test = comp.shading, comp.key_log["agree_end"]
    assert test["fate"] == "moved" and 10.0 < test["angle_deg"] < 30.0 and sh.directions is not None
    assert _angle(torch.tensor(test["from"]), key) < 1e-3 and _angle(sh.directions[0], sh.key_seed()) < 1.0
    assert comp.optimizer is not None and comp.optimizer.param_groups[0]["params"][1] is sh.light


def test_key_agree_deg_is_checked():
    assert any("key_agree_deg" in msg for ok, msg in ShadingConfig(key_agree_deg=200.0).checks() if not ok)
    assert any("key_snap_deg" in msg for ok, msg in ShadingConfig(key_snap_deg=-1.0).checks() if not ok)


def test_without_directional_light_the_key_is_dropped_and_the_run_resumes_exactly(tiny_dataset, tmp_path):
    """The tiny capture is unshaded (no directional light): the check folds the key away at the last stage;
    the run resumes bit for bit across the alignments, and the avatar, its export and the player's header
    read the folded lighting."""
    full = Trainer(small_config(tiny_dataset, tmp_path / "full", 20, SEEDED))
    full.train()
    comp = full.component("shading")
    assert isinstance(comp, ShadingComponent)
    sh = full.shading
    assert sh is not None and sh.occlusion == "none" and sh.dropped_key is not None
    assert comp.key_log["kept"] is False and "seed" in comp.key_log
    av = load_avatar(tmp_path / "full")
    assert av.shading is not None and av.shading.occlusion == "none"
    assert torch.equal(av.shading.coeffs, sh.coeffs.detach())
    assert av.shading.dropped_key is not None and torch.allclose(av.shading.dropped_key, sh.dropped_key)
    export_avatar(av, tmp_path / "export")
    back = load_exported_avatar(tmp_path / "export")
    assert back.shading is not None and back.shading.occlusion == "none" and back.shading.dropped_key is not None
    verts = av.mesh.vertices * torch.tensor([1.1, 0.95, 1.0])
    assert torch.allclose(av.compose(verts).colors, back.compose(verts).colors, atol=1e-5)
    write_viewer_bundle(av, [av.mesh.vertices, verts], tmp_path / "page")
    header = read_viewer_bundle(tmp_path / "page")[0]["shading"]
    assert "key" not in header  # the player shades the folded irradiance alone
    assert torch.allclose(torch.tensor(header["coeffs"], dtype=torch.float64), sh.coeffs.detach().double())
    # resumed from the checkpoint written in the middle of the search: bit-identical, the same decision
    (tmp_path / "res" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000010.pt", tmp_path / "res" / "checkpoints")
    res = Trainer(small_config(tiny_dataset, tmp_path / "res", 20, SEEDED), resume=True)
    assert res.shading is not None and res.shading.key_stage == 2
    res.train()
    assert res.shading.occlusion == "none" and torch.equal(res.shading.coeffs.detach(), sh.coeffs.detach())
    for k in full.params:
        assert torch.equal(full.params[k].detach(), res.params[k].detach()), k
    # resumed after the drop: the checkpoint's folded lighting is accepted under occlusion=key
    (tmp_path / "res2" / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "full" / "checkpoints" / "ckpt_00000020.pt", tmp_path / "res2" / "checkpoints")
    again = Trainer(small_config(tiny_dataset, tmp_path / "res2", 20, SEEDED), resume=True)
    assert again.shading is not None and again.shading.occlusion == "none"
    again_comp = again.component("shading")
    assert isinstance(again_comp, ShadingComponent) and again_comp.key_log["kept"] is False
