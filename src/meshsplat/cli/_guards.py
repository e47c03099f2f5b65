"""Checks every command runs before working: size arguments within documented ranges, a memory
estimate against what is available, and an output location that can be written.

The ranges are the table in docs/limits.md (keep both in step). Memory estimates are measured
on CPU (bench/badinput.py exercises them): the PyTorch rasterizer needs about 160 bytes per
pixel plus up to 1.5 GB for its band of (pixel, Gaussian) pairs; the synth rasterizer about
128 bytes per supersampled pixel.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

from meshsplat.cli._memory import available_memory
from meshsplat.errors import MeshsplatError, MeshsplatWarning, os_error_text

__all__ = [
    "LIMITS",
    "check_range",
    "check_memory",
    "check_output_dir",
    "render_bytes",
    "animation_bytes",
    "synth_bytes",
]

# name -> (low, high, unit); both ends included
LIMITS = {
    "render --size": (16, 8192, "pixels per side"),
    "render --fps": (0.1, 240.0, "frames per second"),
    "render --seconds": (0.01, 3600.0, "seconds"),
    "render frames": (1, 100_000, "frames"),
    "render --fov": (1.0, 170.0, "degrees"),
    "render --elevation": (-89.0, 89.0, "degrees"),
    "synth --resolution": (16, 4096, "pixels"),
    "synth --supersample": (1, 8, "x"),
    "synth resolution x supersample": (16, 8192, "pixels"),
    "synth --frames": (1, 20_000, "frames"),
    "synth --test-frames": (0, 20_000, "frames"),
    "synth --views": (1, 256, "cameras"),
    "synth --test-views": (0, 64, "cameras"),
    "synth --train-fraction": (0.01, 1.0, ""),
    "synth --driver-smooth": (0, 1000, "iterations"),
    "synth --driver-decimate": (0.001, 1.0, ""),
    "synth --pose-noise": (0.0, 1.0, "radians"),
    "synth --spp": (1, 65536, "samples per pixel"),
    "synth --roughness": (0.01, 1.0, ""),
    "synth --seed": (0, 2**31 - 1, ""),
    "view --frames": (1, 100_000, "frames"),
    "view --fps": (0.1, 240.0, "frames per second"),
    "view --port": (1, 65535, ""),
    "eval --max-frames": (1, 1_000_000, "frames"),
    "train --iters": (1, 10_000_000, "iterations"),
    "train --minutes": (0.1, 525_600.0, "minutes"),
}
_MEMORY_HEADROOM = 0.9  # refuse what needs more than this share of the available memory


def check_range(name: str, value, limit: str | None = None) -> None:
    """Raise unless ``value`` lies in ``LIMITS[limit or name]``."""
    lo, hi, unit = LIMITS[limit or name]
    if value is None:
        return
    if value != value or not lo <= value <= hi:  # NaN fails too
        raise MeshsplatError(
            f"{name}: expected {lo:g}..{hi:g}{' ' + unit if unit else ''}, got {value:g} (see docs/limits.md)"
        )


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB"


def check_memory(what: str, needed: float, advice: str) -> None:
    """Refuse a request whose estimated memory does not fit in what is available."""
    avail = available_memory()
    if avail is None:
        warnings.warn(
            f"could not read how much memory this system has free, so {what} (about {_gb(needed)}) is not "
            "checked against it",
            MeshsplatWarning,
            stacklevel=2,
        )
        return
    if needed > _MEMORY_HEADROOM * avail:
        raise MeshsplatError(f"{what} needs about {_gb(needed)} of memory but only {_gb(avail)} is available; {advice}")


def render_bytes(width: int, height: int, frames: int = 1) -> float:
    """Estimate: the rasterizer's buffers plus the rendered frames kept for the video."""
    px = float(width) * float(height)
    return min(1.5e9, 650.0 * px * 8) + 160.0 * px + 2 * 3.0 * px * frames


def animation_bytes(frames: int, num_vertices: int) -> float:
    """Estimate: posed vertex frames kept for rendering or a viewer bundle (float32, plus one working copy)."""
    return 2 * 12.0 * float(frames) * float(num_vertices)


def synth_bytes(resolution: int, supersample: int) -> float:
    return 2e8 + 128.0 * (float(resolution) * supersample) ** 2


def check_output_dir(path: str | os.PathLike, flag: str = "--out") -> Path:
    """``path`` is (or can become) a writable folder; checked before any work, nothing is created."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise MeshsplatError(f"{flag} {p} is an existing file; give a folder (existing or new)")
    probe = p
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise MeshsplatError(f"{flag} {p}: {probe} is a file, so no folder can be made below it")
    if probe.exists() and not os.access(probe, os.W_OK | os.X_OK):
        try:  # access() alone cannot tell a read-only file system from a permission problem
            statvfs = getattr(os, "statvfs", None)  # POSIX only
            ro = statvfs is not None and bool(statvfs(probe).f_flag & os.ST_RDONLY)
        except OSError as exc:
            raise MeshsplatError(f"{flag} {p}: {os_error_text(exc)}") from None
        why = "is on a read-only file system" if ro else "is not writable for this user"
        raise MeshsplatError(f"{flag} {p}: {probe} {why}; choose another location")
    return p
