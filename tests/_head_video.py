"""A short video of the bundled ICT head talking and turning, with its ground truth: for the tracker's
end-to-end tests (MediaPipe must find the face on it, as on a photograph)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from meshsplat.io.video import write_mp4
from meshsplat.track.head_render import render_head
from meshsplat.track.ict_head import IctHead, load_ict_head


@dataclass
class HeadClip:
    path: Path
    weights: torch.Tensor  # [T,E]
    rotations: torch.Tensor  # [T,3]
    translations: torch.Tensor  # [T,3]
    K: torch.Tensor  # [3,3]
    width: int
    height: int


def clip_params(head: IctHead, frames: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Talking (jaw, smile, blinks) and a slow head turn; the head ~60 cm in front of the camera."""
    t = torch.arange(frames, dtype=torch.float32) / max(frames - 1, 1)
    w = torch.zeros(frames, len(head.names))
    w[:, head.names.index("jawOpen")] = 0.45 * (0.5 - 0.5 * torch.cos(2 * math.pi * 2 * t))
    for side in ("L", "R"):
        w[:, head.names.index(f"mouthSmile_{side}")] = 0.5 * t
    rot = torch.stack([0.12 * torch.sin(2 * math.pi * t), 0.35 * torch.sin(math.pi * t) - 0.1, 0.0 * t], 1)
    c = (head.neutral.min(0).values + head.neutral.max(0).values) / 2
    trans = (-c + torch.tensor([0.0, 3.0, -55.0])).expand(frames, 3).clone()
    return w, rot, trans


def write_head_clip(path: Path, frames: int = 24, size: int = 256, fps: float = 12.0) -> HeadClip:
    head = load_ict_head(with_landmarks=False)
    w, rot, trans = clip_params(head, frames)
    gaze = torch.zeros(frames, 2, 2)
    verts = head.pose(torch.zeros_like(head.neutral), w, gaze, rot, trans)
    f = size / (2 * math.tan(math.radians(40) / 2))
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    images = []
    for v in verts:
        img, _, _ = render_head(head, v, K, size, size)
        images.append((img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))
    write_mp4(images, path, fps=fps, quality=9)
    return HeadClip(path, w, rot, trans, K, size, size)
