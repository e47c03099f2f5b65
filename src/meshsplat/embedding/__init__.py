"""Embeddings (face, uv, d) on a mesh: placement, sampling, walking, projection."""

from meshsplat.embedding.barycentric import (
    barycentric_weights,
    gather_rows,
    interpolate,
    project_uv_to_triangle,
    surface_points,
)
from meshsplat.embedding.embedding import SCALE_MODES, check_embedded, embed, pose_frame
from meshsplat.embedding.project import closest_point_on_triangles, project_to_surface
from meshsplat.embedding.sampling import sample_surface
from meshsplat.embedding.walk import WALK_MODES, WalkResult, walk_on_triangles

__all__ = [
    "embed",
    "pose_frame",
    "check_embedded",
    "barycentric_weights",
    "interpolate",
    "surface_points",
    "gather_rows",
    "project_uv_to_triangle",
    "SCALE_MODES",
    "sample_surface",
    "walk_on_triangles",
    "WalkResult",
    "WALK_MODES",
    "project_to_surface",
    "closest_point_on_triangles",
]
