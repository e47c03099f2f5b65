"""The error budget: band / interior / outside partition the image, and an edge error lands in the band."""

from __future__ import annotations

import pytest
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.metrics.budget import error_budget, silhouette_regions


def _disk(h: int, w: int, r: float, cx: float, cy: float) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    return (((x - cx) ** 2 + (y - cy) ** 2) < r * r).float()[..., None]


def test_regions_partition_the_image():
    m = _disk(40, 50, 12, 25, 20)
    reg = silhouette_regions(m, band=2)
    total = reg["band"].int() + reg["interior"].int() + reg["outside"].int()
    assert bool((total == 1).all())
    assert bool(reg["interior"][20, 25]) and bool(reg["outside"][0, 0]) and bool(reg["band"][20, 25 + 12])
    edge = (m[..., 0] > 0.5) & ~(torch.roll(m[..., 0], 1, 1) > 0.5)
    assert bool(reg["band"][edge].all())  # every edge pixel is in the band


def test_a_shifted_silhouette_is_a_band_error_and_a_tint_an_interior_one():
    m = _disk(48, 48, 14, 24, 24)
    gt = m.expand(-1, -1, 3) * torch.tensor([0.8, 0.5, 0.3])
    shifted = torch.roll(gt, 1, dims=1)
    b = error_budget(shifted, gt, m, band=2)
    assert b["share_band"] > 0.99 and b["sse_band"] > 0
    tinted = gt * torch.where(m > 0.5, 0.9, 1.0)
    t = error_budget(tinted, gt, m, band=2)
    assert t["share_interior"] > 0.6 and t["share_outside"] == 0.0
    assert error_budget(gt, gt, m)["share_band"] == 0.0
    assert sum(b[f"pixels_{r}"] for r in ("band", "interior", "outside")) == 48 * 48


def test_budget_errors():
    with pytest.raises(MeshsplatError, match="band"):
        silhouette_regions(torch.ones(4, 4, 1), band=0)
    with pytest.raises(MeshsplatError, match="gt"):
        error_budget(torch.zeros(4, 4, 3), torch.zeros(5, 4, 3), torch.ones(4, 4, 1))
