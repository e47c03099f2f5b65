"""Image files: header-only size query, decoding PNG/JPEG/..., fast PNG encoding, float images to uint8.

Every decode first reads the size from the file's header and refuses an image over ``MAX_PIXELS`` in one
line (a 20000 x 20000 PNG of a few kB would take 1.6 GB decoded, and more as floats). JPEG and WebP files
are turned upright by their EXIF orientation (what a phone records; sizes too; Pillow turns TIFF files
itself), PNG files are taken as stored. :func:`read_mask` is the one mask reader: a matte in an alpha channel (an RGBA cut-out,
or a white image with the matte in its alpha), a 0/1 label map, 0/255 or grey levels, 8 or 16 bits,
and it says which it found.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from meshsplat.errors import MeshsplatError

__all__ = [
    "png_size",
    "read_png",
    "png_max",
    "write_png",
    "image_size",
    "read_image",
    "float_to_uint8",
    "MAX_PIXELS",
    "check_pixels",
    "open_image",
    "read_mask",
    "MASK_READINGS",
]

MAX_PIXELS = 8192 * 8192  # the largest image any command renders; a 6000 x 4000 photo is 24 M

_SIG = b"\x89PNG\r\n\x1a\n"


def png_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` from the IHDR chunk, reading 24 bytes."""
    with open(path, "rb") as fh:
        head = fh.read(24)
    if len(head) < 24 or head[:8] != _SIG or head[12:16] != b"IHDR":
        raise MeshsplatError(f"{path}: not a PNG file")
    w, h = struct.unpack(">II", head[16:24])
    return int(w), int(h)


_WIDE_GREY = ("I;16", "I;16B", "I;16L", "I")  # Pillow's modes for 16-bit grey PNGs


def check_pixels(path: Path, width: int, height: int) -> None:
    """Refuse an image of more than ``MAX_PIXELS`` (from its header, before decoding)."""
    if int(width) * int(height) > MAX_PIXELS:
        raise MeshsplatError(
            f"{path}: {width} x {height} pixels is larger than meshsplat decodes (at most {MAX_PIXELS / 1e6:.0f} "
            "million pixels, e.g. 8192 x 8192); downscale the image first"
        )


def open_image(path: Path) -> Any:
    """PIL's lazy open (header only), the size checked; PIL's own decompression-bomb refusal as one line."""
    from PIL import Image

    try:
        im = Image.open(path)
    except Image.DecompressionBombError as exc:
        raise MeshsplatError(f"{path}: larger than meshsplat decodes ({exc}); downscale the image first") from None
    try:
        check_pixels(path, *im.size)
    except MeshsplatError:
        im.close()
        raise
    return im


_EXIF_ORIENTATION = 0x0112
_SWAPS_SIDES = (5, 6, 7, 8)  # the EXIF orientations that turn the image by 90 degrees
_ORIENTED = ("JPEG", "MPO", "WEBP")  # formats whose EXIF orientation Pillow leaves to the reader


def _upright(im: Any) -> Any:
    """``im`` turned by its EXIF orientation (JPEG, WebP; a PNG is taken as stored, as :func:`png_size` reads it)."""
    if im.format not in _ORIENTED:
        return im
    from PIL import ImageOps

    return ImageOps.exif_transpose(im)


def read_png(path: Path, channels: int) -> np.ndarray:
    """Decode to ``[H, W, channels]`` (1 = grey, 3 = RGB): uint8, or uint16 for 16-bit grey files
    (their full range; converting them to 8 bits would clip). Divide by :func:`png_max` for [0, 1].
    16-bit RGB files are read at 8 bits (Pillow keeps the high byte: scaled, not clipped)."""
    try:
        with open_image(path) as raw:
            im = _upright(raw)
            if im.mode in _WIDE_GREY:
                arr = np.array(im, dtype=np.int64)
                if arr.min() < 0 or arr.max() > 65535:
                    raise ValueError(f"grey values outside 0..65535 in mode {im.mode}")
                arr = arr.astype(np.uint16)
                arr = arr[..., None] if channels == 1 else np.repeat(arr[..., None], 3, axis=-1)
                return np.ascontiguousarray(arr)
            converted = im.convert("L" if channels == 1 else "RGB")
            arr = np.array(converted, dtype=np.uint8)
    except (OSError, ValueError, SyntaxError) as exc:
        raise MeshsplatError(f"{path}: cannot decode image ({exc})") from None
    return arr[..., None] if channels == 1 else arr


def png_max(arr: np.ndarray) -> float:
    """Full-scale value of an array from :func:`read_png` (255 or 65535)."""
    return float(np.iinfo(arr.dtype).max)


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of a PNG (header only) or any image PIL reads (JPEG, ...)."""
    with open(path, "rb") as fh:
        is_png = fh.read(8) == _SIG
    if is_png:
        return png_size(path)
    from PIL import Image

    try:
        with Image.open(path) as im:
            w, h = int(im.size[0]), int(im.size[1])
            turned = im.format in _ORIENTED and im.getexif().get(_EXIF_ORIENTATION) in _SWAPS_SIDES
            return (h, w) if turned else (w, h)
    except Image.DecompressionBombError as exc:
        raise MeshsplatError(f"{path}: larger than meshsplat decodes ({exc}); downscale the image first") from None
    except (OSError, ValueError) as exc:
        raise MeshsplatError(f"{path}: not an image ({exc})") from None


def read_image(path: Path, channels: int) -> np.ndarray:
    """Decode a PNG/JPEG/... to uint8 ``[H, W, channels]`` (1 grey, 3 RGB, 4 RGBA; missing alpha = 255)."""
    if channels != 4:
        return read_png(path, channels)
    try:
        with open_image(path) as im:
            arr = np.array(_upright(im).convert("RGBA"), dtype=np.uint8)
    except (OSError, ValueError) as exc:
        raise MeshsplatError(f"{path}: cannot decode image ({exc})") from None
    return arr


MASK_READINGS = {
    "alpha": "the alpha channel (a cut-out or a matte in alpha)",
    "labels": "a 0/1 label map (1 = subject)",
    "grey": "grey levels (0 = background, full scale = subject)",
}


def read_mask(path: Path) -> tuple[np.ndarray, str]:
    """A mask file as float32 ``[H, W, 1]`` in [0, 1] and which of ``MASK_READINGS`` it was read as.

    An image with an alpha channel that is not uniform is read from its alpha (an RGBA cut-out of the
    subject, or a white image whose alpha is the matte: its colour says nothing); else its grey levels
    (colour images by luminance; 16-bit grey at full range). Grey values all in {0, 1} are a label map
    (1 = subject), not a nearly black mask."""
    try:
        with open_image(path) as raw:
            im = _upright(raw)
            bands = im.getbands()
            if "A" in bands or "transparency" in im.info:
                alpha = np.array(im.convert("RGBA"), dtype=np.uint8)[..., 3]
                if alpha.min() != alpha.max():
                    return (alpha.astype(np.float32) / 255.0)[..., None], "alpha"
    except (OSError, ValueError) as exc:
        raise MeshsplatError(f"{path}: cannot decode image ({exc})") from None
    grey = read_png(path, 1)
    if grey.max() == 1:
        return grey.astype(np.float32), "labels"
    return grey.astype(np.float32) / png_max(grey), "grey"


def write_png(path: Path, img: np.ndarray, compress_level: int = 3) -> None:
    """Write uint8 ``[H,W]``, ``[H,W,1]`` or ``[H,W,3]``."""
    from PIL import Image

    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    Image.fromarray(np.ascontiguousarray(img)).save(path, compress_level=compress_level)


def float_to_uint8(img: torch.Tensor | npt.ArrayLike) -> np.ndarray:
    """Float image in [0, 1] (any shape, tensor or array) -> uint8 of the same shape; uint8 passes through.

    The one rounding rule for written images: ``rint(clamp(x, 0, 1) * 255)`` in float32, ties to even
    (numpy's rounding), so an image read back from an 8-bit file and written again is unchanged.
    """
    a = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    if a.dtype == np.uint8:
        return a
    if a.dtype != np.bool_ and not np.issubdtype(a.dtype, np.floating):
        raise MeshsplatError(f"image: expected float in [0, 1] or uint8, got {a.dtype}")
    a = a.astype(np.float32)
    if not np.isfinite(a).all():
        raise MeshsplatError("image: contains NaN/Inf values")
    return np.rint(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)
