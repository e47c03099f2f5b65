"""Hand-made PeopleSnapshot folders for the format and import tests (written without meshsplat's writer)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

W, H = 64, 48
K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
EXTRINSIC = np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]])  # camera at (0, 0, -3)


def make_capture(
    root: Path,
    n: int = 8,
    masks: str = "png",
    config: dict | None = None,
    thetas=None,
    transl=None,
    betas=None,
    gender: str = "neutral",
) -> Path:
    """A PeopleSnapshot folder written by hand (no meshsplat writer)."""
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    for i in range(n):
        Image.fromarray(np.full((H, W, 3), 10 * i, np.uint8)).save(root / "images" / f"image_{i:04d}.png")
        m = np.ones((H, W), np.uint8)  # the stand-in body fills the frame (the camera check at the door)
        m[0, :] = 0  # a background row
        if masks == "png":
            Image.fromarray(m * 255).save(root / "masks" / f"mask_{i:04d}.png")
        else:
            np.save(root / "masks" / f"mask_{i:04d}.npy", m)
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=EXTRINSIC, height=np.array(H), width=np.array(W))
    np.savez(
        root / "poses.npz",
        betas=np.zeros((1, 10)) if betas is None else betas,
        thetas=np.zeros((n, 72)) if thetas is None else thetas,
        transl=np.zeros((n, 3)) if transl is None else transl,
    )
    cfg = {
        "gender": gender,
        "train": {"start": 0, "end": n - 3, "skip": 1},
        "test": {"start": n - 2, "end": n - 1, "skip": 1},
    }
    (root / "config.json").write_text(json.dumps(cfg if config is None else config))
    return root
