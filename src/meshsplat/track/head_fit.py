"""Fit the bundled ICT head to MediaPipe face landmarks through a clip (one camera).

API::

    fit = fit_head(landmarks, width, height, fps=None, focal=None, identity=None)
    #   landmarks [T,478,2|3]  MediaPipe face mesh with iris (refine_landmarks): x, y in pixels of the
    #                          frame (meshsplat's convention: the image spans [0,W] x [0,H]); a third
    #                          column (MediaPipe's relative depth) is ignored
    fit.vertices(t)      -> [V,3]   the whole ICT head (mouth, teeth, eyeballs) of frame t, world coords
    fit.vertices()       -> [T,V,3]
    fit.faces [F,3], fit.names (57 ARKit names), fit.weights [T,57] in [0,1]
    fit.rotations [T,3]  axis-angle, fit.translations [T,3] (cm): the head pose as BlendshapeDriver
                         applies it (about the bounding-box centre of fit.neutral)
    fit.gaze [T,2,2]     per eye (0 the subject's left) yaw (+ towards the subject's left) and pitch
                         (+ up), radians; the eyeLook* weights follow from it (ict_head.EYE_LOOK_RANGE)
    fit.neutral [V,3]    the identity: the ICT neutral deformed for this person (fit.identity = offset)
    fit.K [3,3], fit.viewmat [4,4], fit.camera() -> Camera   (world -> OpenCV camera; fixed per clip)
    fit.error_px [T]     mean landmark reprojection error per frame (pixels), fit.landmark_error_px [T,478]
    fit.focal            the focal length used (pixels)

Options: ``fps`` (scales the smoothing), ``focal`` (pixels), ``identity`` (a previous fit's, kept fixed),
``smoothing``, ``iterations``, ``progress(step, total)`` (a callback per optimizer step).

World coordinates are the ICT model's (cm, +y up, +z out of the face); the camera sits at the origin
looking along -z (``viewmat = diag(1,-1,-1,1)``), so a frontal head has a rotation near zero and
``BlendshapeDriver(fit.neutral, fit.faces, deltas, weights=fit.weights, rotations=fit.rotations,
translations=fit.translations)`` poses the same head, but for the eyeballs' gaze.

The model (``ict_head``): identity = a smooth deformation of the neutral, a cubic polynomial of the
rest position (19 monomials x 3 axes, no constant: that is the translation), L2-regularized; per frame
49 expression weights (the 57 ARKit shapes less the gaze-driven eyeLook* and PupilDilate*) kept in
[0, 1] with a small L1 prior (shapes the landmarks cannot see stay at 0), the gaze of each eye, the head
rotation and translation. The loss is the Huber loss of the 2D landmark reprojection (robust to a few
bad landmarks), plus the temporal smoothing ``smoothing * (fps/30)^2 * sum_t |x_t+1 - x_t|^2`` of
weights, gaze and pose (``fps=None`` counts as 30). Adam, all frames at once: first the pose alone, then
everything. The absolute size of a head cannot be told from one camera (a larger head farther away
projects the same), so the identity's prior keeps the ICT head's size and the depth follows.

Focal length: ``focal`` in pixels if known; otherwise a 60 degree diagonal field of view is assumed
(``DEFAULT_DIAGONAL_FOV_DEG``; phones' main and front cameras are 65-80 degrees, webcams 55-78):
landmarks alone tell the focal length only poorly (perspective vs. the head's depth profile), and a
wrong focal length mostly changes the distance, which the fit absorbs. Principal point: the image centre.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat.camera import Camera
from meshsplat.errors import MeshsplatError
from meshsplat.track.ict_head import (
    NUM_LANDMARKS,
    IctHead,
    gaze_matrices,
    load_ict_head,
    rotation_matrix,
    with_eye_look,
)
from meshsplat.track.tracker_camera import TRACKER_VIEWMAT, focal_from_fov, project, world_to_camera_axes

__all__ = ["HeadFit", "fit_head", "MIN_FRAMES_FOR_IDENTITY"]

MIN_FRAMES_FOR_IDENTITY = 10
_BASIS_SCALE = 15.0  # cm: the identity polynomial's unit length


@dataclass
class HeadFit:
    """A fitted clip (see the module docstring)."""

    head: IctHead
    identity: torch.Tensor
    weights: torch.Tensor
    gaze: torch.Tensor
    rotations: torch.Tensor
    translations: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    error_px: torch.Tensor
    landmark_error_px: torch.Tensor

    @property
    def names(self) -> list[str]:
        return list(self.head.names)

    @property
    def faces(self) -> torch.Tensor:
        return self.head.faces

    @property
    def neutral(self) -> torch.Tensor:
        return self.head.neutral + self.identity

    @property
    def num_frames(self) -> int:
        return int(self.weights.shape[0])

    @property
    def focal(self) -> float:
        return float(self.K[0, 0])

    @property
    def viewmat(self) -> torch.Tensor:
        return TRACKER_VIEWMAT.clone()

    def camera(self) -> Camera:
        return Camera(self.viewmat, self.K.clone(), self.width, self.height)

    def vertices(self, frame: int | None = None) -> torch.Tensor:
        """World vertices of ``frame`` ``[V,3]``, or of every frame ``[T,V,3]`` when ``frame`` is None."""
        if frame is None:
            sl = slice(None)
        elif not 0 <= frame < self.num_frames:
            raise MeshsplatError(f"frame: expected 0 <= frame < {self.num_frames}, got {frame}")
        else:
            sl = slice(frame, frame + 1)
        with torch.no_grad():
            v = self.head.pose(
                self.identity, self.weights[sl], self.gaze[sl], self.rotations[sl], self.translations[sl]
            )
        return v if frame is None else v[0]

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Pixels ``[...,2]`` of world ``points [...,3]``."""
        return project(points, self.K)


def _identity_basis(neutral: torch.Tensor) -> torch.Tensor:
    """Monomials of degree 1-3 of the centred, scaled rest position: ``[V,19]``."""
    q = (neutral - (neutral.min(0).values + neutral.max(0).values) / 2) / _BASIS_SCALE
    x, y, z = q.unbind(1)
    cols = [x, y, z, x * x, y * y, z * z, x * y, y * z, z * x]
    cols += [x**3, y**3, z**3, x * x * y, x * x * z, y * y * x, y * y * z, z * z * x, z * z * y, x * y * z]
    return torch.stack(cols, 1)


def _as_landmarks(landmarks: torch.Tensor | ArrayLike) -> torch.Tensor:
    a = landmarks.detach().cpu().numpy() if isinstance(landmarks, torch.Tensor) else np.asarray(landmarks)
    if a.dtype.kind not in "fiu" or a.ndim != 3 or a.shape[1] != NUM_LANDMARKS or a.shape[2] not in (2, 3):
        raise MeshsplatError(
            f"landmarks: expected [T,{NUM_LANDMARKS},2|3] numbers (MediaPipe face mesh with refine_landmarks, "
            f"pixels), got {list(a.shape)} {a.dtype}"
        )
    if a.shape[0] == 0:
        raise MeshsplatError("landmarks: no frames; the clip needs at least one frame with a face")
    bad = np.nonzero(~np.isfinite(a[..., :2]).all((1, 2)))[0]
    if len(bad):
        raise MeshsplatError(
            f"landmarks: frames {bad[:10].tolist()} hold NaN/Inf (no face found?); leave those frames out before fitting"
        )
    return torch.from_numpy(a[..., :2].astype(np.float32))


def fit_head(
    landmarks: torch.Tensor | ArrayLike,
    width: int,
    height: int,
    fps: float | None = None,
    focal: float | None = None,
    identity: torch.Tensor | None = None,
    smoothing: float = 1.0,
    iterations: int = 300,
    head: IctHead | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> HeadFit:
    """Fit the ICT head to ``landmarks [T,478,2|3]`` (pixels) of ``width`` x ``height`` frames.

    ``focal`` (pixels) defaults to :func:`focal_from_fov` (60 degrees diagonal); ``identity [V,3]`` (a
    previous fit's ``identity``) is kept fixed instead of fitted, which also lets clips shorter than
    ``MIN_FRAMES_FOR_IDENTITY`` frames be fitted; ``smoothing`` scales the temporal smoothing (0: none);
    ``iterations`` of the joint stage (the pose-only stage runs half as many); ``progress(step, total)``
    is called after each optimizer step (a progress bar)."""
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise MeshsplatError(f"{name}: expected a positive integer (pixels), got {value!r}")
    obs = _as_landmarks(landmarks)
    T = obs.shape[0]
    head = load_ict_head() if head is None else head
    if identity is None and T < MIN_FRAMES_FOR_IDENTITY:
        raise MeshsplatError(
            f"landmarks: {T} frame(s) are too few to fit the head's identity (at least "
            f"{MIN_FRAMES_FOR_IDENTITY}); use a longer clip, or pass identity= from a fit of the same person"
        )
    if identity is not None and tuple(identity.shape) != tuple(head.neutral.shape):
        raise MeshsplatError(
            f"identity: expected [{head.neutral.shape[0]},3] (a HeadFit.identity), got {list(identity.shape)}"
        )
    f = focal_from_fov(int(width), int(height)) if focal is None else float(focal)
    if not (math.isfinite(f) and f > 0):
        raise MeshsplatError(f"focal: expected a positive number of pixels, got {focal!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
        raise MeshsplatError(f"iterations: expected a positive integer, got {iterations!r}")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise MeshsplatError(f"fps: expected a positive frame rate, got {fps!r}")
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # hundreds of small steps: more threads only wait on each other (5-10x slower under load)
    try:
        with torch.enable_grad():
            smooth = smoothing * ((30.0 if fps is None else fps) / 30.0) ** 2
            params = _optimize(head, obs, K, identity, smooth, iterations, progress)
    finally:
        torch.set_num_threads(threads)
    identity_t, weights, gaze, rot, trans, err = params
    return HeadFit(head, identity_t, weights, gaze, rot, trans, K, int(width), int(height), err.mean(1), err)


class _Landmarks:
    """The landmark points as the model poses them, computed on the points themselves: every step of
    ``ict_head.IctHead.pose`` is affine per vertex (an eyeball triangle turns whole), so it commutes with
    the barycentric blend. The pivot stays at the neutral's during the fit."""

    def __init__(self, head: IctHead) -> None:
        tri = head.faces[head.landmark_face]  # [L,3]
        bary = head.landmark_bary

        def blend(x: torch.Tensor) -> torch.Tensor:  # per-vertex [...,V,C] -> per-landmark [...,L,C]
            return (bary[..., None] * x[..., tri, :]).sum(-2)

        basis = _identity_basis(head.neutral)
        self.basis = blend(basis)  # [L,19]
        self.neutral = blend(head.neutral)
        self.deltas = blend(head.deltas).reshape(len(head.names), -1)  # [E,L*3]
        on_eye = [torch.isin(tri, e).all(1) for e in head.eye_vertices]
        self.eye_ids = [torch.nonzero(m).reshape(-1) for m in on_eye]
        self.eye_basis = torch.stack([basis[e].mean(0) for e in head.eye_vertices])  # [2,19]
        self.eye_centers = head.eye_centers
        self.eye_look = head.eye_look
        self.pivot = head.pivot(head.neutral)

    def points(
        self, coeffs: torch.Tensor, w: torch.Tensor, gaze: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor
    ) -> torch.Tensor:
        """World landmark points ``[T,L,3]``."""
        T = w.shape[0]
        w = with_eye_look(w, gaze, self.eye_look)
        v = (self.neutral + self.basis @ coeffs) + (w @ self.deltas).reshape(T, -1, 3)
        gm = gaze_matrices(gaze)  # [T,2,3,3]
        centers = self.eye_centers + self.eye_basis @ coeffs  # [2,3]
        for eye, ids in enumerate(self.eye_ids):
            if len(ids):
                turned = torch.einsum("tij,tvj->tvi", gm[:, eye], v[:, ids] - centers[eye]) + centers[eye]
                v = v.index_copy(1, ids, turned)
        R = rotation_matrix(rot)
        return torch.einsum("tij,tvj->tvi", R, v - self.pivot) + self.pivot + trans[:, None]


def _optimize(
    head: IctHead,
    obs: torch.Tensor,
    K: torch.Tensor,
    identity: torch.Tensor | None,
    smooth: float,
    iterations: int,
    progress: Callable[[int, int], None] | None,
) -> tuple[torch.Tensor, ...]:
    T, E = obs.shape[0], len(head.names)
    sub = _Landmarks(head)
    basis = _identity_basis(head.neutral)
    free = head.free_shapes
    # residuals in units of 1/100 of the landmarks' spread in the image, so the priors' weights do not
    # depend on the resolution or the distance
    spread2d = (obs - obs.mean(1, keepdim=True)).pow(2).sum(-1).mean(1).sqrt()  # [T]
    unit = float(spread2d.mean()) / 100.0
    # initial pose: frontal, at the distance where the neutral's landmarks have the observed spread
    lm0 = head.landmarks(head.neutral)
    spread3 = float((lm0[:, :2] - lm0[:, :2].mean(0)).pow(2).sum(-1).mean().sqrt())
    f = float(K[0, 0])
    z0 = f * spread3 / spread2d
    c2 = obs.mean(1)
    cam_c = torch.stack([(c2[:, 0] - K[0, 2]) * z0 / f, (c2[:, 1] - K[1, 2]) * z0 / f, z0], 1)
    trans = (world_to_camera_axes(cam_c) - lm0.mean(0)).clone().requires_grad_(True)
    rot = torch.zeros(T, 3, requires_grad=True)
    if identity is None:
        coeffs = torch.zeros(basis.shape[1], 3, requires_grad=True)
    else:  # a given identity: its least-squares coefficients stand in for the subset; fixed
        coeffs = torch.linalg.lstsq(basis, identity).solution.detach()
        sub.neutral = head.landmarks(head.neutral + identity) - sub.basis @ coeffs
        eye_mean = torch.stack([identity[e].mean(0) for e in head.eye_vertices])
        sub.eye_centers = head.eye_centers + eye_mean - sub.eye_basis @ coeffs
    w_free = torch.zeros(T, len(free), requires_grad=True)
    gaze = torch.zeros(T, 2, 2, requires_grad=True)

    def weights() -> torch.Tensor:
        return torch.zeros(T, E).index_copy(1, free, w_free)

    def loss_fn(stage: int) -> torch.Tensor:
        pts = sub.points(coeffs, weights(), gaze, rot, trans)
        res = (project(pts, K) - obs) / unit
        loss = torch.nn.functional.huber_loss(res, torch.zeros_like(res), delta=3.0, reduction="sum") / T
        if smooth > 0 and T > 1:
            for x, s in ((w_free, 30.0), (gaze, 30.0), (rot, 100.0), (trans, 0.3)):
                loss = loss + smooth * s * (x[1:] - x[:-1]).pow(2).sum() / T
        if stage == 1:
            loss = loss + 0.5 * w_free.sum() / T + 2.0 * gaze.pow(2).sum() / T
            if identity is None:
                loss = loss + 0.05 * coeffs.pow(2).sum()
        return loss

    rigid_steps = max(iterations // 2, 1)
    done = [0]

    def run(tensors: list[tuple[torch.Tensor, float]], steps: int, stage: int) -> None:
        opt = torch.optim.Adam([{"params": [x], "lr": lr} for x, lr in tensors])
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 0.1 ** (i / max(steps, 1)))
        for _ in range(steps):
            opt.zero_grad()
            loss_fn(stage).backward()
            opt.step()
            sched.step()
            with torch.no_grad():
                w_free.clamp_(0, 1)
                gaze.clamp_(-0.8, 0.8)
            done[0] += 1
            if progress is not None:
                progress(done[0], rigid_steps + iterations)

    run([(rot, 0.05), (trans, 1.0)], rigid_steps, 0)
    run(
        [(rot, 0.02), (trans, 0.3), (w_free, 0.05), (gaze, 0.03)] + ([(coeffs, 0.05)] if identity is None else []),
        iterations,
        1,
    )
    with torch.no_grad():
        ident = basis @ coeffs if identity is None else identity.clone()
        # the fit turned the head about the neutral's pivot; HeadFit (and BlendshapeDriver) about the
        # fitted rest's p': R (v - p) + p + t = R (v - p') + p' + t' with t' = t + (R - I)(p' - p)
        p, p2 = sub.pivot, head.pivot(head.neutral + ident)
        R = rotation_matrix(rot)
        t2 = trans + torch.einsum("tij,j->ti", R - torch.eye(3), p2 - p)
        w = with_eye_look(weights(), gaze, head.eye_look)
        err = (project(sub.points(coeffs, weights(), gaze, rot, trans), K) - obs).norm(dim=-1)  # [T,L]
        return ident, w, gaze.detach().clone(), rot.detach().clone(), t2.detach(), err
