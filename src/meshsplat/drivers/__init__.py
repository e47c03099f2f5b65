"""Mesh drivers: per-frame vertex sequences, glTF skins/morphs/clips, blendshapes, SMPL/SMPL-X/FLAME.
Putting one on an avatar's mesh (``load_animation``) is :mod:`meshsplat.animation`'s job."""

from meshsplat.drivers.base import MeshDriver, SequenceDriver
from meshsplat.drivers.blendshape import BlendshapeDriver
from meshsplat.drivers.body_models import BodyModel, ParametricDriver
from meshsplat.drivers.gltf import GltfDriver, Material

__all__ = [
    "MeshDriver",
    "SequenceDriver",
    "GltfDriver",
    "BlendshapeDriver",
    "Material",
    "BodyModel",
    "ParametricDriver",
]
