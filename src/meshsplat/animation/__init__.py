"""Animation sources and retargeting: what drives an avatar, put on its canonical mesh.

``source``: ``AnimationSource`` (the CLI's ``--animation KIND [FILE]``) and ``load_animation``, which turns it
into vertex frames or a live driver; ``avatar_match``: a driver's vertices matched to the avatar's canonical
mesh (through the source map of a synthesized capture); ``motion``: SMPL/SMPL-X/FLAME motion files and
their re-enactment on another subject. Sits above ``data`` and ``gaussians``; the drivers it uses sit below.
"""

from meshsplat.animation.source import ANIMATION_KINDS, Animation, AnimationSource, load_animation

__all__ = ["ANIMATION_KINDS", "AnimationSource", "Animation", "load_animation"]
