"""Pose-dependent shading: per-Gaussian albedo times a learned illumination shared by the avatar.

With shading on, a Gaussian's SH colour (``sh0``/``shN``) is its *albedo* and the displayed colour is

    colour = albedo * E(n)

where ``n [N,3]`` is the Gaussian's posed normal and ``E`` is second-order spherical-harmonic
irradiance in world space (9 coefficients per channel, ``coeffs [9,3]``; Ramamoorthi & Hanrahan's
form, the 9 real SH basis functions evaluated at ``n``). As the mesh moves, ``n`` turns with it, so
the shading follows the motion while the albedo stays fixed. ``coeffs`` starts at E = 1 (white,
uniform light) so the untrained model equals the unshaded one.

Normals (``normal``): ``"phong"`` - the interpolated vertex normal of the embedding on the posed
mesh (smooth, follows the surface); ``"axis"`` - the Gaussian's own shortest posed axis, signed to
face the same side as the Phong normal (follows the flattened splat).
"""

from __future__ import annotations

from typing import Any

import torch

from meshsplat._typing import Device
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.quaternion import quat_to_matrix

__all__ = ["Shading", "SHADING_MODES", "SHADING_NORMALS", "sh9_basis", "shading_normals"]

SHADING_MODES = ("none", "sh2")  # model.shading: off (the paper) | the learned SH irradiance of this module
SHADING_NORMALS = ("phong", "axis")
_Y00 = 0.28209479177387814


def sh9_basis(n: torch.Tensor) -> torch.Tensor:
    """Real SH basis up to order 2 at unit directions ``n [N,3]`` -> ``[N,9]``."""
    x, y, z = n.unbind(-1)
    return torch.stack(
        [
            torch.full_like(x, _Y00),
            0.4886025119029199 * y,
            0.4886025119029199 * z,
            0.4886025119029199 * x,
            1.0925484305920792 * x * y,
            1.0925484305920792 * y * z,
            0.31539156525252005 * (3 * z * z - 1),
            1.0925484305920792 * x * z,
            0.5462742152960396 * (x * x - y * y),
        ],
        dim=-1,
    )


def shading_normals(kind: str, phong: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Unit normals ``[N,3]``: the Phong normal, or the shortest Gaussian axis facing its side."""
    if kind == "phong":
        return phong
    if kind != "axis":
        raise MeshsplatError(f"shading normal: expected one of {SHADING_NORMALS}, got {kind!r}")
    rot = quat_to_matrix(quats)  # [N,3,3], columns = axes
    idx = scales.detach().argmin(-1)
    axis = rot.gather(-1, idx.view(-1, 1, 1).expand(-1, 3, 1))[..., 0]
    sign = torch.where((axis * phong).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(axis.dtype)
    return axis * sign


class Shading:
    """Learned illumination ``coeffs [9,3]`` (world-space SH irradiance) and which normal it shades."""

    def __init__(
        self,
        coeffs: torch.Tensor | None = None,
        normal: str = "phong",
        device: Device | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        if normal not in SHADING_NORMALS:
            raise MeshsplatError(f"shading normal: expected one of {SHADING_NORMALS}, got {normal!r}")
        if coeffs is None:
            coeffs = torch.zeros(9, 3, device=device, dtype=dtype)
            coeffs[0] = 1.0 / _Y00  # E(n) = 1 everywhere
        if not isinstance(coeffs, torch.Tensor) or tuple(coeffs.shape) != (9, 3) or not coeffs.is_floating_point():
            raise MeshsplatError("shading coeffs: expected a float tensor of shape [9, 3]")
        if not bool(torch.isfinite(coeffs).all()):
            raise MeshsplatError("shading coeffs: contain NaN or infinity")
        self.coeffs = coeffs
        self.normal = normal

    def irradiance(self, normals: torch.Tensor) -> torch.Tensor:
        """``E(n) [N,3]`` (clamped at 0) for unit ``normals [N,3]``."""
        return (sh9_basis(normals) @ self.coeffs.to(normals)).clamp_min(0.0)

    def shade(
        self, albedo: torch.Tensor, phong: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor
    ) -> torch.Tensor:
        """Displayed colour ``[N,3]`` = albedo * E(normal)."""
        return albedo * self.irradiance(shading_normals(self.normal, phong, quats, scales))

    def to(self, device: Device) -> Shading:
        return Shading(self.coeffs.detach().to(device), self.normal)

    def state_dict(self) -> dict[str, Any]:
        return {"coeffs": self.coeffs.detach().cpu().clone(), "normal": self.normal, "space": "world", "order": 2}

    @classmethod
    def from_state_dict(cls, sd: dict[str, Any] | None, device: Device = "cpu") -> Shading | None:
        if sd is None:
            return None
        if not isinstance(sd, dict) or "coeffs" not in sd or not isinstance(sd.get("normal"), str):
            raise MeshsplatError("shading state: expected a dict with coeffs [9,3] and normal (phong|axis)")
        c = sd["coeffs"]
        try:  # a tensor (checkpoint) or nested lists (embedding JSON)
            c = torch.as_tensor(c.detach().cpu() if isinstance(c, torch.Tensor) else c, dtype=torch.float32)
        except (TypeError, ValueError, RuntimeError):
            raise MeshsplatError(f"shading state: coeffs must be numbers [9,3], got {type(c).__name__}") from None
        if tuple(c.shape) != (9, 3) or not bool(torch.isfinite(c).all()):
            raise MeshsplatError(f"shading state: coeffs must be finite numbers [9,3], got shape {list(c.shape)}")
        return cls(c.to(device), sd["normal"])

    def __repr__(self) -> str:
        return f"Shading(normal={self.normal!r}, ambient={(self.coeffs[0] * _Y00).tolist()})"
