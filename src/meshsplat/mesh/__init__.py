"""Triangle mesh: topology, differentiable geometry, posed quantities, quaternions."""

from meshsplat.mesh.geometry import (
    bbox_diagonal,
    degenerate_faces,
    face_area_ratio,
    face_areas,
    face_frames,
    face_normals,
    face_rotations,
    mean_edge_length,
    mesh_extent,
    vertex_normals,
    vertex_quaternions,
)
from meshsplat.mesh.pose import MeshPose
from meshsplat.mesh.quaternion import matrix_to_quat, quat_conjugate, quat_multiply, quat_normalize, quat_to_matrix
from meshsplat.mesh.topology import MeshTopology
from meshsplat.mesh.tri_mesh import MeshReport, TriMesh, validate_mesh

__all__ = [
    "mesh_extent",
    "mean_edge_length",
    "TriMesh",
    "MeshReport",
    "validate_mesh",
    "MeshTopology",
    "MeshPose",
    "bbox_diagonal",
    "face_normals",
    "face_areas",
    "vertex_normals",
    "face_frames",
    "face_rotations",
    "vertex_quaternions",
    "face_area_ratio",
    "degenerate_faces",
    "quat_multiply",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_normalize",
    "quat_conjugate",
]
