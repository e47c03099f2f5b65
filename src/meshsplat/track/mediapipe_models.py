"""MediaPipe's face mesh and person segmentation, as shipped inside its 0.10 wheels (no download).

``mediapipe`` is the ``[track]`` extra, imported here only. The 0.10.21 wheels carry the face
detector, the 478-point face mesh with irises (``face_landmark_with_attention.tflite``) and the selfie
segmentation model (Apache-2.0); later releases dropped these "solutions" and fetch models at run time,
which meshsplat never does.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from meshsplat.errors import MeshsplatError

__all__ = [
    "FaceMesh",
    "PoseLandmarker",
    "PersonSegmenter",
    "NUM_FACE_LANDMARKS",
    "NUM_POSE_LANDMARKS",
    "load_mediapipe",
]

NUM_FACE_LANDMARKS = 478  # 468 face mesh points + 2 x 5 iris points
NUM_POSE_LANDMARKS = 33  # BlazePose: face 0-10, arms 11-22, legs 23-32
_INSTALL = "pip install 'meshsplat[track]' (mediapipe 0.10.21, Python 3.9-3.12)"


def load_mediapipe() -> Any:
    """The ``mediapipe`` module with its bundled solutions, or one line saying what to install."""
    os.environ.setdefault("GLOG_minloglevel", "2")  # its C++ logging: errors only
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    try:
        import mediapipe as mp
    except ImportError as exc:
        raise MeshsplatError(f"tracking needs MediaPipe: {_INSTALL} ({exc})") from None
    if not hasattr(mp, "solutions") or not hasattr(mp.solutions, "face_mesh"):
        raise MeshsplatError(
            f"mediapipe {getattr(mp, '__version__', '?')} has no bundled face mesh model (its 0.10.30+ wheels "
            f"download models at run time); {_INSTALL}"
        )
    return mp


class FaceMesh:
    """Face landmarks of every face in a frame sequence, in pixels.

    ``video=True`` tracks across consecutive frames (MediaPipe's video mode: the next frame's face is
    searched where the last one was, the detector runs again only when it is lost).
    """

    def __init__(self, max_faces: int = 4, video: bool = True, min_confidence: float = 0.5) -> None:
        mp = load_mediapipe()
        self._mesh = mp.solutions.face_mesh.FaceMesh(
            static_image_mode=not video,
            max_num_faces=max_faces,
            refine_landmarks=True,
            min_detection_confidence=min_confidence,
            min_tracking_confidence=min_confidence,
        )

    def __call__(self, frame: np.ndarray) -> list[np.ndarray]:
        """``frame [H,W,3]`` uint8 RGB -> one ``[478,3]`` float32 array per face: x, y in pixels (pixel
        centres at +0.5), z in the same pixel scale (MediaPipe's relative depth, nose tip near 0)."""
        h, w = frame.shape[:2]
        res = self._mesh.process(np.ascontiguousarray(frame))
        faces = []
        for lm in res.multi_face_landmarks or []:
            a = np.array([(p.x, p.y, p.z) for p in lm.landmark], np.float32)
            if a.shape[0] != NUM_FACE_LANDMARKS:
                continue
            faces.append(a * np.array([w, h, w], np.float32))
        return faces

    def close(self) -> None:
        self._mesh.close()

    def __enter__(self) -> FaceMesh:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PoseLandmarker:
    """MediaPipe Pose (BlazePose, the "full" model inside the 0.10.21 wheel; the lite and heavy ones would
    be downloaded, so ``model_complexity`` stays 1): one person per frame, the most prominent one, followed
    from frame to frame in video mode."""

    def __init__(self, video: bool = True, min_confidence: float = 0.5) -> None:
        mp = load_mediapipe()
        self._pose = mp.solutions.pose.Pose(
            static_image_mode=not video,
            model_complexity=1,
            smooth_landmarks=video,
            enable_segmentation=False,
            min_detection_confidence=min_confidence,
            min_tracking_confidence=min_confidence,
        )

    def __call__(self, frame: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """``frame [H,W,3]`` uint8 RGB -> ``[(image [33,4], world [33,3])]`` (empty without a person):
        x, y in pixels (pixel centres at +0.5), z in the same scale (relative depth), visibility in [0,1];
        ``world`` in metres about the hips' midpoint (x right, y down, z away from the camera)."""
        h, w = frame.shape[:2]
        res = self._pose.process(np.ascontiguousarray(frame))
        if res.pose_landmarks is None:
            return []
        lm = np.array([(p.x * w, p.y * h, p.z * w, p.visibility) for p in res.pose_landmarks.landmark], np.float32)
        if res.pose_world_landmarks is None:
            world = np.full((NUM_POSE_LANDMARKS, 3), np.nan, np.float32)
        else:
            world = np.array([(p.x, p.y, p.z) for p in res.pose_world_landmarks.landmark], np.float32)
        if lm.shape[0] != NUM_POSE_LANDMARKS:
            return []
        return [(lm, world)]

    def close(self) -> None:
        self._pose.close()

    def __enter__(self) -> PoseLandmarker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PersonSegmenter:
    """MediaPipe's selfie segmentation: a soft person matte ``[H,W]`` in [0, 1] per frame."""

    def __init__(self) -> None:
        mp = load_mediapipe()
        self._seg = mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=0)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        res = self._seg.process(np.ascontiguousarray(frame))
        m = res.segmentation_mask
        if m is None:
            return np.zeros(frame.shape[:2], np.float32)
        return np.clip(np.asarray(m, np.float32), 0.0, 1.0)

    def close(self) -> None:
        self._seg.close()

    def __enter__(self) -> PersonSegmenter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
