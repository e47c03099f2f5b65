"""Metrics on the subject: inside its ground-truth mask and on the crop around it.

Full-image metrics flatter an avatar that fills a tenth of the frame over an easy background. Here:

- ``*_mask``: PSNR over the mask's pixels only (mask-weighted MSE); SSIM as the mask-weighted mean of
  the SSIM map ("same" padding, so every pixel has a value); LPIPS of the crop with the render's
  pixels outside the mask replaced by the ground truth (no error counted there).
- ``*_crop``: the plain metrics on the mask's bounding box, padded by ``pad`` of its size (and to at
  least 32 pixels a side where the image allows; LPIPS is None on smaller crops).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from meshsplat.metrics.psnr import psnr
from meshsplat.metrics.ssim import ssim, ssim_map

__all__ = ["subject_box", "subject_metrics", "SUBJECT_KEYS"]

SUBJECT_KEYS = ("psnr_mask", "ssim_mask", "lpips_mask", "psnr_crop", "ssim_crop", "lpips_crop")


_LPIPS_MIN = 32  # AlexNet-LPIPS needs at least 31 pixels a side


def subject_box(mask: torch.Tensor, pad: float = 0.08, min_size: int = _LPIPS_MIN) -> tuple[int, int, int, int] | None:
    """``(y0, y1, x0, x1)`` of the pixels with ``mask [H,W,1] > 0.5``, padded; None when empty."""
    m = mask[..., 0] > 0.5
    if not bool(m.any()):
        return None
    h, w = m.shape
    ys = torch.nonzero(m.any(1)).flatten()
    xs = torch.nonzero(m.any(0)).flatten()
    y0, y1, x0, x1 = int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1
    py = max(round(pad * (y1 - y0)), (min_size - (y1 - y0) + 1) // 2, 0)
    px = max(round(pad * (x1 - x0)), (min_size - (x1 - x0) + 1) // 2, 0)
    return max(0, y0 - py), min(h, y1 + py), max(0, x0 - px), min(w, x1 + px)


def subject_metrics(
    img: torch.Tensor,
    gt: torch.Tensor,
    mask: torch.Tensor,
    lpips_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
) -> dict:
    """Subject metrics of ``img [H,W,3]`` vs ``gt [H,W,3]`` (both in [0,1]) with ``mask [H,W,1]``.

    Returns a dict with :data:`SUBJECT_KEYS` (LPIPS entries None without ``lpips_fn``) and
    ``mask_fraction``; empty masks give None values.
    """
    out: dict = {k: None for k in SUBJECT_KEYS}
    m = mask.to(img.dtype).clamp(0, 1)
    out["mask_fraction"] = float(m.mean())
    box = subject_box(m)
    if box is None:
        return out
    y0, y1, x0, x1 = box
    out["psnr_mask"] = float(psnr(img, gt, mask=m))
    smap = ssim_map(img, gt, padding="same")[0]
    out["ssim_mask"] = float((smap * m).sum() / (m.sum() * smap.shape[-1]))
    ci, cg, cm = img[y0:y1, x0:x1], gt[y0:y1, x0:x1], m[y0:y1, x0:x1]
    out["psnr_crop"] = float(psnr(ci, cg))
    out["ssim_crop"] = float(ssim(ci, cg)) if min(ci.shape[:2]) >= 11 else None
    if lpips_fn is not None and min(ci.shape[:2]) >= _LPIPS_MIN:
        out["lpips_crop"] = float(lpips_fn(ci, cg))
        out["lpips_mask"] = float(lpips_fn(ci * cm + cg * (1 - cm), cg))
    return out
