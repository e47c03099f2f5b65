"""Golden cases for every camera convention meshsplat converts from (hand-computed pixels)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meshsplat.camera import (
    Camera,
    K_from_normalized,
    camera_center,
    look_at,
    opengl_c2w_from_viewmat,
    rodrigues,
    viewmat_from_opengl_c2w,
    viewmat_from_rodrigues,
)
from meshsplat.errors import MeshsplatError


def pixel(K, viewmat, X):
    x = viewmat[:3, :3] @ np.asarray(X, float) + viewmat[:3, 3]
    assert x[2] > 0, "point behind the camera"
    u = K @ (x / x[2])
    return u[:2]


K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])


def test_opengl_c2w_camera_at_plus_z_looking_at_origin():
    # OpenGL camera at (0,0,5), identity rotation: looks down -z, y up. The world point (1, 2, 0) is
    # 5 in front, 1 right and 2 up -> pixel (50 + 100*1/5, 40 - 100*2/5) = (70, 0).
    c2w = np.eye(4)
    c2w[:3, 3] = [0, 0, 5]
    vm = viewmat_from_opengl_c2w(c2w)
    np.testing.assert_allclose(camera_center(vm), [0, 0, 5], atol=1e-12)
    np.testing.assert_allclose(pixel(K, vm, [1, 2, 0]), [70, 0], atol=1e-9)
    np.testing.assert_allclose(opengl_c2w_from_viewmat(vm), c2w, atol=1e-12)


def test_opengl_c2w_rotated_camera():
    # OpenGL camera at (3,0,0) turned +90 deg about y: its -z axis points to -x (towards the origin).
    c, s = math.cos(math.pi / 2), math.sin(math.pi / 2)
    c2w = np.eye(4)
    c2w[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    c2w[:3, 3] = [3, 0, 0]
    vm = viewmat_from_opengl_c2w(c2w[:3])  # 3x4 accepted
    # camera right (+x_cam) = c2w column 0 = (0,0,-1) in world: the point (0,0,-1) is 3 ahead, 1 right
    np.testing.assert_allclose(pixel(K, vm, [0, 0, -1]), [50 + 100 / 3, 40], atol=1e-9)
    np.testing.assert_allclose(pixel(K, vm, [0, 1, 0]), [50, 40 - 100 / 3], atol=1e-9)


def test_look_at_matches_opengl_convention():
    # look_at from +z towards the origin with +y up is the identity-rotation OpenGL camera at (0,0,5)
    vm = look_at([0, 0, 5], [0, 0, 0])
    np.testing.assert_allclose(pixel(K, vm, [1, 2, 0]), [70, 0], atol=1e-9)
    c2w = np.eye(4)
    c2w[:3, 3] = [0, 0, 5]
    np.testing.assert_allclose(vm, viewmat_from_opengl_c2w(c2w), atol=1e-12)


def test_normalized_intrinsics_drop_deca_signs():
    Kn = K_from_normalized([-1.5, 1.5, 0.5, 0.5], 512, 512)
    np.testing.assert_allclose(Kn, [[768, 0, 256], [0, 768, 256], [0, 0, 1]])
    with pytest.raises(MeshsplatError, match="4 finite numbers"):
        K_from_normalized([1, 2, 3], 10, 10)


def test_rodrigues_golden():
    R = rodrigues([0, 0, math.pi / 2])  # +90 deg about z maps x to y
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    vm = viewmat_from_rodrigues([0, 0, 0], [0, 0, 2])
    np.testing.assert_allclose(pixel(K, vm, [0.2, -0.4, 0]), [60, 20], atol=1e-9)  # 2 ahead, y down
    with pytest.raises(MeshsplatError):
        viewmat_from_rodrigues([0, 0], [0, 0, 1])


def test_project_golden_pixel_and_depth():
    """A point on the optical axis lands on the principal point; one unit right at depth 2 moves fx / 2."""
    viewmat = torch.eye(4)
    viewmat[2, 3] = 2.0  # the camera 2 units in front of the origin, looking down +z
    K = torch.tensor([[100.0, 0, 32.0], [0, 80.0, 24.0], [0, 0, 1]])
    cam = Camera(viewmat, K, 64, 48)
    pix, z = cam.project(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1.0, 0], [0.0, 0, -3.0]]))
    assert torch.allclose(pix[:3], torch.tensor([[32.0, 24.0], [82.0, 24.0], [32.0, 64.0]]))
    assert torch.allclose(z, torch.tensor([2.0, 2.0, 2.0, -1.0]))
