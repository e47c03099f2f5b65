"""`meshsplat track` end to end on a generated head video (MediaPipe on rendered frames, no network):
video -> landmarks -> fitted ICT head -> capture -> train (tiny) -> eval; and the clips it refuses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from _head_video import write_head_clip
from _train_kit import tiny_train_argv
from meshsplat.cli.main import main
from meshsplat.data import open_dataset
from meshsplat.drivers.blendshape import read_weights
from meshsplat.errors import MeshsplatError
from meshsplat.io.video import read_video_frames, write_mp4
from meshsplat.track.clip import TrackSettings
from meshsplat.track.face_track import track_faces
from meshsplat.track.head_capture import track_head
from meshsplat.viewer.webcam import LANDMARKER_FILES

pytest.importorskip("mediapipe")
from meshsplat.track.mediapipe_models import FaceMesh

FRAMES = 20


@pytest.fixture(scope="module")
def head_clip(tmp_path_factory):
    return write_head_clip(tmp_path_factory.mktemp("clip") / "head.mp4", frames=FRAMES, size=192)


@pytest.fixture(scope="module")
def frames(head_clip):
    return list(read_video_frames(head_clip.path))


@pytest.fixture(scope="module")
def capture(head_clip, tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "capture"
    res = track_head(head_clip.path, out, TrackSettings(size=128))
    return out, res


def test_capture_opens_with_splits_cameras_and_fit(capture, head_clip):
    out, res = capture
    ds = open_dataset(out)
    assert len(ds) == FRAMES == res.frames and not res.dropped
    assert len(ds.split("train")) == 16 and len(ds.split("test_frames")) == 4
    assert ds.frame_camera(0).width == 128
    fit = np.load(out / "head_fit.npz")
    assert fit["weights"].shape == (FRAMES, 57) and fit["rotations"].shape == (FRAMES, 3)
    assert res.error_px < 3.0, res.error_px  # landmark reprojection error in the video's pixels
    # the jaw opens and closes twice in the clip: the fitted jawOpen follows the truth
    names = [str(n) for n in fit["names"]]
    jaw = fit["weights"][:, names.index("jawOpen")]
    truth = head_clip.weights[:, names.index("jawOpen")].numpy()
    assert np.corrcoef(jaw, truth)[0, 1] > 0.8, (jaw, truth)
    # the head turns (yaw) by up to 0.25 rad: recovered within 0.1 rad
    assert np.abs(fit["rotations"][:, 1] - head_clip.rotations[:, 1].numpy()).max() < 0.1
    # masks cover the head: the driving mesh's projection falls inside the matte
    fr = ds[5]
    cam = fr.camera
    v = fr.vertices.float() @ cam.viewmat[:3, :3].T.float() + cam.viewmat[:3, 3].float()
    px = (v @ cam.K.T.float())[:, :2] / v[:, 2:]
    inside = (px[:, 0] >= 0) & (px[:, 0] < 127) & (px[:, 1] >= 0) & (px[:, 1] < 127)
    u, w = px[inside].long().T
    assert fr.mask[w, u, 0].mean() > 0.8


@pytest.mark.slow
def test_trains_evaluates_and_plays_arkit_weights(capture, tmp_path, capsys):
    out, _ = capture
    run = tmp_path / "run"
    assert main(["train", str(out), "--out", str(run), *tiny_train_argv()]) == 0
    assert main(["eval", str(run), "--no-report", "--no-lpips", "--no-progress"]) == 0
    m = json.loads((run / "eval" / "metrics.json").read_text())["splits"]["test_frames"]
    assert m["psnr_mask"] is not None and m["psnr_mask"] > 10
    # ARKit weights drive the trained head through the capture's head model (cross-reenactment's path)
    weights = np.zeros((3, 57), np.float32)
    names = [str(n) for n in np.load(out / "head_fit.npz")["names"]]
    weights[:, names.index("jawOpen")] = [0.0, 0.5, 1.0]
    np.save(tmp_path / "w.npy", weights)
    frames_out = tmp_path / "anim"
    argv = ["render", str(run), "--animation", "blendshapes", str(out / "head_model.npz"), "--weights"]
    argv += [str(tmp_path / "w.npy"), "--size", "64x64", "--no-mp4", "--no-progress", "--out", str(frames_out)]
    assert main(argv) == 0
    from PIL import Image

    imgs = [np.asarray(Image.open(p), dtype=np.float32) for p in sorted((frames_out / "frames").glob("*.png"))]
    assert len(imgs) == 3 and np.abs(imgs[0] - imgs[2]).mean() > 0.3, "the jaw weight does not move the avatar"
    # without a FILE a tracked head plays in its capture's own head model (the bundled ICT head does not fit it)
    default_out = tmp_path / "anim_default"
    argv = ["render", str(run), "--animation", "blendshapes", "--weights", str(tmp_path / "w.npy")]
    argv += ["--size", "64x64", "--no-mp4", "--no-progress", "--out", str(default_out)]
    assert main(argv) == 0
    again = [np.asarray(Image.open(p), dtype=np.float32) for p in sorted((default_out / "frames").glob("*.png"))]
    np.testing.assert_array_equal(np.stack(again), np.stack(imgs))
    capsys.readouterr()
    assert main(["render", str(run), "--animation", "blendshapes", "ict", "--out", str(tmp_path / "ict")]) == 2
    assert "use the blend-shape model the avatar was trained on" in capsys.readouterr().err
    # ... and so in the player's webcam mode: your own head, driven live (the landmarker's files stand in here)
    marker = tmp_path / "face_mesh_pkg"
    marker.mkdir()
    for f in LANDMARKER_FILES:
        (marker / f).write_text("x")
    page = tmp_path / "live"
    assert main(["view", str(run), "--animation", "blendshapes", "--webcam", str(marker), "--out", str(page)]) == 0
    header = json.loads((page / "avatar.json").read_text())
    assert header["webcam"]["names"] and header["driver"]["source"] == "blendshapes"
    assert header["num_vertices"] == open_dataset(out).num_vertices
    # another tracked capture's expressions, named columns matched: the capture folder is the weights source
    got = read_weights(out, list(reversed(names)))
    np.testing.assert_array_equal(got[:, ::-1], np.load(out / "head_fit.npz")["weights"])


def test_frames_without_a_face_are_left_out_and_named(frames, tmp_path):
    clip = [f if i not in (3, 4) else np.full_like(f, 128) for i, f in enumerate(frames)]
    path = write_mp4(clip, tmp_path / "gaps.mp4", fps=10)
    res = track_head(path, tmp_path / "cap", TrackSettings(size=64))
    assert res.dropped == ["0.30s", "0.40s"] and res.frames == FRAMES - 2
    assert any("no face in 2 frame(s)" in n for n in res.notes)


def test_no_face_refused_in_one_line(frames, tmp_path):
    path = write_mp4([np.full_like(frames[0], 90)] * 12, tmp_path / "empty.mp4", fps=10)
    with pytest.raises(MeshsplatError, match="no face found in any of the 12 frames") as exc:
        track_head(path, tmp_path / "cap", TrackSettings(size=64))
    assert "\n" not in str(exc.value) and not (tmp_path / "cap" / "manifest.json").exists()


def test_too_few_faces_refused(frames, tmp_path):
    path = write_mp4(frames[:6], tmp_path / "short.mp4", fps=10)
    with pytest.raises(MeshsplatError, match="a face in only 6 of 6 frames"):
        track_head(path, tmp_path / "cap", TrackSettings(size=64))


def test_scene_cut_refused(frames):
    h, w = frames[0].shape[:2]
    # the second shot shows the face elsewhere and smaller: a cut, not motion
    shot2 = [np.pad(f[::2, ::2], ((0, h - h // 2), (w - w // 2, 0), (0, 0)), constant_values=150) for f in frames[:6]]
    with FaceMesh() as fm, pytest.raises(MeshsplatError, match="scene cut"):
        track_faces(frames[:6] + shot2, fm)


def test_two_faces_follow_the_largest_and_say_so(frames):
    h, w = frames[0].shape[:2]
    small = [
        np.pad(f[::2, ::2], ((h // 4, h - h // 2 - h // 4), (0, w - w // 2), (0, 0)), constant_values=150)
        for f in frames
    ]
    both = [np.concatenate([a, b], 1) for a, b in zip(frames[:6], small[:6], strict=True)]
    with FaceMesh() as fm:
        tr = track_faces(both, fm)
    assert tr.found.all() and tr.faces_seen.max() == 2
    assert (tr.landmarks[:, :468, 0].mean(1) < w).all()  # the large face, on the left half
    assert tr.notes and "following the largest face" in tr.notes[0]


def test_cli_track_one_line_errors(tmp_path, capsys):
    assert main(["track", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "video not found" in err[0]
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x.txt").write_text("mine")
    (tmp_path / "v.mp4").write_bytes(b"x")
    assert main(["track", str(tmp_path / "v.mp4"), "--out", str(tmp_path / "full")]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (tmp_path / "full" / "x.txt").read_text() == "mine"


def test_real_webcam_footage(tmp_path):
    """Two seconds of a real webcam video (tests/data/README.md): every frame tracked, the fitted head's
    landmarks within a few pixels of MediaPipe's, the matte covering the face and leaving the room out."""
    from pathlib import Path

    video = Path(__file__).parents[1] / "data" / "facemesh_input_2s.mp4"
    res = track_head(video, tmp_path / "cap", TrackSettings(size=128))
    assert res.frames == 30 and not res.dropped
    assert res.error_px < 4.0, res.error_px  # pixels of the 480x320 video
    ds = open_dataset(tmp_path / "cap")
    fit = np.load(tmp_path / "cap" / "head_fit.npz")
    for i in (0, 15, 29):
        fr = ds[i]
        K = fr.camera.K.double().numpy() @ np.linalg.inv(fit["K"])  # video pixels -> this frame's crop
        lm = fit["landmarks"][i, :468, :2] @ K[:2, :2].T + K[:2, 2]
        inside = fr.mask[lm[:, 1].astype(int).clip(0, 127), lm[:, 0].astype(int).clip(0, 127), 0]
        assert float(inside.mean()) > 0.9  # the face is in the matte
        assert float(fr.mask[:, :8].mean()) < 0.05 and float(fr.mask[:8].mean()) < 0.2  # the room is not
