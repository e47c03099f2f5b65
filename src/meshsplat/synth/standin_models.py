"""Stand-in SMPL / SMPL-X / FLAME model files for tests and synthetic captures.

The real model files are licensed and never shipped, so tests and ``synth`` write look-alikes at run
time (into a temporary folder; nothing is cached in the repository). They have exactly the keys, shapes
and dtypes smplx 0.1.28 reads, under the names it expects, as plain-numpy pickles (no chumpy), and a
human-like geometry so that renders mean something:

* **Body (SMPL, SMPL-X)** -- the CesiumMan glTF rig (CC-BY 4.0, Cesium), read with ``GltfDriver``:
  its arms are raised from the rest A-pose to SMPL's T-pose with its own skinning, the mesh is welded
  at UV seams (a closed genus-0 surface), scaled to 1.70 m with the pelvis near SMPL's root, and
  refined by splitting the longest edge until exactly 6890 (SMPL: 13776 faces, as the real one) or
  10475 (SMPL-X) vertices, skin weights interpolated at each midpoint. CesiumMan's 19 joints map onto
  SMPL's 24 (kinematic tree of SMPL): spine2, the collars and the hands, which CesiumMan lacks, take a
  share of a neighbour's weight near their position. SMPL-X adds a jaw (a little weight on the lower
  face), two eyes (no weight) and 15 finger joints per hand (half of the hand weight, nearest finger
  joint). ``J_regressor`` rows are sparse convex weights of the ~24 vertices nearest each joint among
  those the joint or its parent skins, fitted by non-negative least squares to reproduce the joint.
  ``shapedirs``: 10 smooth deformations (size, girth about the bones, leg length, shoulder width,
  belly, head size, arm length, torso length, hips, chest depth); SMPL-X adds 10 face-local
  expression bumps (columns 10:20). ``posedirs`` are zero. MALE/FEMALE files are the neutral body
  moved along the shape directions (broader / narrower shoulders, hips).
* **Head (FLAME)** -- the ICT FaceKit head (MIT, USC ICT): its face, back of the head and eyeballs
  (sclera + iris) are subsampled to exactly 5023 vertices: seed vertices one per voxel, normal octant
  and material, geodesic regions grown from them on the mesh, a triangle for every original triangle
  whose corners fall in three regions (non-manifold leftovers dropped), then longest-edge splits up
  to the count. Joints: root at the neck base, neck, jaw hinge (behind the region jawOpen moves),
  eyeball centres; weights blend root/neck by height, move to the jaw where ICT's jawOpen moves the
  surface, and hold each eyeball rigidly on its eye joint. ``shapedirs`` has 400 columns: 300 shape
  (10 named smooth head deformations, then smooth random fields with decaying amplitude) and 100
  expression, whose first 57 are ICT's ARKit blend shapes (jawOpen, smiles, blinks, brows first).
  ``flame_static_embedding.pkl`` holds 51 face-front landmark triangles (farthest-point spread,
  centroid barycentrics; ``flame_dynamic_embedding.npy`` repeats 17 of them for smplx's
  ``use_face_contour``). The same model is written as ``FLAME_NEUTRAL.pkl`` and ``flame2023.pkl``.

Beside each model an ``appearance.npz`` holds ``vertex_colors [V,3]`` (float32, 0..1): skin, hair,
shirt with soft stripes, trousers and shoes for bodies (by dominant joint); skin, lips, brows, hair,
sclera, iris and pupil for the head.
"""

from __future__ import annotations

import os
import pickle
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from meshsplat.errors import MeshsplatError
from meshsplat.synth._standin_body import body_model_dict
from meshsplat.synth._standin_head import flame_model_dict

__all__ = ["write_standin_models", "STANDIN_FILES"]

STANDIN_FILES = {
    "smpl": ["smpl/SMPL_NEUTRAL.pkl", "smpl/SMPL_MALE.pkl", "smpl/SMPL_FEMALE.pkl"],
    "smplx": ["smplx/SMPLX_NEUTRAL.npz", "smplx/SMPLX_MALE.npz", "smplx/SMPLX_FEMALE.npz"],
    "flame": [
        "flame/FLAME_NEUTRAL.pkl",
        "flame/flame2023.pkl",
        "flame/flame_static_embedding.pkl",
        "flame/flame_dynamic_embedding.npy",
    ],
}
_GENDER_BETAS = {
    "MALE": [0.6, 0.4, 0.3, 1.0, 0.3, 0.2, 0.3, 0.3, -0.8, 0.5],
    "FEMALE": [-1.2, -0.4, 0.0, -1.0, -0.3, -0.2, -0.4, -0.2, 1.2, 0.4],
}


def _pickle(path: Path, data: dict) -> None:
    with open(path, "wb") as fh:
        pickle.dump(data, fh, protocol=2)


def _link_or_copy(src: Path, dst: Path) -> None:
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _body_colors(v: np.ndarray, dom: np.ndarray) -> np.ndarray:
    skin, shirt = np.array([0.87, 0.68, 0.55]), np.array([0.2, 0.36, 0.66])
    trousers, shoes, hair = np.array([0.3, 0.26, 0.22]), np.array([0.1, 0.1, 0.12]), np.array([0.24, 0.15, 0.08])
    c = np.tile(skin, (len(v), 1))
    stripes = 0.5 + 0.5 * np.sin(v[:, 1] * 70.0)
    top = np.isin(dom, [3, 6, 9, 13, 14, 16, 17])
    c[top] = shirt * (0.75 + 0.35 * stripes[top, None])
    legs = np.isin(dom, [0, 1, 2, 4, 5])
    c[legs] = trousers * (0.9 + 0.1 * np.sin(v[legs, 0:1] * 120.0))
    c[np.isin(dom, [7, 8, 10, 11])] = shoes
    on_head = dom == 15
    hv = v[on_head]
    centre, half = (hv.max(0) + hv.min(0)) / 2, (hv.max(0) - hv.min(0)) / 2
    r = (v - centre) / half
    hairy = on_head & ((r[:, 1] > 0.35) | ((r[:, 2] < -0.1) & (r[:, 1] > -0.3)))
    c[hairy] = hair
    for side in (1.0, -1.0):  # eyes
        near = on_head & (np.hypot(r[:, 0] - 0.3 * side, r[:, 1] - 0.12) < 0.09) & (r[:, 2] > 0.5)
        c[near] = [0.15, 0.1, 0.08]
    mouth = on_head & (np.hypot(r[:, 0] / 2, r[:, 1] + 0.3) < 0.08) & (r[:, 2] > 0.5)
    c[mouth] = [0.7, 0.38, 0.38]
    return np.clip(c, 0, 1).astype(np.float32)


def _head_colors(v, part, features, joints) -> np.ndarray:
    skin, hair = np.array([0.88, 0.7, 0.58]), np.array([0.22, 0.13, 0.07])
    c = np.tile(skin, (len(v), 1)) * (0.96 + 0.04 * np.sin(v[:, :1] * 300) * np.sin(v[:, 1:2] * 260))
    s = part == 0
    lips, brows = features[:, 0], features[:, 1]
    c[s & (lips > 0.6) & (v[:, 1] < joints[3, 1] - 0.03)] = [0.72, 0.38, 0.38]
    c[s & (brows > 0.5)] = [0.3, 0.2, 0.12]
    top = s & ((v[:, 1] > joints[3, 1] + 0.06) | ((v[:, 2] < joints[2, 2] - 0.02) & (v[:, 1] > joints[0, 1] + 0.1)))
    c[top] = hair
    for p, _j in ((1, 3), (2, 4)):
        eye = part == p
        tip = v[eye][np.argmax(v[eye, 2])]
        d = np.linalg.norm(v - tip, axis=1)
        c[eye] = [0.95, 0.94, 0.92]
        c[eye & (d < 0.0065)] = [0.25, 0.42, 0.6]
        c[eye & (d < 0.0035)] = [0.03, 0.03, 0.03]
    return np.clip(c, 0, 1).astype(np.float32)


def _write_body(out: Path, kind: str) -> None:
    d, dom = body_model_dict(kind)
    folder = out / kind
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "appearance.npz", vertex_colors=_body_colors(d["v_template"], dom))
    for gender in ("NEUTRAL", "MALE", "FEMALE"):
        g = dict(d)
        if gender != "NEUTRAL":
            g["v_template"] = d["v_template"] + d["shapedirs"][:, :, :10] @ np.array(_GENDER_BETAS[gender])
        if kind == "smpl":
            _pickle(folder / f"SMPL_{gender}.pkl", g)
        else:
            np.savez_compressed(folder / f"SMPLX_{gender}.npz", **g)


def _write_head(out: Path) -> None:
    d, emb, part, features = flame_model_dict()
    folder = out / "flame"
    folder.mkdir(parents=True, exist_ok=True)
    d = {**d, "shapedirs": d["shapedirs"].astype(np.float32), "posedirs": d["posedirs"].astype(np.float32)}
    _pickle(folder / "FLAME_NEUTRAL.pkl", d)
    _link_or_copy(folder / "FLAME_NEUTRAL.pkl", folder / "flame2023.pkl")
    _pickle(folder / "flame_static_embedding.pkl", emb)
    contour = {
        "lmk_face_idx": np.tile(emb["lmk_face_idx"][:17], (79, 1)),  # smplx use_face_contour=True
        "lmk_b_coords": np.full((79, 17, 3), 1 / 3),
    }
    np.save(folder / "flame_dynamic_embedding.npy", np.array(contour, dtype=object), allow_pickle=True)
    joints = d["J_regressor"] @ d["v_template"]
    np.savez(folder / "appearance.npz", vertex_colors=_head_colors(d["v_template"], part, features, joints))


def write_standin_models(out_dir: Path | str, kinds: Sequence[str] = ("smpl", "smplx", "flame")) -> Path:
    """Write stand-in model files for ``kinds`` under ``out_dir`` (``smpl/``, ``smplx/``, ``flame/``, each with
    an ``appearance.npz``); returns ``out_dir``, usable as ``--model-dir``."""
    out = Path(out_dir)
    bad = [k for k in kinds if k not in STANDIN_FILES]
    if bad:
        raise MeshsplatError(f"stand-in models: unknown kinds {bad}; expected some of {list(STANDIN_FILES)}")
    out.mkdir(parents=True, exist_ok=True)
    for kind in kinds:
        if kind == "flame":
            _write_head(out)
        else:
            _write_body(out, kind)
    return out
