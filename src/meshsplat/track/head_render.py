"""Photographs of the ICT head that a face landmarker recognises: for deriving the landmark
correspondence (``bench/derive_ict_landmarks.py``) and for testing the tracker on images.

The synthetic generator's procedural skin (``synth.sources.BlendshapeSource``) plus what a landmarker
looks for on a face and ICT leaves uncoloured: darker lips and brows. Lambert shading from a light above
the camera; the transparent eye shells (``M_EyeBlend``, ``M_EyeOcclusion``, ``M_LacrimalFluid``) hidden.
"""

from __future__ import annotations

import math

import torch

from meshsplat.synth.raster import Fragments, interpolate, lambert, rasterize_triangles, vertex_normals
from meshsplat.synth.sources import ICT_HIDDEN_MATERIALS
from meshsplat.track.ict_head import IctHead
from meshsplat.track.tracker_camera import world_to_camera_axes

__all__ = ["head_colors", "visible_faces", "render_head"]

_IRIS_ANGLE = math.radians(38.0)  # half-angle of the iris seen from the eyeball centre
_PUPIL_ANGLE = math.radians(14.0)
_COLORS = {
    "M_EyeLashes": (0.08, 0.06, 0.05),
    "M_GumsTongue": (0.75, 0.35, 0.35),
    "M_IrisLeft": (0.25, 0.3, 0.45),
    "M_IrisRight": (0.25, 0.3, 0.45),
    "M_ScleraLeft": (0.92, 0.9, 0.88),
    "M_ScleraRight": (0.92, 0.9, 0.88),
    "M_Teeth": (0.93, 0.9, 0.82),
}


def _smooth_bump(
    p: torch.Tensor, center: tuple[float, float, float], radius: tuple[float, float, float]
) -> torch.Tensor:
    d = ((p - torch.tensor(center)) / torch.tensor(radius)).pow(2).sum(1)
    return torch.exp(-d * 2)


def head_colors(head: IctHead) -> torch.Tensor:
    """Per-vertex albedo ``[V,3]``: the procedural skin, red lips, dark brows, material colours for the
    eyes, teeth, gums and lashes. Lips and brows are located on the neutral (ICT units, cm)."""
    p = head.neutral
    q = (p - p.mean(0)) / (p.max(0).values - p.min(0).values).max()
    blotch = torch.sin(9 * q[:, 0] + 2) * torch.sin(7 * q[:, 1] + 1) * torch.sin(8 * q[:, 2])
    fine = torch.sin(60 * q[:, 1]) * torch.sin(45 * q[:, 0] + 20 * q[:, 2])
    skin = torch.tensor([0.85, 0.62, 0.50]) * (1 + 0.08 * blotch[:, None] + 0.03 * fine[:, None])
    roll = head.names.index("mouthRollLower"), head.names.index("mouthRollUpper")
    lip_motion = head.deltas[list(roll)].norm(dim=-1).amax(0)
    lips = (lip_motion / lip_motion.max()).clamp(0, 1).pow(0.5) * (p[:, 2] > 9).float()
    lips = lips * _smooth_bump(p, (0.0, -4.2, 11.0), (3.2, 1.6, 3.0)).clamp(0, 1).pow(0.3)
    brows = sum(_smooth_bump(p, (s * 3.6, 6.6, 10.2), (2.6, 0.55, 3.0)) for s in (-1.0, 1.0))
    brow_t = torch.as_tensor(brows)
    color = skin * (1 - lips[:, None]) + torch.tensor([0.62, 0.28, 0.3]) * lips[:, None]
    color = color * (1 - brow_t[:, None]) + torch.tensor([0.22, 0.15, 0.1]) * brow_t[:, None]
    for name, rgb in _COLORS.items():
        if name in head.material_names:
            sel = head.faces[head.face_material == head.material_names.index(name)].reshape(-1)
            color[sel] = torch.tensor(rgb)
    for eye in range(2):  # ICT's sclera is the whole eyeball: paint the iris and pupil on its front
        ids = head.eye_vertices[eye]
        d = p[ids] - head.eye_centers[eye]
        cos = d[:, 2] / d.norm(dim=1).clamp_min(1e-9)
        color[ids[cos > math.cos(_IRIS_ANGLE)]] = torch.tensor(_COLORS["M_IrisLeft"])
        color[ids[cos > math.cos(_PUPIL_ANGLE)]] = torch.tensor((0.05, 0.05, 0.06))
    return color.clamp(0, 1)


def visible_faces(head: IctHead) -> torch.Tensor:
    """Indices ``[F']`` of the faces drawn (all but the transparent eye shells)."""
    hidden = torch.tensor([head.material_names.index(m) for m in ICT_HIDDEN_MATERIALS if m in head.material_names])
    return torch.nonzero(~torch.isin(head.face_material, hidden)).reshape(-1)


def render_head(
    head: IctHead,
    vertices: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: tuple[float, float, float] = (0.55, 0.6, 0.65),
    colors: torch.Tensor | None = None,
) -> tuple[torch.Tensor, Fragments, torch.Tensor]:
    """Render world ``vertices [V,3]`` through ``K`` and :data:`~meshsplat.track.tracker_camera.TRACKER_VIEWMAT`: ``(image [H,W,3]
    float in [0,1], fragments, face_ids [F'])``; ``fragments.face`` indexes ``face_ids`` (-1 background)."""
    cam = world_to_camera_axes(vertices)
    keep = visible_faces(head)
    faces = head.faces[keep]
    frags = rasterize_triangles(cam, faces, K, width, height)
    albedo = head_colors(head) if colors is None else colors
    normals = vertex_normals(cam, head.faces)
    img = torch.ones(height, width, 3) * torch.tensor(background)
    m = frags.mask
    a = interpolate(frags, faces, albedo)[m]
    n = interpolate(frags, faces, normals)[m]
    pos = interpolate(frags, faces, cam)[m]
    light = torch.tensor([0.3, -0.5, -1.0])
    img[m] = lambert(a, n, pos, light / light.norm(), ambient=0.45, diffuse=0.6)
    return img, frags, keep
