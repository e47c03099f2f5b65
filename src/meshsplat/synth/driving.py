"""Driving meshes derived from the rendered surface: welding seam duplicates, Taubin smoothing
and vertex-clustering decimation (all on the rest pose; the result is re-skinned by the source)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import bbox_diagonal

__all__ = ["weld", "taubin_smooth", "cluster_decimate"]


def weld(positions: list[np.ndarray], faces: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge vertices that coincide (within ``tol``) in every pose of ``positions`` (list of ``[V,3]``).

    Only vertices referenced by ``faces`` are kept. Returns ``(group [V] (-1 = unused), rep [G]
    representative vertex per group, faces [F',3] on groups)``; faces that collapse are dropped.
    """
    v = positions[0].shape[0]
    used = np.zeros(v, bool)
    used[faces.reshape(-1)] = True
    ids = np.nonzero(used)[0]
    key = np.concatenate([np.round(p[ids] / tol).astype(np.int64) for p in positions], 1)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    group = np.full(v, -1, np.int64)
    group[ids] = inv.reshape(-1)
    rep = ids[first]
    f = group[faces]
    good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return group, rep, f[good]


def _uniform_laplacian(n: int, faces: np.ndarray) -> sp.csr_matrix:
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
    a = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    a.data[:] = 1.0
    deg = np.asarray(a.sum(1)).reshape(-1)
    return sp.diags(1.0 / np.maximum(deg, 1)) @ a


def taubin_smooth(
    verts: np.ndarray, faces: np.ndarray, iterations: int, lam: float = 0.5, mu: float = -0.53
) -> np.ndarray:
    """Taubin lambda|mu smoothing (uniform weights): removes detail without shrinking the mesh."""
    if iterations < 0:
        raise MeshsplatError(f"iterations: expected >= 0, got {iterations}")
    avg = _uniform_laplacian(len(verts), faces)
    x = np.asarray(verts, np.float64).copy()
    for _ in range(iterations):
        x = x + lam * (avg @ x - x)
        x = x + mu * (avg @ x - x)
    return x


def _cluster(verts: np.ndarray, cell: float):
    key = np.floor((verts - verts.min(0)) / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    return inv.reshape(-1)


def cluster_decimate(verts: np.ndarray, faces: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex-clustering decimation to about ``ratio`` of the vertices.

    Returns ``(new_verts [V',3] cluster means, faces [F',3], nearest [V'] index of the input vertex
    closest to each new vertex)`` — the nearest vertex lends its skin weights.
    """
    if not 0 < ratio <= 1:
        raise MeshsplatError(f"decimate ratio: expected in (0, 1], got {ratio}")
    n = len(verts)
    target = max(4, round(n * ratio))
    diag = bbox_diagonal(verts)
    lo, hi = diag * 1e-5, diag
    for _ in range(30):  # bisection on the cell size
        mid = np.sqrt(lo * hi)
        if _cluster(verts, mid).max() + 1 > target:
            lo = mid
        else:
            hi = mid
    inv = _cluster(verts, hi)
    g = inv.max() + 1
    counts = np.bincount(inv, minlength=g).astype(np.float64)
    means = np.stack([np.bincount(inv, weights=verts[:, k], minlength=g) for k in range(3)], 1) / counts[:, None]
    d = np.linalg.norm(verts - means[inv], axis=1)
    order = np.lexsort((d, inv))
    nearest = order[np.searchsorted(inv[order], np.arange(g))]
    f = inv[faces]
    good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = np.unique(np.sort(f[good], 1), axis=0, return_index=True)[1]
    f = inv[faces][good][np.sort(f)]
    used = np.zeros(g, bool)
    used[f.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return means[used], remap[f], nearest[used]
