"""Synthetic scenes for the rasterizer benchmark and preview (no assets needed)."""

from __future__ import annotations

import math

import torch

from meshsplat.mesh.quaternion import matrix_to_quat

__all__ = ["avatar_scene", "binned_geometry", "look_at", "ring_scene"]

# (centre, radii) of ellipsoids roughly shaped like a standing person, metres, y up.
_BODY = [
    ((0.0, 0.15, 0.0), (0.17, 0.28, 0.11)),  # torso
    ((0.0, 0.58, 0.0), (0.10, 0.12, 0.10)),  # head
    ((-0.09, -0.55, 0.0), (0.07, 0.42, 0.07)),  # legs
    ((0.09, -0.55, 0.0), (0.07, 0.42, 0.07)),
    ((-0.28, 0.12, 0.0), (0.05, 0.30, 0.05)),  # arms
    ((0.28, 0.12, 0.0), (0.05, 0.30, 0.05)),
]


def look_at(eye, target, up=(0.0, 1.0, 0.0), dtype=torch.float32) -> torch.Tensor:
    """World->camera 4x4 (OpenCV: x right, y down, z forward) for a camera at eye."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    f = target - eye
    f = f / f.norm()
    r = torch.linalg.cross(f, up)
    r = r / r.norm()
    d = torch.linalg.cross(f, r)
    R = torch.stack([r, d, f])
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V.to(dtype)


def _ellipsoid_area(r) -> float:
    a, b, c = r
    p = 1.6075
    return 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)


def avatar_scene(n: int, size: int, seed: int = 0, dtype=torch.float32, framing: str = "upper_body"):
    """n surface-aligned Gaussians on a person-sized body seen by one size x size camera.

    framing "upper_body" (~half the image covered, footprints ~5-25 px at 256 px) or
    "full_body" (~12% covered). Returns dict of rasterize() keyword arguments.
    """
    g = torch.Generator().manual_seed(seed)
    areas = torch.tensor([_ellipsoid_area(r) for _, r in _BODY])
    part = torch.multinomial(areas / areas.sum(), n, replacement=True, generator=g)
    centre = torch.tensor([c for c, _ in _BODY])[part]
    radii = torch.tensor([r for _, r in _BODY])[part]
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    pts = centre + radii * d
    normal = d / radii
    normal = normal / normal.norm(dim=1, keepdim=True)
    tangent = torch.linalg.cross(normal, torch.randn(n, 3, generator=g))
    tangent = tangent / tangent.norm(dim=1, keepdim=True)
    frame = torch.stack([tangent, torch.linalg.cross(normal, tangent), normal], dim=-1)
    spacing = math.sqrt(float(areas.sum()) / n)
    scales = torch.stack(
        [
            spacing * (0.4 + 0.5 * torch.rand(n, generator=g)),
            spacing * (0.4 + 0.5 * torch.rand(n, generator=g)),
            torch.full((n,), spacing * 0.08),
        ],
        dim=1,
    )
    # camera 2.6 m away; full body: 1.7 m over ~80% of the height; upper body: ~0.95 m field
    fy, look_y = (1.2 * size, -0.1) if framing == "full_body" else (2.7 * size, 0.3)
    K = torch.tensor([[fy, 0, size / 2], [0, fy, size / 2], [0, 0, 1]])
    return {
        "means": pts.to(dtype),
        "quats": matrix_to_quat(frame).to(dtype),
        "scales": scales.to(dtype),
        "opacities": (0.5 + 0.49 * torch.rand(n, generator=g)).to(dtype),
        "colors": torch.rand(n, 3, generator=g).to(dtype),
        "viewmats": look_at((0.0, look_y + 0.2, 2.6), (0.0, look_y, 0.0))[None].to(dtype),
        "Ks": K[None].to(dtype),
        "width": size,
        "height": size,
        "backgrounds": torch.ones(1, 3, dtype=dtype),
    }


def ring_scene(size: int = 256, n: int = 10, dtype=torch.float32):
    """A tilted ring of n coloured anisotropic Gaussians around three overlapping discs
    (red nearest, then green, then blue: red must cover green, green cover blue)."""
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    ring = torch.stack([torch.cos(t), 0.2 * torch.sin(2 * t), torch.sin(t)], dim=1)
    half = -0.5 * t + math.pi / 4  # long axis along the ring tangent (rotation about y)
    ring_q = torch.stack([torch.cos(half), torch.zeros_like(t), torch.sin(half), torch.zeros_like(t)], 1)
    ring_s = torch.tensor([[0.24, 0.07, 0.04]], dtype=torch.float64).expand(n, 3)
    hue = t[:, None] + torch.tensor([0.0, 2.1, 4.2], dtype=torch.float64)
    ring_c = 0.5 + 0.5 * torch.cos(hue)
    eye = torch.tensor([0.0, 1.2, -2.6], dtype=torch.float64)
    view_dir = -eye / eye.norm()
    side = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    discs = torch.stack([-0.4 * view_dir - 0.3 * side, 0.0 * view_dir, 0.4 * view_dir + 0.3 * side])
    disc_q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).expand(3, 4)
    disc_s = torch.tensor([[0.17, 0.17, 0.17]], dtype=torch.float64).expand(3, 3)
    disc_c = torch.eye(3, dtype=torch.float64)
    fy = 0.75 * size
    K = torch.tensor([[fy, 0, size / 2], [0, fy, size / 2], [0, 0, 1]], dtype=torch.float64)
    return {
        "means": torch.cat([ring, discs]).to(dtype),
        "quats": torch.cat([ring_q, disc_q]).to(dtype),
        "scales": torch.cat([ring_s, disc_s]).to(dtype).contiguous(),
        "opacities": torch.full((n + 3,), 0.97, dtype=dtype),
        "colors": torch.cat([ring_c, disc_c]).to(dtype),
        "viewmats": look_at(tuple(eye.tolist()), (0.0, 0.0, 0.0))[None].to(dtype),
        "Ks": K[None].to(dtype),
        "width": size,
        "height": size,
        "backgrounds": torch.full((1, 3), 0.08, dtype=dtype),
    }


def binned_geometry(scene):
    """A scene's one camera projected and binned by the numba backend: its ``_Geometry`` (no-grad state), as the
    compositing kernels take it."""
    from meshsplat.render.backends import numba_cpu as nc

    k = nc._kernels()
    s = scene
    proj = nc.project_numba(
        (k.project, k.project_backward), s["means"], s["quats"], s["scales"], s["opacities"],
        s["viewmats"], s["Ks"], s["width"], s["height"], 0.01, 1e10,
    )  # fmt: skip
    geo = nc._Geometry(proj, s["means"].shape[0], s["colors"].dim() == 2, s["width"], s["height"], nc.TILE_SIZE)
    geo.bin(s["opacities"], s["colors"])
    return geo
