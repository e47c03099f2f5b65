"""Mesh helpers for the stand-in body/head models: exact-count refinement, surface subsampling,
joint regressors, bone distances."""

from __future__ import annotations

import heapq

import numpy as np
from scipy import sparse
from scipy.optimize import nnls
from scipy.sparse.csgraph import dijkstra

__all__ = [
    "split_to_count",
    "subsample_surface",
    "joint_regressor",
    "weld",
    "bone_closest",
    "smoothstep",
    "farthest_points",
    "vertex_normals",
]


def smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def weld(verts: np.ndarray, faces: np.ndarray, decimals: int = 5):
    """Merge vertices at the same position; returns (verts, faces, first source index per vertex)."""
    _, first, inv = np.unique(verts.round(decimals), axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    f = inv[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return verts[first], f[keep], first


def vertex_normals(verts, faces):
    fn = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    n = np.zeros_like(verts)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _edge_key(a: int, b: int) -> tuple[int, int]:
    """The undirected edge (a, b) as a sorted pair."""
    return (a, b) if a <= b else (b, a)


def split_to_count(verts: np.ndarray, faces: np.ndarray, target: int, attrs: np.ndarray | None = None):
    """Split the longest edge (midpoint, both adjacent faces, orientation kept) until ``target`` vertices.

    ``attrs [V,k]`` are interpolated linearly. A closed genus-0 mesh ends with ``2*target - 4`` faces.
    """
    n0 = len(verts)
    if target < n0:
        raise ValueError(f"split_to_count: mesh already has {n0} > {target} vertices")
    V = np.zeros((target, 3))
    V[:n0] = verts
    A = None
    if attrs is not None:
        A = np.zeros((target, attrs.shape[1]))
        A[:n0] = attrs
    F = [list(map(int, f)) for f in faces]
    edge_faces: dict[tuple[int, int], list[int]] = {}
    for fi, f in enumerate(F):
        for k in range(3):
            edge_faces.setdefault(_edge_key(f[k], f[(k + 1) % 3]), []).append(fi)

    def length(e):
        return float(np.sum((V[e[0]] - V[e[1]]) ** 2))

    heap: list[tuple[float, tuple[int, int]]] = [(-length(e), e) for e in edge_faces]
    heapq.heapify(heap)
    n = n0
    while n < target:
        _, e = heapq.heappop(heap)
        fids = edge_faces.pop(e, None)
        if fids is None:
            continue
        a, b = e
        m = n
        n += 1
        V[m] = (V[a] + V[b]) / 2
        if A is not None:
            A[m] = (A[a] + A[b]) / 2
        touched = {_edge_key(a, m), _edge_key(m, b)}
        for fi in fids:
            f = F[fi]
            i = next(k for k in range(3) if {f[k], f[(k + 1) % 3]} == {a, b})
            p, q, r = f[i], f[(i + 1) % 3], f[(i + 2) % 3]
            nf = len(F)
            F[fi] = [p, m, r]
            F.append([m, q, r])
            lst = edge_faces[_edge_key(q, r)]
            lst[lst.index(fi)] = nf
            edge_faces.setdefault(_edge_key(p, m), []).append(fi)
            edge_faces.setdefault(_edge_key(m, q), []).append(nf)
            edge_faces[_edge_key(m, r)] = [fi, nf]
            touched.add(_edge_key(m, r))
        for key in touched:
            heapq.heappush(heap, (-length(key), key))
    return V, np.asarray(F, np.int64), A


def subsample_surface(verts, faces, target: int, groups: np.ndarray | None = None, iters: int = 30):
    """Pick about ``target`` (<= target) seed vertices evenly spread over the surface (one per voxel and normal
    octant and group) and triangulate their geodesic regions (a face for every original face whose corners fall
    in three regions). Returns ``(seed_index [n], faces [F,3])`` with faces indexing the seeds."""
    vn = vertex_normals(verts, faces)
    groups = np.zeros(len(verts), np.int64) if groups is None else groups
    octant = (vn > 0).astype(np.int64) @ np.array([1, 2, 4])
    ext = np.ptp(verts, axis=0).max()
    lo, hi = ext / 2000, ext / 2
    seeds = None
    for _ in range(iters):
        cell = np.sqrt(lo * hi)
        key = np.concatenate([np.floor(verts / cell).astype(np.int64), octant[:, None], groups[:, None]], 1)
        centre = (np.floor(verts / cell) + 0.5) * cell
        dist = np.linalg.norm(verts - centre, axis=1)
        order = np.lexsort((dist, *key.T[::-1]))
        ks = key[order]
        first = np.ones(len(ks), bool)
        first[1:] = np.any(ks[1:] != ks[:-1], axis=1)
        cand = order[first]
        if len(cand) > target:
            lo = cell
        else:
            hi, seeds = cell, cand
            if len(cand) > 0.985 * target:
                break
    assert seeds is not None, "subsample_surface: iters must be positive"
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    w = np.linalg.norm(verts[e[:, 0]] - verts[e[:, 1]], axis=1)
    G = sparse.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(len(verts),) * 2).tocsr()
    G = G.maximum(G.T)
    _, _, src = dijkstra(G, indices=seeds, min_only=True, return_predecessors=True)
    lab_of_seed = -np.ones(len(verts), np.int64)
    lab_of_seed[seeds] = np.arange(len(seeds))
    lab = lab_of_seed[src]
    tri = lab[faces]
    good = (tri >= 0).all(1) & (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    tri = tri[good]
    _, idx = np.unique(np.sort(tri, 1), axis=0, return_index=True)
    tri = tri[np.sort(idx)]
    tri = _drop_nonmanifold(tri)
    used = np.unique(tri)
    remap = -np.ones(len(seeds), np.int64)
    remap[used] = np.arange(len(used))
    return seeds[used], remap[tri]


def _drop_nonmanifold(tri):
    """Remove faces (last first) until every edge has at most two faces."""
    while True:
        e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), 1)
        _, inv, cnt = np.unique(e, axis=0, return_inverse=True, return_counts=True)
        bad_edge = cnt[inv.reshape(-1)] > 2
        if not bad_edge.any():
            return tri
        bad_face = np.zeros(len(tri), bool)
        np.logical_or.at(bad_face, np.tile(np.arange(len(tri)), 3), bad_edge)
        drop = np.nonzero(bad_face)[0][-1]
        tri = np.delete(tri, drop, 0)


def joint_regressor(verts, joints, candidates: list[np.ndarray], k: int = 24, ridge: float = 1e-3) -> np.ndarray:
    """Sparse convex rows ``[J,V]`` (non-negative, summing to 1) whose weighted means of nearby vertices
    reproduce ``joints [J,3]`` as closely as the vertices' convex hull allows."""
    Jn, Vn = len(joints), len(verts)
    R = np.zeros((Jn, Vn))
    for j in range(Jn):
        cand = candidates[j] if len(candidates[j]) >= 4 else np.arange(Vn)
        d = np.linalg.norm(verts[cand] - joints[j], axis=1)
        near = cand[np.argsort(d)[:k]]
        P = verts[near]
        w0 = 1.0 / (np.linalg.norm(P - joints[j], axis=1) + 1e-3)
        w0 /= w0.sum()
        scale = np.ptp(P, axis=0).max() + 1e-9
        A = np.concatenate([P.T / scale, 10 * np.ones((1, len(near))), ridge * np.eye(len(near))])
        b = np.concatenate([joints[j] / scale, [10.0], ridge * w0])
        w, _ = nnls(A, b)
        R[j, near] = w / w.sum()
    return R


def bone_closest(points, heads, tails):
    """Closest points ``[N,3]`` on segments ``heads[N] -> tails[N]``."""
    d = tails - heads
    t = np.clip(np.einsum("ij,ij->i", points - heads, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0, 1)
    return heads + t[:, None] * d


def farthest_points(points, n: int, start: int = 0) -> np.ndarray:
    """Indices of ``n`` points by farthest point sampling."""
    idx = [start]
    d = np.linalg.norm(points - points[start], axis=1)
    for _ in range(n - 1):
        i = int(np.argmax(d))
        idx.append(i)
        d = np.minimum(d, np.linalg.norm(points - points[i], axis=1))
    return np.asarray(idx)
