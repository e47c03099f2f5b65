"""One person's body landmarks through a clip: which frames have the person, where the shot cuts.

:func:`track_bodies` runs MediaPipe Pose (one person per frame: the most prominent, followed from frame
to frame in video mode) on every frame. Frames without a person, or with the torso (both shoulders and
both hips) out of view, are listed (the capture leaves them out). A jump of the torso larger than its
own size from one frame to the next (or across a gap of up to ``CUT_GAP`` frames without a person), or a
change of its size by more than 1.67x, is a scene cut, which is refused (a capture is one shot of one person). MediaPipe sometimes swaps the left and right limbs of
a person seen from the back or the side: a frame whose limbs sit much closer to the previous frame's
with left and right exchanged is swapped back (and counted in the notes).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from meshsplat.errors import MeshsplatError

__all__ = ["BodyTrack", "track_bodies", "torso_box", "SWAP", "TORSO", "MIN_VISIBILITY"]

NOSE, L_SHOULDER, R_SHOULDER, L_HIP, R_HIP = 0, 11, 12, 23, 24
TORSO = (L_SHOULDER, R_SHOULDER, L_HIP, R_HIP)
CUT_GAP = 3  # frames: a jump across a gap this short is still a cut
MIN_VISIBILITY = 0.5  # a landmark counts as seen (MediaPipe's visibility: in view and not occluded)
# MediaPipe's left/right pairs (eyes, ears, mouth, arms, hands, legs, feet)
_PAIRS = [(1, 4), (2, 5), (3, 6), (7, 8), (9, 10)] + [(a, a + 1) for a in range(11, 33, 2)]
SWAP = np.arange(33)
for _a, _b in _PAIRS:
    SWAP[_a], SWAP[_b] = _b, _a
_LIMBS = [13, 14, 15, 16, 25, 26, 27, 28]  # elbows, wrists, knees, ankles


@dataclass
class BodyTrack:
    """``landmarks [T,33,4]`` (x, y pixels, z, visibility; NaN where ``found`` is false), ``world
    [T,33,3]`` (MediaPipe's metric 3D about the hips), ``found [T]``, ``torso_visible [T]``, the
    frame size, ``swapped [T]`` (left/right exchanged back) and notes."""

    landmarks: np.ndarray
    world: np.ndarray
    found: np.ndarray
    torso_visible: np.ndarray
    width: int
    height: int
    swapped: np.ndarray
    notes: list[str] = field(default_factory=list)

    @property
    def frames(self) -> int:
        return int(self.found.shape[0])

    @property
    def usable(self) -> np.ndarray:
        """``[T]`` bool: a person with the torso in view."""
        return self.found & self.torso_visible


def torso_box(lm: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre ``[2]`` (the torso's middle) and size (shoulder-to-hip length, pixels) of ``lm [33,>=2]``."""
    sh = (lm[L_SHOULDER, :2] + lm[R_SHOULDER, :2]) / 2
    hip = (lm[L_HIP, :2] + lm[R_HIP, :2]) / 2
    return (sh + hip) / 2, float(np.linalg.norm(sh - hip))


def _unswap(lm: np.ndarray, world: np.ndarray, last: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, bool]:
    if last is None:
        return lm, world, False
    direct = np.linalg.norm(lm[_LIMBS, :2] - last[_LIMBS, :2], axis=1).sum()
    crossed = np.linalg.norm(lm[SWAP][_LIMBS, :2] - last[_LIMBS, :2], axis=1).sum()
    if crossed < 0.5 * direct:
        return lm[SWAP], world[SWAP], True
    return lm, world, False


def track_bodies(
    frames: Iterable[np.ndarray],
    detector: Callable[[np.ndarray], list[tuple[np.ndarray, np.ndarray]]],
    progress: Callable[[int], None] | None = None,
    names: Callable[[int], str] | None = None,
) -> BodyTrack:
    """Follow one person through ``frames`` (uint8 ``[H,W,3]``) with ``detector`` (a
    :class:`meshsplat.track.mediapipe_models.PoseLandmarker`). ``names(i)`` names frame ``i`` in messages."""
    name = names or (lambda i: f"frame {i}")
    rows: list[tuple[np.ndarray, np.ndarray] | None] = []
    swapped: list[bool] = []
    last: tuple[np.ndarray, float] | None = None
    last_lm: np.ndarray | None = None
    last_i = -1
    size: tuple[int, int] | None = None
    for i, frame in enumerate(frames):
        h, w = frame.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise MeshsplatError(
                f"{name(i)}: {w}x{h} pixels, the frames before it {size[0]}x{size[1]}; one clip, one size"
            )
        people = detector(frame)
        if not people:
            rows.append(None)
            swapped.append(False)
        else:
            lm, world = people[0]
            lm, world, sw = _unswap(lm, world, last_lm if i == last_i + 1 else None)
            swapped.append(sw)
            box = torso_box(lm)
            # MediaPipe Pose often finds nobody in the first frame after a cut: a gap of up to CUT_GAP
            # frames still compares with the last frame seen
            if last is not None and i - last_i <= CUT_GAP and box[1] > 0:
                jump = float(np.linalg.norm(box[0] - last[0]))
                if jump > max(box[1], last[1]) or not 0.6 < box[1] / max(last[1], 1e-6) < 1.67:
                    raise MeshsplatError(
                        f"{name(i)}: the body jumps {jump:.0f} px (its torso {box[1]:.0f} px, before "
                        f"{last[1]:.0f} px) from the frame before: a scene cut; track one shot (--start/--seconds)"
                    )
            rows.append((lm, world))
            last, last_i, last_lm = box, i, lm
        if progress is not None:
            progress(i)
    if size is None:
        raise MeshsplatError("the video has no frames")
    t = len(rows)
    out = np.full((t, 33, 4), np.nan, np.float32)
    world_out = np.full((t, 33, 3), np.nan, np.float32)
    for i, r in enumerate(rows):
        if r is not None:
            out[i], world_out[i] = r
    found = np.array([r is not None for r in rows])
    vis = np.nan_to_num(out[:, list(TORSO), 3], nan=0.0)
    inside = np.ones(t, bool)
    for j in TORSO:
        x, y = out[:, j, 0], out[:, j, 1]
        inside &= np.nan_to_num((x >= 0) & (x <= size[0]) & (y >= 0) & (y <= size[1])).astype(bool)
    torso = found & (vis >= MIN_VISIBILITY).all(1) & inside
    track = BodyTrack(out, world_out, found, torso, size[0], size[1], np.array(swapped))
    if track.swapped.any():
        track.notes.append(
            f"left and right limbs exchanged back in {int(track.swapped.sum())} frame(s) "
            f"(first {name(int(np.nonzero(track.swapped)[0][0]))}): MediaPipe swapped them"
        )
    return track
