"""EWA projection of 3D Gaussians to screen space (gsplat 1.5.3 `fully_fused_projection`).

Differentiable with autograd (cost is O(C*N), small next to compositing). Culled
Gaussians get zero means2d/conics/depths and zero radii, as in gsplat; their
arithmetic is sanitised first so that no NaN leaks into gradients.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from meshsplat.mesh.quaternion import quat_to_matrix
from meshsplat.render._constants import ALPHA_THRESHOLD, EPS2D, FOV_CLAMP_MARGIN, MAX_EXTEND

__all__ = ["Projection", "project_gaussians", "covariance_3d", "antialias_compensation"]


class Projection(NamedTuple):
    means2d: torch.Tensor  # [C,N,2] pixels (0 where culled)
    conics: torch.Tensor  # [C,N,3] inverse 2D covariance (a, b, c) with b off-diagonal
    depths: torch.Tensor  # [C,N] camera-space z (0 where culled)
    radii: torch.Tensor  # [C,N,2] int32 opacity-aware 3-sigma half extents, 0 = culled
    visible: torch.Tensor  # [C,N] bool


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """``R S S^T R^T`` from quats [N,4] (wxyz, any norm) and scales [N,3] -> [N,3,3]."""
    m = quat_to_matrix(quats) * scales[:, None, :]
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = EPS2D,
) -> Projection:
    """Project means [N,3] etc. into C pinhole cameras (viewmats [C,4,4] world->camera)."""
    z, in_depth, cov2d, mean2d = _screen_covariance(
        means, quats, scales, viewmats, Ks, width, height, near_plane, far_plane
    )
    one = torch.ones((), dtype=z.dtype, device=z.device)
    a = cov2d[..., 0, 0] + eps2d
    b = 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0])
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    valid = in_depth & (det > 0)
    det_s = torch.where(valid, det, one)
    conic = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)

    with torch.no_grad():
        op = opacities.detach().expand_as(z)
        valid = valid & (op >= ALPHA_THRESHOLD)
        extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extend = extend.clamp(max=MAX_EXTEND)
        a_d = torch.where(valid, a.detach(), one)
        c_d = torch.where(valid, c.detach(), one)
        rx = torch.ceil(extend * a_d.clamp_min(0).sqrt())
        ry = torch.ceil(extend * c_d.clamp_min(0).sqrt())
        valid = valid & ((rx > 0) | (ry > 0))
        mx, my = mean2d.detach().unbind(-1)
        valid = valid & ~((mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height))
        radii = torch.where(valid[..., None], torch.stack([rx, ry], -1), 0).to(torch.int32)

    vis3 = valid[..., None]
    zero_t = torch.zeros((), dtype=z.dtype, device=z.device)
    return Projection(
        means2d=torch.where(vis3, mean2d, zero_t),
        conics=torch.where(vis3, conic, zero_t),
        depths=torch.where(valid, z, zero_t),
        radii=radii,
        visible=valid,
    )


def _screen_covariance(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
) -> tuple[torch.Tensor, ...]:
    """Camera-space z ``[C,N]``, depth mask, screen covariance ``[C,N,2,2]`` (no dilation), 2D means."""
    rot = viewmats[:, :3, :3]
    trans = viewmats[:, :3, 3]
    mc = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]  # [C,N,3]
    cov_c = torch.einsum("cij,njk,clk->cnil", rot, covariance_3d(quats, scales), rot)  # [C,N,3,3]

    x, y, z = mc.unbind(-1)
    in_depth = (z >= near_plane) & (z <= far_plane)
    one = torch.ones((), dtype=z.dtype, device=z.device)
    zs = torch.where(in_depth, z, one)
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]

    # Jacobian evaluated at x/z, y/z clamped to 1.3x the field of view.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp = (width - cx) / fx + FOV_CLAMP_MARGIN * tan_x
    lim_xn = cx / fx + FOV_CLAMP_MARGIN * tan_x
    lim_yp = (height - cy) / fy + FOV_CLAMP_MARGIN * tan_y
    lim_yn = cy / fy + FOV_CLAMP_MARGIN * tan_y
    tx = zs * torch.minimum(lim_xp, torch.maximum(-lim_xn, x / zs))
    ty = zs * torch.minimum(lim_yp, torch.maximum(-lim_yn, y / zs))
    rz = 1.0 / zs
    zero = torch.zeros_like(zs)
    jac = torch.stack([fx * rz, zero, -fx * tx * rz * rz, zero, fy * rz, -fy * ty * rz * rz], dim=-1).reshape(
        zs.shape + (2, 3)
    )
    cov2d = jac @ cov_c @ jac.transpose(-1, -2)  # [C,N,2,2]
    mean2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)

    return z, in_depth, cov2d, mean2d


def antialias_compensation(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    eps2d: float = EPS2D,
) -> torch.Tensor:
    """Opacity factor ``[C,N]`` of gsplat's "antialiased" mode: ``sqrt(det(S) / det(S + eps2d I))`` for the
    screen covariance ``S``, so the low-pass dilation spreads a small Gaussian's energy instead of adding
    to it (Mip-Splatting's 2D filter). About 1 for large Gaussians; differentiable."""
    _z, in_depth, cov2d, _ = _screen_covariance(means, quats, scales, viewmats, Ks, width, height, 0.01, 1e10)
    a, c = cov2d[..., 0, 0], cov2d[..., 1, 1]
    b = 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0])
    det = (a * c - b * b).clamp_min(0.0)
    det_eps = (a + eps2d) * (c + eps2d) - b * b
    ok = in_depth & (det_eps > 0)
    ratio = torch.where(ok, det / torch.where(ok, det_eps, torch.ones_like(det_eps)), torch.ones_like(det))
    return ratio.clamp(0.0, 1.0).add(1e-12).sqrt()
