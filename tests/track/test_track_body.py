"""`meshsplat track --subject body` on generated clips of the Anny body (MediaPipe Pose on rendered frames,
no network): the compact body model, the fit recovering known poses, the capture, and the clips it
refuses or trims (no person, too short, scene cut, two people, partly out of frame)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from _body_video import clip_pose, render_clip, write_body_clip
from _train_kit import tiny_train_argv
from meshsplat.animation.source import AnimationSource, load_animation
from meshsplat.cli.main import main
from meshsplat.data import open_dataset
from meshsplat.drivers.anny_body import JOINTS, KEYPOINTS, load_anny_body
from meshsplat.drivers.body_models import model_from_record
from meshsplat.errors import MeshsplatError
from meshsplat.io.video import write_mp4
from meshsplat.mesh import TriMesh
from meshsplat.track.clip import TrackSettings
from meshsplat.track.head_region import mesh_silhouette

pytest.importorskip("mediapipe")
pytest.importorskip("anny")
from meshsplat.track.body_capture import _tracked_person, track_body
from meshsplat.track.body_fit import fit_body
from meshsplat.track.body_track import track_bodies
from meshsplat.track.mediapipe_models import PersonSegmenter, PoseLandmarker

FRAMES = 20
_LIMBS = ("elbow", "wrist", "knee", "ankle")


@pytest.fixture(scope="module")
def body():
    return load_anny_body()


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return write_body_clip(tmp_path_factory.mktemp("clip") / "body.mp4", frames=FRAMES)


@pytest.fixture(scope="module")
def capture(clip, tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "capture"
    res = track_body(clip.path, out, TrackSettings(size=96), iterations=150)
    return out, res


def _rel_joints(body, pose, transl, betas=None):
    _, J = body.pose(pose, betas, transl, torch.zeros(0, dtype=torch.long))
    return J - J[:, :1]


def test_compact_body_is_smpl_shaped(body):
    assert body.num_joints == 24 and body.template.shape == (13718, 3) and len(KEYPOINTS) == 23
    torch.testing.assert_close(body.weights.sum(1), torch.ones(body.num_vertices))
    # the zero pose is SMPL's T-pose: wrists at shoulder height, out along +-x (x: the subject's left)
    _, J = body.pose(torch.zeros(1, 24, 3))
    for side, sign in (("left", 1), ("right", -1)):
        sh, wr = J[0, JOINTS.index(f"{side}_shoulder")], J[0, JOINTS.index(f"{side}_wrist")]
        assert abs(float(wr[1] - sh[1])) < 0.03 and sign * float(wr[0] - sh[0]) > 0.4
    head, ankle = J[0, JOINTS.index("head")], J[0, JOINTS.index("left_ankle")]
    assert 1.2 < float(head[1] - ankle[1]) < 1.6  # metres, +y up
    # the keypoints from bone transforms equal the blend of skinned vertices
    pose, transl, betas = torch.randn(2, 24, 3) * 0.3, torch.randn(2, 3), torch.randn(6) * 0.2
    kp, _ = body.keypoints(pose, betas, transl)
    v, _ = body.pose(pose, betas, transl, body.keypoint_vertices)
    torch.testing.assert_close(kp, torch.einsum("ku,tuc->tkc", body.keypoint_blend, v), atol=1e-5, rtol=0)
    # the manifest's record gives it, with SMPL's parameter names; bad parameters in one line
    model = model_from_record({"type": "anny"})
    out = model.forward({"global_orient": np.zeros((3, 3)), "body_pose": np.zeros((3, 69)), "transl": np.zeros((3, 3))})
    assert out.vertices.shape == (3, 13718, 3)
    with pytest.raises(MeshsplatError, match="Anny parameters: unknown key 'jaw_pose'") as exc:
        model.forward({"global_orient": np.zeros(3), "jaw_pose": np.zeros(3)})
    assert "\n" not in str(exc.value)


def test_fit_recovers_known_poses_without_swapping_limbs(capture, clip, body):
    """Joint positions about the pelvis within 10 cm on average (20 cm for any joint's mean over the
    clip: wrists and hands are the worst, their depth is what one camera sees least), the body's turn within 0.25 rad, keypoints within 2 px; each fitted left limb joint nearer
    the true left one than the true right one, in every frame."""
    out, res = capture
    fit = np.load(out / "body_fit.npz")
    assert fit["global_orient"].shape == (FRAMES, 3) and fit["body_pose"].shape == (FRAMES, 69)
    assert res.error_px < 2.0, res.error_px  # pixels of the 192x256 video
    pose = torch.from_numpy(np.concatenate([fit["global_orient"], fit["body_pose"]], 1)).reshape(FRAMES, 24, 3)
    got = _rel_joints(body, pose, torch.from_numpy(fit["transl"]), torch.from_numpy(fit["betas"]))
    true = _rel_joints(body, clip.pose, clip.transl)
    err = (got - true).norm(dim=-1)  # [T,24] metres
    assert float(err.mean()) < 0.10, float(err.mean())
    assert float(err.mean(0).max()) < 0.20, err.mean(0)

    # the body's turn about the vertical, from its hips and shoulders: within 0.25 rad (14 degrees)
    def turn(J):
        d = sum(J[:, JOINTS.index(f"left_{p}")] - J[:, JOINTS.index(f"right_{p}")] for p in ("hip", "shoulder"))
        return torch.atan2(-d[:, 2], d[:, 0])

    assert float((turn(got) - turn(true)).abs().max()) < 0.25, (turn(got), turn(true))
    for part in _LIMBS:
        left, right = JOINTS.index(f"left_{part}"), JOINTS.index(f"right_{part}")
        to_left = (got[:, left] - true[:, left]).norm(dim=-1)
        to_right = (got[:, left] - true[:, right]).norm(dim=-1)
        assert bool((to_left < to_right).all()), (part, to_left, to_right)


def test_capture_trains_with_refined_anny_poses(capture):
    out, res = capture
    ds = open_dataset(out)
    assert len(ds) == FRAMES == res.frames and not res.dropped
    assert len(ds.split("train")) == 16 and len(ds.split("test_frames")) == 4
    assert ds.driver_info["type"] == "anny" and set(ds.per_frame_param_names) == {
        "global_orient",
        "body_pose",
        "transl",
    }
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["meta"]["subject"] == "body" and "CC0" in manifest["meta"]["attribution"]
    # the stored meshes are the model's, so pose refinement starts where the tracker ended
    fr = ds[7]
    v = ds.body_model(None).forward(ds.frame_params(7)).vertices[0]
    torch.testing.assert_close(v, fr.vertices.float(), atol=1e-4, rtol=0)
    # the mask is the body: it and the posed mesh's silhouette overlap
    cam = fr.camera
    x = fr.vertices.float() @ cam.viewmat[:3, :3].T.float() + cam.viewmat[:3, 3].float()
    px = (x @ cam.K.T.float())[:, :2] / x[:, 2:]
    sil = mesh_silhouette(px.numpy(), 96, radius=1.0) > 0.5
    mask = fr.mask[..., 0].numpy() > 0.5
    assert (sil & mask).sum() / (sil | mask).sum() > 0.65  # limbs are 3-4 px wide at 96 px
    assert fr.mask[:, :4].mean() < 0.05  # the background is not
    assert any("beyond the body model" in n for n in res.notes)


def test_frames_without_a_person_are_named(clip):
    frames = [f if i not in (3, 4) else np.full_like(f, 150) for i, f in enumerate(clip.frames[:12])]
    with PoseLandmarker() as pl:
        tr = track_bodies(frames, pl, names=lambda i: f"{i / 10:.2f}s")
    assert tr.found.tolist() == [i not in (3, 4) for i in range(12)]
    assert tr.usable.sum() == 10


def test_no_person_and_too_short_refused_in_one_line(clip, tmp_path):
    blank = write_mp4([np.full_like(clip.frames[0], 90)] * 12, tmp_path / "empty.mp4", fps=10)
    with pytest.raises(MeshsplatError, match="no person found in any of the 12 frames") as exc:
        track_body(blank, tmp_path / "cap", TrackSettings(size=64))
    assert "\n" not in str(exc.value) and not (tmp_path / "cap" / "manifest.json").exists()
    short = write_mp4(clip.frames[:6], tmp_path / "short.mp4", fps=10)
    with pytest.raises(MeshsplatError, match="torso in view in only 6 of 6 frames") as exc:
        track_body(short, tmp_path / "cap2", TrackSettings(size=64))
    assert "\n" not in str(exc.value)


def test_scene_cut_refused(clip):
    h, w = clip.height, clip.width
    # the second shot shows the person elsewhere and half as large: a cut, not motion
    small = [np.asarray(Image.fromarray(f).resize((w // 2, h // 2))) for f in clip.frames[:5]]
    shot2 = [np.pad(s, ((0, h - h // 2), (w - w // 2, 0), (0, 0)), constant_values=158) for s in small]
    with PoseLandmarker() as pl, pytest.raises(MeshsplatError, match="scene cut") as exc:
        track_bodies(clip.frames[:5] + shot2, pl)
    assert "\n" not in str(exc.value)


def test_two_people_follow_one_and_mask_only_them(clip, body):
    # a second, smaller person beside the first: MediaPipe Pose follows one; the matte keeps that one only
    pose, transl = clip_pose(4)
    transl[:, 0] += 0.7
    transl[:, 2] -= 0.8
    other, _ = render_clip(body, pose, transl, clip.width, clip.height)
    both = [np.concatenate([a, b], 1) for a, b in zip(clip.frames[:4], other, strict=True)]
    with PoseLandmarker() as pl:
        tr = track_bodies(both, pl)
    assert tr.usable.all()
    with PersonSegmenter() as seg:
        matte = seg(both[0])
    kept, flagged = _tracked_person(matte, tr.landmarks[0], 2 * clip.width, clip.height)
    cx = float(np.nanmean(tr.landmarks[0, [11, 12, 23, 24], 0]))
    tracked_left = cx < clip.width
    assert flagged
    half = kept[:, clip.width :] if tracked_left else kept[:, : clip.width]
    assert float(half.sum()) < 0.02 * float(kept.sum())


def test_partly_out_of_frame(clip, body):
    """Legs below the frame: their keypoints do not count (MediaPipe guesses them), the rest fits."""
    cut = int(clip.height * 0.6)
    frames = [f[:cut] for f in clip.frames[:10]]
    with PoseLandmarker() as pl:
        tr = track_bodies(frames, pl)
    assert tr.usable.all()
    fit = fit_body(tr.landmarks, tr.world, clip.width, cut, focal=float(clip.K[0, 0]), iterations=80, body=body)
    assert float(fit.error_px.mean()) < 3.0
    # the torso stays where it was: shoulders about the pelvis within 8 cm of the truth
    got = _rel_joints(body, fit.pose, fit.transl, fit.betas)
    true = _rel_joints(body, clip.pose[:10], clip.transl[:10])
    sh = [JOINTS.index("left_shoulder"), JOINTS.index("right_shoulder")]
    assert float((got[:, sh] - true[:, sh]).norm(dim=-1).mean()) < 0.08
    # a torso out of view: those frames are not usable
    heads = [f[: int(clip.height * 0.2)] for f in clip.frames[:3]]
    with PoseLandmarker() as pl:
        tr2 = track_bodies(heads, pl)
    assert not tr2.usable.any()


def test_cli_body_one_line_errors(tmp_path, capsys):
    assert main(["track", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "c"), "--subject", "body"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "video not found" in err[0]


@pytest.mark.slow
def test_trains_evaluates_and_dances(capture, tmp_path):
    """The tracked capture trains (pose refinement on, as for SMPL captures), evaluates, and the AIST++
    dance plays on it upright without flags."""
    out, _ = capture
    run = tmp_path / "run"
    assert main(["train", str(out), "--out", str(run), *tiny_train_argv()]) == 0
    assert main(["eval", str(run), "--no-report", "--no-lpips", "--no-progress"]) == 0
    m = json.loads((run / "eval" / "metrics.json").read_text())["splits"]["test_frames"]
    assert m["psnr_mask"] is not None and m["psnr_mask"] > 10
    frames_out = tmp_path / "dance"
    argv = ["render", str(run), "--animation", "motion", "aist_demo", "--frames", "3", "--size", "64x64"]
    assert main([*argv, "--no-mp4", "--no-progress", "--out", str(frames_out)]) == 0
    assert len(list((frames_out / "frames").glob("*.png"))) == 3


def test_aist_dance_retargeted_upright_facing_the_camera(capture, body):
    """The bundled AIST++ SMPL dance on the tracked body through `--animation motion`'s loader: every
    frame upright (head above the feet), facing the camera (+z), the arms moving."""
    out, _ = capture
    ds = open_dataset(out)
    mesh = TriMesh(ds.canonical_vertices, ds.faces)
    anim = load_animation(AnimationSource("motion", "aist_demo", frames=60), mesh, dataset=ds)
    verts = torch.stack(anim.frames)  # [S,V,3]
    part = body.weights.argmax(1)
    head = verts[:, part == JOINTS.index("head")].mean(1)
    feet = verts[:, torch.isin(part, torch.tensor([JOINTS.index("left_foot"), JOINTS.index("right_foot")]))].mean(1)
    assert bool((head[:, 1] - feet[:, 1] > 1.2).all())  # metres

    # facing the camera (+z): the turn from the hips and shoulders, as the tracked person's first frame
    # (facing the camera) at the start, never turned away
    def centre(j):
        return verts[:, part == JOINTS.index(j)].mean(1)

    d = centre("left_hip") - centre("right_hip") + centre("left_shoulder") - centre("right_shoulder")
    yaw = torch.atan2(-d[:, 2], d[:, 0])
    assert abs(float(yaw[0])) < 0.3 and bool((yaw.abs() < 1.2).all()), yaw
    wrist = verts[:, part == JOINTS.index("left_wrist")].mean(1)
    assert float((wrist - wrist[:1]).norm(dim=-1).max()) > 0.2  # the dance moves the arms
