"""Stand-in SMPL / SMPL-X bodies built from the CesiumMan rig (see :mod:`meshsplat.synth.standin_models`)."""

from __future__ import annotations

import numpy as np

from meshsplat.drivers.gltf import GltfDriver
from meshsplat.paths import asset
from meshsplat.synth._standin_geometry import (
    bone_closest,
    farthest_points,
    joint_regressor,
    smoothstep,
    split_to_count,
    weld,
)

__all__ = ["SMPL_PARENTS", "SMPLX_PARENTS", "body_model_dict"]

SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
_FINGER_PARENTS_L = [20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38]
SMPLX_PARENTS = (
    SMPL_PARENTS[:22] + [15, 15, 15] + _FINGER_PARENTS_L + [21 if p == 20 else p + 15 for p in _FINGER_PARENTS_L]
)
HEIGHT = 1.70  # metres, SMPL-neutral-like
PELVIS = np.array([0.0, -0.24, 0.02])  # SMPL's root lies near here in its template

# CesiumMan skin joint name -> SMPL joint it drives (torso_joint_3 is split over spine2/spine3/collars)
_DIRECT = {
    "Skeleton_torso_joint_1": 0,
    "leg_joint_L_1": 1,
    "leg_joint_R_1": 2,
    "Skeleton_torso_joint_2": 3,
    "leg_joint_L_2": 4,
    "leg_joint_R_2": 5,
    "leg_joint_L_3": 7,
    "leg_joint_R_3": 8,
    "torso_joint_3": 9,
    "leg_joint_L_5": 10,
    "leg_joint_R_5": 11,
    "Skeleton_neck_joint_1": 12,
    "Skeleton_neck_joint_2": 15,
    "Skeleton_arm_joint_L__4_": 16,
    "Skeleton_arm_joint_R": 17,
    "Skeleton_arm_joint_L__3_": 18,
    "Skeleton_arm_joint_R__2_": 19,
    "Skeleton_arm_joint_L__2_": 20,
    "Skeleton_arm_joint_R__3_": 21,
}


def _cesium():
    """Welded CesiumMan rest mesh, its 24-column SMPL-like skin weights and the 19 rig joint positions."""
    d = GltfDriver(asset("gltf/CesiumMan.glb"))
    world = _t_pose(d, d.node_world_matrices(None, None))
    names = [d.file.doc.nodes[n].name for n in d._pair_node]  # skin joints in pair-table order
    pos = {nm: world[n][:3, 3] for nm, n in zip(names, d._pair_node, strict=True)}
    m = d._blend_matrices(world)  # CesiumMan's own skinning, re-posed (it has no morph targets)
    v0 = np.einsum("vij,vj->vi", m[:, :3, :3], d._rig.base) + m[:, :3, 3]
    w19 = np.zeros((len(v0), len(names)))
    np.add.at(
        w19,
        (np.repeat(np.arange(len(v0)), d._rig.pair_index.shape[1]), d._rig.pair_index.ravel()),
        d._rig.pair_weight.ravel(),
    )
    v, f, first = weld(v0, d.faces.numpy().astype(np.int64))
    w19 = w19[first]
    w = np.zeros((len(v), 24))
    for i, nm in enumerate(names):
        w[:, _DIRECT[nm]] += w19[:, i]
    return v, f, w, pos


def _t_pose(d: GltfDriver, world: np.ndarray) -> np.ndarray:
    """Raise CesiumMan's arms (rest A-pose, ~27 degrees down) to SMPL's horizontal T-pose."""
    world = world.copy()
    nodes = d.file.doc.nodes
    idx = {n.name: i for i, n in enumerate(nodes)}
    for shoulder, elbow in (
        ("Skeleton_arm_joint_L__4_", "Skeleton_arm_joint_L__3_"),
        ("Skeleton_arm_joint_R", "Skeleton_arm_joint_R__2_"),
    ):
        s, e = world[idx[shoulder]][:3, 3], world[idx[elbow]][:3, 3]
        a = -np.arctan2(e[1] - s[1], abs(e[0] - s[0])) * np.sign(e[0] - s[0])
        T = np.eye(4)
        T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
        T[:3, 3] = s - T[:3, :3] @ s
        stack = [idx[shoulder]]
        while stack:
            i = stack.pop()
            world[i] = T @ world[i]
            stack.extend(nodes[i].children or [])
    return world


def _smpl_joints(pos) -> np.ndarray:
    P = {k: np.asarray(p, np.float64) for k, p in pos.items()}
    t1, t2, t3 = P["Skeleton_torso_joint_1"], P["Skeleton_torso_joint_2"], P["torso_joint_3"]
    J = np.zeros((24, 3))
    for nm, j in _DIRECT.items():
        J[j] = P[nm]
    J[6] = t2 + 0.45 * (t3 - t2)  # spine2
    J[9] = t2 + 0.85 * (t3 - t2)  # spine3 (chest)
    J[12] = P["Skeleton_neck_joint_1"]
    J[15] = P["Skeleton_neck_joint_2"] + np.array([0, 0.04, 0.01])  # head
    for collar, shoulder in ((13, 16), (14, 17)):
        J[collar] = t3 + 0.5 * (J[shoulder] - t3) + np.array([0, 0.02, -0.01])
    for hand, wrist, elbow in ((22, 20, 18), (23, 21, 19)):
        dvec = J[wrist] - J[elbow]
        J[hand] = J[wrist] + 0.07 * dvec / np.linalg.norm(dvec)
    J[0] = 0.5 * (t1 + 0.5 * (J[1] + J[2]))
    return J


def _share(w, v, src, dst, fraction):
    """Move ``fraction [V]`` of joint ``src``'s weight to joint ``dst``."""
    moved = w[:, src] * np.clip(fraction, 0, 1)
    w[:, src] -= moved
    w[:, dst] += moved


def _refine_weights(v, w, J):
    """Spread the weights CesiumMan has no joint for: spine2, collars, hands (small, near the joint)."""
    y = v[:, 1]
    # chest weight (on spine3) shared downwards with spine2 by height, torso2 weight upwards
    _share(w, v, 9, 6, 1 - smoothstep((y - J[6, 1]) / (J[9, 1] - J[6, 1] + 1e-9)))
    _share(w, v, 3, 6, smoothstep((y - J[3, 1]) / (J[6, 1] - J[3, 1] + 1e-9)) * 0.5)
    for collar, side in ((13, 1), (14, -1)):
        near = np.exp(-np.sum((v - J[collar]) ** 2, 1) / (2 * 0.05**2)) * (side * v[:, 0] > 0.01)
        _share(w, v, 9, collar, 0.6 * near)
    for hand, wrist, elbow in ((22, 20, 18), (23, 21, 19)):
        dvec = (J[wrist] - J[elbow]) / np.linalg.norm(J[wrist] - J[elbow])
        along = (v - J[wrist]) @ dvec
        _share(w, v, wrist, hand, 0.5 * smoothstep(along / 0.05))


def _shape_fields(v, w, J, parents) -> np.ndarray:
    """Ten smooth shape directions ``[V,3,10]`` (metres per unit beta)."""
    y, V = v[:, 1], len(v)
    foot_y = v[:, 1].min()
    dom = w.argmax(1)
    heads = J[dom]
    child = {p: c for c, p in reversed(list(enumerate(parents))) if p >= 0}
    tails = np.stack([J[child.get(j, parents[j] if parents[j] >= 0 else j)] for j in dom])
    radial = v - bone_closest(v, heads, tails)
    zc = J[:, 2].mean()

    def g(x: np.ndarray, s: float) -> np.ndarray:
        return np.exp(-0.5 * (x / s) ** 2)

    S = np.zeros((V, 3, 10))
    S[:, :, 0] = 0.03 * (v - np.array([0.0, foot_y, 0.0]))  # overall size, feet stay on the floor
    S[:, :, 1] = 0.12 * radial  # girth
    S[:, 1, 2] = -0.04 * np.clip((J[1, 1] - y) / (J[1, 1] - foot_y), 0, 1)  # leg length
    S[:, 0, 3] = (
        0.025 * np.sign(v[:, 0]) * smoothstep((np.abs(v[:, 0]) - 0.04) / 0.12) * smoothstep((y - J[6, 1]) / 0.1)
    )  # shoulder width
    S[:, 2, 4] = 0.04 * g(y - J[3, 1], 0.1) * np.clip((v[:, 2] - zc) / 0.1, 0, 1)  # belly
    head_w = w[:, 15] + w[:, 12] * 0.5
    S[:, :, 5] = 0.06 * (v - J[15]) * head_w[:, None]  # head size
    arm = w[:, [18, 20, 22]].sum(1) - w[:, [19, 21, 23]].sum(1)
    S[:, 0, 6] = 0.03 * arm  # arm length (left +x, right -x)
    S[:, 1, 7] = 0.03 * smoothstep((y - J[3, 1]) / (J[12, 1] - J[3, 1]))  # torso length
    S[:, 0, 8] = 0.03 * np.sign(v[:, 0]) * g(y - J[1, 1], 0.1) * smoothstep(np.abs(v[:, 0]) / 0.1)  # hips
    S[:, 2, 9] = 0.025 * g(y - J[9, 1], 0.08) * np.tanh((v[:, 2] - zc) / 0.05)  # chest depth
    return S


def _expression_fields(v, J) -> np.ndarray:
    """Ten smooth face-local expression directions ``[V,3,10]`` around the head front."""
    head = J[15]
    front = smoothstep((v[:, 2] - head[2]) / 0.06) * np.exp(-np.sum((v - head) ** 2, 1) / (2 * 0.09**2))
    spots = [
        ((0, -0.05, 0.09), (0, -0.012, 0)),
        ((0.03, -0.03, 0.08), (0.004, 0.004, 0)),
        ((-0.03, -0.03, 0.08), (-0.004, 0.004, 0)),
        ((0.035, 0.04, 0.08), (0, 0.006, 0)),
        ((-0.035, 0.04, 0.08), (0, 0.006, 0)),
        ((0, -0.035, 0.1), (0, 0, 0.006)),
        ((0.04, -0.01, 0.07), (0, 0, 0.006)),
        ((-0.04, -0.01, 0.07), (0, 0, 0.006)),
        ((0, 0.0, 0.11), (0, 0.003, 0.002)),
        ((0, 0.06, 0.08), (0, -0.004, 0)),
    ]
    E = np.zeros((len(v), 3, 10))
    for k, (c, d) in enumerate(spots):
        bump = np.exp(-np.sum((v - head - np.array(c)) ** 2, 1) / (2 * 0.025**2)) * front
        E[:, :, k] = bump[:, None] * np.array(d)
    return E


def _hand_joints(J):
    """15 finger joints per hand for SMPL-X: 3 per finger (index, middle, pinky, ring, thumb)."""
    out = []
    for wrist, elbow, side in ((20, 18, 1.0), (21, 19, -1.0)):
        d = (J[wrist] - J[elbow]) / np.linalg.norm(J[wrist] - J[elbow])
        lat = np.cross(d, np.array([0.0, 1.0, 0.0]))
        lat /= np.linalg.norm(lat) + 1e-12
        for off, base, step in (
            (0.015, 0.07, 0.025),
            (0.005, 0.075, 0.027),
            (-0.018, 0.065, 0.02),
            (-0.006, 0.07, 0.024),
            (0.03, 0.025, 0.025),
        ):
            for k in range(3):
                out.append(J[wrist] + d * (base + k * step) + lat * off * side)
    return np.stack(out)


def _smplx_weights(v, w24, J55):
    """55-column weights: SMPL's first 22, a little jaw on the lower face, fingers from the hands."""
    w = np.zeros((len(v), 55))
    w[:, :22] = w24[:, :22]
    for hand, wrist, first in ((22, 20, 25), (23, 21, 40)):
        fingers = J55[first : first + 15]
        near = np.argmin(np.linalg.norm(v[:, None] - fingers[None], axis=2), 1)
        rows = np.nonzero(w24[:, hand] > 0)[0]
        w[rows, wrist] += 0.5 * w24[rows, hand]
        w[rows, first + near[rows]] += 0.5 * w24[rows, hand]
    head = J55[15]
    jaw_region = smoothstep((head[1] - 0.03 - v[:, 1]) / 0.03) * smoothstep((v[:, 2] - head[2]) / 0.04)
    _share(w, v, 15, 22, 0.7 * jaw_region)
    return w


def _place(v, J):
    """Scale to HEIGHT and move the pelvis to PELVIS."""
    s = HEIGHT / np.ptp(v[:, 1])
    off = PELVIS - s * J[0]
    return v * s + off, J * s + off


def _landmarks(v, f, J, n, seed_face=None):
    """``n`` faces spread over the face (front of the head) with centroid barycentrics."""
    c = v[f].mean(1)
    head = J[15]
    cand = np.nonzero((c[:, 2] > head[2] + 0.04) & (np.abs(c[:, 1] - head[1]) < 0.09))[0]
    cand = cand if len(cand) >= n else np.argsort(-c[:, 2])[: 4 * n]
    pick = cand[farthest_points(c[cand], n)]
    return pick.astype(np.int64), np.full((n, 3), 1 / 3)


def body_model_dict(kind: str) -> tuple[dict, np.ndarray]:
    """Model dict with the keys/dtypes/shapes smplx reads for ``kind`` ("smpl" or "smplx"), and the
    dominant-joint labels ``[V]`` used for colouring."""
    v, f, w, pos = _cesium()
    J = _smpl_joints(pos)
    _refine_weights(v, w, J)
    v, J = _place(v, J)
    target = 6890 if kind == "smpl" else 10475
    v, f, w = split_to_count(v, f, target, w)
    w = np.clip(w, 0, None)
    w /= w.sum(1, keepdims=True)
    parents = SMPL_PARENTS
    dom = w.argmax(1)  # dominant SMPL joint, for colours
    if kind == "smplx":
        J = np.concatenate(
            [J[:22], J[15] + np.array([[0, -0.035, 0.05], [0.032, 0.03, 0.08], [-0.032, 0.03, 0.08]]), _hand_joints(J)]
        )
        w = _smplx_weights(v, w, J)
        parents = SMPLX_PARENTS
    nJ = len(parents)
    cands = [
        np.nonzero((w[:, j] > 0.2) | ((w[:, parents[j]] > 0.2) if parents[j] >= 0 else False))[0] for j in range(nJ)
    ]
    jreg = joint_regressor(v, J, cands)
    kintree = np.stack([np.array(parents, np.int64), np.arange(nJ)])
    kintree[0, 0] = 4294967295  # the official files store the root's parent as uint32 -1
    shapedirs = _shape_fields(v, w, J, parents)
    if kind == "smplx":
        shapedirs = np.concatenate([shapedirs, _expression_fields(v, J)], 2)
    d = {
        "v_template": v.astype(np.float64),
        "f": f.astype(np.uint32),
        "shapedirs": shapedirs.astype(np.float64),
        "posedirs": np.zeros((len(v), 3, (nJ - 1) * 9), np.float32),
        "J_regressor": jreg.astype(np.float64),
        "weights": w.astype(np.float64),
        "kintree_table": kintree,
    }
    if kind == "smplx":
        lmk, bary = _landmarks(v, f, J, 51)
        curl = np.zeros(45)
        d.update(
            {
                "hands_componentsl": np.eye(45),
                "hands_componentsr": np.eye(45),
                "hands_meanl": curl.copy(),
                "hands_meanr": curl.copy(),
                "lmk_faces_idx": lmk,
                "lmk_bary_coords": bary,
                "dynamic_lmk_faces_idx": np.tile(lmk[:17], (79, 1)),
                "dynamic_lmk_bary_coords": np.full((79, 17, 3), 1 / 3),
            }
        )
    return d, dom
