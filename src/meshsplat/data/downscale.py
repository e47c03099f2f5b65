"""Reading a capture at a lower resolution (``downscale``): image sizes, intrinsics, area resizing.

One rule for every layout, applied by :class:`~meshsplat.data.dataset.AvatarDataset` as it hands out
cameras and decodes frames (``open_capture(..., downscale=N)``, ``meshsplat train/import/eval
--downscale N``):

- the factor ``N`` is a number >= 1 (1 = as recorded; 2 halves the width and the height);
- the new size of each camera is ``round(W / N) x round(H / N)`` (halves rounded up), at least 1 pixel;
  a factor above the smaller side of any camera is refused;
- ``K`` is scaled per axis by ``new / old`` (``sx = W'/W`` on ``fx``, ``cx`` and the skew, ``sy = H'/H``
  on ``fy``, ``cy``). meshsplat's pixel (i, j) is the unit square starting at (i, j), its centre at
  (i + 0.5, j + 0.5) (``render._constants.PIXEL_CENTER``), so image coordinates scale by exactly
  ``sx``, ``sy``: a 3D point that projects to (u, v) projects to (sx u, sy v) and lands on the new pixel
  that covers the old one. No half-pixel shift is needed (it would be with centres at integers);
- images and masks are area-averaged: each new pixel is the mean of the old pixels it covers, weighted
  by the covered area (exact box filter, also for non-integer factors; for an integer factor it is the
  mean of N x N blocks). Masks stay soft (fractional at the subject's edge), as training and evaluation
  use them: ``composite(image, mask, bg) = image * mask + bg * (1 - mask)``. A frame with a mask has its
  colour averaged over the subject only (``area(image * mask) / area(mask)``; ``area(image)`` where the
  mask is empty), so its composite over any background equals the area-downscaled full-resolution
  composite and the recorded background does not bleed into the subject's edge.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from meshsplat.errors import MeshsplatError

__all__ = ["check_downscale", "downscaled_size", "scale_intrinsics", "area_resize", "downscale_frame"]


def check_downscale(factor: object, sizes: dict[str, tuple[int, int]] | None = None) -> float:
    """``factor`` as a float >= 1, checked against the ``(width, height)`` of each camera in ``sizes``."""
    if isinstance(factor, bool) or not isinstance(factor, (int, float, np.integer, np.floating)):
        raise MeshsplatError(f"downscale: expected a number >= 1 (2 halves width and height), got {factor!r}")
    f = float(factor)
    if not math.isfinite(f) or f < 1:
        raise MeshsplatError(
            f"downscale: expected a factor >= 1 (2 halves width and height; 1 keeps the recorded size), got {f:g}"
        )
    for cid, (w, h) in (sizes or {}).items():
        if f > min(w, h):
            raise MeshsplatError(
                f"downscale: {f:g} is larger than the {w}x{h} image of camera {cid!r} (at most {min(w, h)})"
            )
    return f


def downscaled_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """``(round(width / factor), round(height / factor))``, halves rounded up, at least 1."""
    return max(1, math.floor(width / factor + 0.5)), max(1, math.floor(height / factor + 0.5))


def scale_intrinsics(K: np.ndarray, width: int, height: int, new_width: int, new_height: int) -> np.ndarray:
    """``K [3,3]`` of a ``width x height`` image for the same view at ``new_width x new_height`` (pixel
    centres at +0.5: row 0 scales by ``new_width / width``, row 1 by ``new_height / height``)."""
    out = np.array(K, dtype=np.float64)
    out[0] *= new_width / width
    out[1] *= new_height / height
    return out


@lru_cache(maxsize=16)
def _area_weights(n: int, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(index [m,k], weight [m,k])``: new pixel ``i`` of ``m`` is the weighted sum of old pixels
    ``index[i]`` of ``n``; weights are the overlap of ``[j, j+1)`` with ``[i r, (i+1) r)``, ``r = n / m``,
    divided by ``r`` (each row sums to 1)."""
    r = n / m
    k = math.ceil(r) + 1
    i = np.arange(m, dtype=np.float64)[:, None]
    idx = np.floor(i * r).astype(np.int64) + np.arange(k)[None, :]
    lo = np.maximum(idx, i * r)
    hi = np.minimum(idx + 1, (i + 1) * r)
    w = np.clip(hi - lo, 0.0, None) / r
    w[idx >= n] = 0.0
    return torch.from_numpy(np.minimum(idx, n - 1)), torch.from_numpy(w)


def area_resize(image: torch.Tensor, new_width: int, new_height: int) -> torch.Tensor:
    """``image [H,W,C]`` area-averaged to ``[new_height, new_width, C]`` (exact box filter)."""
    h, w = int(image.shape[0]), int(image.shape[1])
    x = image.to(torch.float64)
    if new_height != h:
        idx, wt = _area_weights(h, new_height)
        x = (x[idx] * wt[:, :, None, None]).sum(1)
    if new_width != w:
        idx, wt = _area_weights(w, new_width)
        x = (x[:, idx] * wt[None, :, :, None]).sum(2)
    return x.to(image.dtype)


def downscale_frame(
    image: torch.Tensor, mask: torch.Tensor | None, new_width: int, new_height: int
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``image [H,W,3]`` and ``mask [H,W,1]`` (or None) at ``new_width x new_height`` (module docstring)."""
    if mask is None:
        return area_resize(image, new_width, new_height).clamp_(0, 1), None
    m = area_resize(mask.to(torch.float64), new_width, new_height)
    fg = area_resize(image.to(torch.float64) * mask.to(torch.float64), new_width, new_height)
    plain = area_resize(image.to(torch.float64), new_width, new_height)
    img = torch.where(m > 1e-6, fg / m.clamp_min(1e-6), plain).clamp_(0, 1)
    return img.to(image.dtype), m.clamp_(0, 1).to(mask.dtype)
