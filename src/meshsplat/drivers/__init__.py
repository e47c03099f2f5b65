"""Mesh drivers: per-frame vertex sequences, glTF skins/morphs/clips, blendshapes, SMPL/SMPL-X/FLAME;
``load_animation`` turns an ``AnimationSource`` into frames or a live driver on an avatar's mesh."""

from meshsplat.drivers.animation import ANIMATION_KINDS, Animation, AnimationSource, load_animation
from meshsplat.drivers.base import MeshDriver, SequenceDriver
from meshsplat.drivers.blendshape import BlendshapeDriver
from meshsplat.drivers.body_models import BodyModel, ParametricDriver
from meshsplat.drivers.gltf import GltfDriver, Material

__all__ = [
    "ANIMATION_KINDS",
    "AnimationSource",
    "Animation",
    "load_animation",
    "MeshDriver",
    "SequenceDriver",
    "GltfDriver",
    "BlendshapeDriver",
    "Material",
    "BodyModel",
    "ParametricDriver",
]
