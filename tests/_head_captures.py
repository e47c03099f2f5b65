"""Hand-made FLAME-layout model and small native FLAME datasets for the head-format tests.

The tiny FLAME (14 vertices) has its five joints as vertices 0-4 (one-hot J_regressor, each skinned to
its own joint), so joint positions are readable from the posed mesh. Surface vertices: 5 forehead,
6/7 cheeks, 10 back of the head (neck-skinned), 8 chin and 9 lower lip (jaw-skinned), 11 neck base
(root), 12/13 eyes. ``flame2023.pkl`` is the same model shifted by +1 cm in x, so using the wrong
FLAME version moves every vertex.
"""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import torch

from meshsplat.camera import intrinsics, look_at
from meshsplat.data.writer import DatasetWriter
from meshsplat.drivers.body_models import BodyModel, driver_record

JOINTS = np.array([[0, -0.08, -0.02], [0, -0.06, -0.02], [0, -0.02, 0.0], [0.03, 0.03, 0.04], [-0.03, 0.03, 0.04]])
SURFACE = np.array(
    [
        [0, 0.07, 0.06],
        [0.06, 0.0, 0.04],
        [-0.06, 0.0, 0.04],
        [0, -0.06, 0.07],
        [0, -0.035, 0.08],
        [0, 0.02, -0.08],
        [0, -0.1, -0.02],
        [0.03, 0.03, 0.06],
        [-0.03, 0.03, 0.06],
    ]
)
SKIN = [1, 1, 1, 2, 2, 1, 0, 3, 4]  # joint of each surface vertex 5..13
JAW_VERTS = {2, 8, 9}  # jaw joint vertex + chin + lower lip
FACES = np.array(
    [
        [5, 6, 7],
        [6, 8, 7],
        [8, 9, 6],
        [5, 10, 6],
        [5, 7, 10],
        [11, 6, 7],
        [12, 5, 6],
        [13, 7, 5],
        [0, 1, 11],
        [2, 8, 9],
        [3, 12, 5],
        [4, 13, 5],
    ],
    np.int64,
)
V = len(JOINTS) + len(SURFACE)
SHIFT_2023 = np.array([0.01, 0.0, 0.0])


def tiny_flame(shift=(0.0, 0.0, 0.0)) -> dict:
    v = np.concatenate([JOINTS, SURFACE]) + np.asarray(shift)
    w = np.zeros((V, 5))
    w[np.arange(5), np.arange(5)] = 1
    w[np.arange(5, V), SKIN] = 1
    jreg = np.zeros((5, V))
    jreg[np.arange(5), np.arange(5)] = 1
    sd = np.zeros((V, 3, 400))
    sd[5, 1, 0] = 0.01  # beta 0 lifts the forehead
    sd[6, 0, 299] = 0.01  # beta 299 widens the left cheek
    sd[8, 2, 300] = 0.01  # expression 0 pushes the chin forward
    sd[9, 1, 399] = -0.01  # expression 99 lowers the lip
    kt = np.stack([np.array([4294967295, 0, 1, 1, 1], np.int64), np.arange(5)])
    return {
        "v_template": v,
        "f": FACES,
        "shapedirs": sd,
        "posedirs": np.zeros((V, 3, 36)),
        "J_regressor": jreg,
        "weights": w,
        "kintree_table": kt,
    }


def write_tiny_flame(model_dir: Path) -> Path:
    d = Path(model_dir) / "flame"
    d.mkdir(parents=True, exist_ok=True)
    for name, shift in (("FLAME_NEUTRAL.pkl", (0, 0, 0)), ("flame2023.pkl", SHIFT_2023)):
        with open(d / name, "wb") as fh:
            pickle.dump(tiny_flame(shift), fh, protocol=2)
    return Path(model_dir)


def rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def project(K, viewmat, p) -> np.ndarray:
    """Pixel ``[2]`` of world point ``p`` with an OpenCV ``viewmat`` and ``K``."""
    K, vm = np.asarray(K, np.float64), np.asarray(viewmat, np.float64)
    c = vm[:3, :3] @ np.asarray(p, np.float64) + vm[:3, 3]
    assert c[2] > 0, f"point behind the camera (z={c[2]})"
    uv = K @ (c / c[2])
    return uv[:2]


def random_params(T: int, seed: int = 0, transl: bool = True, betas: int = 300, expr: int = 100) -> dict:
    g = np.random.default_rng(seed)
    p = {"betas": g.normal(0, 0.5, betas).astype(np.float32)}
    for k in ("global_orient", "neck_pose", "jaw_pose", "leye_pose", "reye_pose"):
        p[k] = g.normal(0, 0.15, (T, 3)).astype(np.float32)
    p["expression"] = g.normal(0, 0.5, (T, expr)).astype(np.float32)
    if transl:
        p["transl"] = g.normal(0, 0.05, (T, 3)).astype(np.float32)
    return p


def native_flame_dataset(
    out: Path,
    model_dir: Path,
    rows: int = 4,
    views: int = 2,
    scale: float = 1.0,
    flame_version: str = "2020",
    transl: bool = True,
    masks: bool = True,
    size=(12, 10),
    static_offset: bool = False,
    shared_K: bool = True,
    seed: int = 0,
    n_betas: int = 300,
    n_expr: int = 100,
) -> Path:
    """A native dataset: ``rows`` FLAME poses seen by ``views`` cameras on an arc in front of the face,
    tiny random images/masks, splits train (all but the last row), test_frames (last row, camera 0),
    test_views (the last camera on training rows, when views > 1)."""
    model = BodyModel("flame", model_dir, flame_version=flame_version, scale=scale)
    params = random_params(rows, seed, transl=transl, betas=n_betas, expr=n_expr)
    if static_offset:
        g = np.random.default_rng(seed + 1)
        params["static_offset"] = g.normal(0, 0.002, (model.num_vertices, 3)).astype(np.float32)
    with torch.no_grad():
        verts = model.forward(params).vertices.numpy()
    canonical = model.rest_vertices(params).numpy()
    W, H = size
    g = np.random.default_rng(seed + 2)
    centre = verts.reshape(-1, 3).mean(0)
    w = DatasetWriter(out, canonical, model.faces.numpy())
    for c in range(views):
        az = math.radians(-25 + 50 * c / max(views - 1, 1))
        eye = centre + 0.6 * scale * np.array([math.sin(az), 0.1, math.cos(az)])
        K = intrinsics(W, H, 20.0 if shared_K else 20.0 + 5 * c)
        w.add_camera(str(c), K, look_at(eye, centre), W, H)
    for r in range(rows):
        w.add_mesh(verts[r])
    train, test_frames, test_views = [], [], []
    for r in range(rows):
        for c in range(views):
            held_row, held_cam = r == rows - 1, views > 1 and c == views - 1
            if held_row and c != 0:
                continue
            img = g.integers(0, 256, (H, W, 3), dtype=np.uint8)
            mask = None
            if masks:
                mask = np.zeros((H, W), np.uint8)
                mask[2:-2, 3:-3] = 255
                mask[2, 3] = 128
            i = w.add_frame(img, str(c), mesh=r, mask=mask, name=f"r{r}_c{c}")
            (test_frames if held_row else test_views if held_cam else train).append(i)
    w.set_split("train", train)
    w.set_split("test_frames", test_frames)
    if test_views:
        w.set_split("test_views", test_views)
    w.set_driver(driver_record(model), params)
    return w.close()


def same_cameras(a, b, i: int, j: int | None = None, atol: float = 1e-6) -> None:
    """Frame ``i`` of dataset ``a`` and frame ``j`` of ``b`` have the same camera (float64 manifests)."""
    j = i if j is None else j
    ca = a.manifest["cameras"][str(a.frame_info(i)["camera"])]
    cb = b.manifest["cameras"][str(b.frame_info(j)["camera"])]
    np.testing.assert_allclose(np.asarray(cb["K"]), np.asarray(ca["K"]), atol=atol, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(cb["viewmat"]), np.asarray(ca["viewmat"]), atol=atol, rtol=0)
    assert (cb["width"], cb["height"]) == (ca["width"], ca["height"])


def assert_vertices_close(a, b, rtol: float = 1e-5) -> None:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = max(float(np.abs(a).max()), 1e-12)
    err = float(np.abs(a - b).max())
    assert err <= rtol * scale, f"vertices differ by {err:.3g} (scale {scale:.3g})"
