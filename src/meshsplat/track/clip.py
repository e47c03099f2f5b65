"""A clip to track, as both trackers (``head_capture``, ``body_capture``) take it: the settings, the output
folder checked, the video probed, its frames streamed, progress per stage, and what was written."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from meshsplat.errors import MeshsplatError
from meshsplat.io.video import VideoInfo, probe_video, read_video_frames

__all__ = ["TrackSettings", "TrackResult", "Clip", "open_clip", "MIN_FRAMES", "TRACK_MAX_SIDE"]

MIN_FRAMES = 10  # fewer frames with a face than this cannot pin an identity (and leave nothing to test)
TRACK_MAX_SIDE = 1920  # frames are tracked and cropped at most this large (4K is scaled down by ffmpeg)


@dataclass
class TrackSettings:
    """What :func:`track_head` does with a clip: output ``size`` (square crops, pixels), ``fps``
    (resample; None keeps every frame), ``start``/``seconds`` (a time range), ``max_frames``, the
    ``train_fraction`` of frames (from the start) that train, and ``overwrite``."""

    size: int = 512
    fps: float | None = None
    start: float = 0.0
    seconds: float | None = None
    max_frames: int | None = None
    train_fraction: float = 0.8
    overwrite: bool = False

    def check(self) -> None:
        if not 64 <= self.size <= 2048:
            raise MeshsplatError(f"size: expected 64 to 2048 pixels, got {self.size}")
        if not 0.0 < self.train_fraction < 1.0:
            raise MeshsplatError(f"train fraction: expected a number between 0 and 1, got {self.train_fraction}")
        if self.max_frames is not None and self.max_frames < MIN_FRAMES:
            raise MeshsplatError(f"max frames: expected at least {MIN_FRAMES}, got {self.max_frames}")


@dataclass
class TrackResult:
    """What was written: the capture folder, frame counts, the fit's landmark error, times (seconds)."""

    capture: Path
    frames: int
    dropped: list[str]
    train: int
    test: int
    error_px: float
    seconds: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


@dataclass
class Clip:
    """The video to track: its settings (checked), ``info``, frame rate after resampling ``fps`` and the
    number of frames it will give at most (``total``, for progress)."""

    settings: TrackSettings
    info: VideoInfo
    fps: float
    total: int
    progress: Callable[[str, int, int], None] | None = None

    def frames(self) -> Iterator[np.ndarray]:
        """The frames ``[H,W,3]`` uint8 in order (resampled, in the time range, at most ``max_frames``)."""
        s = self.settings
        for i, frame in enumerate(read_video_frames(self.info.path, s.fps, s.start, s.seconds, TRACK_MAX_SIDE)):
            if s.max_frames is not None and i >= s.max_frames:
                return
            yield frame

    def tick(self, stage: str) -> Callable[[int], None]:
        """A callback reporting frame ``i`` of ``stage`` as done."""
        progress, total = self.progress, self.total
        return (lambda i: progress(stage, i + 1, total)) if progress else (lambda i: None)

    def time_of(self, i: int) -> str:
        """Frame ``i``'s time in the video, as the messages name it."""
        return f"{self.settings.start + i / self.fps:.2f}s"

    def times(self, n: int) -> np.ndarray:
        """The times (seconds) of the first ``n`` frames ``[n]``."""
        return self.settings.start + np.arange(n) / self.fps


def open_clip(
    video: str | Path,
    out: Path,
    settings: TrackSettings | None,
    progress: Callable[[str, int, int], None] | None,
) -> Clip:
    """Check ``settings`` and that ``out`` may be written (new, empty, or ``overwrite``), then probe ``video``."""
    s = settings or TrackSettings()
    s.check()
    if out.exists() and any(out.iterdir()) and not s.overwrite:
        raise MeshsplatError(f"{out}: not empty; choose a new folder, or pass --overwrite to replace its capture")
    info = probe_video(video)
    fps = s.fps or info.fps
    total = info.frames if s.seconds is None else max(1, round(fps * s.seconds))
    if s.max_frames is not None:
        total = min(total, s.max_frames)
    return Clip(s, info, fps, total, progress)
