"""Per-Gaussian parameters, stored pre-activation in a plain ``dict[str, Tensor]``.

Trainable (``torch.nn.Parameter``, one optimizer per key):
    ``rotation [N,4]``      canonical rotation q̄, wxyz, normalized on use
    ``log_scale [N,3]``     canonical log-scale s̄
    ``opacity_logit [N]``   opacity = sigmoid(opacity_logit)
    ``sh0 [N,1,3]``         colour as the SH DC term: rgb = 0.5 + C0 * sh0 (3DGS/.ply convention)
    ``shN [N,K,3]``         higher SH bands, K = (deg+1)^2 - 1; absent when sh_degree == 0
    ``duv [N,2]``           trainable barycentric offset (δu, δv), folded into ``uv`` by walking
    ``d [N]``               displacement along the Phong normal
Embedding state (plain tensors, no gradient): ``face [N] long``, ``uv [N,2]``.

The rendered position uses ``uv + duv``; with ``trainable_embedding=False`` (ablation) ``duv``
and ``d`` are kept as frozen zero tensors.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat.embedding import sample_surface, surface_points
from meshsplat.errors import MeshsplatError
from meshsplat.mesh import TriMesh

__all__ = [
    "SH_C0",
    "PARAM_KEYS",
    "EMBEDDING_STATE_KEYS",
    "num_sh_rest",
    "rgb_to_sh0",
    "sh0_to_rgb",
    "knn_scales",
    "make_params",
    "init_params",
    "check_params",
    "num_gaussians",
    "sh_degree_of",
]

SH_C0 = 0.28209479177387814
PARAM_KEYS = ("rotation", "log_scale", "opacity_logit", "sh0", "shN", "duv", "d")
EMBEDDING_STATE_KEYS = ("face", "uv")


def num_sh_rest(sh_degree: int) -> int:
    return (sh_degree + 1) ** 2 - 1


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """[N,3] colour in [0,1] -> [N,1,3] DC coefficient."""
    return ((rgb - 0.5) / SH_C0)[:, None, :]


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """[N,1,3] -> [N,3] (not clamped)."""
    return sh0[:, 0, :] * SH_C0 + 0.5


def knn_scales(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """[N,3] -> [N] sqrt of the mean squared distance to the k nearest other points (3DGS init)."""
    from scipy.spatial import cKDTree

    pts = points.detach().double().cpu().numpy()
    n = pts.shape[0]
    if n < 2:
        return torch.full((n,), 1e-2, dtype=points.dtype, device=points.device)
    kk = min(k, n - 1)
    dist, _ = cKDTree(pts).query(pts, k=kk + 1)
    dist = np.asarray(dist).reshape(n, kk + 1)[:, 1:]
    mean_sq = (dist**2).mean(axis=1)
    out = np.sqrt(np.maximum(mean_sq, 1e-14))
    return torch.from_numpy(out).to(points)


def make_params(
    face: torch.Tensor,
    uv: torch.Tensor,
    *,
    d: torch.Tensor | None = None,
    duv: torch.Tensor | None = None,
    log_scale: torch.Tensor,
    rotation: torch.Tensor | None = None,
    opacity_logit: torch.Tensor,
    sh0: torch.Tensor,
    shN: torch.Tensor | None = None,
    trainable_embedding: bool = True,
) -> dict[str, torch.Tensor]:
    """Assemble a parameter dict from tensors (copied; trainable ones wrapped as Parameters)."""
    n = face.shape[0]
    dev, dt = uv.device, uv.dtype
    rotation = rotation if rotation is not None else torch.tensor([1.0, 0, 0, 0], device=dev, dtype=dt).repeat(n, 1)
    d = d if d is not None else torch.zeros(n, device=dev, dtype=dt)
    duv = duv if duv is not None else torch.zeros(n, 2, device=dev, dtype=dt)
    P = torch.nn.Parameter
    params: dict[str, torch.Tensor] = {
        "rotation": P(rotation.detach().clone()),
        "log_scale": P(log_scale.detach().clone()),
        "opacity_logit": P(opacity_logit.detach().clone()),
        "sh0": P(sh0.detach().clone()),
    }
    if shN is not None and shN.shape[1] > 0:
        params["shN"] = P(shN.detach().clone())
    params["duv"] = P(duv.detach().clone(), requires_grad=trainable_embedding)
    params["d"] = P(d.detach().clone(), requires_grad=trainable_embedding)
    params["face"] = face.detach().clone().long()
    params["uv"] = uv.detach().clone()
    check_params(params)
    return params


def init_params(
    mesh: TriMesh,
    n: int = 10_000,
    *,
    sh_degree: int = 0,
    init_opacity: float = 0.1,
    knn: int = 3,
    colors_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    generator: torch.Generator | None = None,
    trainable_embedding: bool = True,
) -> dict[str, torch.Tensor]:
    """Paper initialisation on the canonical ``mesh`` (a ``TriMesh``).

    ``n`` area-weighted samples (face, uv), d = 0, duv = 0, identity rotation, isotropic scale
    from the mean distance to the ``knn`` nearest neighbours, opacity ``init_opacity``,
    colour grey, or ``colors_fn(face [N], uv [N,2]) -> [N,3]`` in [0,1] when given (e.g. the
    colour of the embedded point projected into a first training image).
    """
    if n < 1:
        raise MeshsplatError(f"n: expected at least 1 Gaussian, got {n}")
    verts, faces = mesh.vertices, mesh.faces
    face, uv = sample_surface(verts, faces, n, generator=generator)
    face = face.to(verts.device).long()
    uv = uv.to(verts)
    means = surface_points(verts, faces, face, uv)
    scale = knn_scales(means, knn)
    rgb = torch.full((n, 3), 0.5, dtype=verts.dtype, device=verts.device)
    if colors_fn is not None:
        rgb = colors_fn(face, uv).to(rgb).clamp(0.0, 1.0)
    logit = math.log(init_opacity / (1.0 - init_opacity))
    k = num_sh_rest(sh_degree)
    return make_params(
        face,
        uv,
        log_scale=scale.log()[:, None].repeat(1, 3),
        opacity_logit=torch.full((n,), logit, dtype=verts.dtype, device=verts.device),
        sh0=rgb_to_sh0(rgb),
        shN=torch.zeros(n, k, 3, dtype=verts.dtype, device=verts.device) if k > 0 else None,
        trainable_embedding=trainable_embedding,
    )


def num_gaussians(params: dict[str, torch.Tensor]) -> int:
    return int(params["face"].shape[0])


def sh_degree_of(params: dict[str, torch.Tensor]) -> int:
    k = params["shN"].shape[1] if "shN" in params else 0
    return round(math.sqrt(k + 1)) - 1


def check_params(params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Validate keys, shapes and dtypes of a parameter dict; returns it."""
    if not isinstance(params, dict):
        raise MeshsplatError(f"params: expected a dict of tensors, got {type(params).__name__}")
    required = ("rotation", "log_scale", "opacity_logit", "sh0", "duv", "d", "face", "uv")
    missing = [k for k in required if k not in params]
    if missing:
        raise MeshsplatError(f"params: missing key(s) {', '.join(missing)}")
    unknown = [k for k in params if k not in PARAM_KEYS + EMBEDDING_STATE_KEYS]
    if unknown:
        raise MeshsplatError(f"params: unknown key(s) {', '.join(unknown)}")
    dims: dict[str, int] = {}
    check_tensor("params['face']", params["face"], "N", dims, dtype="int")
    check_tensor("params['uv']", params["uv"], "N,2", dims, dtype="float")
    check_tensor("params['duv']", params["duv"], "N,2", dims, dtype="float")
    check_tensor("params['d']", params["d"], "N", dims, dtype="float")
    check_tensor("params['rotation']", params["rotation"], "N,4", dims, dtype="float")
    check_tensor("params['log_scale']", params["log_scale"], "N,3", dims, dtype="float")
    check_tensor("params['opacity_logit']", params["opacity_logit"], "N", dims, dtype="float")
    check_tensor("params['sh0']", params["sh0"], "N,1,3", dims, dtype="float")
    if "shN" in params:
        check_tensor("params['shN']", params["shN"], "N,K,3", dims, dtype="float")
        k = params["shN"].shape[1]
        if k not in (3, 8, 15):
            raise MeshsplatError(f"params['shN']: K must be 3, 8 or 15 (SH degree 1..3), got {k}")
    return params
