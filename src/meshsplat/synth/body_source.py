"""Synthetic subjects from parametric models: SMPL / SMPL-X dancing a captured AIST++ motion, FLAME talking.

A :class:`ModelSource` has the source interface of :mod:`meshsplat.synth.sources` (``faces``,
``clips``, ``time_range``, ``pose``, ``rest``, colours) plus the model parameters of every pose, so a
generated dataset stores its driver (``DatasetWriter.set_driver``). Motions:

- SMPL / SMPL-X: the bundled ``motion/aist_demo.npz`` (``poses [S,72]``, ``trans [S,3]``),
  played at ``BODY_FPS`` frames per second (clip ``"dance"``); SMPL-X takes the first 21 body joints.
  The clip is stored y-down (camera-like, as PeopleSnapshot); it is turned 180 degrees about x so
  the subject stands along +y.
- FLAME: procedural clips ``"talk"`` (jaw, expression, small head motion) and ``"nod"`` (neck nods and
  shakes, smile), ``HEAD_SECONDS`` long at ``HEAD_FPS``.

A time picks the nearest motion frame (no interpolation), so stored parameters are exact.
Colours: ``appearance.npz`` (``vertex_colors [V,3]``) beside the model file when present, else a
procedural colouring from the skin weights (one hue per joint) with a fine surface pattern.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np
import torch
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from meshsplat.drivers.body_models import BodyModel, driver_record
from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npz
from meshsplat.paths import asset

__all__ = [
    "ModelSource",
    "load_model_source",
    "rotate_params",
    "perturb_pose",
    "MODEL_SOURCES",
    "BODY_FPS",
    "HEAD_FPS",
]

MODEL_SOURCES = ("smpl", "smplx", "flame")
BODY_FPS = 30.0
HEAD_FPS = 25.0
HEAD_SECONDS = 8.0
_ROOT_KEYS = ("global_orient", "transl")


def rotate_params(params: dict, R: np.ndarray, pivot: np.ndarray, root_joint: np.ndarray) -> dict:
    """Parameters whose posed mesh is the original one rotated by ``R [3,3]`` about ``pivot [3]``.

    The model rotates about its root joint ``root_joint [3]`` (rest pose, after betas):
    ``global_orient' = R * global_orient`` and ``transl' = R (J0 + transl - p) + p - J0``.
    Per-frame ``global_orient [T,3]`` and ``transl [T,3]`` (or ``[3]``); other keys are kept.
    """
    R = np.asarray(R, np.float64)
    p, j0 = np.asarray(pivot, np.float64), np.asarray(root_joint, np.float64)
    go = np.asarray(params["global_orient"], np.float64)
    tr = np.asarray(params.get("transl", np.zeros_like(go)), np.float64)
    new_go = (Rotation.from_matrix(R) * Rotation.from_rotvec(go.reshape(-1, 3))).as_rotvec().reshape(go.shape)
    new_tr = (j0 + tr - p) @ R.T + p - j0
    return {**params, "global_orient": new_go.astype(np.float32), "transl": new_tr.astype(np.float32)}


def perturb_pose(params: dict[str, np.ndarray], sigma: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Tracking error: every joint rotation (``global_orient`` and the ``*_pose`` keys, axis-angle
    triples) turned by an independent random rotation whose axis-angle components have standard
    deviation ``sigma`` radians; translation, shape and expression are kept."""
    out = dict(params)
    for k in sorted(params):
        if k != "global_orient" and not k.endswith("_pose"):
            continue
        aa = np.asarray(params[k], np.float64).reshape(-1, 3)
        noise = Rotation.from_rotvec(rng.normal(0.0, sigma, aa.shape))
        out[k] = (noise * Rotation.from_rotvec(aa)).as_rotvec().reshape(np.shape(params[k])).astype(np.float32)
    return out


class ModelSource:
    """A :class:`BodyModel` posed by named clips of per-frame parameters (``[T,k]`` arrays)."""

    def __init__(
        self,
        model: BodyModel,
        clips: dict[str, dict[str, np.ndarray]],
        shared: dict[str, np.ndarray],
        fps: float,
        vertex_colors: torch.Tensor,
        attribution: str = "",
        test_clips: Sequence[str] = (),
    ) -> None:
        self.model = model
        self.shared = {k: np.asarray(v, np.float32) for k, v in shared.items()}
        self.motions = {c: {k: np.asarray(v, np.float32) for k, v in p.items()} for c, p in clips.items()}
        self.fps = float(fps)
        self.clips = list(clips)
        self.default_test_clips = [c for c in test_clips if c in clips]
        self.faces = model.faces.cpu()
        V = model.num_vertices
        self.uvs = torch.zeros(V, 2)
        self.vertex_colors = vertex_colors.float()
        self.face_material = torch.zeros(len(self.faces), dtype=torch.long)
        self.materials = [(torch.ones(3), None)]
        self.attribution = attribution
        self._cache: dict[tuple[str, int], torch.Tensor] = {}
        with torch.no_grad():
            rest = model.forward(dict(self.shared))
        self._rest = rest.vertices[0].float().cpu()
        self.root_joint = rest.joints[0, 0].double().cpu().numpy()

    @property
    def kind(self) -> str:
        return self.model.kind

    def _row(self, clip: str, time: float) -> int:
        if clip not in self.motions:
            raise MeshsplatError(f"clip: {clip!r} not in {self.clips}")
        n = len(next(iter(self.motions[clip].values())))
        return int(min(max(round(float(time) * self.fps), 0), n - 1))

    def time_range(self, clip: str) -> tuple[float, float]:
        n = len(next(iter(self.motions[clip].values())))
        return 0.0, (n - 1) / self.fps

    def frame_params(self, clip: str, time: float) -> dict[str, np.ndarray]:
        """Per-frame parameters of the motion frame nearest ``time`` (each ``[k]``)."""
        r = self._row(clip, time)
        return {k: v[r] for k, v in self.motions[clip].items()}

    def vertices_of(self, frame_params: dict[str, np.ndarray]) -> torch.Tensor:
        """Posed vertices ``[V,3]`` of per-frame parameters ``frame_params`` (each ``[k]``)."""
        p = {**self.shared, **{k: np.asarray(v, np.float32).reshape(1, -1) for k, v in frame_params.items()}}
        with torch.no_grad():
            return self.model.forward(p).vertices[0].float().cpu()

    def pose(self, clip: str, time: float) -> torch.Tensor:
        key = (clip, self._row(clip, time))
        if key not in self._cache:
            p = {**self.shared, **{k: v[None] for k, v in self.frame_params(clip, time).items()}}
            with torch.no_grad():
                self._cache[key] = self.model.forward(p).vertices[0].float().cpu()
        return self._cache[key].clone()

    def rest(self) -> torch.Tensor:
        return self._rest.clone()

    def placed_params(self, clip: str, time: float, yaw: float, pivot: np.ndarray) -> dict[str, np.ndarray]:
        """Per-frame parameters ``[k]`` of the pose at ``time`` turned by ``yaw`` about the vertical through ``pivot``."""
        p = self.frame_params(clip, time)
        if yaw == 0.0:
            return p
        c, s = math.cos(yaw), math.sin(yaw)
        Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        return {k: v.reshape(-1) for k, v in rotate_params(p, Ry, pivot, self.root_joint_of(p)).items()}

    def root_joint_of(self, frame_params: dict) -> np.ndarray:
        """Root joint ``[3]`` in the unposed shape of a frame (expression moves it too: FLAME's regressor
        sees the expression blend shapes)."""
        if "expression" not in frame_params:
            return self.root_joint
        shape = {**self.shared, "expression": np.asarray(frame_params["expression"], np.float32)[None]}
        with torch.no_grad():
            return self.model.forward(shape).joints[0, 0].double().cpu().numpy()

    def driver_record(self) -> dict:
        return driver_record(self.model)

    def derive(self, src: ArrayLike, faces: ArrayLike, rest: ArrayLike | None = None) -> NoReturn:
        raise MeshsplatError(
            "driver smoothing/decimation is not available for body/head model sources: the "
            "stored mesh must stay the model's so its parameters reproduce it"
        )


# ---------------------------------------------------------------- colours
def _appearance(model: BodyModel) -> torch.Tensor | None:
    p = model.path.parent / "appearance.npz"
    if not p.is_file():
        return None
    z = read_npz(p, "vertex colours")
    if "vertex_colors" not in z:
        raise MeshsplatError(f"{p}: cannot read vertex_colors (no such array; found {sorted(z)})")
    c = z["vertex_colors"]
    if c.ndim != 2 or c.shape[0] != model.num_vertices or c.shape[1] < 3:
        raise MeshsplatError(f"{p}: vertex_colors must be [{model.num_vertices},3], got {list(c.shape)}")
    c = c[:, :3].astype(np.float32)
    if c.max(initial=0) > 1.0:
        c = c / 255.0
    return torch.from_numpy(np.clip(c, 0, 1))


def procedural_colors(model: BodyModel, rest: torch.Tensor) -> torch.Tensor:
    """One muted hue per joint blended by the skin weights, times a fine pattern fixed to the rest surface."""
    J = model.num_joints
    hues = (np.arange(J) * 0.618034) % 1.0
    palette = np.stack([0.55 + 0.3 * np.cos(2 * math.pi * (hues + o)) for o in (0.0, 1 / 3, 2 / 3)], 1)
    base = model.lbs_weights.cpu().float() @ torch.from_numpy(palette).float()
    p = (rest - rest.mean(0)) / (rest.max(0).values - rest.min(0).values).max()
    fine = torch.sin(70 * p[:, 1]) * torch.sin(50 * p[:, 0] + 30 * p[:, 2])
    blotch = torch.sin(11 * p[:, 0] + 1) * torch.sin(9 * p[:, 1] + 2) * torch.sin(10 * p[:, 2])
    return (base * (1 + 0.08 * fine[:, None] + 0.12 * blotch[:, None])).clamp(0, 1)


# ---------------------------------------------------------------- motions
def _aist_motion(model: BodyModel, root_joint: np.ndarray) -> dict[str, np.ndarray]:
    path = asset("motion/aist_demo.npz")
    with np.load(path, allow_pickle=False) as z:
        poses, trans = np.asarray(z["poses"], np.float64), np.asarray(z["trans"], np.float64)
    if poses.ndim != 2 or poses.shape[1] < 72 or trans.shape != (len(poses), 3):
        raise MeshsplatError(
            f"{path}: expected poses [S,72] and trans [S,3], got {list(poses.shape)}, {list(trans.shape)}"
        )
    params = {"global_orient": poses[:, :3], "body_pose": poses[:, 3:72], "transl": trans}
    up = Rotation.from_rotvec(poses[:, :3]).apply([0.0, 1.0, 0.0]).mean(0)
    if up[1] < 0:  # stored y-down: stand the subject up along +y
        params = rotate_params(params, np.diag([1.0, -1.0, -1.0]), np.zeros(3), root_joint)
    if model.kind == "smplx":
        params["body_pose"] = params["body_pose"][:, :63]  # SMPL's hand joints 22, 23 are SMPL-X's hands
    return {k: np.asarray(v, np.float32) for k, v in params.items()}


def _head_motion(model: BodyModel, clip: str) -> dict[str, np.ndarray]:
    n = int(HEAD_SECONDS * HEAD_FPS)
    t = np.arange(n) / HEAD_FPS
    E = model.num_expression
    expr = np.zeros((n, E))
    jaw, neck = np.zeros((n, 3)), np.zeros((n, 3))
    env = np.clip(np.sin(math.pi * t / HEAD_SECONDS) * 3, 0, 1)  # ease in/out
    if clip == "talk":
        syll = 0.5 + 0.5 * np.sin(2 * math.pi * 3.1 * t) * np.sin(2 * math.pi * 0.7 * t + 0.3)
        jaw[:, 0] = 0.22 * syll * env
        neck[:, 0] = 0.05 * np.sin(2 * math.pi * 0.4 * t)
        neck[:, 1] = 0.08 * np.sin(2 * math.pi * 0.23 * t + 1.0)
        for k in range(min(E, 10)):
            expr[:, k] = (1.2 / (1 + k)) * np.sin(2 * math.pi * (0.5 + 0.37 * k) * t + k) * env
    else:  # nod
        neck[:, 0] = 0.25 * np.sin(2 * math.pi * 0.8 * t) * env
        neck[:, 1] = 0.35 * np.sin(2 * math.pi * 0.3 * t + 0.5) * env
        jaw[:, 0] = 0.05 + 0.05 * np.sin(2 * math.pi * 0.5 * t)
        for k in range(min(E, 4)):
            expr[:, k] = (1.5 / (1 + k)) * np.sin(2 * math.pi * 0.25 * t + 0.8 * k) * env
    zeros = np.zeros((n, 3))
    out = {
        "global_orient": zeros,
        "neck_pose": neck,
        "jaw_pose": jaw,
        "leye_pose": zeros,
        "reye_pose": zeros,
        "transl": zeros,
    }
    if E:
        out["expression"] = expr
    return {k: np.asarray(v, np.float32) for k, v in out.items()}


def _subject_betas(model: BodyModel) -> np.ndarray:
    """A fixed, mild, non-zero shape (exercises the betas path end to end)."""
    k = min(model.num_betas, 10)
    return (0.4 * np.cos(np.arange(k) * 1.7) / (1 + np.arange(k))).astype(np.float32)


def load_model_source(kind: str, model_dir: Path | str | None = None, gender: str = "neutral") -> ModelSource:
    """SMPL / SMPL-X (AIST++ dance) or FLAME (procedural talk / nod) from the user's model files."""
    kind = str(kind).lower()
    if kind not in MODEL_SOURCES:
        raise MeshsplatError(f"model source: expected one of {list(MODEL_SOURCES)}, got {kind!r}")
    model = BodyModel(kind, model_dir, gender=gender)
    shared = {"betas": _subject_betas(model)}
    with torch.no_grad():
        rest_out = model.forward(shared)
    root = rest_out.joints[0, 0].double().numpy()
    tests: tuple[str, ...]
    if kind == "flame":
        clips = {c: _head_motion(model, c) for c in ("talk", "nod")}
        fps, tests = HEAD_FPS, ("nod",)
        attribution = "FLAME model from the user's files; procedural talking/nodding motion"
    else:
        clips = {"dance": _aist_motion(model, root)}
        fps, tests = BODY_FPS, ()
        attribution = (
            f"{kind.upper()} model from the user's files; motion: AIST++ (CC-BY 4.0, Google / AIST Dance "
            "Video Database), aist_demo.npz as distributed with InstantAvatar"
        )
    colors = _appearance(model)
    if colors is None:
        colors = procedural_colors(model, rest_out.vertices[0].float())
    return ModelSource(model, clips, shared, fps, colors, attribution, tests)
