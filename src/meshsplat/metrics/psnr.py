"""Peak signal-to-noise ratio for images in [0, 1]."""

from __future__ import annotations

import torch

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError

__all__ = ["psnr", "as_batch_hwc"]


def as_batch_hwc(name: str, img: torch.Tensor) -> torch.Tensor:
    """``[H,W,C]`` or ``[B,H,W,C]`` -> ``[B,H,W,C]`` (validated, floating point, finite)."""
    if not isinstance(img, torch.Tensor) or img.dim() not in (3, 4):
        got = list(img.shape) if isinstance(img, torch.Tensor) else type(img).__name__
        raise MeshsplatError(f"{name}: expected shape [H,W,C] or [B,H,W,C], got {got}")
    check_tensor(name, img, "...,H,W,C", dtype="float", finite=True)
    return img if img.dim() == 4 else img.unsqueeze(0)


def _mask_batch(mask: torch.Tensor, img: torch.Tensor) -> torch.Tensor:
    """Mask ``[H,W]``, ``[H,W,1]``, ``[B,H,W]`` or ``[B,H,W,1]`` -> ``[B,H,W,1]`` float."""
    b, h, w, _ = img.shape
    m = mask.to(img.dtype)
    if m.dim() == 2:
        m = m[None, :, :, None]
    elif m.dim() == 3:
        m = m[None] if (m.shape[0], m.shape[1]) == (h, w) and m.shape[2] == 1 else m.unsqueeze(-1)
    if m.dim() != 4 or tuple(m.shape[1:]) != (h, w, 1) or m.shape[0] not in (1, b):
        raise MeshsplatError(
            f"mask: expected shape [H,W], [H,W,1], [B,H,W] or [B,H,W,1] with H={h}, W={w}, got {list(mask.shape)}"
        )
    return m.expand(b, h, w, 1)


def psnr(
    img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None = None, reduction: str = "mean"
) -> torch.Tensor:
    """PSNR in dB of ``img`` against ``ref`` ([H,W,3] or [B,H,W,3], range [0, 1]).

    ``mask`` ([H,W], [H,W,1] or [B,H,W,1], weights in [0,1]) restricts the mean squared
    error to the masked pixels. Computed per image; ``reduction="mean"`` averages the
    per-image dB values, ``"none"`` returns ``[B]``. Identical images give ``inf``.
    """
    a = as_batch_hwc("img", img)
    b = as_batch_hwc("ref", ref)
    if a.shape != b.shape:
        raise MeshsplatError(f"ref: expected shape {list(img.shape)} like img, got {list(ref.shape)}")
    se = (a - b.to(a.dtype)).pow(2)
    if mask is None:
        mse = se.mean(dim=(1, 2, 3))
    else:
        m = _mask_batch(mask, a)
        denom = m.sum(dim=(1, 2, 3)) * a.shape[-1]
        if bool((denom <= 0).any()):
            raise MeshsplatError("mask: selects no pixel in at least one image")
        mse = (se * m).sum(dim=(1, 2, 3)) / denom
    out = -10.0 * torch.log10(mse)
    if reduction == "none":
        return out
    if reduction != "mean":
        raise MeshsplatError(f"reduction: expected 'mean' or 'none', got {reduction!r}")
    return out.mean()
