"""Fit the compact Anny body to MediaPipe Pose landmarks and person mattes through a clip (one camera).

API::

    fit = fit_body(landmarks, world, width, height, fps=None, focal=None, mattes=None)
    #   landmarks [T,33,4]  MediaPipe Pose: x, y pixels of the frame (pixel centres at +0.5), z, visibility
    #   world [T,33,3]      its metric 3D landmarks about the hips (x right, y down, z away from the camera)
    #   mattes [T,h,w]      optional person mattes in [0,1] at any size (the frame's aspect)
    fit.params()         -> SMPL-style dict: global_orient [T,3], body_pose [T,69], transl [T,3], betas [6]
    fit.vertices(t)      -> [V,3] world vertices of frame t (fit.vertices() -> [T,V,3])
    fit.K [3,3], fit.viewmat [4,4] (TRACKER_VIEWMAT: camera at the origin looking along -z, +y up)
    fit.error_px [T]     mean 2D keypoint reprojection error per frame over the seen keypoints (pixels)

The model (``drivers.anny_body``): shape once per clip (6 phenotype offsets ``betas``, kept in [-0.5, 0.5]
with an L2 prior, which also fixes the body's size: one camera cannot tell a tall person far away from a
short one near), per frame the 24 joint rotations (axis-angle, SMPL's convention) and the translation.

Loss, all frames at once (Adam, 1 thread):

- 2D: the Huber loss of the 21 keypoints the two skeletons share (``KEYPOINT_MAP``: face, shoulders,
  elbows, wrists, hips, knees, ankles, heels, big toes) reprojected, each weighted by MediaPipe's
  visibility (0 below 0.3, 1 above 0.7) and 0 outside the frame, in units of 1/100 of the torso's size;
- 3D: the directions of 11 bones (upper and lower arms and legs, shoulders, hips, the spine) against
  MediaPipe's metric landmarks: this says which way a limb points in depth, which 2D keypoints cannot;
- priors: an L2 pull of each joint towards zero (weak on limbs, strong on the spine, collars, wrists,
  hands and feet, which no keypoint pins), and joint limits: knees bend backwards only (rotation about
  x in [0, 2.6] rad, little about y or z), elbows forwards only (left about -y, right about +y);
- temporal smoothing ``smoothing * (fps/30)^2 * sum_t |x_t+1 - x_t|^2`` of the rotations and the
  translation (``fps=None`` counts as 30);
- silhouette (with ``mattes``, last stage): 600 mesh vertices' projections must fall inside the matte
  (its distance transform outside), and the matte must be covered (each of 150 matte pixels per frame
  near a projected vertex).

Stages: the torso (global rotation and translation, initialised from MediaPipe's metric torso by a
Procrustes turn and from the torso's size in pixels), then every joint and the shape, then the same with
the silhouette.

Focal length: ``focal`` in pixels if known; otherwise a 60 degree diagonal field of view is assumed
(``DEFAULT_DIAGONAL_FOV_DEG``, as the head tracker; phones' main cameras are 65-80 degrees): a wrong
guess mostly changes the fitted distance and the perspective of near limbs. Principal point: the centre.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat.camera import Camera
from meshsplat.drivers.anny_body import JOINTS, KEYPOINTS, AnnyBody, load_anny_body
from meshsplat.errors import MeshsplatError
from meshsplat.track.tracker_camera import (
    DEFAULT_DIAGONAL_FOV_DEG,
    TRACKER_VIEWMAT,
    focal_from_fov,
    project,
    world_to_camera_axes,
)

__all__ = ["BodyFit", "fit_body", "KEYPOINT_MAP", "MIN_FRAMES_FOR_SHAPE"]

MIN_FRAMES_FOR_SHAPE = 10
# Anny keypoint name -> MediaPipe Pose landmark (their small toes have no MediaPipe counterpart)
KEYPOINT_MAP = {
    "nose": 0, "left_eye": 2, "right_eye": 5, "left_ear": 7, "right_ear": 8,
    "left_shoulder": 11, "right_shoulder": 12, "left_elbow": 13, "right_elbow": 14, "left_wrist": 15,
    "right_wrist": 16, "left_hip": 23, "right_hip": 24, "left_knee": 25, "right_knee": 26,
    "left_ankle": 27, "right_ankle": 28, "left_heel": 29, "right_heel": 30, "left_big_toe": 31,
    "right_big_toe": 32,
}  # fmt: skip
_KP_WEIGHT = {
    "left_hip": 0.6,
    "right_hip": 0.6,
    "nose": 0.5,
    "left_eye": 0.3,
    "right_eye": 0.3,
    "left_ear": 0.3,
    "right_ear": 0.3,
}
# bones for the 3D direction term: (from, to) as MediaPipe ids
_BONES = [(11, 13), (13, 15), (12, 14), (14, 16), (23, 25), (25, 27), (24, 26), (26, 28), (12, 11), (24, 23)]
_TORSO = [11, 12, 23, 24]
_PRIOR = {  # L2 pull towards zero, per joint (rotations no keypoint pins get a strong one)
    "spine1": 3.0, "spine2": 3.0, "spine3": 3.0, "neck": 1.0, "head": 0.5, "left_collar": 5.0,
    "right_collar": 5.0, "left_wrist": 2.0, "right_wrist": 2.0, "left_hand": 10.0, "right_hand": 10.0,
    "left_foot": 10.0, "right_foot": 10.0, "left_ankle": 1.0, "right_ankle": 1.0,
}  # fmt: skip
_LIMB_PRIOR = 0.02


@dataclass
class BodyFit:
    """A fitted clip (see the module docstring)."""

    body: AnnyBody
    betas: torch.Tensor
    pose: torch.Tensor
    transl: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    error_px: torch.Tensor
    keypoint_error_px: torch.Tensor

    @property
    def num_frames(self) -> int:
        return int(self.pose.shape[0])

    @property
    def viewmat(self) -> torch.Tensor:
        return TRACKER_VIEWMAT.clone()

    def camera(self) -> Camera:
        return Camera(self.viewmat, self.K.clone(), self.width, self.height)

    def params(self) -> dict[str, np.ndarray]:
        """SMPL-style parameters: ``global_orient [T,3]``, ``body_pose [T,69]``, ``transl [T,3]``, ``betas [6]``."""
        p = self.pose.detach().cpu().numpy().astype(np.float32)
        return {
            "global_orient": p[:, 0],
            "body_pose": p[:, 1:].reshape(len(p), 69),
            "transl": self.transl.detach().cpu().numpy().astype(np.float32),
            "betas": self.betas.detach().cpu().numpy().astype(np.float32),
        }

    def vertices(self, frame: int | None = None) -> torch.Tensor:
        """World vertices of ``frame`` ``[V,3]``, or of every frame ``[T,V,3]`` when ``frame`` is None."""
        if frame is not None and not 0 <= frame < self.num_frames:
            raise MeshsplatError(f"frame: expected 0 <= frame < {self.num_frames}, got {frame}")
        sl = slice(None) if frame is None else slice(frame, frame + 1)
        with torch.no_grad():
            v, _ = self.body.pose(self.pose[sl], self.betas, self.transl[sl])
        return v if frame is None else v[0]

    def joints(self) -> torch.Tensor:
        """World joint centres ``[T,24,3]``."""
        with torch.no_grad():
            return self.body.pose(self.pose, self.betas, self.transl, torch.zeros(0, dtype=torch.long))[1]

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Pixels ``[...,2]`` of world ``points [...,3]``."""
        return project(points, self.K)


def _check_inputs(landmarks: ArrayLike, world: ArrayLike | None) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(landmarks)
    if a.dtype.kind not in "fiu" or a.ndim != 3 or a.shape[1:] != (33, 4):
        raise MeshsplatError(
            f"landmarks: expected [T,33,4] (MediaPipe Pose: x, y pixels, z, visibility), got {list(a.shape)}"
        )
    if a.shape[0] == 0:
        raise MeshsplatError("landmarks: no frames; the clip needs at least one frame with a person")
    if not np.isfinite(a).all():
        bad = np.nonzero(~np.isfinite(a).all((1, 2)))[0]
        raise MeshsplatError(
            f"landmarks: frames {bad[:10].tolist()} hold NaN/Inf (no person?); leave them out before fitting"
        )
    w = np.full((a.shape[0], 33, 3), np.nan, np.float32) if world is None else np.asarray(world, np.float32)
    if w.shape != (a.shape[0], 33, 3):
        raise MeshsplatError(f"world: expected [{a.shape[0]},33,3] (MediaPipe's metric landmarks), got {list(w.shape)}")
    return a.astype(np.float32), w


def _procrustes(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """Rotations ``[T,3,3]`` turning centred ``src [P,3]`` onto centred ``dst [T,P,3]`` (least squares)."""
    H = torch.einsum("pi,tpj->tij", src - src.mean(0), dst - dst.mean(1, keepdim=True))
    U, _, Vh = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vh.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], 1))
    return Vh.transpose(1, 2) @ D @ U.transpose(1, 2)


def _matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    from scipy.spatial.transform import Rotation

    return torch.from_numpy(Rotation.from_matrix(R.double().numpy()).as_rotvec()).float()


def _distance_outside(mattes: np.ndarray) -> np.ndarray:
    """Per frame, each pixel's distance (pixels of the matte) to the matte (0 inside)."""
    from scipy import ndimage

    return np.stack([ndimage.distance_transform_edt(m < 0.5) for m in mattes]).astype(np.float32)


def fit_body(
    landmarks: ArrayLike,
    world: ArrayLike | None,
    width: int,
    height: int,
    fps: float | None = None,
    focal: float | None = None,
    mattes: ArrayLike | None = None,
    betas: torch.Tensor | None = None,
    smoothing: float = 1.0,
    iterations: int = 300,
    body: AnnyBody | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> BodyFit:
    """Fit the Anny body to ``landmarks [T,33,4]`` and ``world [T,33,3]`` of ``width`` x ``height`` frames.

    ``focal`` (pixels) defaults to :func:`focal_from_fov` (60 degrees diagonal); ``mattes [T,h,w]`` adds
    the silhouette stage; ``betas [6]`` (a previous fit's) is kept fixed instead of fitted, which also
    lets clips shorter than ``MIN_FRAMES_FOR_SHAPE`` be fitted; ``smoothing`` scales the temporal
    smoothing (0: none); ``iterations`` of the joint stage (the torso and silhouette stages run a half and
    a third as many); ``progress(step, total)`` after each optimizer step."""
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise MeshsplatError(f"{name}: expected a positive integer (pixels), got {value!r}")
    lm, wl = _check_inputs(landmarks, world)
    T = lm.shape[0]
    if betas is None and T < MIN_FRAMES_FOR_SHAPE:
        raise MeshsplatError(
            f"landmarks: {T} frame(s) are too few to fit the body's shape (at least {MIN_FRAMES_FOR_SHAPE}); "
            "use a longer clip, or pass betas= from a fit of the same person"
        )
    f = focal_from_fov(int(width), int(height), DEFAULT_DIAGONAL_FOV_DEG) if focal is None else float(focal)
    if not (math.isfinite(f) and f > 0):
        raise MeshsplatError(f"focal: expected a positive number of pixels, got {focal!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
        raise MeshsplatError(f"iterations: expected a positive integer, got {iterations!r}")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise MeshsplatError(f"fps: expected a positive frame rate, got {fps!r}")
    m = None
    if mattes is not None:
        m = np.asarray(mattes, np.float32)
        if m.ndim != 3 or m.shape[0] != T:
            raise MeshsplatError(f"mattes: expected [{T},h,w] in [0,1], got {list(m.shape)}")
    body = load_anny_body() if body is None else body
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # hundreds of small steps: more threads only wait on each other
    try:
        with torch.enable_grad():
            smooth = smoothing * ((30.0 if fps is None else fps) / 30.0) ** 2
            out = _optimize(body, lm, wl, m, K, int(width), int(height), betas, smooth, iterations, progress)
    finally:
        torch.set_num_threads(threads)
    b, pose, transl, err = out
    seen = torch.from_numpy(_weights(lm, int(width), int(height)) > 0)
    per_frame = (err * seen).sum(1) / seen.sum(1).clamp_min(1)
    return BodyFit(body, b, pose, transl, K, int(width), int(height), per_frame, err)


def _weights(lm: np.ndarray, width: int, height: int) -> np.ndarray:
    """``[T,21]`` keypoint weights: visibility ramped over [0.3, 0.7], 0 outside the frame."""
    ids = list(KEYPOINT_MAP.values())
    v = np.clip((lm[:, ids, 3] - 0.3) / 0.4, 0, 1)
    x, y = lm[:, ids, 0], lm[:, ids, 1]
    inside = (x >= 0) & (x <= width) & (y >= 0) & (y <= height)
    return (v * inside).astype(np.float32)


def _optimize(
    body: AnnyBody,
    lm: np.ndarray,
    world: np.ndarray,
    mattes: np.ndarray | None,
    K: torch.Tensor,
    width: int,
    height: int,
    betas_fixed: torch.Tensor | None,
    smooth: float,
    iterations: int,
    progress: Callable[[int, int], None] | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    T = lm.shape[0]
    kp_ids = torch.tensor([KEYPOINTS.index(k) for k in KEYPOINT_MAP])
    obs = torch.from_numpy(lm[:, list(KEYPOINT_MAP.values()), :2])  # [T,21,2]
    w2d = torch.from_numpy(_weights(lm, width, height)) * torch.tensor([_KP_WEIGHT.get(k, 1.0) for k in KEYPOINT_MAP])
    vis = torch.from_numpy(np.clip((lm[:, :, 3] - 0.3) / 0.4, 0, 1))  # [T,33]
    mp3 = world_to_camera_axes(torch.from_numpy(np.nan_to_num(world)))  # MediaPipe's metric landmarks in world axes
    has3 = torch.from_numpy(np.isfinite(world).all((1, 2)).astype(np.float32))  # [T]
    mp_of = {mp: i for i, mp in enumerate(KEYPOINT_MAP.values())}  # MediaPipe id -> column of obs

    # units: 1/100 of the torso's mean size in pixels
    sh = (obs[:, mp_of[11]] + obs[:, mp_of[12]]) / 2
    hip = (obs[:, mp_of[23]] + obs[:, mp_of[24]]) / 2
    torso_px = (sh - hip).norm(dim=-1).clamp_min(1.0)  # [T]
    unit = float(torso_px.mean()) / 100.0

    # initial shape, rotation and translation
    b = torch.zeros(body.num_betas) if betas_fixed is None else betas_fixed.detach().clone().float()
    kp0, _ = body.keypoints(torch.zeros(1, 24, 3), b)
    kp0 = kp0[0]
    torso_ids = [KEYPOINTS.index(k) for k in ("left_shoulder", "right_shoulder", "left_hip", "right_hip")]
    src = kp0[torso_ids]
    dst = mp3[:, _TORSO]
    R0 = _procrustes(src, dst)
    R0 = torch.where(has3[:, None, None] > 0, R0, torch.eye(3).expand(T, 3, 3))
    go = _matrix_to_axis_angle(R0)
    torso3 = float((src[:2].mean(0) - src[2:].mean(0)).norm())
    f = float(K[0, 0])
    z0 = f * torso3 / torso_px
    mid_rest = src.mean(0)
    c2 = (sh + hip) / 2
    target = torch.stack([(c2[:, 0] - K[0, 2]) * z0 / f, -(c2[:, 1] - K[1, 2]) * z0 / f, -z0], 1)
    transl0 = target - torch.einsum("tij,j->ti", R0, mid_rest)
    pose = torch.zeros(T, 24, 3)
    pose[:, 0] = go
    pose.requires_grad_(True)
    transl = transl0.clone().requires_grad_(True)
    betas = b.clone().requires_grad_(betas_fixed is None)

    prior_w = torch.full((24,), _LIMB_PRIOR)
    for k, v in _PRIOR.items():
        prior_w[JOINTS.index(k)] = v
    prior_w[0] = 0.0
    knees = [JOINTS.index("left_knee"), JOINTS.index("right_knee")]
    elbows = [JOINTS.index("left_elbow"), JOINTS.index("right_elbow")]

    # silhouette data
    sil = None
    if mattes is not None:
        h, w = mattes.shape[1:]
        dist = torch.from_numpy(_distance_outside(mattes))[:, None]  # [T,1,h,w]
        scale = torch.tensor([w / width, h / height])
        gen = torch.Generator().manual_seed(0)
        vid = torch.randperm(body.num_vertices, generator=gen)[:600]
        pts = []
        for t in range(T):  # 150 matte pixels per frame (frame pixel coordinates)
            ys, xs = np.nonzero(mattes[t] >= 0.5)
            if len(xs) == 0:
                pts.append(torch.full((150, 2), float("nan")))
                continue
            pick = torch.randint(len(xs), (150,), generator=gen)
            pts.append(
                torch.stack([torch.from_numpy(xs + 0.5)[pick], torch.from_numpy(ys + 0.5)[pick]], 1).float() / scale
            )
        sil = (dist, scale, vid, torch.stack(pts), (h, w))

    def bone_dirs(x: torch.Tensor, ids: dict[int, int]) -> torch.Tensor:
        d = torch.stack(
            [x[:, ids[b]] - x[:, ids[a]] for a, b in _BONES]
            + [(x[:, ids[11]] + x[:, ids[12]]) / 2 - (x[:, ids[23]] + x[:, ids[24]]) / 2],
            1,
        )
        return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-6)

    mp_dirs = bone_dirs(mp3, {i: i for i in range(33)})  # [T,11,3]
    bone_w = (
        torch.stack([torch.minimum(vis[:, a], vis[:, b]) for a, b in _BONES] + [vis[:, _TORSO].min(1).values], 1)
        * has3[:, None]
    )

    def loss_fn(stage: int) -> torch.Tensor:
        kp, _ = body.keypoints(pose, betas, transl)
        kp = kp[:, kp_ids]  # [T,21,3]
        res = (project(kp, K) - obs) / unit
        r = torch.nn.functional.huber_loss(res, torch.zeros_like(res), delta=5.0, reduction="none").sum(-1)
        if stage == 0:
            sel = torch.tensor([mp_of[i] for i in _TORSO])
            loss = (r[:, sel] * w2d[:, sel]).sum() / T
        else:
            loss = (r * w2d).sum() / T
        pred_dirs = bone_dirs(kp, mp_of)
        d3 = (pred_dirs - mp_dirs).pow(2).sum(-1)
        loss = loss + 30.0 * ((d3 * bone_w)[:, -3:].sum() if stage == 0 else (d3 * bone_w).sum()) / T
        if stage > 0:
            loss = loss + (prior_w[None, :, None] * pose.pow(2)).sum() * 10.0 / T
            kx, ky, kz = pose[:, knees].unbind(-1)
            ey = pose[:, elbows, 1]
            limit = torch.relu(-kx).pow(2) + torch.relu(kx - 2.6).pow(2) + 0.5 * (ky.pow(2) + kz.pow(2))
            limit = limit.sum() + torch.relu(ey[:, 0]).pow(2).sum() + torch.relu(-ey[:, 1]).pow(2).sum()
            loss = loss + 300.0 * limit / T
            if betas_fixed is None:
                loss = loss + 20.0 * betas.pow(2).sum()
        if smooth > 0 and T > 1:
            loss = loss + smooth * 300.0 * (pose[1:] - pose[:-1]).pow(2).sum() / T
            loss = loss + smooth * 3000.0 * (transl[1:] - transl[:-1]).pow(2).sum() / T
        if stage == 2 and sil is not None:
            dist, scale, vid, pts, (h, w) = sil
            v, _ = body.pose(pose, betas, transl, vid)
            px = project(v, K)  # [T,600,2] frame pixels
            g = (px * scale) / torch.tensor([w, h]) * 2 - 1
            out = torch.nn.functional.grid_sample(dist, g[:, None], align_corners=False, padding_mode="border")
            loss = loss + 0.3 * (out / (unit * float(scale.mean()))).pow(2).clamp_max(400).mean() * 21
            valid = torch.isfinite(pts[..., 0])
            d = torch.cdist(torch.nan_to_num(pts), px).min(-1).values / unit  # [T,150]
            loss = loss + 0.3 * (d.clamp_max(20).pow(2) * valid).sum() / valid.sum().clamp_min(1) * 21
        return loss

    rigid = max(iterations // 2, 1)
    last = max(iterations // 3, 1) if sil is not None else 0
    total = rigid + iterations + last
    done = [0]

    def run(tensors: list[tuple[torch.Tensor, float]], steps: int, stage: int) -> None:
        opt = torch.optim.Adam([{"params": [x], "lr": lr} for x, lr in tensors])
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 0.1 ** (i / max(steps, 1)))
        for _ in range(steps):
            opt.zero_grad()
            loss_fn(stage).backward()
            if stage == 0:
                assert pose.grad is not None
                pose.grad[:, 1:] = 0
            opt.step()
            sched.step()
            with torch.no_grad():
                betas.clamp_(-0.5, 0.5)
            done[0] += 1
            if progress is not None:
                progress(done[0], total)

    run([(pose, 0.03), (transl, 0.05)], rigid, 0)
    params: list[tuple[torch.Tensor, float]] = [(pose, 0.03), (transl, 0.02)]
    if betas_fixed is None:
        params.append((betas, 0.02))
    run(params, iterations, 1)
    if last:
        run(params, last, 2)
    with torch.no_grad():
        kp, _ = body.keypoints(pose, betas, transl)
        err = (project(kp[:, kp_ids], K) - obs).norm(dim=-1)  # [T,21]
    return betas.detach().clone(), pose.detach().clone(), transl.detach().clone(), err
