"""gsplat 1.5.3 CUDA backend, mapped to the RenderOutput/meta contract.

gsplat is imported lazily inside :func:`rasterize_gsplat`, which :func:`meshsplat.render.rasterize`
only calls for CUDA tensors.
"""

from __future__ import annotations

import torch

from meshsplat.errors import MeshsplatError
from meshsplat.render._constants import EPS2D
from meshsplat.render.types import RenderOutput

__all__ = ["rasterize_gsplat"]


def _import_gsplat():
    try:
        import gsplat
    except Exception as exc:  # ImportError, or a failed JIT build
        raise MeshsplatError(f"gsplat could not be imported ({exc}); use backend='torch'") from exc
    return gsplat


def rasterize_gsplat(
    *,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
) -> RenderOutput:
    """Arguments as :func:`meshsplat.render.rasterize` (validated there); CUDA tensors only."""
    if means.device.type != "cuda":
        raise MeshsplatError(f"the gsplat backend needs CUDA tensors, got {means.device}")
    gsplat = _import_gsplat()
    img, alphas, info = gsplat.rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        int(width),
        int(height),
        near_plane=near_plane,
        far_plane=far_plane,
        radius_clip=0.0,
        eps2d=EPS2D,
        sh_degree=None,
        packed=False,
        tile_size=16,
        backgrounds=backgrounds,
        render_mode=render_mode,
        rasterize_mode="classic",
        absgrad=False,
        sparse_grad=False,
    )
    means2d = info["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = info["radii"]
    if radii.dim() == 2:  # older layouts: one isotropic radius
        radii = radii[..., None].expand(*radii.shape, 2)
    radii = radii.to(torch.int32)
    meta = {
        "means2d": means2d,
        "radii": radii,
        "depths": info["depths"],
        "conics": info.get("conics"),
        "visible": (radii > 0).any(dim=-1),
        "width": int(width),
        "height": int(height),
        "n_cameras": int(viewmats.shape[0]),
        "backend": "gsplat",
        "gsplat_info": info,
    }
    return RenderOutput(img, alphas, meta)
