"""Initial colours of embedded points, read from training images (``model.init_color = "image"``).

A view is ``(image [H,W,3], mask [H,W,1] | None, camera: Camera, vertices [V,3])``: one training frame.
A point takes the colour of the pixel it projects to (``Camera.project``) when it lies in front of the
camera, inside the image and inside the mask; points never seen stay grey (0.5).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from meshsplat.camera import Camera
from meshsplat.embedding import embed, surface_points
from meshsplat.mesh import MeshPose, TriMesh

__all__ = ["View", "first_view_colors", "mean_view_colors"]

View = tuple[torch.Tensor, torch.Tensor | None, Camera, torch.Tensor]


def _pixels_seen(
    image: torch.Tensor, mask: torch.Tensor | None, camera: Camera, points: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(ok [N] bool, row [N], col [N])``: which ``points [N,3]`` land in the image (and mask), and where."""
    pix, z = camera.project(points)
    ix, iy = pix[:, 0].floor().long(), pix[:, 1].floor().long()
    h, wd = image.shape[:2]
    ok = (z > 0) & (ix >= 0) & (ix < wd) & (iy >= 0) & (iy < h)
    ixc, iyc = ix.clamp(0, wd - 1), iy.clamp(0, h - 1)
    if mask is not None:
        ok &= mask[iyc, ixc, 0] > 0.5
    return ok, iyc, ixc


@torch.no_grad()
def first_view_colors(mesh: TriMesh, view: View, face: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Colour ``[N,3]`` of each embedded point ``(face [N], uv [N,2])`` of the canonical ``mesh`` in one
    ``view`` (the paper's initialisation: the first training frame); grey where unseen."""
    image, mask, camera, verts = view
    pts = surface_points(verts, mesh.faces, face, uv)
    ok, iy, ix = _pixels_seen(image, mask, camera, pts)
    rgb = torch.full((face.shape[0], 3), 0.5, dtype=uv.dtype, device=uv.device)
    rgb[ok] = image[iy[ok], ix[ok]].to(rgb)
    return rgb


@torch.no_grad()
def mean_view_colors(mesh: TriMesh, views: Iterable[View], face: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Mean colour ``[N,3]`` of each embedded point over ``views``, counting a view where the point is in
    the image and the mask and its Phong normal faces the camera; grey where never seen."""
    acc = torch.zeros(face.shape[0], 3, dtype=uv.dtype, device=uv.device)
    cnt = torch.zeros(face.shape[0], 1, dtype=uv.dtype, device=uv.device)
    for image, mask, camera, verts in views:
        pts, nrm = embed(MeshPose.from_vertices(mesh, verts), face, uv, torch.zeros_like(uv[:, 0]))
        campos = torch.linalg.inv(camera.viewmat)[:3, 3]
        ok, iy, ix = _pixels_seen(image, mask, camera, pts)
        ok &= ((campos - pts) * nrm).sum(-1) > 0
        acc[ok] += image[iy[ok], ix[ok]].to(acc)
        cnt[ok] += 1
    return torch.where(cnt > 0, acc / cnt.clamp_min(1), torch.full_like(acc, 0.5))
