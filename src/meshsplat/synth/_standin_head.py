"""Stand-in FLAME head built from the ICT FaceKit head (see :mod:`meshsplat.synth.standin_models`)."""

from __future__ import annotations

import numpy as np

from meshsplat.paths import asset
from meshsplat.synth._standin_geometry import (
    farthest_points,
    joint_regressor,
    smoothstep,
    split_to_count,
    subsample_surface,
)

__all__ = ["FLAME_PARENTS", "flame_model_dict"]

FLAME_PARENTS = [-1, 0, 1, 1, 1]  # root (neck base), neck, jaw, left eye, right eye
NUM_VERTICES = 5023
_SKIN = ("M_Face", "M_BackHead")
_EYES = {"left": ("M_ScleraLeft", "M_IrisLeft"), "right": ("M_ScleraRight", "M_IrisRight")}
_FIRST_EXPRESSIONS = (
    "jawOpen",
    "mouthSmile_L",
    "mouthSmile_R",
    "eyeBlink_L",
    "eyeBlink_R",
    "browInnerUp_L",
    "browInnerUp_R",
    "mouthPucker",
    "mouthFunnel",
    "jawLeft",
    "jawRight",
)


def _ict():
    with np.load(asset("ict_facekit/ict_face_arkit53.npz")) as z:
        mats = [str(s) for s in z["material_names"]]
        return (
            z["neutral"].astype(np.float64) * 0.01,
            z["faces"].astype(np.int64),
            z["face_material"].astype(np.int64),
            mats,
            [str(s) for s in z["expr_names"]],
            z["expr_deltas"].astype(np.float64) * 0.01,
        )


def _head_mesh():
    """ICT skin + eyeballs subsampled to 5023 vertices; returns verts, faces, part [V] (0 skin, 1 left eye,
    2 right eye), expression deltas [E,V,3], expression names."""
    v, f, fm, mats, names, deltas = _ict()
    part_of_mat = np.full(len(mats), -1)
    for m in _SKIN:
        part_of_mat[mats.index(m)] = 0
    for p, side in ((1, "left"), (2, "right")):
        for m in _EYES[side]:
            part_of_mat[mats.index(m)] = p
    fpart = part_of_mat[fm]
    keep = fpart >= 0
    used, inv = np.unique(f[keep], return_inverse=True)
    sub_f = inv.reshape(-1, 3)
    vmat = np.zeros(len(used), np.int64)
    vmat[sub_f.ravel()] = np.repeat(fm[keep], 3)
    vpart = part_of_mat[vmat]
    sub_v = v[used]
    seeds, faces = subsample_surface(sub_v, sub_f, int(NUM_VERTICES * 0.97), groups=vmat)
    src = used[seeds]
    attrs = np.concatenate(
        [vpart[seeds, None].astype(np.float64), deltas[:, src].transpose(1, 0, 2).reshape(len(src), -1)], 1
    )
    verts, faces, attrs = split_to_count(v[src], faces, NUM_VERTICES, attrs)
    part = np.rint(attrs[:, 0]).astype(np.int64)
    return verts, faces, part, attrs[:, 1:].reshape(NUM_VERTICES, len(names), 3).transpose(1, 0, 2), names


def _joints(v, part, jaw_motion):
    """root at the neck base, neck above it, jaw hinge between the ears, eyeball centres."""
    skin = v[part == 0]
    bottom = skin[:, 1].min()
    low = skin[skin[:, 1] < bottom + 0.02]
    root = np.array([0.0, bottom + 0.01, low[:, 2].mean()])
    eyes = [v[part == p].mean(0) for p in (1, 2)]
    moving = v[jaw_motion > 0.5 * jaw_motion.max()]
    jaw = np.array([0.0, moving[:, 1].max() + 0.005, moving[:, 2].min() - 0.03])
    neck = np.array([0.0, root[1] + 0.45 * (jaw[1] - root[1]), root[2] - 0.01])
    return np.stack([root, neck, jaw, eyes[0], eyes[1]])


def _weights(v, part, J, jaw_motion):
    w = np.zeros((len(v), 5))
    skin = part == 0
    t = smoothstep((v[:, 1] - J[0, 1]) / (J[1, 1] - J[0, 1] + 0.03))
    jaw = smoothstep(1.3 * jaw_motion / jaw_motion.max()) * skin
    w[:, 0] = (1 - t) * skin
    w[:, 1] = t * skin * (1 - jaw)
    w[:, 2] = t * skin * jaw
    w[part == 1, 3] = 1
    w[part == 2, 4] = 1
    return w / w.sum(1, keepdims=True)


def _shape_fields(v, part, J, n=300) -> np.ndarray:
    """``[V,3,n]``: ten named smooth head deformations, then smooth random fields with decaying amplitude.
    Eyeballs only translate (the mean of the field over each eye)."""
    c = v[part == 0].mean(0)
    r = v - c

    def g(x: np.ndarray, s: float) -> np.ndarray:
        return np.exp(-0.5 * np.sum(x**2, -1) / s**2)

    nose = v[np.argmax(v[:, 2] * (part == 0))]
    chin_y = J[2, 1] - 0.06
    S = np.zeros((len(v), 3, n))
    S[:, 0, 0] = 0.08 * r[:, 0]  # width
    S[:, 1, 1] = 0.06 * r[:, 1]  # height
    S[:, 2, 2] = 0.06 * r[:, 2]  # depth
    S[:, :, 3] = 0.3 * (v - nose) * g(v - nose, 0.015)[:, None]  # nose size
    S[:, 0, 4] = 0.08 * r[:, 0] * smoothstep((J[2, 1] - v[:, 1]) / 0.04)  # jaw width
    S[:, 1, 5] = -0.008 * smoothstep((chin_y + 0.03 - v[:, 1]) / 0.04) * (v[:, 2] > J[2, 2])  # chin length
    S[:, 0, 6] = 0.004 * np.sign(r[:, 0]) * g(v - np.array([0, J[3, 1], J[3, 2]]), 0.03) / 1.0  # eye distance
    S[:, 2, 7] = 0.006 * g(v - np.array([0.045, J[2, 1] - 0.01, c[2] + 0.05]), 0.02) + 0.006 * g(
        v - np.array([-0.045, J[2, 1] - 0.01, c[2] + 0.05]), 0.02
    )  # cheeks
    S[:, 2, 8] = -0.006 * smoothstep((v[:, 1] - J[3, 1] - 0.03) / 0.04) * (r[:, 2] > 0)  # forehead slope
    S[:, 1, 9] = 0.005 * np.tanh(r[:, 0] / 0.05)  # asymmetry
    rng = np.random.default_rng(9)
    for k in range(10, n):
        freq = rng.normal(size=(3, 3)) * (6 + 14 * rng.random())
        phase = rng.random(3) * 2 * np.pi
        S[:, :, k] = 0.004 / (1 + k / 30) * np.sin(r @ freq + phase)
    for p in (1, 2):
        S[part == p] = S[part == p].mean(0)
    return S


def flame_model_dict() -> tuple[dict, dict, np.ndarray, np.ndarray]:
    """FLAME model dict (keys/dtypes/shapes smplx reads), its static landmark embedding, the part labels ``[V]``
    and the lip/brow mask ``[V]`` used for colouring."""
    v, f, part, deltas, names = _head_mesh()
    jaw_motion = np.linalg.norm(deltas[names.index("jawOpen")], axis=1)
    J = _joints(v, part, jaw_motion)
    w = _weights(v, part, J, jaw_motion)
    cands = [np.nonzero(part == 0)[0]] * 3 + [np.nonzero(part == 1)[0], np.nonzero(part == 2)[0]]
    jreg = joint_regressor(v, J[:3], cands[:3], k=32)
    jreg = np.concatenate([jreg[:3], np.stack([(part == p) / (part == p).sum() for p in (1, 2)])])
    order = [names.index(n) for n in _FIRST_EXPRESSIONS] + [
        i for i, n in enumerate(names) if n not in _FIRST_EXPRESSIONS
    ]
    expr = np.zeros((len(v), 3, 100))
    expr[:, :, : len(order)] = deltas[order].transpose(1, 2, 0)
    shapedirs = np.concatenate([_shape_fields(v, part, J), expr], 2)
    kintree = np.stack([np.array(FLAME_PARENTS, np.int64), np.arange(5)])
    kintree[0, 0] = 4294967295
    d = {
        "v_template": v,
        "f": f.astype(np.uint32),
        "shapedirs": shapedirs,
        "posedirs": np.zeros((len(v), 3, 36)),
        "J_regressor": jreg,
        "weights": w,
        "kintree_table": kintree,
    }
    c = v[f].mean(1)
    front = np.nonzero((part[f] == 0).all(1) & (c[:, 2] > J[3, 2] - 0.01) & (c[:, 1] < J[3, 1] + 0.04))[0]
    lmk = front[farthest_points(c[front], 51)]
    emb = {"lmk_face_idx": lmk.astype(np.int64), "lmk_b_coords": np.full((51, 3), 1 / 3)}
    lips = np.linalg.norm(deltas[names.index("mouthPucker")], axis=1)
    brows = np.linalg.norm(deltas[names.index("browInnerUp_L")] + deltas[names.index("browInnerUp_R")], axis=1)
    features = np.stack([lips / lips.max(), brows / brows.max()], 1)
    return d, emb, part, features
