"""Mesh drivers: per-frame vertex sequences, glTF skins/morphs/clips, blendshapes."""
from meshsplat.drivers.base import MeshDriver, SequenceDriver
from meshsplat.drivers.blendshape import BlendshapeDriver
from meshsplat.drivers.gltf import GltfDriver, Material

__all__ = ["MeshDriver", "SequenceDriver", "GltfDriver", "BlendshapeDriver", "Material"]
