"""Cameras for the generator: look-at extrinsics (OpenCV axes, world +y up) and pinhole intrinsics."""
from __future__ import annotations

import math

import numpy as np

__all__ = ["look_at", "intrinsics", "orbit_position", "yaw_matrix"]


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World->camera ``[4,4]``: camera at ``eye`` looking at ``target``; image y points along -up."""
    eye, target, up = (np.asarray(x, np.float64) for x in (eye, target, up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-8:
        right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = -R @ eye
    return m


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Square pixels, vertical field of view ``fov_deg``, principal point at the image centre."""
    f = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float64)


def orbit_position(center, distance: float, azimuth: float, elevation: float) -> np.ndarray:
    """Point at ``distance`` from ``center``; azimuth 0 is +z (the glTF front), angles in radians."""
    c = np.asarray(center, np.float64)
    return c + distance * np.array([math.cos(elevation) * math.sin(azimuth), math.sin(elevation),
                                    math.cos(elevation) * math.cos(azimuth)])


def yaw_matrix(angle: float) -> np.ndarray:
    """Rotation about +y by ``angle`` radians ``[3,3]``."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
