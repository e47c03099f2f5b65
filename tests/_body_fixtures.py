"""Tiny hand-made SMPL / SMPL-X / FLAME model dicts in smplx's key layout (golden tests)."""

from __future__ import annotations

import pickle

import numpy as np

SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
L_SHOULDER, L_ELBOW = 16, 18


def _kintree(parents):
    p = np.array(parents, np.int64)
    p[0] = 4294967295  # as in the official files
    return np.stack([p, np.arange(len(parents))])


def tiny_smpl() -> dict:
    """24 joints, one vertex per joint (one-hot J_regressor) + vertex 24 at (0.8,0,0) skinned to the
    left elbow and vertex 25 at (0.8,0,0) skinned to the left shoulder."""
    J = 24
    joints = np.zeros((J, 3))
    joints[L_SHOULDER] = (0.2, 0, 0)
    joints[L_ELBOW] = (0.5, 0, 0)
    v = np.concatenate([joints, [[0.8, 0, 0], [0.8, 0, 0]]])
    V = len(v)
    w = np.zeros((V, J))
    w[np.arange(J), np.arange(J)] = 1
    w[24, L_ELBOW] = 1
    w[25, L_SHOULDER] = 1
    jreg = np.zeros((J, V))
    jreg[np.arange(J), np.arange(J)] = 1
    shapedirs = np.zeros((V, 3, 10))
    shapedirs[L_ELBOW, 0, 0] = 0.5  # beta0 moves the elbow (vertex and regressed joint) along +x
    return {
        "v_template": v,
        "f": np.array([[0, 16, 18], [16, 18, 24]], np.uint32),
        "shapedirs": shapedirs,
        "posedirs": np.zeros((V, 3, 207)),
        "J_regressor": jreg,
        "weights": w,
        "kintree_table": _kintree(SMPL_PARENTS),
    }


def tiny_flame() -> dict:
    """FLAME layout: joints root(0,0,0), neck(0,0.1,0), jaw(0,0.15,0.05), eyes (+-0.03,0.2,0.05);
    vertex 5 at (0,0.1,0.15) on the jaw, vertex 6 at (0.03,0.2,0.1) on the left eye; 400 shape columns."""
    joints = np.array([[0, 0, 0], [0, 0.1, 0], [0, 0.15, 0.05], [0.03, 0.2, 0.05], [-0.03, 0.2, 0.05]])
    v = np.concatenate([joints, [[0, 0.1, 0.15], [0.03, 0.2, 0.1]]])
    V, J = len(v), 5
    w = np.zeros((V, J))
    w[np.arange(J), np.arange(J)] = 1
    w[5, 2] = 1
    w[6, 3] = 1
    jreg = np.zeros((J, V))
    jreg[np.arange(J), np.arange(J)] = 1
    sd = np.zeros((V, 3, 400))
    sd[5, 2, 300] = 0.01  # expression 0 pushes the chin vertex forward by 1 cm
    sd[5, 1, 0] = 0.02  # beta 0 lifts it by 2 cm
    return {
        "v_template": v,
        "f": np.array([[0, 1, 5], [1, 5, 6]], np.int64),
        "shapedirs": sd,
        "posedirs": np.zeros((V, 3, 36)),
        "J_regressor": jreg,
        "weights": w,
        "kintree_table": _kintree([-1, 0, 1, 1, 1]),
    }


def write_pickle(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        pickle.dump(data, fh, protocol=2)
    return path


def tiny_smplx() -> dict:
    """55 joints (SMPL-X tree), one vertex per joint at x = joint index / 100, 10 shape + 10 expression."""
    parents = (
        SMPL_PARENTS[:22]
        + [15, 15, 15]
        + [20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38]
        + [21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53]
    )
    J = 55
    v = np.stack([np.arange(J) / 100, np.zeros(J), np.zeros(J)], 1)
    eye = np.eye(J)
    return {
        "v_template": v,
        "f": np.array([[0, 1, 2]], np.int64),
        "shapedirs": np.zeros((J, 3, 20)),
        "posedirs": np.zeros((J, 3, 486)),
        "J_regressor": eye,
        "weights": eye,
        "kintree_table": _kintree(parents),
        "hands_componentsl": np.eye(45),
        "hands_componentsr": np.eye(45),
        "hands_meanl": np.zeros(45),
        "hands_meanr": np.zeros(45),
        "lmk_faces_idx": np.zeros(51, np.int64),
        "lmk_bary_coords": np.ones((51, 3)) / 3,
    }


def write_tiny_models(root):
    """``root/{smpl,smplx,flame}/`` with the tiny models under smplx's names; returns root."""
    write_pickle(root / "smpl" / "SMPL_NEUTRAL.pkl", tiny_smpl())
    write_pickle(root / "flame" / "FLAME_NEUTRAL.pkl", tiny_flame())
    (root / "smplx").mkdir(parents=True, exist_ok=True)
    np.savez(root / "smplx" / "SMPLX_NEUTRAL.npz", **tiny_smplx())
    return root
