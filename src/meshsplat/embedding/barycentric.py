"""Barycentric coordinates on triangles: weights, interpolation, projection onto the triangle.

Convention: for ``faces[k] = (a, b, c)``, ``u`` weights ``a``, ``v`` weights ``b`` and
``w = 1 - u - v`` weights ``c``. ``uv`` outside the triangle (a component < 0) extrapolates the face.
"""

from __future__ import annotations

import torch

__all__ = ["barycentric_weights", "gather_rows", "interpolate", "surface_points", "project_uv_to_triangle"]


def barycentric_weights(uv: torch.Tensor) -> torch.Tensor:
    """``uv [..., 2]`` -> ``(u, v, 1-u-v) [..., 3]``."""
    return torch.cat([uv, 1.0 - uv.sum(-1, keepdim=True)], dim=-1)


def gather_rows(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values[index]`` for ``values [V,...]`` and any long ``index`` -> ``[*index.shape, ...]``, through
    ``index_select``: its backward sums in a fixed order, where ``values[index]``'s scatters with atomics on
    CPU and is not bit-reproducible on several threads (pose refinement's gradients reach the vertices)."""
    return values.index_select(0, index.reshape(-1)).view(*index.shape, *values.shape[1:])


def interpolate(values: torch.Tensor, faces: torch.Tensor, face: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Blend per-vertex ``values [V,C]`` at the points ``(face [N], weights [N,3])`` -> ``[N,C]``."""
    corners = gather_rows(values, faces[face])  # [N,3,C]
    return (weights.unsqueeze(-1).to(corners.dtype) * corners).sum(-2)


def surface_points(verts: torch.Tensor, faces: torch.Tensor, face: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Points ``[N,3]`` at ``uv [N,2]`` on the flat triangles ``faces[face]`` of ``verts [V,3]``."""
    return interpolate(verts, faces, face, barycentric_weights(uv))


def project_uv_to_triangle(uv: torch.Tensor) -> torch.Tensor:
    """``uv [N,2]`` -> the nearest point (in (u, v, w) space) of the triangle ``u, v, w >= 0``, as ``[N,2]``.

    Euclidean projection onto the probability simplex of (u, v, 1-u-v); differentiable almost
    everywhere (zero gradient along clipped directions).
    """
    bary = barycentric_weights(uv)
    srt, _ = bary.sort(dim=-1, descending=True)
    css = srt.cumsum(-1) - 1
    ks = torch.arange(1, 4, device=uv.device, dtype=uv.dtype)
    cond = srt - css / ks > 0
    rho = cond.to(torch.int64).cumsum(-1).argmax(-1, keepdim=True)  # last index where cond holds
    theta = css.gather(-1, rho) / (rho + 1).to(uv.dtype)
    return (bary - theta).clamp_min(0)[..., :2]
