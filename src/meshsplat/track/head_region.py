"""Where the head is in a frame: the crop each capture image is cut from, and the head region that
restricts a person matte to what the head model and its Gaussians can cover.

Both are built from the face's forehead-chin axis (so a tilted head gets a tilted region) and its size
``s`` (forehead-to-chin length in pixels): the crop is a square of side ``CROP_SIDE * s`` centred
between forehead and chin, the same side in every frame of a clip. The region is the fitted head mesh's
silhouette (face, ears, neck down to where the mesh ends: :func:`mesh_silhouette`) joined with an
ellipse around skull and hair (``HAIR_*``, feathered: :func:`hair_region`); the person matte outside it
(shoulders, a ponytail below the neck) is left out of the capture's mask, and so are the parts of the
matte inside it that do not touch the head (a bottle or a lamp the segmentation took for the person:
:func:`regions_touching`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meshsplat.track.face_track import CHIN, FOREHEAD

__all__ = [
    "Crop",
    "clip_crops",
    "hair_region",
    "mesh_silhouette",
    "regions_touching",
    "crop_frame",
    "crop_inside",
    "CROP_SIDE",
    "MATTE_HALO",
]

MATTE_HALO = 2  # pixels of a kept region's soft edge (matte below 0.5) that stay in the mask

CROP_SIDE = 2.6  # crop side in face sizes: hair above the forehead and the neck below the chin fit in
HAIR_UP, HAIR_ALONG, HAIR_ACROSS = 0.25, 0.95, 0.95  # ellipse centre shift (up) and semi-axes, face sizes
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


def crop_inside(height: int, width: int, crop: Crop) -> np.ndarray:
    """``[size,size]`` float32 in [0, 1]: the part of the crop that lies inside a ``height x width`` frame
    (:func:`crop_frame` fills the rest with black, which no matte may count as the subject)."""
    return crop_frame(np.full((height, width), 255, np.uint8), crop).astype(np.float32) / 255


def hair_region(landmarks: np.ndarray, width: int, height: int) -> np.ndarray:
    """Soft region ``[height, width]`` in [0, 1] of skull, hair and ears for one face ``[478,3]`` in these
    pixel coordinates: an ellipse around the face, shifted up, tilted with it."""
    mid, up, s = _axis(landmarks)
    right = np.array([-up[1], up[0]])
    ys, xs = np.mgrid[0:height, 0:width]
    p = np.stack([xs + 0.5, ys + 0.5], -1) - mid
    along, across = p @ up, p @ right
    r = np.sqrt(((along - HAIR_UP * s) / (HAIR_ALONG * s)) ** 2 + (across / (HAIR_ACROSS * s)) ** 2)
    # the scaled radius as a signed distance (exact on the minor axis), feathered over FEATHER * s
    return np.clip((1 - r) * HAIR_ACROSS / FEATHER + 0.5, 0, 1).astype(np.float32)


def mesh_silhouette(points: np.ndarray, size: int, radius: float) -> np.ndarray:
    """Where a dense mesh covers a ``size x size`` image: its projected vertices ``[N,2]`` (pixels) as
    discs of ``radius`` pixels, holes filled; ``[size,size]`` float32 in {0, 1}."""
    from scipy import ndimage

    img = np.zeros((size, size), bool)
    p = np.floor(points).astype(np.int64)
    inside = (p[:, 0] >= 0) & (p[:, 0] < size) & (p[:, 1] >= 0) & (p[:, 1] < size)
    img[p[inside, 1], p[inside, 0]] = True
    r = max(1, int(np.ceil(radius)))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disc = xx**2 + yy**2 <= radius**2 + 0.5
    img = ndimage.binary_closing(ndimage.binary_dilation(img, disc), disc, iterations=2, border_value=0)
    return ndimage.gaussian_filter(ndimage.binary_fill_holes(img).astype(np.float32), 0.7)


def regions_touching(matte: np.ndarray, seed: np.ndarray, halo: int = MATTE_HALO) -> np.ndarray:
    """``matte [H,W]`` in [0, 1] without its regions that do not touch ``seed [H,W]`` (bool).

    A region is an 8-connected set of matte >= 0.5; the soft edge below 0.5 stays within ``halo`` pixels
    of a kept region and goes with the others. When no region touches the seed (the segmentation missed
    the head in this frame) the matte is returned as it is.
    """
    from scipy import ndimage

    solid = matte >= 0.5
    labels, n = ndimage.label(solid, structure=np.ones((3, 3), bool))
    touching = np.unique(labels[seed & solid])
    if n == 0 or touching.size == 0 or touching.size == n:
        return matte
    kept = np.isin(labels, touching)
    near = ndimage.binary_dilation(kept, iterations=halo) if halo > 0 else kept
    return (matte * (near & (kept | ~solid))).astype(matte.dtype, copy=False)
