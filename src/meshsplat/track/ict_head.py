"""The bundled ICT FaceKit head as a model a tracker poses: identity, expressions, eye gaze and head pose.

World coordinates are the model's own (centimetres, +y up, +z out of the face, +x the subject's left).
One frame's vertices, batched over frames ``T``:

    rest  = neutral + identity                        identity [V,3]: a per-clip offset of the neutral
    v     = rest + sum_e w_e * delta_e                w [T,E] in [0, 1] (the 57 ARKit-named shapes)
    eyes  : the eyeball vertices of each eye turned about its centre by the gaze (yaw, pitch)
    world = R (v - pivot) + pivot + t                 R from axis-angle [T,3], pivot the rest's bbox centre

as :class:`meshsplat.drivers.blendshape.BlendshapeDriver` poses it (same pivot rule), plus the gaze.
Gaze ``[T,2,2]``: per eye (0 the subject's left eye, ``M_IrisLeft``/``M_ScleraLeft``; 1 the right) the
yaw (radians, positive towards +x, the subject's left) and pitch (positive up) of the eyeball. The
eyelids follow the gaze as in ARKit: ``eyeLook*`` weights are set from it (``EYE_LOOK_RANGE`` radians
of gaze give weight 1), so a tracker never fits those eight shapes freely.

The landmark correspondence (``ict_facekit/ict_mediapipe_landmarks.npz``, derived by
``bench/derive_ict_landmarks.py``) ties MediaPipe face-mesh landmark ``i`` (478 with the iris) to the
surface point ``bary[i]`` of triangle ``face[i]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npz
from meshsplat.paths import asset

__all__ = [
    "IctHead",
    "load_ict_head",
    "LANDMARKS_ASSET",
    "NUM_LANDMARKS",
    "EYE_LOOK_RANGE",
    "gaze_matrices",
    "rotation_matrix",
    "with_eye_look",
    "eye_look_weights",
]

LANDMARKS_ASSET = "ict_facekit/ict_mediapipe_landmarks.npz"
NUM_LANDMARKS = 478  # MediaPipe face mesh with refine_landmarks (468 + 10 iris points)
EYE_LOOK_RANGE = math.radians(30.0)  # gaze angle at which an ARKit eyeLook* weight reaches 1
_EYE_MATERIALS = (("M_IrisLeft", "M_ScleraLeft"), ("M_IrisRight", "M_ScleraRight"))
# eyeLook shape per (eye, direction): directions yaw+ (towards +x), yaw-, pitch+ (up), pitch-
_EYE_LOOK = (
    ("eyeLookOut_L", "eyeLookIn_L", "eyeLookUp_L", "eyeLookDown_L"),  # left eye: out is +x
    ("eyeLookIn_R", "eyeLookOut_R", "eyeLookUp_R", "eyeLookDown_R"),  # right eye: in is +x
)


@dataclass
class IctHead:
    """The head model: ``neutral [V,3]``, ``faces [F,3]``, ``deltas [E,V,3]``, ``names`` (E),
    ``face_material [F]`` -> ``material_names``, ``eye_vertices`` (two index tensors), ``eye_centers [2,3]``
    (least-squares sphere centres of each eyeball), ``eye_look [2,4]`` (the eyeLook shape indices,
    order yaw+, yaw-, pitch+, pitch-), and the landmark correspondence ``landmark_face [L]``,
    ``landmark_bary [L,3]``."""

    neutral: torch.Tensor
    faces: torch.Tensor
    deltas: torch.Tensor
    names: list[str]
    face_material: torch.Tensor
    material_names: list[str]
    eye_vertices: tuple[torch.Tensor, torch.Tensor]
    eye_centers: torch.Tensor
    eye_look: torch.Tensor
    landmark_face: torch.Tensor
    landmark_bary: torch.Tensor

    @property
    def free_shapes(self) -> torch.Tensor:
        """Indices of the shapes a tracker fits: all but the gaze-driven eyeLook* and PupilDilate*."""
        fixed = set(self.eye_look.reshape(-1).tolist())
        fixed |= {i for i, n in enumerate(self.names) if n.startswith("PupilDilate")}
        return torch.tensor([i for i in range(len(self.names)) if i not in fixed], dtype=torch.long)

    def pivot(self, rest: torch.Tensor) -> torch.Tensor:
        """Head-pose centre ``[3]``: the bounding-box centre of ``rest [V,3]`` (BlendshapeDriver's rule)."""
        return (rest.min(0).values + rest.max(0).values) / 2

    def pose(
        self,
        identity: torch.Tensor,
        weights: torch.Tensor,
        gaze: torch.Tensor,
        rotations: torch.Tensor,
        translations: torch.Tensor,
        vertices: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """World vertices ``[T,V',3]`` for ``identity [V,3]``, ``weights [T,E]`` (the eyeLook columns are
        replaced by the gaze's), ``gaze [T,2,2]``, ``rotations [T,3]``, ``translations [T,3]``;
        ``vertices [V']`` picks a subset (default all)."""
        rest = self.neutral + identity
        pivot = self.pivot(rest)
        idx = torch.arange(rest.shape[0]) if vertices is None else vertices
        w = with_eye_look(weights, gaze, self.eye_look)
        v = rest[idx] + torch.einsum("te,evc->tvc", w, self.deltas[:, idx])
        gm = gaze_matrices(gaze)  # [T,2,3,3]
        for eye in range(2):
            sel = torch.isin(idx, self.eye_vertices[eye])
            if bool(sel.any()):
                c = self.eye_centers[eye] + identity[self.eye_vertices[eye]].mean(0)
                turned = torch.einsum("tij,tvj->tvi", gm[:, eye], v[:, sel] - c) + c
                v = v.clone()
                v[:, sel] = turned
        R = rotation_matrix(rotations)
        return torch.einsum("tij,tvj->tvi", R, v - pivot) + pivot + translations[:, None]

    def landmarks(self, vertices: torch.Tensor) -> torch.Tensor:
        """Landmark points ``[...,L,3]`` from vertices ``[...,V,3]`` (all of them)."""
        tri = vertices[..., self.faces[self.landmark_face], :]  # [...,L,3,3]
        return (self.landmark_bary[..., None] * tri).sum(-2)

    @property
    def landmark_vertices(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(vertices [U], corners [L,3])``: the vertices landmarks touch and each landmark's three
        corners as positions in that list, for posing only what a fit needs."""
        corners = self.faces[self.landmark_face]
        uniq, inv = torch.unique(corners.reshape(-1), return_inverse=True)
        return uniq, inv.reshape(-1, 3)


def rotation_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues ``aa [...,3]`` -> ``[...,3,3]`` with a gradient at zero (``drivers.blendshape.
    axis_angle_to_matrix`` normalises the axis, which leaves a fit starting at zero rotation stuck)."""
    theta2 = aa.pow(2).sum(-1, keepdim=True)[..., None]
    theta = (theta2 + 1e-12).sqrt()
    x, y, z = aa.unbind(-1)
    o = torch.zeros_like(x)
    Kx = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(aa.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(Kx)
    return eye + torch.sin(theta) / theta * Kx + (1 - torch.cos(theta)) / (theta * theta) * (Kx @ Kx)


def gaze_matrices(gaze: torch.Tensor) -> torch.Tensor:
    """Eyeball rotations ``[...,2,3,3]`` for ``gaze [...,2,2]`` (yaw about +y, then pitch about -x)."""
    yaw, pitch = gaze[..., 0], gaze[..., 1]
    cy, sy, cp, sp = torch.cos(yaw), torch.sin(yaw), torch.cos(pitch), torch.sin(pitch)
    z, o = torch.zeros_like(yaw), torch.ones_like(yaw)
    ry = torch.stack([cy, z, sy, z, o, z, -sy, z, cy], -1).reshape(gaze.shape[:-1] + (3, 3))
    rx = torch.stack([o, z, z, z, cp, sp, z, -sp, cp], -1).reshape(gaze.shape[:-1] + (3, 3))
    return ry @ rx  # forward +z -> (sin yaw cos pitch, sin pitch, cos yaw cos pitch)


def eye_look_weights(gaze: torch.Tensor) -> torch.Tensor:
    """ARKit eyeLook weights ``[...,2,4]`` (yaw+, yaw-, pitch+, pitch-) for ``gaze [...,2,2]``."""
    g = torch.stack([gaze[..., 0], -gaze[..., 0], gaze[..., 1], -gaze[..., 1]], -1)
    return (g / EYE_LOOK_RANGE).clamp(0, 1)


def with_eye_look(weights: torch.Tensor, gaze: torch.Tensor, eye_look: torch.Tensor) -> torch.Tensor:
    """``weights [T,E]`` with the eyeLook columns set from ``gaze [T,2,2]``."""
    w = weights.clone()
    w[:, eye_look.reshape(-1)] = eye_look_weights(gaze).reshape(gaze.shape[0], -1).to(w)
    return w


def _sphere_center(points: torch.Tensor) -> torch.Tensor:
    """Least-squares sphere centre of ``points [N,3]``: |p|^2 = 2 p.c + (r^2 - |c|^2)."""
    p = points.double()
    A = torch.cat([2 * p, torch.ones(len(p), 1, dtype=p.dtype)], 1)
    sol = torch.linalg.lstsq(A, (p * p).sum(1, keepdim=True)).solution
    return sol[:3, 0].float()


def load_ict_head(with_landmarks: bool = True) -> IctHead:
    """The bundled ICT head (``paths.asset``) with its landmark correspondence (unless ``with_landmarks``
    is False: the derivation script builds the correspondence from a head without one)."""
    arrays = read_npz(asset("ict_facekit/ict_face_arkit53.npz"), "ICT head .npz")
    neutral = torch.from_numpy(arrays["neutral"].astype(np.float32))
    faces = torch.from_numpy(arrays["faces"].astype(np.int64))
    deltas = torch.from_numpy(arrays["expr_deltas"].astype(np.float32))
    names = [str(s) for s in arrays["expr_names"]]
    fm = torch.from_numpy(arrays["face_material"].astype(np.int64))
    mats = [str(s) for s in arrays["material_names"]]
    eyes = []
    for group in _EYE_MATERIALS:
        ids = torch.tensor([mats.index(m) for m in group])
        eyes.append(torch.unique(faces[torch.isin(fm, ids)].reshape(-1)))
    centers = torch.stack([_sphere_center(neutral[e]) for e in eyes])
    eye_look = torch.tensor([[names.index(n) for n in row] for row in _EYE_LOOK], dtype=torch.long)
    lface = torch.zeros(0, dtype=torch.long)
    lbary = torch.zeros(0, 3)
    if with_landmarks:
        lm = read_npz(asset(LANDMARKS_ASSET), "ICT landmark correspondence .npz")
        lface = torch.from_numpy(lm["face"].astype(np.int64))
        lbary = torch.from_numpy(lm["bary"].astype(np.float32))
        if lface.shape != (NUM_LANDMARKS,) or lbary.shape != (NUM_LANDMARKS, 3):
            raise MeshsplatError(
                f"{LANDMARKS_ASSET}: expected face [{NUM_LANDMARKS}] and bary [{NUM_LANDMARKS},3]; "
                "re-derive it with bench/derive_ict_landmarks.py"
            )
    return IctHead(neutral, faces, deltas, names, fm, mats, (eyes[0], eyes[1]), centers, eye_look, lface, lbary)
