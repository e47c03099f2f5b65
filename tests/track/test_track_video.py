"""Reading videos as phones write them (io.video), and the crops the tracker cuts (track.head_region)."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from meshsplat.errors import MeshsplatError
from meshsplat.io.video import probe_video, read_video_frames, write_mp4
from meshsplat.track.head_region import Crop, crop_frame, crop_inside, regions_touching

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")


def _gradient_clip(path, frames=10, w=64, h=48, fps=10.0):
    """A clip whose pixels say where they are: red grows with x, green with y, blue with time."""
    ys, xs = np.mgrid[0:h, 0:w]
    imgs = []
    for t in range(frames):
        img = np.stack([xs * 255 // (w - 1), ys * 255 // (h - 1), np.full_like(xs, t * 255 // (frames - 1))], -1)
        imgs.append(img.astype(np.uint8))
    return write_mp4(imgs, path, fps=fps, quality=10)


def test_reads_frames_size_and_rate(tmp_path):
    p = _gradient_clip(tmp_path / "a.mp4")
    info = probe_video(p)
    assert (info.width, info.height, info.fps) == (64, 48, 10.0)
    assert not info.rotated
    frames = list(read_video_frames(p))
    assert len(frames) == 10 and frames[0].shape == (48, 64, 3) and frames[0].dtype == np.uint8
    # red grows to the right, green downwards: the frame is not transposed or flipped
    f = frames[0].astype(int)
    assert f[24, 60, 0] > f[24, 4, 0] + 150 and f[44, 32, 1] > f[4, 32, 1] + 150


def test_rotation_metadata_turns_the_frames(tmp_path):
    """A portrait phone clip: stored landscape with a display rotation, read upright (ffmpeg applies it)."""
    src = _gradient_clip(tmp_path / "a.mp4")
    rot = tmp_path / "rot.mp4"
    ffmpeg = imageio_ffmpeg.get_ffmpeg_exe()
    subprocess.run(
        [ffmpeg, "-y", "-loglevel", "error", "-display_rotation", "90", "-i", str(src), "-c", "copy", str(rot)],
        check=True,
    )
    info = probe_video(rot)
    assert (info.width, info.height) == (48, 64) and info.rotated
    f = next(read_video_frames(rot)).astype(int)
    assert f.shape == (64, 48, 3)
    # display rotation 90 (counter-clockwise): the stored image's right edge (red 255) is now the top row
    assert f[2, :, 0].mean() > f[-3, :, 0].mean() + 150


def test_resample_range_and_scale(tmp_path):
    p = _gradient_clip(tmp_path / "a.mp4", frames=20)
    assert len(list(read_video_frames(p, fps=5))) == 10
    late = list(read_video_frames(p, start=1.0))
    assert len(late) == 10 and late[0][..., 2].mean() > 110  # blue says the time: the second half
    assert len(list(read_video_frames(p, seconds=0.5))) == 5
    small = next(read_video_frames(p, max_side=32))
    assert small.shape == (24, 32, 3)


@pytest.mark.parametrize(
    "make, expect",
    [
        (lambda p: None, "video not found"),
        (lambda p: p.write_bytes(b""), "empty"),
        (lambda p: p.write_text("not a video at all"), "not a video ffmpeg can read"),
        (lambda p: p.mkdir(), "not a file"),
    ],
)
def test_bad_video_files_one_line(tmp_path, make, expect):
    p = tmp_path / "clip.mp4"
    make(p)
    with pytest.raises(MeshsplatError, match=expect) as exc:
        probe_video(p)
    assert "\n" not in str(exc.value)


def test_crop_intrinsics_match_the_cut(tmp_path):
    """A 3D point projected with the frame's K, then moved into the crop, lands where the crop's K puts it."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    crop = Crop(x0=150.3, y0=80.7, side=210.5, size=128)
    rng = np.random.default_rng(0)
    X = rng.normal(size=(20, 3)) * [5, 5, 2] + [0, 0, 60]
    px = (X @ K.T)[:, :2] / X[:, 2:]
    pc = (X @ crop.K(K).T)[:, :2] / X[:, 2:]
    np.testing.assert_allclose(crop.to_crop(px), pc, atol=1e-9)


def test_crop_frame_samples_the_box():
    """A frame whose pixel values are their x coordinate: the crop's pixel centres read the right x."""
    w, h = 400, 300
    frame = np.broadcast_to((np.arange(w) * 255 // (w - 1)).astype(np.uint8)[None, :, None], (h, w, 3)).copy()
    crop = Crop(x0=100.0, y0=50.0, side=200.0, size=100)
    out = crop_frame(frame, crop).astype(float)
    # crop pixel u (centre u+0.5) is frame x = 100 + 2 (u + 0.5)
    for u in (5, 50, 95):
        x = 100 + 2 * (u + 0.5)
        assert abs(out[50, u, 0] - (x - 0.5) * 255 / (w - 1)) < 2.5
    # outside the frame is black
    edge = crop_frame(frame, Crop(x0=-50.0, y0=0.0, side=100.0, size=50))
    assert edge[:, :24].max() == 0 and edge[:, 27:].min() > 0  # crop columns 0-24 lie left of the frame


def test_crop_inside_marks_the_frame():
    """The black margin of a crop that leaves the frame is never part of a matte."""
    inside = crop_inside(300, 400, Crop(x0=-50.0, y0=250.0, side=100.0, size=50))
    assert inside[:, :24].max() == 0 and inside[:24, 26:].min() == 1  # left of the frame; inside it
    assert inside[26:].max() == 0  # below the frame's last row (y >= 300)


def test_matte_keeps_only_the_regions_touching_the_head():
    """A bottle the segmentation took for the person, apart from the head, leaves the matte; the head's region
    keeps its values and the soft edge beside it; a frame whose matte misses the head keeps its matte."""
    ys, xs = np.mgrid[0:64, 0:64] + 0.5
    head = np.clip(12.5 - np.hypot(xs - 24, ys - 30), 0, 1).astype(np.float32)  # soft disc, radius ~12
    bottle = np.clip(4.5 - np.hypot(xs - 52, ys - 20), 0, 1).astype(np.float32)  # a separate blob
    edge_only = np.zeros((64, 64), np.float32)
    edge_only[5, 5] = 0.3  # a faint pixel far from the head: not the head's edge
    matte = np.maximum(np.maximum(head, bottle), edge_only)
    seed = np.hypot(xs - 24, ys - 30) < 6
    kept = regions_touching(matte, seed)
    assert kept.dtype == matte.dtype
    assert np.array_equal(kept[head > 0], matte[head > 0])  # the head, soft edge included
    assert kept[bottle > 0].max() == 0 and kept[5, 5] == 0
    assert np.array_equal(regions_touching(matte, np.zeros((64, 64), bool)), matte)  # nothing touches: as it is
    assert np.array_equal(regions_touching(head, seed), head)  # one region: nothing to drop
