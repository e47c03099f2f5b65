"""Brute-force rasterizer for tests only: every pixel against every Gaussian.

Written plainly and independently of ``torch_ref``: per camera, Gaussians are
visited in depth order and composited front to back with a multiplicative
transmittance, applying only the near/far cull and the same alpha/transmittance
rules. Differentiable by autograd. O(C * N * H * W) time: tiny scenes only.
"""

from __future__ import annotations

import torch

from meshsplat.render._constants import (
    ALPHA_MAX,
    ALPHA_THRESHOLD,
    DEPTH_ALPHA_MIN,
    EPS2D,
    FOV_CLAMP_MARGIN,
    PIXEL_CENTER,
    TRANSMITTANCE_MIN,
)

__all__ = ["rasterize_dense"]


def _rotation(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = (q / q.norm()).unbind()
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )


def _splat(mean, quat, scale, viewmat, K, width, height):
    """One Gaussian in one camera -> (camera point [3], pixel mean [2], 2D covariance [2,2])."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = R @ mean + t
    M = _rotation(quat) @ torch.diag(scale)
    cov_cam = R @ (M @ M.T) @ R.T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x, y, z = p
    tx_lim = (-(cx / fx + FOV_CLAMP_MARGIN * 0.5 * width / fx), (width - cx) / fx + FOV_CLAMP_MARGIN * 0.5 * width / fx)
    ty_lim = (
        -(cy / fy + FOV_CLAMP_MARGIN * 0.5 * height / fy),
        (height - cy) / fy + FOV_CLAMP_MARGIN * 0.5 * height / fy,
    )
    u = torch.clamp(x / z, min=tx_lim[0], max=tx_lim[1])
    v = torch.clamp(y / z, min=ty_lim[0], max=ty_lim[1])
    zero = torch.zeros_like(z)
    J = torch.stack(
        [
            torch.stack([fx / z, zero, -fx * u / z]),
            torch.stack([zero, fy / z, -fy * v / z]),
        ]
    )
    cov2d = J @ cov_cam @ J.T + EPS2D * torch.eye(2, dtype=z.dtype, device=z.device)
    return p, torch.stack([fx * x / z + cx, fy * y / z + cy]), cov2d


def rasterize_dense(
    means,
    quats,
    scales,
    opacities,
    colors,
    viewmats,
    Ks,
    width,
    height,
    near_plane=0.01,
    far_plane=1e10,
    backgrounds=None,
    render_mode="RGB",
):
    """Same arguments as ``rasterize`` (colors [N,D]); returns (colors [C,H,W,D'], alphas [C,H,W,1])."""
    dtype, dev = means.dtype, means.device
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=dev) + PIXEL_CENTER,
        torch.arange(width, dtype=dtype, device=dev) + PIXEL_CENTER,
        indexing="ij",
    )
    images, alphas = [], []
    for c in range(viewmats.shape[0]):
        splats = []
        for n in range(means.shape[0]):
            p, m2d, cov = _splat(means[n], quats[n], scales[n], viewmats[c], Ks[c], width, height)
            if near_plane <= float(p[2].detach()) <= far_plane:
                splats.append((float(p[2].detach()), n, p[2], m2d, cov))
        splats.sort(key=lambda s: s[0])
        D = colors.shape[1] + (1 if render_mode == "RGB+ED" else 0)
        out = torch.zeros(height, width, D, dtype=dtype, device=dev)
        T = torch.ones(height, width, dtype=dtype, device=dev)
        done = torch.zeros(height, width, dtype=torch.bool, device=dev)
        for _, n, z, m2d, cov in splats:
            color = colors[n] if render_mode == "RGB" else torch.cat([colors[n], z[None]])
            conic = torch.linalg.inv(cov)
            dx, dy = m2d[0] - xs, m2d[1] - ys
            sigma = 0.5 * (conic[0, 0] * dx * dx + conic[1, 1] * dy * dy) + conic[0, 1] * dx * dy
            alpha = torch.clamp(opacities[n] * torch.exp(-sigma), max=ALPHA_MAX)
            used = (alpha >= ALPHA_THRESHOLD) & (sigma >= 0) & ~done
            next_T = T * (1 - alpha)
            stop = used & (next_T <= TRANSMITTANCE_MIN)
            done = done | stop
            used = used & ~stop
            out = out + torch.where(used[..., None], (alpha * T)[..., None] * color, 0.0)
            T = torch.where(used, next_T, T)
        if backgrounds is not None:
            bg = backgrounds[c] if render_mode == "RGB" else torch.cat([backgrounds[c], backgrounds[c][:1] * 0])
            out = out + T[..., None] * bg
        alpha_img = (1 - T)[..., None]
        if render_mode == "RGB+ED":
            out = torch.cat([out[..., :-1], out[..., -1:] / alpha_img.clamp(min=DEPTH_ALPHA_MIN)], dim=-1)
        images.append(out)
        alphas.append(alpha_img)
    return torch.stack(images), torch.stack(alphas)
