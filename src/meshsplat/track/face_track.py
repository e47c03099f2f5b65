"""One person's face landmarks through a clip: which face, which frames, where the shot cuts.

:func:`track_faces` runs the face mesh on every frame and follows one face: the largest in the first
frame that has a face, then in each frame the face nearest to where it was. Frames without it are
listed (the capture leaves them out); a jump of the face larger than its own size from one frame to
the next is a scene cut, which is refused (a capture is one shot of one person).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from meshsplat.errors import MeshsplatError

__all__ = ["FaceTrack", "track_faces", "face_box", "FOREHEAD", "CHIN", "CHEEK_RIGHT", "CHEEK_LEFT"]

# MediaPipe face-mesh landmark ids (its canonical face model's numbering)
FOREHEAD, CHIN = 10, 152
CHEEK_RIGHT, CHEEK_LEFT = 234, 454  # the subject's right (image left) and left side of the face oval


@dataclass
class FaceTrack:
    """``landmarks [T,478,3]`` (pixels; NaN where ``found`` is false), ``found [T]``, the number of
    faces seen per frame ``faces_seen [T]``, and the frame size."""

    landmarks: np.ndarray
    found: np.ndarray
    faces_seen: np.ndarray
    width: int
    height: int
    notes: list[str] = field(default_factory=list)

    @property
    def frames(self) -> int:
        return int(self.found.shape[0])


def face_box(lm: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre ``[2]`` and size (forehead-to-chin length, pixels) of one face's landmarks ``[478,3]``."""
    centre = lm[:468, :2].mean(0)
    size = float(np.linalg.norm(lm[FOREHEAD, :2] - lm[CHIN, :2]))
    return centre, size


def _pick(faces: list[np.ndarray], last: tuple[np.ndarray, float] | None) -> int:
    if last is None:
        return int(np.argmax([face_box(f)[1] for f in faces]))
    return int(np.argmin([np.linalg.norm(face_box(f)[0] - last[0]) for f in faces]))


def track_faces(
    frames: Iterable[np.ndarray],
    detector: Callable[[np.ndarray], list[np.ndarray]],
    progress: Callable[[int], None] | None = None,
    names: Callable[[int], str] | None = None,
) -> FaceTrack:
    """Follow one face through ``frames`` (uint8 ``[H,W,3]``) with ``detector`` (e.g. a
    :class:`meshsplat.track.mediapipe_models.FaceMesh`). ``names(i)`` names frame ``i`` in messages."""
    name = names or (lambda i: f"frame {i}")
    rows: list[np.ndarray | None] = []
    seen: list[int] = []
    last: tuple[np.ndarray, float] | None = None
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
        faces = detector(frame)
        seen.append(len(faces))
        if not faces:
            rows.append(None)
        else:
            lm = faces[_pick(faces, last)]
            box = face_box(lm)
            if last is not None and i == last_i + 1:
                jump = float(np.linalg.norm(box[0] - last[0]))
                if jump > max(box[1], last[1]) or not 0.6 < box[1] / max(last[1], 1e-6) < 1.67:
                    raise MeshsplatError(
                        f"{name(i)}: the face jumps {jump:.0f} px (its size {box[1]:.0f} px) from the frame before: "
                        "a scene cut; track one shot (--start/--seconds)"
                    )
            rows.append(lm)
            last, last_i = box, i
        if progress is not None:
            progress(i)
    if size is None:
        raise MeshsplatError("the video has no frames")
    t = len(rows)
    out = np.full((t, 478, 3), np.nan, np.float32)
    found = np.array([r is not None for r in rows])
    for i, r in enumerate(rows):
        if r is not None:
            out[i] = r
    track = FaceTrack(out, found, np.array(seen), size[0], size[1])
    multi = np.nonzero(track.faces_seen > 1)[0]
    if len(multi):
        first = int(np.nonzero(found)[0][0])
        c = face_box(out[first])[0]
        track.notes.append(
            f"{int(track.faces_seen.max())} faces in {len(multi)} frame(s) (first {name(int(multi[0]))}): "
            f"following the largest face of {name(first)}, at x={c[0]:.0f}, y={c[1]:.0f} px, and the face nearest it after"
        )
    return track
