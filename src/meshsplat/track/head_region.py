"""Where the head is in a frame: the crop each capture image is cut from, and the head region that
restricts a person matte to head, hair and neck.

Both are built from the face's forehead-chin axis (so a tilted head gets a tilted region) and its size
``s`` (forehead-to-chin length in pixels): the crop is a square of side ``CROP_SIDE * s`` centred
between forehead and chin, the same side in every frame of a clip; the region is an ellipse around the
skull and hair (``HAIR_*``) joined with a band for the neck below the chin (``NECK_*``), feathered.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meshsplat.track.face_track import CHIN, FOREHEAD

__all__ = ["Crop", "clip_crops", "head_region", "crop_frame", "CROP_SIDE"]

CROP_SIDE = 2.6  # crop side in face sizes: hair above the forehead and the neck below the chin fit in
HAIR_UP, HAIR_ALONG, HAIR_ACROSS = 0.15, 1.05, 0.95  # ellipse centre shift (up) and semi-axes, face sizes
NECK_DOWN, NECK_HALF_WIDTH = 0.75, 0.5  # neck band below the chin: length and half width, face sizes
FEATHER = 0.06  # soft edge width, face sizes


@dataclass
class Crop:
    """A square crop: top-left corner ``x0, y0`` and ``side`` in source pixels; ``size`` output pixels."""

    x0: float
    y0: float
    side: float
    size: int

    @property
    def scale(self) -> float:
        return self.size / self.side

    def K(self, K_src: np.ndarray) -> np.ndarray:
        """Intrinsics ``[3,3]`` of the crop, from the source frame's (pixel centres at +0.5 in both)."""
        s = self.scale
        A = np.array([[s, 0, -s * self.x0], [0, s, -s * self.y0], [0, 0, 1]], np.float64)
        return A @ np.asarray(K_src, np.float64)

    def to_crop(self, xy: np.ndarray) -> np.ndarray:
        """Source pixel coordinates ``[...,2]`` -> crop pixel coordinates."""
        return (xy - np.array([self.x0, self.y0])) * self.scale


def _axis(lm: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Face midpoint ``[2]``, unit up vector ``[2]`` (image coordinates, y down) and size."""
    top, bottom = lm[FOREHEAD, :2].astype(np.float64), lm[CHIN, :2].astype(np.float64)
    d = top - bottom
    s = float(np.linalg.norm(d))
    return (top + bottom) / 2, d / max(s, 1e-9), s


def clip_crops(landmarks: np.ndarray, size: int, smooth: int = 5) -> list[Crop]:
    """One crop per frame of ``landmarks [T,478,3]`` (pixels; every row a found face): the side is
    ``CROP_SIDE`` times the clip's median face size, the centre follows the face (a centred moving
    average over ``smooth`` frames keeps it steady)."""
    axes = [_axis(lm) for lm in landmarks]
    side = CROP_SIDE * float(np.median([a[2] for a in axes]))
    centres = np.array([a[0] for a in axes])
    k = max(1, int(smooth))
    if k > 1 and len(centres) > 1:
        pad = np.pad(centres, ((k // 2, k - 1 - k // 2), (0, 0)), mode="edge")
        kernel = np.ones(k) / k
        centres = np.stack([np.convolve(pad[:, j], kernel, mode="valid") for j in range(2)], 1)
    return [Crop(float(c[0] - side / 2), float(c[1] - side / 2), side, int(size)) for c in centres]


def crop_frame(frame: np.ndarray, crop: Crop) -> np.ndarray:
    """Cut ``crop`` out of ``frame [H,W,C]`` (uint8 or float) and resize it to ``size x size``
    (area-weighted when shrinking); outside the frame is black."""
    from PIL import Image

    h, w = frame.shape[:2]
    x0, y0 = int(np.floor(crop.x0)), int(np.floor(crop.y0))
    side = int(np.ceil(crop.side + (crop.x0 - x0))) + 1
    pad = [(max(0, -y0), max(0, y0 + side - h)), (max(0, -x0), max(0, x0 + side - w))] + [(0, 0)] * (frame.ndim - 2)
    src = np.pad(frame, pad)
    sx, sy = x0 + pad[1][0], y0 + pad[0][0]
    patch = src[sy : sy + side, sx : sx + side]
    # the exact box (sub-pixel start) resampled by PIL, which takes source-pixel box coordinates
    box = (crop.x0 - x0, crop.y0 - y0, crop.x0 - x0 + crop.side, crop.y0 - y0 + crop.side)
    img = Image.fromarray(patch if patch.dtype == np.uint8 else np.clip(patch * 255 + 0.5, 0, 255).astype(np.uint8))
    out = np.asarray(
        img.resize(
            (crop.size, crop.size), Image.Resampling.BOX if crop.scale < 1 else Image.Resampling.BILINEAR, box=box
        )
    )
    return out


def head_region(landmarks: np.ndarray, width: int, height: int) -> np.ndarray:
    """Soft head region ``[height, width]`` in [0, 1] for one face ``[478,3]`` in these pixel
    coordinates: skull, hair and ears in an ellipse around the face, and the neck below the chin."""
    mid, up, s = _axis(landmarks)
    right = np.array([-up[1], up[0]])
    ys, xs = np.mgrid[0:height, 0:width]
    p = np.stack([xs + 0.5, ys + 0.5], -1) - mid
    along, across = p @ up, p @ right
    f = FEATHER * s
    # ellipse: signed distance approximated by the scaled radius
    r = np.sqrt(((along - HAIR_UP * s) / (HAIR_ALONG * s)) ** 2 + (across / (HAIR_ACROSS * s)) ** 2)
    ellipse = np.clip((1 - r) * HAIR_ACROSS * s / f + 0.5, 0, 1)
    chin = -0.5 * s  # the chin lies half a face size below the midpoint
    neck = np.minimum(
        np.clip((along - (chin - NECK_DOWN * s)) / f + 0.5, 0, 1),
        np.clip((NECK_HALF_WIDTH * s - np.abs(across)) / f + 0.5, 0, 1),
    )
    neck = np.minimum(neck, np.clip((0.2 * s - along) / f + 0.5, 0, 1))  # up to just above the chin
    return np.maximum(ellipse, neck).astype(np.float32)
