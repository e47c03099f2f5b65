"""A short video of the Anny body moving and turning, with its ground truth: for the body tracker's tests
(MediaPipe Pose must find the person on it, as on a photograph)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from meshsplat.drivers.anny_body import JOINTS, AnnyBody, load_anny_body
from meshsplat.io.video import write_mp4
from meshsplat.track.body_render import render_body


@dataclass
class BodyClip:
    path: Path | None
    frames: list[np.ndarray]  # uint8 [H,W,3]
    pose: torch.Tensor  # [T,24,3]
    transl: torch.Tensor  # [T,3]
    K: torch.Tensor  # [3,3]
    width: int
    height: int


def clip_pose(frames: int, turn: float = 0.6) -> tuple[torch.Tensor, torch.Tensor]:
    """Arms raising and lowering out of phase, a knee bending, the elbows bending, a slow turn about the
    vertical (up to ``turn`` rad); the body ~3.3 m in front of the camera."""
    t = torch.arange(frames, dtype=torch.float32) / max(frames - 1, 1)
    pose = torch.zeros(frames, 24, 3)
    j = JOINTS.index
    pose[:, 0, 1] = turn * torch.sin(math.pi * t)
    pose[:, j("left_shoulder"), 2] = -1.0 + 0.6 * torch.sin(2 * math.pi * t)
    pose[:, j("right_shoulder"), 2] = 1.2 - 0.9 * torch.cos(2 * math.pi * t) * 0.8
    pose[:, j("left_elbow"), 1] = -0.9 * (0.5 - 0.5 * torch.cos(2 * math.pi * t))
    pose[:, j("right_elbow"), 1] = 0.6
    pose[:, j("left_knee"), 0] = 0.8 * (0.5 - 0.5 * torch.cos(2 * math.pi * t))
    pose[:, j("left_hip"), 0] = -0.5 * (0.5 - 0.5 * torch.cos(2 * math.pi * t))
    pose[:, j("right_hip"), 2] = 0.15
    transl = torch.zeros(frames, 3)
    transl[:, 2] = -3.3
    transl[:, 0] = 0.15 * torch.sin(2 * math.pi * t)
    return pose, transl


def render_clip(
    body: AnnyBody, pose: torch.Tensor, transl: torch.Tensor, width: int, height: int, fov_deg: float = 50.0
) -> tuple[list[np.ndarray], torch.Tensor]:
    f = 0.5 * math.hypot(width, height) / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    verts, _ = body.pose(pose, transl=transl)
    images = []
    for v in verts:
        img, _ = render_body(body, v, K, width, height)
        images.append((img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))
    return images, K


def write_body_clip(
    path: Path | None, frames: int = 20, width: int = 192, height: int = 256, fps: float = 10.0
) -> BodyClip:
    body = load_anny_body()
    pose, transl = clip_pose(frames)
    images, K = render_clip(body, pose, transl, width, height)
    if path is not None:
        write_mp4(images, path, fps=fps, quality=9)
    return BodyClip(path, images, pose, transl, K, width, height)
