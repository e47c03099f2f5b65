"""Return type of :func:`meshsplat.render.rasterize`."""

from __future__ import annotations

from typing import Any, NamedTuple

import torch

__all__ = ["RenderOutput"]


class RenderOutput(NamedTuple):
    """``colors [C,H,W,D']``, ``alphas [C,H,W,1]`` and ``meta`` (dict).

    A NamedTuple, so ``colors, alphas, meta = rasterize(...)`` works as with gsplat.
    ``meta`` keys: ``means2d [C,N,2]`` (retain_grad: ``.grad`` holds the per-camera
    screen-space gradient after backward), ``radii [C,N,2] int32`` (0 = culled),
    ``depths [C,N]`` (camera z), ``visible [C,N] bool``, ``conics [C,N,3]``,
    ``width``, ``height``, ``n_cameras``, ``backend`` and, for the torch backend,
    ``n_pairs`` (pixel-Gaussian pairs composited).
    """

    colors: torch.Tensor
    alphas: torch.Tensor
    meta: dict[str, Any]
