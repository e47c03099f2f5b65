"""Path-traced ground truth (``--renderer pbr``, Mitsuba 3) and imperfect tracking (``pose_noise``).

Golden: the path tracer and the Lambert rasterizer see the same silhouette through the same camera
(a mirrored or shifted image would fail), the same seed renders the same image, and the settings are
in the manifest. Pose noise: the images show the exact pose, the stored meshes and parameters the
perturbed one, and the parameters still reproduce the stored meshes.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from meshsplat.cli.main import main as cli_main
from meshsplat.data import open_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.synth.generate import synthesize
from meshsplat.synth.pbr import PbrSettings, load_mitsuba

ONE = dict(rig="monocular-turn", frames=1, test_frames=0, test_views=0, test_clips=[], overwrite=True)


def _iou(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a > 0.5, b > 0.5
    return float((a & b).sum() / (a | b).sum())


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    pytest.importorskip("mitsuba")
    root = tmp_path_factory.mktemp("pbr")
    lam = open_dataset(synthesize("CesiumMan", root / "lambert", resolution=64, supersample=4, **ONE))
    pbr = open_dataset(
        synthesize("CesiumMan", root / "pbr", resolution=64, renderer="pbr", pbr=PbrSettings(spp=64), **ONE)
    )
    return lam, pbr


def test_pbr_and_lambert_agree_on_the_silhouette(pair):
    lam, pbr = pair
    assert len(lam) == len(pbr) == 1
    assert lam.split("train") == pbr.split("train")
    a, b = lam[0], pbr[0]
    assert torch.equal(a.camera.viewmat, b.camera.viewmat) and torch.equal(a.camera.K, b.camera.K)
    assert torch.equal(a.vertices, b.vertices)
    ma, mb = a.mask, b.mask
    # coverage at every pixel: 4x4 supersampling vs 64 random samples (a few % noise on edge pixels only)
    assert float((ma - mb).abs().mean()) < 0.006
    assert _iou(ma, mb) > 0.93
    assert abs(float(ma.mean()) - float(mb.mean())) < 0.003
    # the same check fails for a mirrored or one-pixel-shifted silhouette (a camera convention slip)
    assert _iou(ma, mb.flip(1)) < 0.85
    assert float((ma - torch.roll(mb, 1, dims=1)).abs().mean()) > 2 * float((ma - mb).abs().mean())
    # the background stays the background, the subject is lit, and the texture is where the rasterizer puts it
    assert float(b.image[mb[..., 0] < 0.01].max()) < 0.02
    inside = (ma[..., 0] > 0.99) & (mb[..., 0] > 0.99)
    x, y = a.image[inside].flatten(), b.image[inside].flatten()
    assert float(torch.corrcoef(torch.stack([x, y]))[0, 1]) > 0.6


def test_pbr_manifest_records_how_it_was_made(pair):
    _, pbr = pair
    r = pbr.meta["renderer"]
    assert r["name"] == "pbr" and r["engine"] == "mitsuba3" and r["spp"] == 64 and r["seed"] == 0
    assert 0.3 <= r["roughness"] <= 0.6
    assert pbr.meta["seconds_per_frame"] > 0


def test_pbr_is_deterministic_for_a_seed():
    pytest.importorskip("mitsuba")
    from meshsplat.synth.generate import _LIGHT
    from meshsplat.synth.pbr import PbrRenderer
    from meshsplat.synth.sources import load_source

    src = load_source("RiggedSimple")
    v = src.pose(src.clips[0], 0.3)
    lo, hi = v.min(0).values.numpy(), v.max(0).values.numpy()
    center = (lo + hi) / 2
    size = float(np.linalg.norm(hi - lo))
    from meshsplat.camera import intrinsics, look_at

    view = look_at(center + np.array([0.0, 0.2, 1.0]) * 2.5 * size, center)
    K = intrinsics(32, 32, 40.0)
    r = PbrRenderer(src, None, center, size, _LIGHT, PbrSettings(spp=4, seed=7))
    a = r.render(v, view, K, 32, 32, frame=3)
    b = r.render(v, view, K, 32, 32, frame=3)
    c = r.render(v, view, K, 32, 32, frame=4)
    assert float(a[1].mean()) > 0.05
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0], c[0])


def test_pbr_errors(monkeypatch, tmp_path):
    with pytest.raises(MeshsplatError, match="spp"):
        PbrSettings(spp=0).check()
    with pytest.raises(MeshsplatError, match="roughness"):
        PbrSettings(roughness=0.0).check()
    with pytest.raises(MeshsplatError, match="renderer"):
        synthesize("RiggedSimple", tmp_path / "x", renderer="raytrace", resolution=16, **{**ONE, "overwrite": False})
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # as if the extra were not installed
    with pytest.raises(MeshsplatError, match=r"meshsplat\[pbr\]"):
        load_mitsuba()


def test_cli_refuses_supersample_with_pbr(tmp_path, capsys):
    rc = cli_main(["synth", "RiggedSimple", "--out", str(tmp_path / "d"), "--renderer", "pbr", "--supersample", "2"])
    assert rc == 2
    assert "--spp" in capsys.readouterr().err


# ---------------------------------------------------------------- imperfect tracking
def test_pose_noise_moves_the_tracked_mesh_not_the_images(tmp_path, standin_model_dir):
    from _synth_kit import _params_reproduce_meshes

    kw = dict(model_dir=standin_model_dir, frames=3, resolution=32, test_frames=1, test_views=0)
    clean = open_dataset(synthesize("smpl", tmp_path / "clean", **kw))
    noisy = open_dataset(synthesize("smpl", tmp_path / "noisy", pose_noise=0.05, seed=1, **kw))
    again = open_dataset(synthesize("smpl", tmp_path / "again", pose_noise=0.05, seed=1, **kw))
    assert noisy.meta["pose_noise"] == 0.05
    _params_reproduce_meshes(noisy, standin_model_dir)
    for i in range(len(clean)):
        assert torch.equal(clean[i].image, noisy[i].image)  # the camera sees the true pose
        d = (clean.vertices(i) - noisy.vertices(i)).norm(dim=1)
        assert 0.005 < float(d.mean()) < 0.15  # metres: a tracker's error, not a different pose
        assert torch.equal(noisy.vertices(i), again.vertices(i))  # seeded
    g0 = clean.frame_params(0)["body_pose"]
    g1 = noisy.frame_params(0)["body_pose"]
    assert 0.02 < float(np.abs(g1 - g0).mean()) < 0.1


def test_pose_noise_needs_a_body_model(tmp_path):
    with pytest.raises(MeshsplatError, match="body/head models"):
        synthesize("RiggedSimple", tmp_path / "x", pose_noise=0.1, resolution=16, **ONE)
