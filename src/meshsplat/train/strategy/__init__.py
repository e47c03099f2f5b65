"""Densification strategy and embedding walk for mesh-embedded Gaussians."""

from meshsplat.train.strategy.default import DensifyStrategy
from meshsplat.train.strategy.ops import duplicate, remove, reset_opacity, split_append, update_all, zero_moments
from meshsplat.train.strategy.walk import walk_embeddings

__all__ = [
    "DensifyStrategy",
    "walk_embeddings",
    "duplicate",
    "remove",
    "split_append",
    "reset_opacity",
    "update_all",
    "zero_moments",
]
