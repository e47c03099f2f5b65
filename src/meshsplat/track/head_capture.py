"""A head video -> a native capture: landmarks, the ICT head fitted to them, crops and head mattes.

:func:`track_head` reads the video twice, streaming: first the face landmarks of every frame (then the
fit), then each frame's crop around the head, its matte and the fitted head mesh. The capture is a
native dataset (``docs/dataset-format.md``) with:

- one camera per frame: the video's pinhole camera (``K`` from the fit) cut to that frame's crop, at the
  world origin looking along -z (``+y`` up, the head model's own axes and centimetres);
- the driving mesh: the ICT head with the fitted identity, its transparent eye shells left out and
  seams welded; ``source_map.npz`` ties it to ``head_model.npz``, so ``meshsplat render RUN
  --animation blendshapes CAPTURE/head_model.npz --weights W`` plays the avatar with ARKit weights;
- ``head_fit.npz``: per frame ``weights [T,57]`` (ARKit names in ``names``), ``gaze [T,2,2]``,
  ``rotations``/``translations [T,3]``, ``time [T]`` (seconds), the fit's landmark error ``error_px [T]``,
  the source video's ``K [3,3]``, and ``landmarks [T,478,3]`` (pixels of the video);
- splits: ``train`` the first ``train_fraction`` of the frames, ``test_frames`` the rest (later
  frames: new expressions and poses).
"""

from __future__ import annotations

import time as _time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from meshsplat.data.writer import DatasetWriter
from meshsplat.errors import MeshsplatError
from meshsplat.synth.driving import weld
from meshsplat.track.clip import MIN_FRAMES, Clip, TrackResult, TrackSettings, open_clip
from meshsplat.track.face_track import FaceTrack, track_faces
from meshsplat.track.head_fit import HeadFit, fit_head
from meshsplat.track.head_region import (
    clip_crops,
    crop_frame,
    crop_inside,
    hair_region,
    mesh_silhouette,
    regions_touching,
)
from meshsplat.track.head_render import visible_faces
from meshsplat.track.ict_head import IctHead
from meshsplat.track.mediapipe_models import FaceMesh, PersonSegmenter
from meshsplat.track.tracker_camera import TRACKER_VIEWMAT

__all__ = ["track_head"]


def _check_found(track: FaceTrack, times: np.ndarray) -> list[str]:
    """Names (times) of frames without the face; refuses a clip with too few faces."""
    found = int(track.found.sum())
    missing = [f"{t:.2f}s" for t in times[~track.found]]
    if found == 0:
        raise MeshsplatError(
            f"no face found in any of the {track.frames} frames; give a video of a face (frontal, lit)"
        )
    if found < MIN_FRAMES:
        raise MeshsplatError(
            f"a face in only {found} of {track.frames} frames; tracking needs at least {MIN_FRAMES} "
            "(a longer clip, or one where the face stays in view)"
        )
    return missing


def _driving_mesh(head: IctHead, rest: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(source_index [Vd], faces [Fd,3])``: the head without its transparent shells, seams welded."""
    faces = head.faces[visible_faces(head)].numpy()
    r = rest.numpy().astype(np.float64)
    probe = r + head.deltas[head.names.index("jawOpen")].numpy()  # lips and teeth part: not welded
    diag = float(np.linalg.norm(r.max(0) - r.min(0)))
    _, rep, wfaces = weld([r, probe], faces, 1e-6 * diag)
    return rep.astype(np.int64), wfaces.astype(np.int64)


def _silhouette(world: torch.Tensor, faces: np.ndarray, K: np.ndarray, size: int) -> np.ndarray:
    """Where the posed driving mesh ``world [V,3]`` covers the crop seen through ``K``."""
    cam = world.numpy().astype(np.float64) @ TRACKER_VIEWMAT[:3, :3].numpy().T  # the camera sits at the origin
    px = cam @ K.T
    px = px[:, :2] / np.maximum(px[:, 2:], 1e-9)
    edges = np.linalg.norm(px[faces[:, 0]] - px[faces[:, 1]], axis=1)
    return mesh_silhouette(px, size, radius=float(np.percentile(edges, 90)))


def _write_npz(path: Path, **arrays: np.ndarray) -> None:
    np.savez(path, **cast("dict[str, Any]", arrays))  # cast: the savez stub matches a key against allow_pickle


def _write_head_model(path: Path, head: IctHead, rest: torch.Tensor) -> None:
    """The fitted head as a blend-shape model (the ICT npz layout ``BlendshapeDriver`` reads)."""
    _write_npz(
        path,
        neutral=rest.numpy().astype(np.float32),
        faces=head.faces.numpy().astype(np.int32),
        expr_names=np.array(head.names),
        expr_deltas=head.deltas.numpy().astype(np.float16),
        face_material=head.face_material.numpy().astype(np.int8),
        material_names=np.array(head.material_names),
    )


def track_head(
    video: str | Path,
    out: str | Path,
    settings: TrackSettings | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> TrackResult:
    """Track the head in ``video`` and write a native capture to ``out`` (see the module docstring).

    ``progress(stage, done, total)`` reports frames as they go (stages ``landmarks``, ``frames``).
    """
    out = Path(out)
    clip = open_clip(video, out, settings, progress)
    fps, tick = clip.fps, clip.tick
    seconds: dict[str, float] = {}

    t0 = _time.perf_counter()
    with FaceMesh() as mesh:
        track = track_faces(clip.frames(), mesh, tick("landmarks"), names=clip.time_of)
    seconds["landmarks"] = _time.perf_counter() - t0
    times = clip.times(track.frames)
    missing = _check_found(track, times)
    notes = list(track.notes)
    if missing:
        notes.append(
            f"no face in {len(missing)} frame(s), left out: "
            + ", ".join(missing[:12])
            + (" ..." if len(missing) > 12 else "")
        )

    t0 = _time.perf_counter()
    keep = np.nonzero(track.found)[0]
    fit: HeadFit = fit_head(track.landmarks[keep], track.width, track.height, fps=fps)
    seconds["fit"] = _time.perf_counter() - t0

    t0 = _time.perf_counter()
    result = _write_capture(clip, out, track, keep, times, fit, tick("frames"))
    seconds["frames"] = _time.perf_counter() - t0
    result.seconds, result.notes, result.dropped = seconds, notes, missing
    return result


def _write_capture(
    clip: Clip,
    out: Path,
    track: FaceTrack,
    keep: np.ndarray,
    times: np.ndarray,
    fit: HeadFit,
    tick: Callable[[int], Any],
) -> TrackResult:
    s = clip.settings
    head = fit.head
    rest = (head.neutral + fit.identity).detach()
    index, faces = _driving_mesh(head, rest)
    lm = track.landmarks[keep]
    crops = clip_crops(lm, s.size)
    n_train = min(len(keep) - 1, max(1, round(s.train_fraction * len(keep))))
    meta = {
        "generator": "meshsplat.track",
        "subject": "head",
        "video": clip.info.path.name,
        "up": "y",
        "units": "cm",
        "head_model": "head_model.npz",
        "head_fit": "head_fit.npz",
        "split_rule": f"train: the first {n_train} frames with a face; test_frames: the {len(keep) - n_train} after",
        "attribution": "head mesh: ICT FaceKit (MIT, (c) 2020 USC Institute for Creative Technologies)",
    }
    viewmat = TRACKER_VIEWMAT.numpy().astype(np.float64)
    out.mkdir(parents=True, exist_ok=True)
    writer = DatasetWriter(out, rest[index].numpy(), faces, overwrite=s.overwrite, meta=meta)
    writer.set_source_map(index, rest.numpy(), head.faces.numpy(), exact=True)
    verts = fit.vertices()  # [T,V,3] world
    pos = {int(k): j for j, k in enumerate(keep)}
    with PersonSegmenter() as seg:
        for i, frame in enumerate(clip.frames()):
            tick(i)
            j = pos.get(i)
            if j is None:
                continue
            crop = crops[j]
            img = crop_frame(frame, crop)
            person = seg(img)
            lm_crop = lm[j].copy()
            lm_crop[:, :2] = crop.to_crop(lm_crop[:, :2])
            Kc = crop.K(fit.K.numpy())
            silhouette = _silhouette(verts[j][index], faces, Kc, s.size)
            matte = regions_touching(
                person
                * crop_inside(frame.shape[0], frame.shape[1], crop)
                * np.maximum(hair_region(lm_crop, s.size, s.size), silhouette),
                silhouette >= 0.5,
            )
            cid = writer.add_camera(f"{j:06d}", Kc, viewmat, s.size, s.size)
            writer.add_frame(
                img, cid, vertices=verts[j][index], mask=matte, name=f"{j:06d}", clip="video", time=float(times[i])
            )
    writer.set_split("train", range(n_train))
    writer.set_split("test_frames", range(n_train, len(keep)))
    writer.close()
    _write_npz(
        out / "head_fit.npz",
        weights=fit.weights.numpy().astype(np.float32),
        names=np.array(head.names),
        gaze=fit.gaze.numpy().astype(np.float32),
        rotations=fit.rotations.numpy().astype(np.float32),
        translations=fit.translations.numpy().astype(np.float32),
        time=times[keep].astype(np.float64),
        error_px=fit.error_px.numpy().astype(np.float32),
        K=np.asarray(fit.K, np.float64),
        landmarks=lm.astype(np.float32),
    )
    _write_head_model(out / "head_model.npz", head, rest)
    return TrackResult(out, len(keep), [], n_train, len(keep) - n_train, float(fit.error_px.mean()))
