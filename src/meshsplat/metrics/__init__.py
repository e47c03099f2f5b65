"""Image metrics: PSNR, SSIM, LPIPS (images [H,W,3] or [B,H,W,3] in [0, 1])."""

from __future__ import annotations

import torch

from meshsplat.errors import MeshsplatError
from meshsplat.metrics.lpips_net import LPIPS, get_lpips, load_lpips, lpips_available
from meshsplat.metrics.psnr import as_batch_hwc, psnr
from meshsplat.metrics.ssim import ssim, ssim_map

__all__ = ["psnr", "ssim", "ssim_map", "lpips", "LPIPS", "load_lpips", "get_lpips", "lpips_available"]


def lpips(img: torch.Tensor, ref: torch.Tensor, net: str = "alex", reduction: str = "mean") -> torch.Tensor:
    """LPIPS distance of ``img`` vs ``ref`` ([H,W,3] or [B,H,W,3] in [0, 1]).

    Uses the cached trained network for ``net`` on the inputs' device; raises
    MeshsplatError when no weights are installed. Differentiable; ``reduction="none"``
    gives ``[B]``.
    """
    a = as_batch_hwc("img", img)
    b = as_batch_hwc("ref", ref)
    if a.shape != b.shape:
        raise MeshsplatError(f"ref: expected shape {list(img.shape)} like img, got {list(ref.shape)}")
    if a.shape[-1] != 3:
        raise MeshsplatError(f"img: LPIPS needs 3 channels, got {a.shape[-1]}")
    model = get_lpips(net, a.device)
    per = model(a.permute(0, 3, 1, 2), b.to(a.dtype).permute(0, 3, 1, 2))
    if reduction == "none":
        return per
    if reduction != "mean":
        raise MeshsplatError(f"reduction: expected 'mean' or 'none', got {reduction!r}")
    return per.mean()
