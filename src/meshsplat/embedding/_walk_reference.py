"""Plain per-point reference for :func:`walk_on_triangles` (test oracle and bench baseline).

One Python loop per point, Python floats (double precision), no precomputed maps:

- adjacency from a dict ``edge -> half-edges``; only edges with exactly two faces connect,
  and never across a degenerate face;
- ``paper``: the remaining rates are re-expressed by Algorithm 1's parallelogram rule
  (shared corners ``δ_c + δ_i``, the neighbour's far corner ``-δ_i``);
- ``unfold``: the remaining step is turned into a 3D vector, rotated about the shared
  edge (Rodrigues) so that leaving ``f`` becomes entering ``g``, and expressed in ``g``'s
  barycentric rates by least squares.

Same decisions as the vectorized walk: exit corner = smallest ``b_c / -δ_c`` over rates
below ``-tol * max|δ|`` (``tol = eps(dtype)**0.75``), ties to the lowest corner, never
back through the edge just entered; stop on the exit edge at walls and after
``max_crossings`` crossings. Slow (microseconds per crossing per point); for tests.
"""

from __future__ import annotations

import math

import torch

from meshsplat.embedding.walk import WALK_MODES, WalkResult
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import degenerate_faces
from meshsplat.mesh.tri_mesh import TriMesh

__all__ = ["walk_on_triangles_reference"]


def _sub(a, b):
    return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _scale(a, s):
    return [a[0] * s, a[1] * s, a[2] * s]


def _unit(a):
    n = math.sqrt(_dot(a, a))
    return _scale(a, 1.0 / n) if n > 0 else [0.0, 0.0, 0.0]


def _clamp_bary(b):
    b = [min(max(x, 0.0), 1.0) for x in b]
    s = max(b[0] + b[1] + b[2], 1e-30)
    return [x / s for x in b]


class _Mesh:
    """Python-list view of a mesh: corner positions, walls, neighbours by edge lookup."""

    def __init__(self, mesh: TriMesh, verts: torch.Tensor):
        self.faces = mesh.faces.tolist()
        self.pos = verts.detach().double().cpu().tolist()
        self.deg = degenerate_faces(verts.detach(), mesh.faces.to(verts.device)).cpu().tolist()
        self.edges: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for f, tri in enumerate(self.faces):
            for j in range(3):
                a, b = tri[j], tri[(j + 1) % 3]
                self.edges.setdefault((min(a, b), max(a, b)), []).append((f, j))

    def corners(self, f):
        return [self.pos[v] for v in self.faces[f]]

    def neighbour(self, f, j):
        """(g, k): face across local edge j of f and that edge's local index in g, or None (wall)."""
        a, b = self.faces[f][j], self.faces[f][(j + 1) % 3]
        users = self.edges[(min(a, b), max(a, b))]
        if a == b or len(users) != 2 or self.deg[f]:
            return None
        g, k = users[1] if users[0] == (f, j) else users[0]
        return None if self.deg[g] else (g, k)


def _rates_3d(p, d):
    """Barycentric rates ``δ`` (sum 0) of the in-plane part of 3D vector d in triangle p (least squares)."""
    e0, e1 = _sub(p[0], p[2]), _sub(p[1], p[2])
    a00, a01, a11 = _dot(e0, e0), _dot(e0, e1), _dot(e1, e1)
    r0, r1 = _dot(e0, d), _dot(e1, d)
    det = a00 * a11 - a01 * a01
    x0, x1 = (a11 * r0 - a01 * r1) / det, (a00 * r1 - a01 * r0) / det
    return [x0, x1, -(x0 + x1)]


def _unfold(m: _Mesh, f, j, g, k, rem):
    """Rates in g of the remaining step ``rem`` (rates in f) leaving f through its edge j."""
    p, q = m.corners(f), m.corners(g)
    i = (j + 2) % 3
    d = [sum(rem[c] * p[c][x] for c in range(3)) for x in range(3)]  # 3D remaining step
    axis = _unit(_sub(p[(j + 1) % 3], p[j]))
    to_i = _sub(p[i], p[j])
    out_f = _unit(_scale(_sub(to_i, _scale(axis, _dot(to_i, axis))), -1.0))  # leaving f, across the edge
    to_far = _sub(q[(k + 2) % 3], p[j])
    in_g = _unit(_sub(to_far, _scale(axis, _dot(to_far, axis))))  # entering g, across the edge
    ang = math.atan2(_dot(_cross(out_f, in_g), axis), _dot(out_f, in_g))
    c, s = math.cos(ang), math.sin(ang)
    axd = _cross(axis, d)
    ad = _dot(axis, d) * (1.0 - c)
    d_rot = [d[x] * c + axd[x] * s + axis[x] * ad for x in range(3)]
    return _rates_3d(q, d_rot)


def _walk_one(m: _Mesh, f, uv, step, mode, max_crossings, tol):
    b = _clamp_bary([uv[0], uv[1], 1.0 - (uv[0] + uv[1])])
    r = [step[0], step[1], -(step[0] + step[1])]
    if mode == "unfold" and m.deg[f]:
        r = [0.0, 0.0, 0.0]
    if max(abs(x) for x in r) == 0:
        return f, b
    entry, crossings = -1, 0
    while True:
        lim = -tol * max(abs(x) for x in r)
        t, i = math.inf, -1
        for c in range(3):
            if c != entry and r[c] < lim and b[c] / -r[c] < t:
                t, i = b[c] / -r[c], c
        if t >= 1.0:
            return f, _clamp_bary([b[c] + r[c] for c in range(3)])
        b_exit = [0.0 if c == i else b[c] + t * r[c] for c in range(3)]
        b_exit = _clamp_bary(b_exit)
        j = (i + 1) % 3  # exit edge, opposite i
        nb = m.neighbour(f, j)
        if nb is None or crossings == max_crossings:
            return f, b_exit
        g, k = nb
        rem = [(1.0 - t) * x for x in r]
        from_f = {m.faces[f][c]: c for c in (j, (j + 1) % 3)}  # shared vertex -> corner of f
        b_new, r_new = [0.0] * 3, [0.0] * 3
        if mode == "unfold":
            r_new = _unfold(m, f, j, g, k, rem)
        for cg in range(3):
            cf = from_f.get(m.faces[g][cg])
            if cf is None:  # g's far corner
                if mode == "paper":
                    r_new[cg] = -rem[i]
                entry = cg
            else:
                b_new[cg] = b_exit[cf]
                if mode == "paper":
                    r_new[cg] = rem[cf] + rem[i]
        f, b, r, crossings = g, b_new, r_new, crossings + 1


def walk_on_triangles_reference(
    mesh: TriMesh,
    verts: torch.Tensor,
    face: torch.Tensor,
    uv: torch.Tensor,
    step: torch.Tensor,
    mode: str = "paper",
    max_crossings: int = 64,
) -> WalkResult:
    """Per-point reference of :func:`meshsplat.embedding.walk_on_triangles` (same arguments and result)."""
    if mode not in WALK_MODES:
        raise MeshsplatError(f"mode: expected one of {WALK_MODES}, got {mode!r}")
    m = _Mesh(mesh, verts)
    tol = torch.finfo(uv.dtype).eps ** 0.75
    faces, uvs = [], []
    for f, p, s in zip(face.tolist(), uv.detach().double().tolist(), step.detach().double().tolist(), strict=True):
        g, b = _walk_one(m, f, p, s, mode, int(max_crossings), tol)
        faces.append(g)
        uvs.append(b[:2])
    out_face = torch.tensor(faces, dtype=torch.long, device=face.device)
    out_uv = torch.tensor(uvs, dtype=torch.float64).reshape(-1, 2).to(device=uv.device, dtype=uv.dtype)
    return WalkResult(out_face, out_uv, out_face != face.long())
