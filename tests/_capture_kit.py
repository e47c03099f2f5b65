"""A small capture whose every frame is known, for the downscale and reader tests."""

from __future__ import annotations

import numpy as np

from meshsplat.data import DatasetWriter

S = 64
K64 = np.array([[80.0, 0.0, 31.3], [0.0, 75.0, 33.1], [0.0, 0.0, 1.0]])  # off-centre principal point
VIEWMAT = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 4], [0, 0, 0, 1]])  # at z=4 looking at 0


def _capture(root, size=(S, S), n=6):
    """A native capture: an icosphere, random images, masks with edges off the 2x2 grid (the last frame
    has none)."""
    import trimesh

    w_, h_ = size
    m = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(0)
    w = DatasetWriter(root, m.vertices, m.faces)
    w.add_camera("0", K64, VIEWMAT, w_, h_)
    for i in range(n):
        mask = None
        if i < n - 1:
            mask = np.zeros((h_, w_), np.uint8)
            mask[11 + i : 45 + i, 9:51] = 255
        w.add_frame(rng.integers(0, 256, (h_, w_, 3), dtype=np.uint8), "0", vertices=m.vertices, mask=mask)
    w.set_split("train", list(range(n - 2)))
    w.set_split("test_frames", [n - 2, n - 1])
    return w.close()
