"""Differentiable per-face / per-vertex geometry, batched over leading dims.

``verts`` is ``[..., V, 3]``, ``faces`` is ``[F, 3]`` long on the same device.
Every normalization is eps-guarded, so degenerate (zero-area) faces give
finite values and finite gradients, never NaN.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.mesh.quaternion import matrix_to_quat, quat_normalize

__all__ = [
    "bbox_diagonal",
    "mesh_extent",
    "mean_edge_length",
    "safe_normalize",
    "face_corners",
    "face_normals",
    "face_areas",
    "vertex_normals",
    "face_frames",
    "face_rotations",
    "vertex_quaternions",
    "face_area_ratio",
    "pose_quantities",
    "degenerate_faces",
]

_EPS = 1e-12


def bbox_diagonal(points: torch.Tensor | np.ndarray) -> float:
    """Length of the axis-aligned bounding box's diagonal of ``points [N, 3]`` (a mesh's size).

    Computed in the input's own type and precision (torch or numpy), so callers keep their numbers.
    """
    if isinstance(points, torch.Tensor):
        return float((points.amax(0) - points.amin(0)).norm())
    p = np.asarray(points)
    return float(np.linalg.norm(p.max(0) - p.min(0)))


def mesh_extent(vertices: torch.Tensor) -> float:
    """Half the bounding-box diagonal of ``vertices [V,3]``: the 'scene extent' of an avatar (≈1 for a 1.7 m
    body); the unit of the training config's relative sizes."""
    return 0.5 * bbox_diagonal(vertices)


def mean_edge_length(vertices: torch.Tensor, faces: torch.Tensor) -> float:
    """Mean length of the edges of the faces ``[F,3]`` over ``vertices [V,3]`` (each edge once per face)."""
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return float((vertices[e[:, 0]] - vertices[e[:, 1]]).norm(dim=-1).mean())


def safe_normalize(x: torch.Tensor, eps: float = _EPS) -> torch.Tensor:
    """x / |x| along the last dim; zero vectors stay zero (finite gradient)."""
    return x * torch.rsqrt((x * x).sum(-1, keepdim=True).clamp_min(eps * eps))


def _safe_norm(x: torch.Tensor, eps: float = _EPS) -> torch.Tensor:
    return (x * x).sum(-1).clamp_min(eps * eps).sqrt()


def face_corners(verts: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Corner positions ``a, b, c`` each ``[..., F, 3]``."""
    # one index_select of the flat corner list: about 2x faster than three advanced-indexing gathers
    a, b, c = verts.index_select(-2, faces.reshape(-1)).unflatten(-2, (faces.shape[0], 3)).unbind(-2)
    return a, b, c


class _FaceGeometry:
    """The per-face quantities of one vertex set ``[..., V, 3]`` over ``faces [F,3]``, each computed once
    (posing a mesh needs the same corners, edges and cross products for its normals, rotations and areas)."""

    def __init__(self, verts: torch.Tensor, faces: torch.Tensor) -> None:
        self.a, self.b, self.c = face_corners(verts, faces)
        self.e0, self.e2 = self.b - self.a, self.c - self.a
        self.cross = torch.linalg.cross(self.e0, self.e2, dim=-1)  # [..., F, 3], |cross| = 2 * area

    @functools.cached_property
    def areas(self) -> torch.Tensor:
        """[..., F]"""
        return 0.5 * _safe_norm(self.cross)

    def ok(self, rel: float = 1e-10) -> torch.Tensor:
        """[..., F] True where a face is not degenerate (relative to its edge lengths)."""
        cross2 = (self.cross**2).sum(-1)
        scale = (self.e0 * self.e0).sum(-1) * (self.e2 * self.e2).sum(-1)
        return (cross2 > rel * scale) & (scale > 0)

    @functools.cached_property
    def frames(self) -> torch.Tensor:
        """[..., F, 3, 3], see :func:`face_frames`."""
        t = safe_normalize(self.e0)
        n = safe_normalize(self.cross)
        bt = torch.linalg.cross(n, t, dim=-1)
        frame = torch.stack([t, bt, n], dim=-1)
        eye = torch.eye(3, dtype=frame.dtype, device=frame.device).expand_as(frame)
        return torch.where(self.ok()[..., None, None], frame, eye)


def _face_cross(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    a, b, c = face_corners(verts, faces)
    return torch.linalg.cross(b - a, c - a, dim=-1)


def face_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals ``[..., F, 3]`` (zero for degenerate faces)."""
    return safe_normalize(_face_cross(verts, faces))


def face_areas(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Face areas ``[..., F]``."""
    return 0.5 * _safe_norm(_face_cross(verts, faces))


def _scatter_to_vertices(values: torch.Tensor, faces: torch.Tensor, num_vertices: int) -> torch.Tensor:
    """values ``[..., F, 3, C]`` (per corner) -> summed per vertex ``[..., V, C]``.

    One ``scatter_add`` per pose along its flat corner values (corners in order, so the sums are those of
    ``index_add``): on CPU about 10x faster than ``index_add`` along the vertex dimension, forward and
    backward. The index ``[3F*C]`` is shared by the poses (an expanded view), not one per pose.
    """
    lead = values.shape[:-3]
    c = values.shape[-1]
    flat = values.reshape(-1, faces.shape[0] * 3 * c)  # [B, 3F*C]
    per_corner = (faces.reshape(1, -1, 1) * c + torch.arange(c, device=faces.device)).reshape(1, -1)  # [1, 3F*C]
    out = flat.new_zeros(flat.shape[0], num_vertices * c).scatter_add(1, per_corner.expand_as(flat), flat)
    return out.reshape(lead + (num_vertices, c))


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor, weighting: str = "area") -> torch.Tensor:
    """Unit vertex normals ``[..., V, 3]``, ``weighting`` "area" or "angle".

    Vertices without (non-degenerate) faces get a zero normal.
    """
    return _vertex_normals(_FaceGeometry(verts, faces), faces, verts.shape[-2], weighting)


def _vertex_normals(geo: _FaceGeometry, faces: torch.Tensor, num_vertices: int, weighting: str) -> torch.Tensor:
    cross = geo.cross
    if weighting == "area":
        corner = cross.unsqueeze(-2).expand(cross.shape[:-1] + (3, 3))
    elif weighting == "angle":
        n = safe_normalize(cross)
        angles = []
        for p, q, r in ((geo.a, geo.b, geo.c), (geo.b, geo.c, geo.a), (geo.c, geo.a, geo.b)):
            e1, e2 = q - p, r - p
            sin = _safe_norm(torch.linalg.cross(e1, e2, dim=-1))
            angles.append(torch.atan2(sin, (e1 * e2).sum(-1)))
        corner = torch.stack(angles, -1).unsqueeze(-1) * n.unsqueeze(-2)
    else:
        raise MeshsplatError(f"weighting: expected 'area' or 'angle', got {weighting!r}")
    return safe_normalize(_scatter_to_vertices(corner, faces, num_vertices))


def face_frames(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Orthonormal frames ``[..., F, 3, 3]`` with columns (tangent, bitangent, normal).

    tangent = normalized first edge (a -> b), normal = face normal, bitangent = n x t.
    Degenerate faces get the identity frame.
    """
    return _FaceGeometry(verts, faces).frames


def face_rotations(v_cano: torch.Tensor, v_posed: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Rotation ``[..., F, 3, 3]`` taking each canonical face frame to its posed frame."""
    return face_frames(v_posed, faces) @ face_frames(v_cano, faces).transpose(-1, -2)


def vertex_quaternions(v_cano: torch.Tensor, v_posed: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Per-vertex rotations ``[..., V, 4]`` (wxyz): area-weighted average of incident face quaternions.

    Signs are aligned per vertex to the quaternion of its largest incident face
    (posed area) before averaging; vertices with no usable face get identity.
    """
    return _vertex_quaternions(_FaceGeometry(v_cano, faces), _FaceGeometry(v_posed, faces), faces, v_posed.shape[-2])


def _vertex_quaternions(cano: _FaceGeometry, posed: _FaceGeometry, faces: torch.Tensor, nv: int) -> torch.Tensor:
    q_face = matrix_to_quat(posed.frames @ cano.frames.transpose(-1, -2))  # [..., F, 4]
    w_face = posed.areas  # [..., F]
    lead = q_face.shape[:-2]
    nf = faces.shape[0]
    q = q_face.reshape(-1, nf, 4)
    w = w_face.expand(lead + (nf,)).reshape(-1, nf)
    bsz = q.shape[0]
    vidx = faces.reshape(-1)  # corner -> vertex
    fidx = torch.arange(nf, device=faces.device).repeat_interleave(3)  # corner -> face
    w_c = w.index_select(1, fidx)  # [B, 3F]
    wc = w_c.detach()
    # reference face per vertex: largest weight, ties -> largest face index
    wmax = wc.new_full((bsz, nv), -1.0).scatter_reduce(1, vidx.expand(bsz, -1), wc, "amax")
    is_max = wc >= wmax.index_select(1, vidx)
    cand = torch.where(is_max, fidx.expand(bsz, -1), torch.full_like(wc, -1, dtype=torch.long))
    ref_face = torch.full((bsz, nv), -1, dtype=torch.long, device=faces.device)
    ref_face = ref_face.scatter_reduce(1, vidx.expand(bsz, -1), cand, "amax").clamp_min(0)
    q_ref = torch.gather(q.detach(), 1, ref_face[..., None].expand(-1, -1, 4))  # [B, V, 4]
    qc = q.index_select(1, fidx)  # [B, 3F, 4]
    sign = torch.where((qc.detach() * q_ref.index_select(1, vidx)).sum(-1) < 0, -1.0, 1.0).to(q.dtype)
    contrib = (w_c * sign)[..., None] * qc
    acc = _scatter_to_vertices(contrib.view(bsz, nf, 3, 4), faces, nv)  # [B, V, 4]
    norm2 = (acc * acc).sum(-1, keepdim=True)
    ident = torch.zeros_like(acc)
    ident[..., 0] = 1.0
    out = torch.where(norm2 > 1e-30, quat_normalize(acc, eps=1e-15), ident)
    return out.reshape(lead + (nv, 4))


def face_area_ratio(
    v_cano: torch.Tensor, v_posed: torch.Tensor, faces: torch.Tensor, eps: float = 1e-12
) -> torch.Tensor:
    """Posed / canonical face area ``[..., F]``; 1 where the canonical face is degenerate."""
    return _area_ratio(face_areas(v_cano, faces), face_areas(v_posed, faces), eps)


def _area_ratio(a0: torch.Tensor, a1: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    ok = a0 > eps
    return torch.where(ok, a1 / torch.where(ok, a0, torch.ones_like(a0)), torch.ones_like(a1))


def pose_quantities(
    v_cano: torch.Tensor, v_posed: torch.Tensor, faces: torch.Tensor, normal_weighting: str = "area"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(:func:`vertex_normals` ``[..., V, 3]``, :func:`vertex_quaternions` ``[..., V, 4]``,
    :func:`face_area_ratio` ``[..., F]``) of ``v_posed`` against ``v_cano``, sharing their per-face work."""
    cano, posed = _FaceGeometry(v_cano, faces), _FaceGeometry(v_posed, faces)
    nv = v_posed.shape[-2]
    return (
        _vertex_normals(posed, faces, nv, normal_weighting),
        _vertex_quaternions(cano, posed, faces, nv),
        _area_ratio(cano.areas, posed.areas),
    )


def degenerate_faces(verts: torch.Tensor, faces: torch.Tensor, rel: float = 1e-10) -> torch.Tensor:
    """[F] bool: repeated vertex index or (near) zero area in any leading batch entry."""
    bad = ~_FaceGeometry(verts.detach(), faces).ok(rel)
    while bad.ndim > 1:
        bad = bad.any(0)
    idx = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    return bad | idx
