"""Place embedded points on a posed mesh: Phong point + displacement, pose rotation and scale.

Barycentric convention: ``meshsplat.embedding.barycentric``. Callers pass ``uv + duv`` so the trainable offsets get gradients.
"""

from __future__ import annotations

import torch

from meshsplat._checks import check_tensor
from meshsplat.embedding.barycentric import barycentric_weights, gather_rows, interpolate
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import safe_normalize
from meshsplat.mesh.pose import MeshPose
from meshsplat.mesh.quaternion import quat_normalize

__all__ = ["embed", "pose_frame", "check_embedded", "SCALE_MODES"]

SCALE_MODES = ("sqrt_area", "area", "none")


def check_embedded(pose: MeshPose, face: torch.Tensor, uv: torch.Tensor) -> dict:
    """Check embedded points ``(face [N], uv [N,2])`` on ``pose`` (a ``MeshPose``): shapes, dtypes, faces in range.
    Returns the dims (``N``)."""
    if not isinstance(pose, MeshPose):
        raise MeshsplatError(f"pose: expected a MeshPose, got {type(pose).__name__}")
    dims: dict[str, int] = {}
    check_tensor("face", face, "N", dims, dtype="int")
    check_tensor("uv", uv, "N,2", dims, dtype="float")
    if face.numel() and (int(face.min()) < 0 or int(face.max()) >= pose.num_faces):
        raise MeshsplatError(
            f"face: indices must lie in [0, {pose.num_faces}), got [{int(face.min())}, {int(face.max())}]"
        )
    return dims


def embed(pose: MeshPose, face: torch.Tensor, uv: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Posed means ``mu = P + d*n`` ``[N,3]`` and Phong normals ``n`` ``[N,3]``.

    face [N] long, uv [N,2], d [N]. Differentiable w.r.t. uv, d and the pose vertices.
    """
    dims = check_embedded(pose, face, uv)
    check_tensor("d", d, "N", dims, dtype="float")
    w = barycentric_weights(uv)
    p = interpolate(pose.verts, pose.faces, face, w)
    n = safe_normalize(interpolate(pose.vertex_normals, pose.faces, face, w))
    return p + d.unsqueeze(-1) * n, n


def pose_frame(
    pose: MeshPose, face: torch.Tensor, uv: torch.Tensor, scale_mode: str = "sqrt_area"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose rotation ``delta_q [N,4]`` (wxyz) and scale factor ``[N,1]`` per embedded point.

    delta_q is the normalized barycentric blend of the face's vertex quaternions, with the
    corners' signs aligned to corner a first; compose as ``q = delta_q ⊗ q_canonical``.
    scale_mode: "area" (factor = A_pose/A_cano, the paper), "sqrt_area" (its square root, a
    length scale) or "none" (1).
    """
    check_embedded(pose, face, uv)
    if scale_mode not in SCALE_MODES:
        raise MeshsplatError(f"scale_mode: expected one of {SCALE_MODES}, got {scale_mode!r}")
    w = barycentric_weights(uv)
    q = gather_rows(pose.vertex_quats, pose.faces[face])  # [N,3,4]
    sign = torch.where((q * q[:, :1]).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q.dtype)
    delta_q = quat_normalize((w.unsqueeze(-1).to(q.dtype) * sign * q).sum(-2), eps=1e-12)
    ratio = gather_rows(pose.area_ratio, face).unsqueeze(-1)
    if scale_mode == "area":
        factor = ratio
    elif scale_mode == "sqrt_area":
        factor = ratio.clamp_min(0.0).add(1e-20).sqrt()
    else:
        factor = torch.ones_like(ratio)
    return delta_q, factor
