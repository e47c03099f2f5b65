"""Render an avatar through any animation to PNG frames and an MP4.

    src = AnimationSource("gltf", "walk.glb", clip="Walk", fps=25)         # --animation gltf walk.glb --clip Walk
    anim = load_animation(src, avatar)                                      # frames on the avatar's mesh
    cams = orbit_cameras(anim.frames, 512, 512, orbit_deg=360)              # auto-framed
    render_animation(avatar, anim, cams, "out/")                            # out/frames/*.png, out/animation.mp4

What drives the avatar, and how a driver is matched to its canonical mesh, is the animation package's business
(:mod:`meshsplat.animation.source`, :mod:`meshsplat.animation.avatar_match`); this module renders.
Cameras follow the project convention (world->camera ``viewmat`` in OpenCV axes, world +y up).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from meshsplat.animation import Animation, AnimationSource, load_animation
from meshsplat.camera import Camera, orbit_cameras
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.source_map import SourceMap
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.io.video import to_uint8, write_png_frames, write_video
from meshsplat.render.background import background_color

__all__ = ["AnimationResult", "render_animation"]


@dataclass
class AnimationResult:
    """``mp4`` path (None when it could not be written, see ``error``), ``pngs``, timing."""

    mp4: Path | None
    pngs: list[Path] = field(default_factory=list)
    num_frames: int = 0
    render_ms_mean: float = 0.0
    error: str | None = None


# ---------------------------------------------------------------- rendering
@torch.no_grad()
def render_animation(
    avatar: Avatar,
    vertices: Iterable[torch.Tensor] | torch.Tensor | Animation | AnimationSource,
    cameras: Camera | Sequence[Camera] | Callable[[int], Camera] | None,
    out_dir: str | Path,
    fps: float | None = None,
    background: str | Sequence[float] | torch.Tensor = (1.0, 1.0, 1.0),
    name: str = "animation",
    write_pngs: bool = True,
    write_mp4: bool = True,
    backend: str = "auto",
    progress: bool = False,
    dataset: AvatarDataset | None = None,
    source_map: SourceMap | None = None,
) -> AnimationResult:
    """Render ``avatar`` at every frame of ``vertices`` to ``out_dir``.

    ``vertices``: frames (each ``[V,3]``), a loaded :class:`~meshsplat.animation.Animation`, or an
    :class:`~meshsplat.animation.AnimationSource` (loaded here with ``dataset`` and ``source_map``,
    see :func:`~meshsplat.animation.load_animation`).
    ``cameras``: one :class:`Camera` for all frames, one per frame, ``frame -> Camera``, or None: the
    animation's own per-frame cameras (a dataset split), else an orbit auto-framed on it (512x512).
    ``fps``: default the animation's (25 for plain frames).
    Writes ``out_dir/frames/frame_00000.png ...`` and ``out_dir/<name>.mp4`` (PNG frames are kept as
    the fallback when no ffmpeg is available). ``background``: ``[3]`` in [0, 1] or white/black.
    """
    if isinstance(vertices, AnimationSource):
        vertices = load_animation(vertices, avatar, dataset=dataset, source_map=source_map)
    if isinstance(vertices, Animation):
        fps = vertices.fps if fps is None else fps
        if cameras is None and vertices.cameras is not None:
            cameras = vertices.cameras
        vertices = vertices.vertex_frames()
    fps = 25.0 if fps is None else fps
    if fps <= 0:
        raise MeshsplatError(f"fps: expected > 0, got {fps}")
    if not (write_pngs or write_mp4):
        raise MeshsplatError("render_animation: nothing to write (write_pngs and write_mp4 are both False)")
    seq = list(vertices) if not isinstance(vertices, torch.Tensor) else list(vertices.unbind(0))
    if cameras is None:
        if not seq:
            raise MeshsplatError("vertices: the animation has no frames")
        cameras = orbit_cameras(seq, 512, 512)
    if isinstance(cameras, Camera):
        cameras = [cameras] * len(seq)  # one camera for every frame
    if callable(cameras):
        cam_at = cameras
    else:
        cam_list = list(cameras)

        def cam_at(i: int) -> Camera:
            if i >= len(cam_list):
                raise MeshsplatError(f"cameras: {len(cam_list)} given, but the animation has more frames")
            return cam_list[i]

    bg = background_color(background)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frames, times = [], []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(seq), desc="render", dynamic_ncols=True)
    for i, v in enumerate(seq):
        cam = cam_at(i)
        t0 = time.perf_counter()
        r = avatar.render(v, cam, bg, backend=backend)
        frames.append(to_uint8(r.image.float().clamp(0, 1)))
        times.append(time.perf_counter() - t0)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    if not frames:
        raise MeshsplatError("vertices: the animation has no frames")
    result = AnimationResult(mp4=None, num_frames=len(frames), render_ms_mean=1000.0 * float(np.mean(times)))
    png_dir = out / "frames"
    if write_mp4:
        vr = write_video(frames, out / f"{name}.mp4", fps=fps, png_dir=png_dir if write_pngs else None)
        result.mp4, result.pngs, result.error = vr.mp4, vr.pngs, vr.error
    else:
        result.pngs = write_png_frames(frames, png_dir)
    return result
