"""Random scenes and gradient helpers shared by the rasterizer parity tests."""

from __future__ import annotations

import torch

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def random_scene(n=40, seed=0, dtype=torch.float64, width=32, height=24):
    """Random anisotropic Gaussians + a stack of opaque ones (forces T < 1e-4), 3 cameras:
    one outside, one oblique, one inside the cloud (behind-camera and off-screen splats)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.6
    means[:8] = (
        torch.tensor([0.05, -0.02, 0.0], dtype=torch.float64) + 0.01 * torch.arange(8.0, dtype=torch.float64)[:, None]
    )
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64) * 2.0
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.15 + 0.02
    scales[:8] = 0.2
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05
    opac[:8] = 0.95
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    viewmats = torch.stack(
        [look_at([0, 0, -3], [0, 0, 0]), look_at([2.5, 0.5, -1], [0, 0, 0]), look_at([0.1, 0, 0.3], [0, 0, 3])]
    )
    K = torch.tensor(
        [[1.3 * width, 0, width / 2 + 0.3], [0, 1.25 * width, height / 2 - 0.2], [0, 0, 1]], dtype=torch.float64
    )
    bg = torch.rand(3, 3, generator=g, dtype=torch.float64)
    scene = dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opac,
        colors=colors,
        viewmats=viewmats,
        Ks=K.expand(3, 3, 3).clone(),
        width=width,
        height=height,
        backgrounds=bg,
    )
    return {k: (v.to(dtype) if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}


def _with_grad(scene, names=PARAMS + ("backgrounds",)):
    return {k: (v.clone().requires_grad_(True) if k in names else v) for k, v in scene.items()}


def _loss(colors, alphas, seed=1):
    g = torch.Generator().manual_seed(seed)
    wc = torch.randn(colors.shape, generator=g, dtype=colors.dtype)
    wa = torch.randn(alphas.shape, generator=g, dtype=alphas.dtype)
    return (colors * wc).sum() + (alphas * wa).sum()


def _gradcheck_scene():
    """3 well-separated-ish Gaussians, inside the view, opacities < 0.9, 2 cameras."""
    means = torch.tensor([[0.0, 0.0, 0.0], [0.25, 0.1, 0.3], [-0.2, -0.15, -0.2]], dtype=torch.float64)
    quats = torch.tensor([[0.9, 0.2, -0.3, 0.1], [0.5, 0.5, 0.1, -0.6], [1.0, 0.0, 0.3, 0.2]], dtype=torch.float64)
    scales = torch.tensor([[0.12, 0.06, 0.09], [0.08, 0.15, 0.05], [0.1, 0.07, 0.11]], dtype=torch.float64)
    opac = torch.tensor([0.8, 0.6, 0.7], dtype=torch.float64)
    colors = torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9]], dtype=torch.float64)
    viewmats = torch.stack([look_at([0.1, 0.05, -2.0], [0, 0, 0]), look_at([1.6, 0.3, -1.2], [0, 0, 0])])
    K = torch.tensor([[22.0, 0, 8.3], [0, 21.0, 6.1], [0, 0, 1]], dtype=torch.float64).expand(2, 3, 3).clone()
    bg = torch.tensor([[0.3, 0.4, 0.5], [0.6, 0.2, 0.1]], dtype=torch.float64)
    return means, quats, scales, opac, colors, viewmats, K, bg


def look_at(eye, target, dtype=torch.float64):
    eye, target = torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    f = (target - eye) / (target - eye).norm()
    r = torch.linalg.cross(f, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    r = r / r.norm()
    R = torch.stack([r, torch.linalg.cross(f, r), f])
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3], V[:3, 3] = R, -R @ eye
    return V.to(dtype)
