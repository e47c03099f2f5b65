"""Structural similarity (Wang et al. 2004) with an 11x11 Gaussian window (sigma 1.5)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from meshsplat.errors import MeshsplatError
from meshsplat.metrics.psnr import as_batch_hwc

__all__ = ["ssim", "ssim_map", "gaussian_window", "gaussian_blur"]

C1 = 0.01**2  # (K1 * L)^2 with L = 1
C2 = 0.03**2  # (K2 * L)^2


def gaussian_window(
    size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> torch.Tensor:
    """Normalized 1-D Gaussian ``[size]``."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _blur(x: torch.Tensor, g: torch.Tensor, padding: str) -> torch.Tensor:
    """Separable depthwise Gaussian on ``[B,C,H,W]``; "same" zero-pads, "valid" crops."""
    c = x.shape[1]
    k = g.numel()
    pad = k // 2 if padding == "same" else 0
    x = F.conv2d(x, g.view(1, 1, k, 1).expand(c, 1, k, 1), padding=(pad, 0), groups=c)
    return F.conv2d(x, g.view(1, 1, 1, k).expand(c, 1, 1, k), padding=(0, pad), groups=c)


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of ``x [H,W,C]`` with standard deviation ``sigma`` px (radius ceil(3 sigma), zero outside)."""
    g = gaussian_window(2 * max(1, math.ceil(3 * sigma)) + 1, sigma, dtype=x.dtype, device=x.device)
    return _blur(x.permute(2, 0, 1)[None], g, "same")[0].permute(1, 2, 0)


def ssim_map(
    img: torch.Tensor, ref: torch.Tensor, window_size: int = 11, sigma: float = 1.5, padding: str = "valid"
) -> torch.Tensor:
    """Per-pixel SSIM ``[B,H',W',C]`` of [H,W,C] / [B,H,W,C] images in [0, 1].

    padding: "valid" (the reference definition, only windows fully inside the image;
    ``H' = H - window_size + 1``) or "same" (zero padding as in the 3DGS training loss).
    """
    if padding not in ("valid", "same"):
        raise MeshsplatError(f"padding: expected 'valid' or 'same', got {padding!r}")
    a = as_batch_hwc("img", img)
    b = as_batch_hwc("ref", ref)
    if a.shape != b.shape:
        raise MeshsplatError(f"ref: expected shape {list(img.shape)} like img, got {list(ref.shape)}")
    h, w = a.shape[1:3]
    if padding == "valid" and min(h, w) < window_size:
        raise MeshsplatError(
            f"ssim: images must be at least {window_size}x{window_size} pixels for padding='valid', got {h}x{w}"
        )
    x = a.permute(0, 3, 1, 2)
    y = b.to(a.dtype).permute(0, 3, 1, 2)
    g = gaussian_window(window_size, sigma, dtype=x.dtype, device=x.device)
    mu_x, mu_y = _blur(x, g, padding), _blur(y, g, padding)
    sxx = _blur(x * x, g, padding) - mu_x**2
    syy = _blur(y * y, g, padding) - mu_y**2
    sxy = _blur(x * y, g, padding) - mu_x * mu_y
    num = (2 * mu_x * mu_y + C1) * (2 * sxy + C2)
    den = (mu_x**2 + mu_y**2 + C1) * (sxx + syy + C2)
    return (num / den).permute(0, 2, 3, 1)


def ssim(
    img: torch.Tensor,
    ref: torch.Tensor,
    window_size: int = 11,
    sigma: float = 1.5,
    padding: str = "valid",
    reduction: str = "mean",
) -> torch.Tensor:
    """Mean SSIM of ``img`` vs ``ref`` ([H,W,3] or [B,H,W,3] in [0, 1]); differentiable.

    Constants K1=0.01, K2=0.03, data range 1. ``reduction="none"`` gives ``[B]``.
    """
    per = ssim_map(img, ref, window_size, sigma, padding).mean(dim=(1, 2, 3))
    if reduction == "none":
        return per
    if reduction != "mean":
        raise MeshsplatError(f"reduction: expected 'mean' or 'none', got {reduction!r}")
    return per.mean()
