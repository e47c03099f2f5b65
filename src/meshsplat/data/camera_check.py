"""Cameras checked at the door: is each frame's mesh in front of its camera, in its image, on its mask?

Every reader ends in ``build_dataset``, which calls :func:`check_cameras`. The rule (docs/real-captures.md):

- every frame: at least half of the mesh's vertices (a subsample of at most ``MAX_VERTICES``) in front of
  the camera and at least ``MIN_VISIBLE`` of them projecting inside the image (geometry only, no decoding);
- every frame with a mask, against it: at least
  ``MIN_ON_MASK`` of the visible vertices (when ``MIN_MASK_POINTS`` or more are visible) on the frame's
  mask (pooled to a grid of about 64 cells a side, dilated one cell), and no
  other camera convention fitting clearly better (rolled by 180 degrees: the overlap with the projection
  turned about the principal point exceeds the overlap as is by ``CLEARLY_BETTER``). A badly tracked frame
  anywhere in the capture is found (a sample of 32 frames missed them); the cost is a mask decode and a
  pooling per frame (``bench/badinput.py``).
- a camera failing on at least ``BROKEN_SHARE`` of its checked frames is a wrong camera: the capture is
  refused, naming the convention mix-up that makes it fit (y and z flipped, rolled by 180 degrees,
  camera-to-world given for world-to-camera, an OpenGL camera-to-world); fewer failing frames are bad
  frames, listed (the caller refuses them unless asked to drop them).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from meshsplat.plausible import group_ids

__all__ = [
    "CameraCheck",
    "check_cameras",
    "group_ids",
    "MAX_VERTICES",
    "MIN_VISIBLE",
    "MIN_ON_MASK",
    "MIN_MASK_POINTS",
    "BROKEN_SHARE",
    "CLEARLY_BETTER",
]

MAX_VERTICES = 512  # vertices projected per frame (an even subsample of larger meshes)
MIN_IN_FRONT = 0.5  # share of the vertices in front of the camera
MIN_VISIBLE = 0.1  # share of the vertices in front and inside the image
MIN_ON_MASK = 0.5  # share of the visible vertices on the (dilated) mask
MIN_MASK_POINTS = 16  # fewer visible vertices than this say nothing about the overlap: geometry only
BROKEN_SHARE = 0.8  # a camera failing on this share of its checked frames is wrong, not its frames
CLEARLY_BETTER = 0.25  # another convention beating "as is" on the mask by this much means "as is" is wrong
PROBE_FRAMES = 8  # frames of a wrong camera on which the convention fixes are tried
_GRID = 64  # masks are pooled to about this many cells along their longer side, then dilated one cell

_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])
_ROLL = np.diag([-1.0, -1.0, 1.0, 1.0])
# the conventions tried on a wrong camera: (what the fix means, viewmat -> corrected viewmat)
_FIXES: tuple[tuple[str, Callable[[np.ndarray], np.ndarray]], ...] = (
    ("its y and z axes are flipped (OpenGL/Blender camera axes read as OpenCV's)", lambda vm: _FLIP_YZ @ vm),
    ("it is rolled by 180 degrees about its optical axis (the projection is upside down)", lambda vm: _ROLL @ vm),
    ("the extrinsic is camera-to-world, given where world-to-camera is expected (its inverse fits)", np.linalg.inv),
    (
        "the extrinsic is an OpenGL camera-to-world (NeRF/Blender transform_matrix); invert it and flip y and z",
        lambda vm: _FLIP_YZ @ np.linalg.inv(vm),
    ),
)


@dataclass
class _Score:
    in_front: float  # share of vertices with z > 0
    visible: float  # share in front and inside the image
    on_mask: float | None  # share of the visible ones on the mask (None: no mask read, or nothing visible)

    @property
    def ok(self) -> bool:
        return (
            self.in_front >= MIN_IN_FRONT
            and self.visible >= MIN_VISIBLE
            and (self.on_mask is None or self.on_mask >= MIN_ON_MASK)
        )

    def why(self) -> str:
        if self.in_front < MIN_IN_FRONT:
            return "the mesh is behind the camera"
        if self.visible < MIN_VISIBLE:
            return "the mesh projects outside the image"
        return "the mesh projects off the mask"


@dataclass
class CameraCheck:
    """What :func:`check_cameras` found: ``wrong`` cameras (one sentence each) and ``bad_frames``
    (frame index -> reason) of the other cameras; ``checked`` frames and ``masks_read``."""

    wrong: dict[str, str] = field(default_factory=dict)
    bad_frames: dict[int, str] = field(default_factory=dict)
    checked: int = 0
    masks_read: int = 0

    @property
    def ok(self) -> bool:
        return not self.wrong and not self.bad_frames


def _mask_grid(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """Mask ``[H,W]`` or ``[H,W,1]`` -> (pooled and dilated boolean grid, cell size in pixels)."""
    m = torch.from_numpy(np.ascontiguousarray(np.asarray(mask, np.float32).reshape(mask.shape[0], mask.shape[1])))
    cell = max(1, math.ceil(max(m.shape) / _GRID))
    g = F.max_pool2d((m > 0.5).float()[None, None], cell, cell, ceil_mode=True)
    g = F.max_pool2d(g, 3, 1, padding=1)
    return g[0, 0].numpy() > 0, cell


def _score(vm: np.ndarray, K: np.ndarray, w: int, h: int, verts: np.ndarray, grid) -> _Score:
    p = verts @ vm[:3, :3].T + vm[:3, 3]
    z = p[:, 2]
    front = z > 1e-9
    zs = np.where(front, z, 1.0)
    u = K[0, 0] * p[:, 0] / zs + K[0, 1] * p[:, 1] / zs + K[0, 2]
    v = K[1, 1] * p[:, 1] / zs + K[1, 2]
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    n = max(len(verts), 1)
    on_mask = None
    if grid is not None and int(inside.sum()) >= MIN_MASK_POINTS:
        g, cell = grid
        cu = np.clip((u[inside] // cell).astype(np.int64), 0, g.shape[1] - 1)
        cv = np.clip((v[inside] // cell).astype(np.int64), 0, g.shape[0] - 1)
        on_mask = float(g[cv, cu].mean())
    return _Score(float(front.sum()) / n, float(inside.sum()) / n, on_mask)


INVERTED = "the mask looks inverted (the subject black on white)"


def _inverted(vm: np.ndarray, K, w, h, verts, grid) -> bool:
    """Whether the mask covers most of the image while the mesh lands mostly off it: a mask with subject
    and background swapped (the camera may be right)."""
    g, cell = grid
    if g.mean() <= 0.5:
        return False
    flipped = F.max_pool2d(torch.from_numpy(~g).float()[None, None], 3, 1, padding=1)[0, 0].numpy() > 0
    s = _score(vm, K, w, h, verts, (flipped, cell))
    return s.on_mask is not None and s.on_mask >= MIN_ON_MASK


def _fails(vm: np.ndarray, K, w, h, verts, grid) -> str | None:
    """Why the frame fails as is (None when it passes): its own score, or the roll fitting clearly better."""
    s = _score(vm, K, w, h, verts, grid)
    if not s.ok:
        if s.on_mask is not None and s.on_mask < MIN_ON_MASK and _inverted(vm, K, w, h, verts, grid):
            return INVERTED
        return s.why()
    if s.on_mask is not None:
        r = _score(_ROLL @ vm, K, w, h, verts, grid)
        if r.ok and r.on_mask is not None and r.on_mask >= s.on_mask + CLEARLY_BETTER:
            return "the mesh fits the mask much better turned by 180 degrees (camera rolled?)"
    return None


def _spread(items: list[int], k: int) -> list[int]:
    if len(items) <= k:
        return list(items)
    return [items[j] for j in sorted({round(x) for x in np.linspace(0, len(items) - 1, k)})]


def check_cameras(
    cameras: dict[str, tuple[np.ndarray, np.ndarray, int, int]],
    frames: Sequence[tuple[str, int]],
    vertices: np.ndarray,
    load_mask: Callable[[int], np.ndarray | None],
) -> CameraCheck:
    """Check every frame's camera against its mesh and its mask; see the module's rule.

    ``cameras``: id -> ``(K [3,3], viewmat [4,4], width, height)``; ``frames``: ``(camera id, mesh row)``
    per frame; ``vertices [T,V,3]`` (a memory map is fine: a subsample of columns is read);
    ``load_mask(i)``: frame ``i``'s mask ``[H,W(,1)]`` in [0, 1], or None.
    """
    report = CameraCheck()
    n_v = int(vertices.shape[1])
    cols = np.unique(np.linspace(0, n_v - 1, min(n_v, MAX_VERTICES)).round().astype(np.int64))
    rows = sorted({m for _, m in frames})
    sub = {m: np.asarray(vertices[m], np.float64)[cols] for m in rows}
    by_cam: dict[str, list[int]] = {}
    for i, (cid, _) in enumerate(frames):
        by_cam.setdefault(cid, []).append(i)
    grids: dict[int, tuple[np.ndarray, int] | None] = {}  # kept for the frames a diagnosis probes only

    def grid(i: int):
        if i in grids:
            return grids[i]
        mask = load_mask(i)
        g = None if mask is None else _mask_grid(mask)
        report.masks_read += mask is not None
        if i in probe:
            grids[i] = g
        return g

    for cid, ids in by_cam.items():
        K, vm, w, h = cameras[cid]
        probe = _spread(ids, PROBE_FRAMES)
        fails: dict[int, str] = {}
        for i in ids:  # geometry, then the mask, of every frame
            s = _score(vm, K, w, h, sub[frames[i][1]], None)
            if not s.ok:
                fails[i] = s.why()
            else:
                _mask_fail(i, vm, K, w, h, sub[frames[i][1]], grid(i), fails)
        report.checked += len(ids)
        if len(fails) >= max(1, BROKEN_SHARE * len(ids)):
            report.wrong[cid] = _diagnose(cid, fails, len(ids), vm, K, w, h, probe, frames, sub, grid)
        else:
            report.bad_frames.update(fails)
    return report


def _mask_fail(i, vm, K, w, h, verts, g, fails: dict[int, str]) -> bool:
    why = _fails(vm, K, w, h, verts, g)
    if why is not None:
        fails[i] = why
    return why is not None


def _diagnose(cid, fails, n_checked, vm, K, w, h, probe, frames, sub, grid) -> str:
    reasons: dict[str, int] = {}
    for why in fails.values():
        reasons[why] = reasons.get(why, 0) + 1
    main = max(reasons, key=lambda r: reasons[r])
    if main == INVERTED:  # the masks are wrong, not the camera
        return (
            f"the masks of camera {cid!r} look inverted on {reasons[main]} of {n_checked} frames (the subject black "
            "on white, the mesh landing on the black): invert them, white = subject"
        )
    what = f"camera {cid!r} does not see the subject on {len(fails)} of {n_checked} frames ({main})"
    for meaning, fix in _FIXES:
        try:
            vm2 = fix(vm)
        except np.linalg.LinAlgError:
            continue
        good = sum(_fails(vm2, K, w, h, sub[frames[i][1]], grid(i)) is None for i in probe)
        if good >= max(1, BROKEN_SHARE * len(probe)):
            return f"{what}: likely {meaning}, which fits {good} of {len(probe)} checked frames"
    return f"{what}: no common convention mix-up (y/z flip, 180-degree roll, inverse) fixes it"
