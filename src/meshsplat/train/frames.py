"""The training frames kept in memory: decoded images, masks, cameras and vertices, and their posed meshes."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from meshsplat.data.dataset import AvatarDataset
from meshsplat.gaussians.avatar import Avatar
from meshsplat.gaussians.init_colors import first_view_colors, mean_view_colors
from meshsplat.gaussians.shading import Shading
from meshsplat.mesh import MeshPose, TriMesh

__all__ = ["FrameCache", "CACHE_BYTES"]

CACHE_BYTES = 2 * 1024**3  # decoded training frames (and their posed meshes) kept in memory


class FrameCache:
    """Frames of ``dataset`` on ``device`` (float32), and their posed meshes, within ``CACHE_BYTES``."""

    def __init__(self, dataset: AvatarDataset, device: torch.device, budget: int = CACHE_BYTES) -> None:
        self.dataset, self.device, self.budget = dataset, device, budget
        self._frames: dict[int, tuple] = {}
        self._poses: dict[int, MeshPose] = {}
        self._bytes = 0

    def frame(self, idx: int) -> tuple:
        """(image [H,W,3], mask [H,W,1]|None, camera, vertices [V,3]) of frame ``idx``."""
        hit = self._frames.get(idx)
        if hit is not None:
            return hit
        fr = self.dataset[idx]
        dev = self.device
        item = (
            fr.image.to(dev, torch.float32),
            None if fr.mask is None else fr.mask.to(dev, torch.float32),
            fr.camera.to(dev, torch.float32),
            fr.vertices.to(dev, torch.float32),
        )
        size = sum(t.numel() * 4 for t in item if isinstance(t, torch.Tensor)) + 4 * (16 + 9)
        if self._bytes + size <= self.budget:
            self._frames[idx] = item
            self._bytes += size
        return item

    def pose(self, idx: int, avatar: Avatar, shading: Shading | None) -> MeshPose:
        """Frame ``idx``'s ``MeshPose`` of its (fixed) vertices: posed once (posing the mesh is a few milliseconds
        of every iteration otherwise), with the shadow maps ``shading`` will keep counted in its size."""
        hit = self._poses.get(idx)
        if hit is not None:
            return hit
        pose = avatar.pose(self.frame(idx)[3])
        size = sum(t.numel() * t.element_size() for t in (pose.vertex_normals, pose.vertex_quats, pose.area_ratio))
        dirs = None if shading is None else shading.shadow_directions()
        if shading is not None and dirs is not None:  # float64 when compiled
            size += dirs.shape[0] * shading.grid**2 * 8
        if self._bytes + size <= self.budget:
            self._poses[idx] = pose
            self._bytes += size
        return pose

    def colors_fn(
        self, mesh: TriMesh, ids: list[int], frames: int
    ) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """Initial colours ``[N,3]`` of points ``(face [N], uv [N,2])`` on ``mesh``: the first of ``ids``'
        pixel (``frames`` = 1, the paper) or the mean over ``frames`` frames spread over ``ids``."""

        def colors(face: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
            if frames == 1:
                return first_view_colors(mesh, self.frame(ids[0]), face, uv)
            k = min(frames, len(ids))
            picks = sorted({ids[round(x)] for x in np.linspace(0, len(ids) - 1, k)})
            return mean_view_colors(mesh, (self.frame(i) for i in picks), face, uv)

        return colors
