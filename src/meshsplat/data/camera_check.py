"""Cameras checked at the door: is each frame's mesh in front of its camera, in its image, on its mask?

Every reader ends in ``build_dataset``, which calls :func:`check_cameras`. The rule (docs/real-captures.md):

- every frame: at least half of the mesh's vertices (a subsample of at most ``MAX_VERTICES``) in front of
  the camera and at least ``MIN_VISIBLE`` of them projecting inside the image (geometry only, no decoding);
  a frame with fewer in the image and no mask (none given, or ``check_masks=False``: ``render``, ``view``)
  passes as a close-up when, with the faces, the projected mesh covers ``MIN_COVER`` of the image and the
  camera is not inside the mesh (its winding number);
- every frame with a mask, against it: at least
  ``MIN_ON_MASK`` of the visible vertices (when ``MIN_MASK_POINTS`` or more are visible) on the frame's
  mask (pooled to a grid of about 64 cells a side, dilated one cell), and no
  other camera convention fitting clearly better (rolled by 180 degrees: the overlap with the projection
  turned about the principal point exceeds the overlap as is by ``CLEARLY_BETTER``). With the faces, the
  mask is also compared the other way (:func:`_within`): a frame whose vertices miss the mask (occlusion)
  or lie mostly outside the image (a close-up) passes when the mask lies within the projected silhouette
  (``MIN_WITHIN``), its outline on the silhouette's (``MIN_OUTLINE``) and no shrunk projection
  (``SMALLER``, about the principal point or the world origin's image) fits clearly better
  (``SMALLER_BETTER`` more of the outline on it); a mask may be loose or off by ``SLACK`` of the subject's
  projected width (the best such fit counts). A frame passing on its vertices with under ``SIZE_CHECKED`` of
  them on the mask is compared with the shrunk projections too (a camera too close) when its mask spans
  ``SIZE_CELLS`` cells, the mask then allowed ``TIGHT`` cells inside the silhouette. The roll then wins when
  it fits clearly better (vertices on the mask, mask within, outline on the silhouette's). A badly tracked
  frame anywhere in the capture is found (a sample of 32 frames missed them); the cost is a mask decode and
  a pooling per frame (``bench/badinput.py``). A mask filling the image (no outline in it) says nothing
  about the subject's size: such frames are listed (``CameraCheck.unsized``), the reader notes them.
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
    "MIN_WITHIN",
    "MIN_OUTLINE",
    "SLACK",
    "SIZE_CHECKED",
    "LARGER",
]

MAX_VERTICES = 512  # vertices projected per frame (an even subsample of larger meshes)
MIN_IN_FRONT = 0.5  # share of the vertices in front of the camera
MIN_VISIBLE = 0.1  # share of the vertices in front and inside the image
MIN_ON_MASK = 0.5  # share of the visible vertices on the (dilated) mask
MOSTLY_ON_MASK = 0.8  # under this share on the mask (occlusion?), the roll is compared even with fewer on it
MIN_MASK_POINTS = 16  # fewer visible vertices than this say nothing about the overlap: geometry only
BROKEN_SHARE = 0.8  # a camera failing on this share of its checked frames is wrong, not its frames
CLEARLY_BETTER = 0.25  # another convention beating "as is" on the mask by this much means "as is" is wrong
MIN_WITHIN = 0.9  # share of the mask's cells on the projected mesh: the mask is the visible part of the subject
MIN_OUTLINE = 0.5  # ... and share of its outline on the projection's outline (not a projection larger than it)
MIN_COVER = 0.01  # without a mask: share of the image the projected mesh must cover when under MIN_VISIBLE is in it
# the projection shrunk by these factors must not fit clearly better (a focal length or distance off)
SMALLER = (0.8, 0.7, 0.6, 0.45)
SMALLER_BETTER = 0.08  # ... by this much more of the mask's outline on the shrunk projection's
SLACK = 0.2  # a mask may be loose or off by this share of the subject's projected width (a matte, a tracker)
# under this share of the visible vertices on the mask, a frame passing on them is compared with the shrunk
# projections too: a camera too close (a translation scaled) puts only part of them on it
SIZE_CHECKED = 0.9
TIGHT = 1  # ... its mask then allowed this many cells inside the silhouette (a tight matte, a mesh fatter than it)
SIZE_CELLS = 12  # ... when the mask spans this many cells (fewer: a fifth of its size is within those tolerances)
BAND_IN, BAND_OUT = 2.2, 0.5  # a mask's outline cell on the silhouette's: its signed distance (cells) in this band
_MAX_SLACK = 2  # ... in grid cells at most (close-ups: the silhouette is wider than the image)
PROBE_FRAMES = 8  # frames of a wrong camera on which the convention fixes are tried
_RASTER_CHUNK = 1 << 20  # (triangle, sample) pairs tested at a time when a silhouette is rasterized
_SAMPLES = 2  # samples per cell side (at most) when a silhouette is rasterized (4 cost twice as much)
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
    (frame index -> reason) of the other cameras; ``checked`` frames and ``masks_read``; ``unsized``: the
    passing frames whose mask fills the image (no outline in it), so that their camera's distance to the
    subject could not be checked against it (a face-filling close-up)."""

    wrong: dict[str, str] = field(default_factory=dict)
    bad_frames: dict[int, str] = field(default_factory=dict)
    checked: int = 0
    masks_read: int = 0
    unsized: list[int] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.wrong and not self.bad_frames


def _mask_grid(mask: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
    """Mask ``[H,W]`` or ``[H,W,1]`` -> (pooled and dilated boolean grid, cell size in pixels, pooled grid)."""
    m = torch.from_numpy(np.ascontiguousarray(np.asarray(mask, np.float32).reshape(mask.shape[0], mask.shape[1])))
    cell = max(1, math.ceil(max(m.shape) / _GRID))
    g = F.max_pool2d((m > 0.5).float()[None, None], cell, cell, ceil_mode=True)
    d = F.max_pool2d(g, 3, 1, padding=1)
    return d[0, 0].numpy() > 0, cell, g[0, 0].numpy() > 0


def _project(vm: np.ndarray, K: np.ndarray, w: int, h: int, verts: np.ndarray):
    """(u, v, in front, inside the image) of ``verts [N,3]``."""
    p = verts @ vm[:3, :3].T + vm[:3, 3]
    z = p[:, 2]
    front = z > 1e-9
    zs = np.where(front, z, 1.0)
    u = K[0, 0] * p[:, 0] / zs + K[0, 1] * p[:, 1] / zs + K[0, 2]
    v = K[1, 1] * p[:, 1] / zs + K[1, 2]
    return u, v, front, front & (u >= 0) & (u < w) & (v >= 0) & (v < h)


def _silhouette(vm: np.ndarray, K, w, h, verts: np.ndarray, faces: np.ndarray, shape, cell: int) -> np.ndarray:
    """The mesh's projection on the mask grid ``shape`` (cells of ``cell`` pixels), pooled as the mask is: a
    cell is in when a triangle covers one of its samples (up to ``_SAMPLES`` a side, at pixel centres;
    triangles with a corner behind the camera are left out) or it holds a vertex. ``verts [V,3]``, ``faces
    [F,3]``."""
    u, v, front, inside = _project(vm, K, w, h, verts)
    gh, gw = shape
    sub = min(cell, _SAMPLES)  # samples per cell side
    step = cell / sub  # pixels between samples
    out = np.zeros((gh * sub, gw * sub), bool)
    f = faces[front[faces].all(1)]
    tri = np.stack([u[f], v[f]], -1) / step - 0.5  # [F,3,2] in samples, sample centres on integers
    tri = tri[np.isfinite(tri).all((1, 2))]
    top = np.array([gw * sub - 1, gh * sub - 1])
    # boxes clipped to just beyond the grid before the integer casts (an absurd intrinsic puts corners at 1e19)
    lo = np.maximum(np.ceil(np.clip(tri.min(1), -1, top + 1)), 0).astype(np.int64)
    hi = np.minimum(np.floor(np.clip(tri.max(1), -1, top + 1)), top).astype(np.int64)
    keep = (hi >= lo).all(1)
    tri, lo, hi = tri[keep], lo[keep], hi[keep]
    count = (hi[:, 0] - lo[:, 0] + 1) * (hi[:, 1] - lo[:, 1] + 1)
    csum = np.cumsum(count)
    start = 0
    while start < len(tri):  # candidate (triangle, sample) pairs inside each bounding box, about 1M at a time
        base = int(csum[start - 1]) if start else 0
        stop = max(start + 1, int(np.searchsorted(csum, base + _RASTER_CHUNK, side="right")))
        t, a, b, n = tri[start:stop], lo[start:stop], hi[start:stop], count[start:stop]
        bw = b[:, 0] - a[:, 0] + 1
        k = np.repeat(np.arange(len(t)), n)
        off = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        cx, cy = a[k, 0] + off % bw[k], a[k, 1] + off // bw[k]
        p0, p1, p2 = t[k, 0], t[k, 1], t[k, 2]
        e0 = (p1[:, 0] - cx) * (p2[:, 1] - cy) - (p1[:, 1] - cy) * (p2[:, 0] - cx)
        e1 = (p2[:, 0] - cx) * (p0[:, 1] - cy) - (p2[:, 1] - cy) * (p0[:, 0] - cx)
        e2 = (p0[:, 0] - cx) * (p1[:, 1] - cy) - (p0[:, 1] - cy) * (p1[:, 0] - cx)
        hit = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
        out[cy[hit], cx[hit]] = True
        start = stop
    cells = out.reshape(gh, sub, gw, sub).any(axis=(1, 3))
    cells[
        np.clip((v[inside] // cell).astype(np.int64), 0, gh - 1),
        np.clip((u[inside] // cell).astype(np.int64), 0, gw - 1),
    ] = True
    return cells


def _winding_number(point: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> float:
    """The generalized winding number of the mesh ``verts [V,3]``, ``faces [F,3]`` about ``point [3]``: about
    +-1 inside a closed mesh, 0 outside, in between near holes (Jacobson et al. 2013: the triangles' solid
    angles over 4 pi; either winding of the faces)."""
    a, b, c = (verts[faces[:, k]] - point for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    dots = np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la + np.einsum("ij,ij->i", c, a) * lb
    return float(np.arctan2(det, la * lb * lc + dots).sum() / (2 * np.pi))


def _seen_without_mask(vm: np.ndarray, K, w: int, h: int, mesh: tuple[np.ndarray, np.ndarray] | None) -> str | None:
    """Why a frame with no mask, its mesh in front of the camera but under ``MIN_VISIBLE`` of its vertices in
    the image, is wrong (None: a close-up, whose image the mesh fills while most of it lies outside): the
    camera is inside the mesh, or the projected mesh covers under ``MIN_COVER`` of the image. Without the
    faces (``mesh`` None) nothing tells a close-up: the vertex count decides."""
    if mesh is None:
        return "the mesh projects outside the image"
    verts, faces = mesh
    eye = -vm[:3, :3].T @ vm[:3, 3]
    if abs(_winding_number(eye, verts, faces)) > 0.5:
        return "the camera is inside the mesh"
    # the cover on a grid of about _GRID cells a side, one sample per cell (the image scaled to the grid)
    cell = max(1, math.ceil(max(w, h) / _GRID))
    gw, gh = math.ceil(w / cell), math.ceil(h / cell)
    Kg = np.diag([1.0 / cell, 1.0 / cell, 1.0]) @ K
    if float(_silhouette(vm, Kg, gw, gh, verts, faces, (gh, gw), 1).mean()) < MIN_COVER:
        return "the mesh projects outside the image"
    return None


def _dilate(a: np.ndarray) -> np.ndarray:
    return F.max_pool2d(torch.from_numpy(a).float()[None, None], 3, 1, padding=1)[0, 0].numpy() > 0


def _outline(a: np.ndarray) -> np.ndarray:
    """The cells of ``a`` with a cell outside it among their 8 neighbours, the grid's border left out (the
    image edge cuts a close-up; that is no outline of the subject)."""
    inner = ~_dilate(~a)
    out = a & ~inner
    out[0, :] = out[-1, :] = out[:, 0] = out[:, -1] = False
    return out


def _signed_distance(a: np.ndarray, pad: int) -> np.ndarray:
    """Signed distance in cells to the outline of ``a`` (positive outside, negative inside), on the grid
    padded by ``pad`` cells on each side; beyond the grid's border ``a`` continues as at the border (the
    image edge cuts the subject: no outline there)."""
    from scipy.ndimage import distance_transform_edt

    p = np.pad(a, pad + 2, mode="edge")
    sd = distance_transform_edt(~p) - distance_transform_edt(p)
    return sd[2:-2, 2:-2]


def _within(vm: np.ndarray, K, w, h, mesh: tuple[np.ndarray, np.ndarray], grid, tight: int = 0) -> tuple[float, float]:
    """:func:`_fits` with one ``tight``."""
    return _fits(vm, K, w, h, mesh, grid, (tight,))[0]


def _fits(
    vm: np.ndarray, K, w, h, mesh: tuple[np.ndarray, np.ndarray], grid, tights: tuple[int, ...]
) -> list[tuple[float, float]]:
    """How the mask lies in the mesh's projection (``mesh``: every vertex ``[V,3]`` and the faces ``[F,3]``,
    :func:`_silhouette`): (share of the mask's cells within the projection, share of the mask's outline on
    the projection's outline). Both near 1 when the mask is a part of the projected silhouette cut only by
    occluders or the image edge; a projection larger than the subject holds the mask with its outline
    inside. Tolerances are relative to the subject's projected width (its widest inscribed disc on the grid):
    the mask may be loose (its outline up to ``SLACK`` of that width outside the silhouette's, at least one
    cell and at most ``_MAX_SLACK``) and off by as much in any direction, the two together within that
    slack; the best fit, of those holding ``MIN_WITHIN`` of the mask, is taken. With a ``tight`` of n the
    mask's outline may also lie up to n cells inside the silhouette's (a tight matte, a mesh fatter than the
    body). One (within, outline) per entry of ``tights``, from one raster; (0, 0) for an empty mask."""
    _, cell, raw = grid
    if not raw.any():
        return [(0.0, 0.0)] * len(tights)
    sil = _silhouette(vm, K, w, h, mesh[0], mesh[1], raw.shape, cell)
    if not sil.any():
        return [(0.0, 0.0)] * len(tights)
    sd = _signed_distance(sil, _MAX_SLACK)
    # the slack: SLACK of the subject's projected width (its widest inscribed disc), 1 to _MAX_SLACK cells
    t = int(min(_MAX_SLACK, max(1, round(SLACK * 2.0 * float(-sd.min())))))
    sd = sd[_MAX_SLACK - t : sd.shape[0] - _MAX_SLACK + t, _MAX_SLACK - t : sd.shape[1] - _MAX_SLACK + t]
    ys, xs = np.nonzero(raw)
    m_out = _outline(raw)
    oy, ox = np.nonzero(m_out)
    shifts = np.arange(-t, t + 1)
    dy, dx = (a.ravel() for a in np.meshgrid(shifts, shifts, indexing="ij"))
    return [_fit(sd, t, ys, xs, oy, ox, dy, dx, tight) for tight in tights]


def _fit(sd, t: int, ys, xs, oy, ox, dy, dx, tight: int) -> tuple[float, float]:
    """:func:`_fits`'s best fit on the silhouette's signed distances ``sd`` (cropped to the slack ``t``)."""
    loose = np.arange(-tight, t + 1, dtype=np.float64)  # how far outside the silhouette the mask's outline lies
    # [shift, cell] signed distances of the mask's cells and outline cells, the mask moved by each shift
    d_in = sd[ys[None] + t + dy[:, None], xs[None] + t + dx[:, None]]
    inside = (d_in[:, None, :] <= loose[None, :, None] + 1.5).mean(-1)  # [shift, loose]
    if len(oy):
        d_out = sd[oy[None] + t + dy[:, None], ox[None] + t + dx[:, None]][:, None, :] - loose[None, :, None]
        on_line = ((d_out >= -BAND_IN) & (d_out <= BAND_OUT)).mean(-1)
    else:
        on_line = np.ones_like(inside)
    budget = np.maximum(np.abs(dy), np.abs(dx))[:, None] + np.maximum(loose, 0.0)[None, :] <= t
    ok = (inside >= MIN_WITHIN) & budget
    if ok.any():
        k = np.argmax(np.where(ok, on_line, -1.0))
    else:
        k = np.argmax(np.where(budget, inside, -1.0))
    return float(inside.flat[k]), float(on_line.flat[k])


def _score(vm: np.ndarray, K: np.ndarray, w: int, h: int, verts: np.ndarray, grid) -> _Score:
    u, v, front, inside = _project(vm, K, w, h, verts)
    n = max(len(verts), 1)
    on_mask = None
    if grid is not None and int(inside.sum()) >= MIN_MASK_POINTS:
        g, cell = grid[0], grid[1]
        cu = np.clip((u[inside] // cell).astype(np.int64), 0, g.shape[1] - 1)
        cv = np.clip((v[inside] // cell).astype(np.int64), 0, g.shape[0] - 1)
        on_mask = float(g[cv, cu].mean())
    return _Score(float(front.sum()) / n, float(inside.sum()) / n, on_mask)


INVERTED = "the mask looks inverted (the subject black on white)"
LARGER = "the mesh projects larger than the subject on the mask"


def _inverted(vm: np.ndarray, K, w, h, verts, grid) -> bool:
    """Whether the mask covers most of the image while the mesh lands mostly off it: a mask with subject
    and background swapped (the camera may be right)."""
    g, cell = grid[0], grid[1]
    if g.mean() <= 0.5:
        return False
    flipped = F.max_pool2d(torch.from_numpy(~g).float()[None, None], 3, 1, padding=1)[0, 0].numpy() > 0
    s = _score(vm, K, w, h, verts, (flipped, cell))
    return s.on_mask is not None and s.on_mask >= MIN_ON_MASK


def _fails(vm: np.ndarray, K, w, h, verts, grid, mesh: Callable[[], tuple] | None = None) -> str | None:
    """Why the frame fails as is (None when it passes): its own score, or the roll fitting clearly better.

    With ``mesh()`` (the frame's every vertex and the faces) the mask is also compared the other way
    (:func:`_within`): a frame whose vertices miss the mask (occlusion) or lie mostly outside the image (a
    close-up) passes when the mask lies within the projected silhouette (``MIN_WITHIN``) and its outline
    on the silhouette's (``MIN_OUTLINE``: cut only by occluders and the image edge), a loose or offset mask
    fitted within ``SLACK`` of the subject's width, and no shrunk projection fits clearly better (a
    projection larger than the subject holds the mask too, its outline inside: ``LARGER``); a frame passing
    on its vertices with under ``SIZE_CHECKED`` of them on the mask is compared with the shrunk projections
    too, its mask allowed ``TIGHT`` cells inside the silhouette. The roll wins when its outline fits by
    ``SMALLER_BETTER`` more, or its vertices on the mask, mask within and outline together by
    ``CLEARLY_BETTER`` more."""
    s = _score(vm, K, w, h, verts, grid)
    held: tuple[float, float] | None = None  # _within as is, computed when needed (a raster of the mesh)
    if s.ok:
        if grid is None:
            return None
        if mesh is not None and s.on_mask is not None and s.on_mask < SIZE_CHECKED and _span(grid[2]) >= SIZE_CELLS:
            # enough vertices on the mask, not nearly all: a projection larger than the subject (a camera too
            # close) puts about half of them there; a shrunk one must not fit clearly better
            held, (_, line) = _fits(vm, K, w, h, mesh(), grid, (0, TIGHT))
            if _smaller_fits(vm, K, w, h, verts, grid, mesh(), s, line):
                return LARGER
    elif s.in_front < MIN_IN_FRONT:
        return s.why()
    elif grid is None:  # no mask: a close-up passes when the mesh fills the image, the camera outside it
        return _seen_without_mask(vm, K, w, h, None if mesh is None else mesh())
    if not s.ok:
        if mesh is not None and s.visible > 0:
            held = _within(vm, K, w, h, mesh(), grid)
        why: str | None = None
        if mesh is None or held is None or held[0] < MIN_WITHIN or held[1] < MIN_OUTLINE:
            why = s.why()  # not within the projected silhouette: the mesh is where the subject is not
        elif _smaller_fits(vm, K, w, h, verts, grid, mesh(), s, held[1]):
            why = LARGER
        if why is not None:
            if s.on_mask is not None and s.on_mask < MIN_ON_MASK and _inverted(vm, K, w, h, verts, grid):
                return INVERTED
            return why
    if s.on_mask is not None:
        r = _score(_ROLL @ vm, K, w, h, verts, grid)
        if r.on_mask is None or r.visible < MIN_VISIBLE:
            return None
        if r.on_mask <= s.on_mask and (mesh is None or s.on_mask >= MOSTLY_ON_MASK):
            return None  # (most of the mesh on the mask: no roll can fit better)
        if mesh is None:
            better = r.on_mask >= s.on_mask + CLEARLY_BETTER
        else:
            # what the projection as is misses of the mask may be occluded: the roll must fit the mask's
            # outline clearly better, or the mask on all three counts together
            within, line = held or _within(vm, K, w, h, mesh(), grid)
            r_within, r_line = _within(_ROLL @ vm, K, w, h, mesh(), grid)
            if r.on_mask > s.on_mask:
                better = (r_within >= MIN_WITHIN and r_line >= line + SMALLER_BETTER) or (
                    r.on_mask + r_within + r_line >= s.on_mask + within + line + CLEARLY_BETTER
                )
            else:  # fewer vertices on the mask (occluded?): the outline must fit far better
                better = r_within >= MIN_WITHIN and r_line >= line + CLEARLY_BETTER
        if better:
            return "the mesh fits the mask much better turned by 180 degrees (camera rolled?)"
    return None


def _span(a: np.ndarray) -> int:
    """The longer side, in cells, of the bounding box of ``a`` (0 when empty)."""
    ys, xs = np.nonzero(a.any(1))[0], np.nonzero(a.any(0))[0]
    return 0 if len(ys) == 0 else int(max(ys[-1] - ys[0], xs[-1] - xs[0])) + 1


def _smaller_fits(vm, K, w, h, verts, grid, mesh, s: _Score, outline: float) -> bool:
    """Whether the projection shrunk (``SMALLER``) fits the mask clearly better than as is: the mask within
    it (:func:`_within`) and either its outline on the shrunk one's by ``SMALLER_BETTER`` more, or as much
    of it with ``CLEARLY_BETTER`` more of the vertices on the mask. A mask held by a projection larger than
    the subject. Shrunk about the principal point (a focal length too long, a camera too close along its
    axis) and about the world origin's image (a translation scaled: in other units than the meshes, or the
    meshes scaled without their cameras, moves the camera towards the world origin)."""
    centres = [K[:2, 2]]
    o = vm[:3, 3]  # the world origin in the camera's frame
    if o[2] > 1e-9:
        c = np.array([K[0, 0] * o[0] / o[2] + K[0, 1] * o[1] / o[2] + K[0, 2], K[1, 1] * o[1] / o[2] + K[1, 2]])
        if np.abs(c - K[:2, 2]).max() >= grid[1]:  # (within a cell of the principal point: the same shrink)
            centres.append(c)
    for c, k in ((c, k) for c in centres for k in SMALLER):
        K2 = K.copy()
        K2[:2, :2] *= k
        K2[:2, 2] = k * K[:2, 2] + (1.0 - k) * c  # u -> c + k (u - c)
        r = _score(vm, K2, w, h, verts, grid)
        if r.on_mask is None:
            continue  # too few vertices in the image (a close-up): its mask's outline is mostly the image edge
        more = r.on_mask >= (s.on_mask or 0.0) + CLEARLY_BETTER
        if not more and outline + SMALLER_BETTER > 1.0:
            continue  # nothing to gain: the outline as is is on the silhouette's, the vertices no better
        if not _may_hold(vm, K2, w, h, mesh[0], grid):
            continue  # (the shrunk projection's bounding box misses the mask: it cannot hold it)
        cover, line = _within(vm, K2, w, h, mesh, grid)
        if cover >= MIN_WITHIN and (line >= outline + SMALLER_BETTER or (more and line >= outline)):
            return True
    return False


def _may_hold(vm: np.ndarray, K, w, h, verts: np.ndarray, grid) -> bool:
    """False when the projection of ``verts [V,3]`` cannot hold ``MIN_WITHIN`` of the mask by
    :func:`_within`'s measure: more of the mask's cells lie beyond its bounding box (on the grid) than any
    shift and looseness reach. Spares a raster."""
    _, cell, raw = grid
    u, v, front, _ = _project(vm, K, w, h, verts)
    if not front.any():
        return False
    x0, x1 = np.floor(u[front].min() / cell), np.floor(u[front].max() / cell)
    y0, y1 = np.floor(v[front].min() / cell), np.floor(v[front].max() / cell)
    ys, xs = np.nonzero(raw)
    dx, dy = np.maximum(np.maximum(x0 - xs, xs - x1), 0), np.maximum(np.maximum(y0 - ys, ys - y1), 0)
    reach = 1.5 + math.sqrt(2.0) * _MAX_SLACK  # a cell within the silhouette by _within's measure lies this near
    return float((np.hypot(dx, dy) <= reach).mean()) >= MIN_WITHIN


def _spread(items: list[int], k: int) -> list[int]:
    if len(items) <= k:
        return list(items)
    return [items[j] for j in sorted({round(x) for x in np.linspace(0, len(items) - 1, k)})]


def check_cameras(
    cameras: dict[str, tuple[np.ndarray, np.ndarray, int, int]],
    frames: Sequence[tuple[str, int]],
    vertices: np.ndarray,
    load_mask: Callable[[int], np.ndarray | None],
    faces: np.ndarray | None = None,
) -> CameraCheck:
    """Check every frame's camera against its mesh and its mask; see the module's rule.

    ``cameras``: id -> ``(K [3,3], viewmat [4,4], width, height)``; ``frames``: ``(camera id, mesh row)``
    per frame; ``vertices [T,V,3]`` (a memory map is fine: a subsample of columns is read);
    ``load_mask(i)``: frame ``i``'s mask ``[H,W(,1)]`` in [0, 1], or None; ``faces [F,3]`` (optional): the
    mask is then also checked to lie within the projected silhouette (occlusion, close-ups).
    """
    report = CameraCheck()
    n_v = int(vertices.shape[1])
    cols = np.unique(np.linspace(0, n_v - 1, min(n_v, MAX_VERTICES)).round().astype(np.int64))
    rows = sorted({m for _, m in frames})
    sub = {m: np.asarray(vertices[m], np.float64)[cols] for m in rows}
    by_cam: dict[str, list[int]] = {}
    for i, (cid, _) in enumerate(frames):
        by_cam.setdefault(cid, []).append(i)
    grids: dict[int, tuple[np.ndarray, int, np.ndarray] | None] = {}  # kept for the probed frames and the last one

    def full(m: int) -> Callable[[], tuple[np.ndarray, np.ndarray]] | None:
        """Mesh row ``m``'s every vertex and the faces, read when asked (None without faces)."""
        if faces is None:
            return None
        return lambda: (np.asarray(vertices[m], np.float64), np.asarray(faces, np.int64))

    def grid(i: int):
        if i in grids:
            return grids[i]
        mask = load_mask(i)
        g = None if mask is None else _mask_grid(mask)
        report.masks_read += mask is not None
        for j in [j for j in grids if j not in probe]:  # at most one frame's grid besides the probed ones
            del grids[j]
        grids[i] = g
        return g

    for cid, ids in by_cam.items():
        K, vm, w, h = cameras[cid]
        probe = _spread(ids, PROBE_FRAMES)
        fails: dict[int, str] = {}
        unsized: list[int] = []
        for i in ids:  # geometry, then the mask, of every frame
            s = _score(vm, K, w, h, sub[frames[i][1]], None)
            close_up = s.in_front >= MIN_IN_FRONT and s.visible > 0  # its mask may show it is a close-up
            no_mask = s.in_front >= MIN_IN_FRONT and grid(i) is None  # a close-up when the mesh fills the image
            if s.ok or (close_up and grid(i) is not None) or no_mask:
                if not _mask_fail(i, vm, K, w, h, sub[frames[i][1]], grid(i), fails, full(frames[i][1])):
                    g = grid(i)
                    if g is not None and g[2].mean() > 0.5 and not _outline(g[2]).any():
                        unsized.append(i)  # the mask fills the image: nothing in it shows the subject's size
            else:
                fails[i] = s.why()
        report.checked += len(ids)
        if len(fails) >= max(1, BROKEN_SHARE * len(ids)):
            report.wrong[cid] = _diagnose(cid, fails, len(ids), vm, K, w, h, probe, frames, sub, grid, full)
        else:
            report.bad_frames.update(fails)
            report.unsized += unsized
    return report


def _mask_fail(i, vm, K, w, h, verts, g, fails: dict[int, str], full=None) -> bool:
    why = _fails(vm, K, w, h, verts, g, full)
    if why is not None:
        fails[i] = why
    return why is not None


def _diagnose(cid, fails, n_checked, vm, K, w, h, probe, frames, sub, grid, full) -> str:
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

    def on_mask(m: np.ndarray) -> float:  # the mean share of the vertices on the mask, over the probed frames
        return float(np.mean([_score(m, K, w, h, sub[frames[i][1]], grid(i)).on_mask or 0.0 for i in probe]))

    for meaning, fix in _FIXES:
        try:
            vm2 = fix(vm)
        except np.linalg.LinAlgError:
            continue
        good = sum(_fails(vm2, K, w, h, sub[frames[i][1]], grid(i), full(frames[i][1])) is None for i in probe)
        if good < max(1, BROKEN_SHARE * len(probe)):
            continue
        if main == LARGER and on_mask(vm2) < on_mask(vm) + CLEARLY_BETTER:
            continue  # a camera too close: a mix-up that passes as narrowly as it (a large blob of a mask) is no fix
        return f"{what}: likely {meaning}, which fits {good} of {len(probe)} checked frames"
    if main == LARGER:
        return (
            f"{what}: no common convention mix-up fixes it; the camera looks too close or its focal length too long "
            "(a translation in other units than the meshes, or meshes scaled without their cameras?)"
        )
    return f"{what}: no common convention mix-up (y/z flip, 180-degree roll, inverse) fixes it"
