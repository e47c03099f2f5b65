"""Training components: the features beyond the published method, each in one module (``base`` says what a
component is). ``COMPONENTS`` is the order the trainer calls their hooks in."""

from meshsplat.train.components.albedo_prior import AlbedoPrior, AlbedoPriorConfig
from meshsplat.train.components.base import Component, TrainingState
from meshsplat.train.components.mask_loss import MaskLoss, MaskLossConfig
from meshsplat.train.components.offset_bound import OffsetBound, OffsetBoundConfig
from meshsplat.train.components.pose_refine import PoseRefineConfig, PoseRefinement
from meshsplat.train.components.shading import ShadingComponent, ShadingConfig

__all__ = [
    "COMPONENTS",
    "Component",
    "TrainingState",
    "ShadingConfig",
    "AlbedoPriorConfig",
    "MaskLossConfig",
    "OffsetBoundConfig",
    "PoseRefineConfig",
]

# hook order: the offset bound projects before the lighting steps, the pose offsets step last; loss terms add
# in this order (mask, then albedo)
COMPONENTS: tuple[tuple[type[Component], type], ...] = (
    (OffsetBound, OffsetBoundConfig),
    (ShadingComponent, ShadingConfig),
    (PoseRefinement, PoseRefineConfig),
    (MaskLoss, MaskLossConfig),
    (AlbedoPrior, AlbedoPriorConfig),
)
