"""Derive the MediaPipe face-mesh landmark -> ICT head surface correspondence that the tracker ships.

Writes ``src/meshsplat/assets/ict_facekit/ict_mediapipe_landmarks.npz``: ``face [478] int32`` (triangle
of the ICT head), ``bary [478,3] float32`` (weights of its corners a, b, c), ``spread [478] float32``
(cm: median distance of the per-render points to their median, how much the renders disagreed),
``views [478] int32`` (renders that located it), ``mediapipe`` (the version used).

How: the ICT head is rendered (``meshsplat.track.head_render``: procedural skin, red lips, dark brows,
iris and pupil painted on the eyeball) in 7 expressions (neutral, jaw open twice, smile, pucker, brows
up, a half blink) at 5 yaws (-30..30 degrees) and 3 pitches, plus gaze turns for the iris, at 512 x 512
with a known pinhole camera. MediaPipe's face mesh (``static_image_mode``, ``refine_landmarks``: 468
points and 10 iris points) runs on each render; each landmark pixel is looked up in the rasterizer's
triangle buffer (triangle + perspective-correct barycentrics). Landmarks 0-467 must land on the skin
(``M_Face``/``M_BackHead``), 468-477 on an eyeball (iris or sclera); a pixel on anything else (the
lashes, teeth) takes the nearest visible vertex of the allowed materials within 6 px. The triangle and
barycentrics carry the point back to the neutral head, where expressions and gaze no longer move it;
across renders the medoid (the render's point nearest to the coordinate-wise median) is kept, so a
few bad detections (silhouette points at large yaws) do not move it.

Run: ``.venv/bin/python bench/derive_ict_landmarks.py`` (needs ``meshsplat[track]``; about two minutes
on 2 cores). ``--check`` derives into a temporary file and reports the distance to the shipped one.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from meshsplat.paths import assets_dir
from meshsplat.track.head_render import render_head
from meshsplat.track.ict_head import LANDMARKS_ASSET, NUM_LANDMARKS, IctHead, load_ict_head

SIZE = 512
FOCAL = 900.0
DISTANCE = 60.0  # cm from the camera
EXPRESSIONS: list[dict[str, float]] = [
    {},
    {"jawOpen": 0.35},
    {"jawOpen": 0.7},
    {"mouthSmile_L": 0.7, "mouthSmile_R": 0.7},
    {"mouthPucker": 0.6},
    {"browInnerUp_L": 0.6, "browInnerUp_R": 0.6, "browOuterUp_L": 0.5, "browOuterUp_R": 0.5},
    {"eyeBlink_L": 0.4, "eyeBlink_R": 0.4},
]
YAWS_DEG = (-30.0, -15.0, 0.0, 15.0, 30.0)
PITCHES_DEG = (-10.0, 0.0, 10.0)
GAZES_DEG = ((15.0, 0.0), (-15.0, 0.0), (0.0, 12.0), (0.0, -12.0))
SKIN = ("M_Face", "M_BackHead")
EYES = ("M_IrisLeft", "M_IrisRight", "M_ScleraLeft", "M_ScleraRight")
SNAP_PX = 6.0


def _views() -> list[tuple[dict[str, float], float, float, tuple[float, float]]]:
    out = []
    for expr in EXPRESSIONS:
        for yaw in YAWS_DEG:
            out.append((expr, yaw, 0.0, (0.0, 0.0)))
        for pitch in PITCHES_DEG:
            if pitch:
                out.append((expr, 0.0, pitch, (0.0, 0.0)))
    for gaze in GAZES_DEG:
        for yaw in (-15.0, 0.0, 15.0):
            out.append(({}, yaw, 0.0, gaze))
    return out


def _pose(head: IctHead, expr: dict[str, float], yaw: float, pitch: float, gaze: tuple[float, float]) -> torch.Tensor:
    w = torch.zeros(1, len(head.names))
    for name, value in expr.items():
        w[0, head.names.index(name)] = value
    g = torch.tensor([[gaze, gaze]]).mul(math.pi / 180)
    rot = torch.tensor([[-math.radians(pitch), math.radians(yaw), 0.0]])
    t = torch.tensor([[0.0, 1.5, -DISTANCE]])
    return head.pose(torch.zeros_like(head.neutral), w, g, rot, t)[0]


def _material_mask(head: IctHead, names: tuple[str, ...]) -> torch.Tensor:
    ids = torch.tensor([head.material_names.index(n) for n in names])
    return torch.isin(head.face_material, ids)


def derive(out: Path) -> None:
    import mediapipe as mp  # optional dependency: meshsplat[track]

    head = load_ict_head(with_landmarks=False)
    K = torch.tensor([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1.0]])
    allowed = {"skin": _material_mask(head, SKIN), "eye": _material_mask(head, EYES)}
    allowed_vertex = {k: torch.zeros(len(head.neutral), dtype=torch.bool) for k in allowed}
    vertex_face = {}
    for group, m in allowed.items():
        allowed_vertex[group][head.faces[m].reshape(-1)] = True
        fid = torch.nonzero(m).reshape(-1)
        vf = torch.full((len(head.neutral),), -1, dtype=torch.long)
        vf[head.faces[fid].reshape(-1)] = fid.repeat_interleave(3)
        vertex_face[group] = vf
    points: list[list[tuple[int, np.ndarray, np.ndarray]]] = [[] for _ in range(NUM_LANDMARKS)]
    mesh = mp.solutions.face_mesh.FaceMesh(static_image_mode=True, refine_landmarks=True, max_num_faces=1)
    views = _views()
    t0 = time.time()
    missed = 0
    for i, (expr, yaw, pitch, gaze) in enumerate(views):
        verts = _pose(head, expr, yaw, pitch, gaze)
        img, frags, keep = render_head(head, verts, K, SIZE, SIZE)
        res = mesh.process((img.numpy() * 255).round().astype(np.uint8))
        if not res.multi_face_landmarks:
            missed += 1
            continue
        lm = np.array([(p.x * SIZE, p.y * SIZE) for p in res.multi_face_landmarks[0].landmark])
        cam = verts * torch.tensor([1.0, -1.0, -1.0])
        pix = cam @ K.T
        pix = pix[:, :2] / pix[:, 2:]
        ij = pix.floor().long().clamp(0, SIZE - 1)
        vis = (cam[:, 2] - frags.depth[ij[:, 1], ij[:, 0]]).abs() < 0.15
        for j in range(NUM_LANDMARKS):
            kind = "skin" if j < 468 else "eye"
            x, y = int(lm[j, 0]), int(lm[j, 1])
            if not (0 <= x < SIZE and 0 <= y < SIZE):
                continue
            f = int(frags.face[y, x])
            face = int(keep[f]) if f >= 0 else -1
            if face >= 0 and bool(allowed[kind][face]):
                bary = frags.bary[y, x].numpy().astype(np.float64)
            else:  # the nearest visible vertex of an allowed material
                cand = torch.nonzero(vis & allowed_vertex[kind]).reshape(-1)
                if len(cand) == 0:
                    continue
                d = (pix[cand] - torch.tensor(lm[j], dtype=torch.float32)).norm(dim=1)
                near = int(d.argmin())
                if float(d[near]) > SNAP_PX:
                    continue
                v = int(cand[near])
                face = int(vertex_face[kind][v])
                bary = (head.faces[face] == v).double().numpy()
            p = (torch.from_numpy(bary).float()[:, None] * head.neutral[head.faces[face]]).sum(0).numpy()
            points[j].append((face, bary, p))
        print(f"\r{i + 1}/{len(views)} renders, {time.time() - t0:.0f} s", end="", file=sys.stderr)
    print(file=sys.stderr)
    face_out = np.zeros(NUM_LANDMARKS, np.int32)
    bary_out = np.zeros((NUM_LANDMARKS, 3), np.float32)
    spread = np.zeros(NUM_LANDMARKS, np.float32)
    count = np.zeros(NUM_LANDMARKS, np.int32)
    for j, hits in enumerate(points):
        if not hits:
            raise SystemExit(f"landmark {j} was never located on the head; add views")
        ps = np.stack([h[2] for h in hits])
        med = np.median(ps, 0)
        best = int(np.linalg.norm(ps - med, axis=1).argmin())
        face_out[j], bary_out[j] = hits[best][0], hits[best][1]
        spread[j] = np.median(np.linalg.norm(ps - med, axis=1))
        count[j] = len(hits)
    np.savez_compressed(
        out, face=face_out, bary=bary_out, spread=spread, views=count, mediapipe=np.array(mp.__version__)
    )
    print(
        f"{len(views)} renders ({missed} without a face) in {time.time() - t0:.0f} s; spread median "
        f"{np.median(spread):.3f} cm, max {spread.max():.3f} cm (landmark {int(spread.argmax())}); "
        f"fewest views {count.min()}; wrote {out}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="derive into a temporary file and compare")
    args = ap.parse_args()
    torch.set_num_threads(2)
    shipped = assets_dir() / LANDMARKS_ASSET
    if not args.check:
        derive(shipped)
        return
    with tempfile.TemporaryDirectory() as tmp:
        fresh = Path(tmp) / "landmarks.npz"
        derive(fresh)
        head = load_ict_head()
        a = head.landmarks(head.neutral)
        b = np.load(fresh)
        pts = torch.from_numpy(b["bary"])[:, :, None] * head.neutral[head.faces[torch.from_numpy(b["face"]).long()]]
        d = (pts.sum(1) - a).norm(dim=1)
        print(f"distance to the shipped correspondence: median {float(d.median()):.4f} cm, max {float(d.max()):.4f} cm")


if __name__ == "__main__":
    main()
