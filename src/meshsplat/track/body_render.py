"""Pictures of the Anny body that a pose landmarker recognises as a person: for testing the body tracker
on generated clips (``tests/_body_video.py``) and for the bench's previews.

Per-vertex colours by body part (skin, a shirt, trousers, shoes, hair), Lambert shading from a light
above the camera, through the trackers' camera (``tracker_camera.TRACKER_VIEWMAT``: at the origin, looking along -z).
"""

from __future__ import annotations

import torch

from meshsplat.drivers.anny_body import JOINTS, AnnyBody
from meshsplat.synth.raster import Fragments, interpolate, lambert, rasterize_triangles, vertex_normals
from meshsplat.track.tracker_camera import world_to_camera_axes

__all__ = ["body_colors", "render_body"]

_SKIN = (0.86, 0.64, 0.52)
_PART_COLORS = {  # joint -> albedo of the vertices it moves most
    "shirt": ((0.2, 0.35, 0.7), ("spine1", "spine2", "spine3", "left_collar", "right_collar", "left_shoulder", "right_shoulder")),
    "trousers": ((0.25, 0.25, 0.28), ("pelvis", "left_hip", "right_hip", "left_knee", "right_knee")),
    "shoes": ((0.12, 0.1, 0.1), ("left_ankle", "right_ankle", "left_foot", "right_foot")),
}  # fmt: skip


def body_colors(body: AnnyBody) -> torch.Tensor:
    """Per-vertex albedo ``[V,3]``: skin, a blue shirt with short sleeves, dark trousers and shoes, dark
    hair on the back and top of the head."""
    part = body.weights.argmax(1)
    color = torch.tensor(_SKIN).repeat(body.num_vertices, 1)
    for rgb, joints in _PART_COLORS.values():
        ids = torch.tensor([JOINTS.index(j) for j in joints])
        color[torch.isin(part, ids)] = torch.tensor(rgb)
    v = body.template
    head = JOINTS.index("head")
    top = body.joints_rest[head]
    hair = (part == head) & ((v[:, 1] > top[1] + 0.1) | ((v[:, 2] < top[2] - 0.02) & (v[:, 1] > top[1] + 0.02)))
    color[hair] = torch.tensor((0.18, 0.12, 0.08))
    return color


def render_body(
    body: AnnyBody,
    vertices: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: tuple[float, float, float] = (0.62, 0.64, 0.6),
    colors: torch.Tensor | None = None,
) -> tuple[torch.Tensor, Fragments]:
    """Render world ``vertices [V,3]`` through ``K [3,3]``: ``(image [H,W,3] in [0,1], fragments)``."""
    cam = world_to_camera_axes(vertices)
    frags = rasterize_triangles(cam, body.faces, K, width, height)
    albedo = body_colors(body) if colors is None else colors
    normals = vertex_normals(cam, body.faces)
    img = torch.ones(height, width, 3) * torch.tensor(background)
    m = frags.mask
    a = interpolate(frags, body.faces, albedo)[m]
    n = interpolate(frags, body.faces, normals)[m]
    pos = interpolate(frags, body.faces, cam)[m]
    light = torch.tensor([0.3, -0.6, -1.0])
    img[m] = lambert(a, n, pos, light / light.norm(), ambient=0.45, diffuse=0.6)
    return img, frags
