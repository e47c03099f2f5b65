"""Video files in and out (imageio-ffmpeg, imported lazily), and numbered PNGs.

Reading (:func:`probe_video`, :func:`read_video_frames`): MP4/MOV/WebM/MKV/AVI as phones and cameras
write them; ffmpeg applies the rotation metadata (a portrait phone clip comes out upright), ``fps``
resamples by timestamps (variable frame rate included), ``max_side`` scales large frames down before
they reach Python. Frames come out as uint8 ``[H,W,3]``.

Writing: frames are ``[H,W,3]`` (or ``[H,W,4]``/``[H,W,1]``) arrays or tensors, float in ``[0, 1]``
or uint8. When the MP4 cannot be written (no ffmpeg), :func:`write_video` says why and
writes PNGs instead.
"""

from __future__ import annotations

import errno
import math
import os
import shutil
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.io.images import float_to_uint8

__all__ = [
    "to_uint8",
    "write_png_frames",
    "write_mp4",
    "write_video",
    "VideoResult",
    "VideoInfo",
    "probe_video",
    "read_video_frames",
]


def to_uint8(frame: torch.Tensor | np.ndarray) -> np.ndarray:
    """``[H,W,C]`` float in [0,1] (clamped) or uint8, tensor or array -> uint8 ``[H,W,3|4]``."""
    if isinstance(frame, torch.Tensor):
        frame = frame.detach().cpu().numpy()
    a = np.asarray(frame)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise MeshsplatError(f"frame: expected shape [H,W,3] (or 1/4 channels), got {list(a.shape)}")
    if a.dtype != np.uint8:
        if not np.issubdtype(a.dtype, np.floating):
            raise MeshsplatError(f"frame: expected float in [0,1] or uint8, got {a.dtype}")
        if not np.isfinite(a).all():
            raise MeshsplatError("frame: contains NaN/Inf values")
        a = float_to_uint8(a)
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    return a


def write_png_frames(frames: Iterable, folder: str | os.PathLike, prefix: str = "frame_") -> list[Path]:
    """Write ``<folder>/<prefix>00000.png``, ...; returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, fr in enumerate(frames):
        p = folder / f"{prefix}{i:05d}.png"
        Image.fromarray(to_uint8(fr)).save(p)
        paths.append(p)
    return paths


def _even(a: np.ndarray) -> np.ndarray:
    """Pad to even width/height by repeating the last row/column (yuv420p needs it)."""
    h, w = a.shape[:2]
    return np.pad(a, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") if (h % 2 or w % 2) else a


def write_mp4(frames: Iterable, path: str | os.PathLike, fps: float = 30.0, quality: int = 8) -> Path:
    """H.264 MP4 via imageio-ffmpeg; raises MeshsplatError when it is unavailable or fails."""
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (ensures the ffmpeg binary package is present)
    except ImportError as exc:
        raise MeshsplatError(
            f"MP4 output needs imageio and imageio-ffmpeg (pip install 'meshsplat[video]'): {exc}"
        ) from None
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    count = 0
    try:
        writer = imageio.get_writer(
            str(path), fps=fps, codec="libx264", quality=quality, pixelformat="yuv420p", macro_block_size=1
        )
        try:
            for fr in frames:
                writer.append_data(_even(to_uint8(fr)[..., :3]))
                count += 1
        finally:
            writer.close()
    except MeshsplatError:
        raise
    except Exception as exc:  # noqa: BLE001 - ffmpeg missing or failing: fall back to PNG frames
        path.unlink(missing_ok=True)
        raise MeshsplatError(f"could not write MP4 {str(path)!r}: {type(exc).__name__}: {exc}") from None
    if count == 0:
        path.unlink(missing_ok=True)
        raise MeshsplatError("write_mp4: no frames given")
    _check_written(path, count)
    return path


def _check_written(path: Path, count: int) -> None:
    """ffmpeg can fail (a full disk) without imageio raising: count the frames that really landed."""
    import imageio_ffmpeg

    try:
        got = imageio_ffmpeg.count_frames_and_secs(str(path))[0]
    except Exception:  # noqa: BLE001 - unreadable output counts as no frames
        got = 0
    if got == count:
        return
    path.unlink(missing_ok=True)
    free = shutil.disk_usage(path.parent).free
    if free < 4 * 1024**2:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    raise MeshsplatError(f"could not write MP4 {str(path)!r}: ffmpeg wrote {got} of {count} frames")


@dataclass
class VideoResult:
    """What :func:`write_video` wrote: ``mp4`` (None on failure), ``pngs``, and ``error``."""

    mp4: Path | None
    pngs: list[Path] = field(default_factory=list)
    error: str | None = None


def write_video(
    frames: Iterable,
    path: str | os.PathLike,
    fps: float = 30.0,
    png_dir: str | os.PathLike | None = None,
    png_fallback: bool = True,
) -> VideoResult:
    """Write ``frames`` to the MP4 ``path``; PNGs too when ``png_dir`` is given.

    If the MP4 fails and ``png_fallback`` is true, the frames are written as PNGs to
    ``png_dir`` (default ``<path without suffix>_frames/``) and a warning gives the reason.
    """
    frames = [to_uint8(f) for f in frames]
    if not frames:
        raise MeshsplatError("write_video: no frames given")
    path = Path(path)
    result = VideoResult(mp4=None)
    if png_dir is not None:
        result.pngs = write_png_frames(frames, png_dir)
    try:
        result.mp4 = write_mp4(frames, path, fps=fps)
    except MeshsplatError as exc:
        result.error = str(exc)
        if not png_fallback:
            raise
        if not result.pngs:
            folder = Path(png_dir) if png_dir is not None else path.with_name(path.stem + "_frames")
            result.pngs = write_png_frames(frames, folder)
        warnings.warn(
            f"{exc}; wrote {len(result.pngs)} PNG frames to {result.pngs[0].parent} instead",
            MeshsplatWarning,
            stacklevel=2,
        )
    return result


@dataclass
class VideoInfo:
    """What :func:`probe_video` found: the frame size as read (after rotation, before ``max_side``),
    ``fps`` (nominal), ``duration`` (seconds), ``rotated`` (the file asked for a quarter turn)."""

    path: Path
    width: int
    height: int
    fps: float
    duration: float
    rotated: bool

    @property
    def frames(self) -> int:
        """The nominal frame count, ``fps * duration``."""
        return max(1, round(self.fps * self.duration))


def _ffmpeg_reader(path: Path, input_params: list[str], output_params: list[str]):
    """imageio-ffmpeg's frame generator, started; ``(generator, meta)``."""
    try:
        import imageio_ffmpeg
    except ImportError as exc:
        raise MeshsplatError(f"reading a video needs imageio-ffmpeg (pip install 'meshsplat[video]'): {exc}") from None
    import logging

    logging.getLogger("imageio_ffmpeg").setLevel(logging.ERROR)  # its "size differs" note is the rotation
    gen = imageio_ffmpeg.read_frames(str(path), input_params=input_params, output_params=output_params)
    try:
        meta = next(gen)
    except (OSError, RuntimeError, StopIteration, IndexError, AttributeError) as exc:
        gen.close()
        text = " ".join(str(exc).split())[-200:]
        raise MeshsplatError(
            f"{path}: not a video ffmpeg can read ({type(exc).__name__}: {text}); give an MP4, MOV, WebM or MKV file"
        ) from None
    return gen, meta


def _video_path(path: str | os.PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise MeshsplatError(f"video not found: {p}")
    if not p.is_file():
        raise MeshsplatError(f"{p}: not a file (a video file: MP4, MOV, WebM or MKV)")
    if p.stat().st_size == 0:
        raise MeshsplatError(f"{p}: the file is empty; give a video file")
    return p


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """Size, frame rate and duration of a video file, without decoding more than its first frame."""
    p = _video_path(path)
    gen, meta = _ffmpeg_reader(p, [], [])
    gen.close()
    w, h = (int(x) for x in meta["size"])
    sw, sh = (int(x) for x in meta.get("source_size", meta["size"]))
    fps = float(meta.get("fps") or 0.0)
    if not (w > 0 and h > 0 and math.isfinite(fps) and fps > 0):
        raise MeshsplatError(f"{p}: ffmpeg reports no usable video stream ({w}x{h} at {fps} fps)")
    duration = float(meta.get("duration") or 0.0)
    return VideoInfo(p, w, h, fps, duration, rotated=(w, h) == (sh, sw) and w != h)


def read_video_frames(
    path: str | os.PathLike,
    fps: float | None = None,
    start: float = 0.0,
    seconds: float | None = None,
    max_side: int | None = None,
) -> Iterator[np.ndarray]:
    """The frames of a video as uint8 ``[H,W,3]``, one at a time (rotation applied).

    ``fps`` resamples to that rate by timestamps (None: every frame as stored), ``start``/``seconds``
    cut a time range, ``max_side`` scales frames whose longer side is larger down to it (aspect kept).
    """
    p = _video_path(path)
    for name, v in (("fps", fps), ("seconds", seconds)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise MeshsplatError(f"{name}: expected a positive number, got {v}")
    if not (math.isfinite(start) and start >= 0):
        raise MeshsplatError(f"start: expected seconds >= 0, got {start}")
    inp = ["-ss", f"{start:.6f}"] if start > 0 else []
    filters = [f"fps={fps:g}"] if fps is not None else []
    if max_side is not None:
        m = int(max_side)
        # longer side to at most m, even sizes (yuv decoders), aspect kept
        filters.append(f"scale='if(gt(iw,ih),min({m},iw),-2)':'if(gt(iw,ih),-2,min({m},ih))'")
    out = (["-vf", ",".join(filters)] if filters else []) + (["-t", f"{seconds:.6f}"] if seconds else [])
    gen, meta = _ffmpeg_reader(p, inp, out)
    w, h = (int(x) for x in meta["size"])
    n = w * h * 3
    try:
        for buf in gen:
            if len(buf) != n:
                break
            yield np.frombuffer(buf, np.uint8).reshape(h, w, 3)
    finally:
        gen.close()
