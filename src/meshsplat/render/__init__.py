"""Differentiable Gaussian rasterization with gsplat 1.5.3 conventions.

``rasterize(...) -> RenderOutput(colors, alphas, meta)``; backends in ``render.backends``.
"""

from __future__ import annotations

from meshsplat.render.api import BACKENDS, RENDER_MODES, rasterize
from meshsplat.render.background import BACKGROUNDS, background_color, composite
from meshsplat.render.projection import Projection, project_gaussians
from meshsplat.render.types import RenderOutput

__all__ = [
    "rasterize",
    "RenderOutput",
    "RENDER_MODES",
    "BACKENDS",
    "project_gaussians",
    "Projection",
    "BACKGROUNDS",
    "background_color",
    "composite",
]
