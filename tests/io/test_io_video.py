"""Video output: MP4 through imageio-ffmpeg, PNG frames, and the PNG fallback."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.io import write_png_frames, write_video
from meshsplat.io.video import to_uint8


def _frames(n=4, h=17, w=23):
    return [torch.full((h, w, 3), i / (n - 1)) for i in range(n)]


def test_to_uint8():
    assert to_uint8(torch.tensor([[[0.0, 0.5, 1.2]]])).tolist() == [[[0, 128, 255]]]
    assert to_uint8(np.zeros((2, 2), np.uint8)).shape == (2, 2, 3)
    with pytest.raises(MeshsplatError, match="frame"):
        to_uint8(np.zeros((2, 2, 2)))
    with pytest.raises(MeshsplatError, match="NaN"):
        to_uint8(np.full((2, 2, 3), np.nan))


def test_png_frames(tmp_path):
    paths = write_png_frames(_frames(), tmp_path / "f")
    assert [p.name for p in paths] == [f"frame_{i:05d}.png" for i in range(4)]
    assert np.asarray(Image.open(paths[-1])).shape == (17, 23, 3)
    assert np.asarray(Image.open(paths[-1]))[0, 0].tolist() == [255, 255, 255]


def test_mp4_written_with_odd_size(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    res = write_video(_frames(n=5), tmp_path / "out.mp4", fps=10)
    assert res.error is None and res.mp4 is not None and res.pngs == []
    decoded = subprocess.run(
        [
            imageio_ffmpeg.get_ffmpeg_exe(),
            "-v",
            "error",
            "-i",
            str(res.mp4),
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
            "-",
        ],
        capture_output=True,
        check=True,
    )
    frames = np.frombuffer(decoded.stdout, np.uint8).reshape(-1, 18, 24, 3)
    assert len(frames) == 5 and frames[0].shape == (18, 24, 3)  # padded to even size
    assert abs(int(frames[-1][5, 5, 0]) - 255) < 8 and int(frames[0][5, 5, 0]) < 8


def test_mp4_failure_falls_back_to_png(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails as if not installed
    with pytest.warns(MeshsplatWarning, match="imageio-ffmpeg"):
        res = write_video(_frames(), tmp_path / "out.mp4")
    assert res.mp4 is None and "imageio-ffmpeg" in res.error
    assert len(res.pngs) == 4 and res.pngs[0].parent == tmp_path / "out_frames"
    assert not (tmp_path / "out.mp4").exists()
    with pytest.raises(MeshsplatError, match="imageio-ffmpeg"):
        write_video(_frames(), tmp_path / "out2.mp4", png_fallback=False)
