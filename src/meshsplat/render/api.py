"""Public entry point: validated, backend-dispatching Gaussian rasterization."""

from __future__ import annotations

from typing import Any

import torch

from meshsplat._checks import check_same_device, check_tensor
from meshsplat.errors import MeshsplatError
from meshsplat.render.backends import gsplat_available, numba_available
from meshsplat.render.backends.gsplat_cuda import rasterize_gsplat
from meshsplat.render.backends.numba_cpu import rasterize_numba
from meshsplat.render.backends.torch_ref import rasterize_torch
from meshsplat.render.types import RenderOutput

__all__ = ["rasterize", "RENDER_MODES", "BACKENDS"]

RENDER_MODES = ("RGB", "RGB+ED")
BACKENDS = ("auto", "torch", "numba", "gsplat")
TORCH_OPTIONS = ("pair_budget", "saved_pair_limit", "grad_mode")


def _validate(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    backgrounds: torch.Tensor | None,
    render_mode: str,
    backend: str,
) -> None:
    dims: dict[str, int] = {}
    check_tensor("means", means, "N,3", dims, dtype="float", finite=True)
    check_tensor("quats", quats, "N,4", dims, dtype="float", finite=True)
    check_tensor("scales", scales, "N,3", dims, dtype="float", finite=True)
    check_tensor("opacities", opacities, "N", dims, dtype="float", finite=True)
    check_tensor("viewmats", viewmats, "C,4,4", dims, dtype="float", finite=True)
    check_tensor("Ks", Ks, "C,3,3", dims, dtype="float", finite=True)
    if isinstance(colors, torch.Tensor) and colors.dim() == 3:
        check_tensor("colors", colors, "C,N,D", dims, dtype="float", finite=True)
    else:
        check_tensor("colors", colors, "N,D", dims, dtype="float", finite=True)
    if backgrounds is not None:
        check_tensor("backgrounds", backgrounds, "C,D", dims, dtype="float", finite=True)
    check_same_device(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        backgrounds=backgrounds,
    )
    tensors = {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "colors": colors,
        "viewmats": viewmats,
        "Ks": Ks,
    }
    if backgrounds is not None:
        tensors["backgrounds"] = backgrounds
    dtypes = {k: v.dtype for k, v in tensors.items()}
    if len(set(dtypes.values())) > 1:
        listing = ", ".join(f"{k}={v}" for k, v in dtypes.items())
        raise MeshsplatError(f"all tensors must share one float dtype, got {listing}")
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise MeshsplatError(f"{name}: expected a positive int, got {v!r}")
    if not (0 <= float(near_plane) < float(far_plane)):
        raise MeshsplatError(f"near_plane/far_plane: expected 0 <= near < far, got {near_plane}, {far_plane}")
    if render_mode not in RENDER_MODES:
        raise MeshsplatError(f"render_mode: expected one of {RENDER_MODES}, got {render_mode!r}")
    if backend not in BACKENDS:
        raise MeshsplatError(f"backend: expected one of {BACKENDS}, got {backend!r}")


def _pick_backend(backend: str, device: torch.device, dtype: torch.dtype = torch.float32) -> str:
    if backend == "torch":
        return "torch"
    if backend == "numba":
        if device.type != "cpu":
            raise MeshsplatError(
                f"backend='numba' needs CPU tensors, got tensors on {device}; use backend='torch' or 'auto'"
            )
        if dtype not in (torch.float32, torch.float64):
            raise MeshsplatError(f"backend='numba' needs float32 or float64 tensors, got {dtype}")
        if not numba_available():
            raise MeshsplatError(
                "backend='numba' needs numba, which did not import: pip install numba (or backend='torch')"
            )
        return "numba"
    if backend == "gsplat":
        if device.type != "cuda":
            raise MeshsplatError(
                f"backend='gsplat' needs CUDA tensors, got tensors on {device}; use backend='torch' or 'auto'"
            )
        if not gsplat_available():
            raise MeshsplatError("backend='gsplat' needs gsplat==1.5.3: pip install 'meshsplat[cuda]'")
        return "gsplat"
    if device.type == "cuda" and gsplat_available():
        return "gsplat"
    if device.type == "cpu" and dtype in (torch.float32, torch.float64) and numba_available():
        return "numba"
    return "torch"


def rasterize(
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
    backend: str = "auto",
    **backend_options: Any,
) -> RenderOutput:
    """Render 3D Gaussians into C pinhole cameras (gsplat 1.5.3 ``rasterization`` conventions).

    means [N,3], quats [N,4] (wxyz, any norm), scales [N,3], opacities [N] (post-sigmoid),
    colors [N,D] (or [C,N,D]), viewmats [C,4,4] world->camera (OpenCV axes), Ks [C,3,3],
    backgrounds [C,D] or None. render_mode "RGB" or "RGB+ED" (one extra channel: expected
    depth sum(w_i z_i) / max(alpha, 1e-10)). backend "auto" (gsplat for CUDA tensors when
    importable, numba for CPU tensors when importable, else torch), "torch", "numba" or "gsplat".
    ``backend_options`` go to the torch backend (``pair_budget``, ``saved_pair_limit``,
    ``grad_mode``; see ``rasterize_torch``); with ``backend="auto"`` they select the torch backend.

    Returns RenderOutput(colors [C,H,W,D'], alphas [C,H,W,1], meta) with meta["means2d"]
    [C,N,2] retaining its gradient, meta["radii"] [C,N,2] int32, meta["depths"] [C,N],
    meta["visible"] [C,N] bool, width, height, n_cameras.
    """
    _validate(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane,
        far_plane,
        backgrounds,
        render_mode,
        backend,
    )
    if backend == "auto" and backend_options:
        backend = "torch"  # the options tune the torch backend: the caller asked for it
    chosen = _pick_backend(backend, means.device, means.dtype)
    scene: dict[str, Any] = {  # one keyword set for every backend (all keyword-only)
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "colors": colors,
        "viewmats": viewmats,
        "Ks": Ks,
        "width": width,
        "height": height,
        "near_plane": near_plane,
        "far_plane": far_plane,
        "backgrounds": backgrounds,
        "render_mode": render_mode,
    }
    if chosen == "gsplat":  # backend_options tune the torch backend only
        return rasterize_gsplat(**scene)
    if chosen == "numba":
        if backend_options:
            raise MeshsplatError(f"backend='numba' takes no backend options, got {sorted(backend_options)}")
        return rasterize_numba(**scene)
    unknown = set(backend_options) - set(TORCH_OPTIONS)
    if unknown:
        raise MeshsplatError(f"unknown backend option(s) {sorted(unknown)}; known: {', '.join(TORCH_OPTIONS)}")
    return rasterize_torch(**scene, **backend_options)
