"""Where the error is: squared error split into the silhouette band, the interior and the outside.

The band is the pixels within ``band`` pixels of the ground-truth mask's edge (the mask dilated minus
the mask eroded, both by a ``(2 band + 1)`` square); the interior is the eroded mask, the outside the
rest. A render that is right inside but soft or misplaced at the edge shows a large band share.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError

__all__ = ["silhouette_regions", "error_budget", "BUDGET_REGIONS"]

BUDGET_REGIONS = ("band", "interior", "outside")


def silhouette_regions(mask: torch.Tensor, band: int = 2) -> dict[str, torch.Tensor]:
    """Boolean ``[H,W]`` maps ``band``, ``interior``, ``outside`` (a partition) of ``mask [H,W,1]``."""
    check_tensor("mask", mask, "H,W,1")
    if band < 1:
        raise MeshsplatError(f"band: expected >= 1 pixel, got {band}")
    m = (mask[..., 0] > 0.5).float()[None, None]
    k = 2 * band + 1
    dilated = F.max_pool2d(m, k, stride=1, padding=band)[0, 0] > 0.5
    eroded = -F.max_pool2d(-m, k, stride=1, padding=band)[0, 0] > 0.5
    return {"band": dilated & ~eroded, "interior": eroded, "outside": ~dilated}


def error_budget(img: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, band: int = 2) -> dict[str, float]:
    """Sum of squared error of ``img [H,W,3]`` vs ``gt [H,W,3]`` per region of ``mask [H,W,1]``:
    ``sse_<region>``, ``pixels_<region>`` and ``share_<region>`` (its part of the total, 0 when the
    images agree)."""
    dims: dict[str, int] = {}
    check_tensor("img", img, "H,W,3", dims)
    check_tensor("gt", gt, "H,W,3", dims)
    check_tensor("mask", mask, "H,W,1", dims)
    err = (img.float() - gt.float()).pow(2).sum(-1)
    regions = silhouette_regions(mask, band)
    out: dict[str, float] = {}
    for name, sel in regions.items():
        out[f"sse_{name}"] = float(err[sel].sum())
        out[f"pixels_{name}"] = float(sel.sum())
    total = sum(out[f"sse_{r}"] for r in BUDGET_REGIONS)
    for r in BUDGET_REGIONS:
        out[f"share_{r}"] = out[f"sse_{r}"] / total if total > 0 else 0.0
    return out
