"""Compose renderable Gaussians from embedded parameters and one posed mesh.

``mu = embed(pose, face, uv + duv, d)``, ``q = delta_q ⊗ normalize(rotation)``,
``scale = exp(log_scale) * scale_factor``, ``opacity = sigmoid(opacity_logit)``,
``colour = max(0, 0.5 + SH(sh0, shN; view direction))``, times ``E(posed normal)`` when a
``Shading`` is given (then the SH colour is the albedo; see ``meshsplat.gaussians.shading``); a
shading with occlusion also reads the visibility of each Gaussian's surface point (at ``uv + duv``,
before the offset ``d``) from the posed mesh.

``sh_frame``: the frame the view direction is expressed in for SH degree > 0. ``"world"`` (the
published code); ``"triangle"``: rotated back by the embedding triangle's pose rotation, i.e. into
the canonical frame of the surface, so view-dependent colour turns with the surface.

The position uses ``uv + duv`` so that the trainable offsets receive gradients; between walks
``uv + duv`` may leave the triangle (linear extrapolation of the face). ``clamp_to_face=True``
(the no-walking ablation) projects ``uv + duv`` back onto the triangle instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meshsplat._numba import numba_available
from meshsplat.embedding import SCALE_MODES, check_embedded, embed, pose_frame, project_uv_to_triangle, surface_points
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians._compose_numba import compose_geometry_compiled
from meshsplat.gaussians.params import SH_C0, check_params
from meshsplat.gaussians.shading import Shading
from meshsplat.mesh import MeshPose
from meshsplat.mesh.quaternion import quat_multiply, quat_normalize, quat_to_matrix

__all__ = ["ComposedGaussians", "compose", "effective_uv", "eval_sh", "SH_FRAMES"]

SH_FRAMES = ("world", "triangle")

_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


@dataclass
class ComposedGaussians:
    means: torch.Tensor  # [N,3]
    quats: torch.Tensor  # [N,4] wxyz, unit
    scales: torch.Tensor  # [N,3]
    opacities: torch.Tensor  # [N]
    colors: torch.Tensor  # [N,3]

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def detach(self) -> ComposedGaussians:
        return ComposedGaussians(
            *(t.detach() for t in (self.means, self.quats, self.scales, self.opacities, self.colors))
        )


def effective_uv(params: dict[str, torch.Tensor], clamp_to_face: bool = False) -> torch.Tensor:
    """``uv + duv`` [N,2] (projected onto the triangle when ``clamp_to_face``)."""
    uv = params["uv"] + params["duv"]
    return project_uv_to_triangle(uv) if clamp_to_face else uv


def eval_sh(sh0: torch.Tensor, shN: torch.Tensor | None, dirs: torch.Tensor | None) -> torch.Tensor:
    """Colour [N,3] = 0.5 + sum_l SH_l(dirs) * coeffs, clamped at 0. ``dirs`` [N,3] (any length).

    Without ``dirs`` only the DC band is used (the view-independent colour).
    """
    rgb = SH_C0 * sh0[:, 0]
    if shN is not None and shN.shape[1] > 0 and dirs is not None:
        x, y, z = torch.nn.functional.normalize(dirs, dim=-1).unbind(-1)
        x, y, z = x[:, None], y[:, None], z[:, None]
        k = shN.shape[1]
        rgb = rgb - _C1 * y * shN[:, 0] + _C1 * z * shN[:, 1] - _C1 * x * shN[:, 2]
        if k >= 8:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            rgb = (
                rgb
                + _C2[0] * xy * shN[:, 3]
                + _C2[1] * yz * shN[:, 4]
                + _C2[2] * (2 * zz - xx - yy) * shN[:, 5]
                + _C2[3] * xz * shN[:, 6]
                + _C2[4] * (xx - yy) * shN[:, 7]
            )
            if k >= 15:
                rgb = (
                    rgb
                    + _C3[0] * y * (3 * xx - yy) * shN[:, 8]
                    + _C3[1] * xy * z * shN[:, 9]
                    + _C3[2] * y * (4 * zz - xx - yy) * shN[:, 10]
                    + _C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * shN[:, 11]
                    + _C3[4] * x * (4 * zz - xx - yy) * shN[:, 12]
                    + _C3[5] * z * (xx - yy) * shN[:, 13]
                    + _C3[6] * x * (xx - 3 * yy) * shN[:, 14]
                )
    return (rgb + 0.5).clamp_min(0.0)


def compose(
    params: dict[str, torch.Tensor],
    pose: MeshPose,
    scale_mode: str = "sqrt_area",
    *,
    campos: torch.Tensor | None = None,
    clamp_to_face: bool = False,
    shading: Shading | None = None,
    sh_frame: str = "world",
    compiled: bool | None = None,
) -> ComposedGaussians:
    """Renderable Gaussians for one posed mesh (``pose``: a ``MeshPose``).

    campos [3]: camera centre for view-dependent colour (SH degree > 0); without it only the
    DC band is used. shading: a ``Shading`` (colour = SH colour * irradiance of the posed normal).
    sh_frame: "world" | "triangle" (see the module docstring). compiled: the means, rotations and scales
    by numba's kernels (``gaussians._compose_numba``, the same values to rounding) instead of torch's
    operations, and the shading's irradiance likewise; default: on CPU when numba is available.
    """
    check_params(params)
    if scale_mode not in SCALE_MODES:
        raise MeshsplatError(f"scale_mode: expected one of {SCALE_MODES}, got {scale_mode!r}")
    face = params["face"]
    uv = effective_uv(params, clamp_to_face)
    if sh_frame not in SH_FRAMES:
        raise MeshsplatError(f"sh_frame: expected one of {SH_FRAMES}, got {sh_frame!r}")
    if compiled is None:
        compiled = uv.device.type == "cpu" and pose.verts.device.type == "cpu" and numba_available()
    points = None  # the surface points (at uv + duv, before the offset d), for the shading's visibility
    if compiled:
        check_embedded(pose, face, uv)
        means, normals, quats, scales, delta_q, points = compose_geometry_compiled(
            pose.verts, pose.vertex_normals, pose.vertex_quats, pose.area_ratio, pose.faces,
            face, uv, params["d"], params["rotation"], params["log_scale"], scale_mode,
        )  # fmt: skip
    else:
        means, normals = embed(pose, face, uv, params["d"])
        delta_q, scale_factor = pose_frame(pose, face, uv, scale_mode=scale_mode)
        quats = quat_normalize(quat_multiply(delta_q, quat_normalize(params["rotation"])))
        scales = params["log_scale"].exp() * scale_factor.reshape(-1, 1)
    opacities = torch.sigmoid(params["opacity_logit"])
    dirs = None
    if "shN" in params and campos is not None:
        dirs = means - campos.to(means).reshape(1, 3)
        if sh_frame == "triangle":  # world -> canonical surface frame: R(delta_q)^T dirs
            dirs = (quat_to_matrix(delta_q).transpose(-1, -2) @ dirs.unsqueeze(-1))[..., 0]
    colors = eval_sh(params["sh0"], params.get("shN"), dirs)
    if shading is not None:
        visible = None
        if shading.occlusion != "none":
            with torch.no_grad():
                if points is None:
                    points = surface_points(pose.verts.detach(), pose.faces, face, uv.detach())
                visible = shading.visibility(pose, points, normals.detach())
        colors = shading.shade(colors, normals, quats, scales, visible, compiled)
    return ComposedGaussians(means, quats, scales, opacities, colors)
