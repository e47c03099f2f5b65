"""File formats: atomic checkpoints, 3DGS .ply (+ .splat, .spz, glTF splats), embedding JSON, OBJ meshes, images, video."""

from __future__ import annotations

from meshsplat.io.checkpoint import (
    checkpoint_path,
    list_checkpoints,
    load_checkpoint,
    prune_checkpoints,
    save_checkpoint,
)
from meshsplat.io.embedding_json import read_embedding_json, write_embedding_json
from meshsplat.io.obj import ObjMesh, read_obj, write_obj
from meshsplat.io.ply import read_gaussian_ply, write_gaussian_ply
from meshsplat.io.splat_formats import (
    read_gltf_splats,
    read_splat,
    read_spz,
    write_gltf_splats,
    write_splat,
    write_spz,
)
from meshsplat.io.video import VideoResult, write_mp4, write_png_frames, write_video

__all__ = [
    "save_checkpoint",
    "load_checkpoint",
    "list_checkpoints",
    "prune_checkpoints",
    "checkpoint_path",
    "write_gaussian_ply",
    "read_gaussian_ply",
    "write_splat",
    "read_splat",
    "write_spz",
    "read_spz",
    "write_gltf_splats",
    "read_gltf_splats",
    "write_embedding_json",
    "read_embedding_json",
    "ObjMesh",
    "read_obj",
    "write_obj",
    "write_video",
    "write_mp4",
    "write_png_frames",
    "VideoResult",
]
