"""The trackers' camera: a pinhole at the world origin looking along world -z (+y up), principal point at
the image centre, focal length from a diagonal field of view (60 degrees unless the user gives one).

Both trackers fit in this camera's world (heads: ``head_fit``, bodies: ``body_fit``) and write it into the
captures they make; the player's webcam mode solves in the same camera (``viewer.webcam``).
"""

from __future__ import annotations

import math

import torch

__all__ = ["TRACKER_VIEWMAT", "DEFAULT_DIAGONAL_FOV_DEG", "focal_from_fov", "project", "world_to_camera_axes"]

# world (+y up, the subject facing +z) -> OpenCV camera (x right, y down, z forward); its own inverse
TRACKER_VIEWMAT = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))
DEFAULT_DIAGONAL_FOV_DEG = 60.0  # phones' main and front cameras are 65-80 degrees, webcams 55-78


def focal_from_fov(width: int, height: int, diagonal_fov_deg: float = DEFAULT_DIAGONAL_FOV_DEG) -> float:
    """Focal length in pixels of a ``width`` x ``height`` image with the given diagonal field of view."""
    return 0.5 * math.hypot(width, height) / math.tan(math.radians(diagonal_fov_deg) / 2)


def world_to_camera_axes(points: torch.Tensor) -> torch.Tensor:
    """World points ``[...,3]`` in the camera's (OpenCV) axes; the same map takes camera axes back to world."""
    return points * TRACKER_VIEWMAT.diagonal()[:3].to(points)


def project(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pixels ``[...,2]`` of world ``points [...,3]`` through intrinsics ``K [3,3]`` (depth clamped at 1 mm)."""
    cam = world_to_camera_axes(points)
    z = cam[..., 2:].clamp_min(1e-3)
    return torch.stack([K[0, 0] * cam[..., 0], K[1, 1] * cam[..., 1]], -1) / z + K[:2, 2]
