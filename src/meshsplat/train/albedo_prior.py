"""A prior on a shaded avatar's albedo: nearby Gaussians of one colour share one albedo.

With shading on, a Gaussian's colour is an albedo times the learned light. The albedo is learned fast and per
Gaussian, so it can keep part of the light: on the path-traced robot (one uniform paint) the trained albedo
followed the key light each Gaussian received in the training frames, 2.7-fold, and a new pose that lights a
part the training clip kept in shadow rendered it too dark (docs/quality.md). The prior

    L = mean_i,k  w_ik |a_i - a_nb(i,k)|,   w_ik = exp(-|c_i - c_nb(i,k)|^2 / CHROMA_SIGMA^2)

over each Gaussian's neighbours on the canonical mesh (albedo ``a [N,3]``, chromaticity ``c = a / sum(a)``, the
weights without gradient) pulls neighbours of one hue to one albedo. Light changes brightness, not hue, so the
light the albedo kept must move into the lighting; a change of hue (a painted edge, a texture) keeps a small
weight and stays sharp. L1 keeps the remaining edges sharp too.

The neighbours are the ``NEIGHBOURS`` nearest and, with a ``reach`` above that, ``NEIGHBOURS`` more spread
evenly by rank over the ``reach`` nearest: the far ones carry the albedo across a region in fewer steps (a part
the training frames kept in shadow, or saw little, takes the albedo of the lit paint around it).
"""

from __future__ import annotations

import numpy as np
import torch

from meshsplat._numba import numba_available
from meshsplat.embedding import gather_rows, surface_points
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.params import SH_C0
from meshsplat.train._albedo_prior_numba import albedo_smoothness_compiled

__all__ = [
    "NEIGHBOURS",
    "CHROMA_SIGMA",
    "REFRESH_EVERY",
    "MAX_REACH",
    "neighbour_ranks",
    "albedo_neighbours",
    "albedo_smoothness",
]

NEIGHBOURS = 8  # nearest Gaussians each one is compared with (and as many farther ones, with a reach)
MAX_REACH = 1024  # the largest reach (neighbour rank) a search may ask for
CHROMA_SIGMA = 0.05  # chromaticity difference at which a neighbour's weight falls to 1/e
REFRESH_EVERY = 100  # training iterations between neighbour searches (and whenever the count changes)


def neighbour_ranks(reach: int) -> np.ndarray:
    """The ranks (1: the nearest other) of the neighbours a search with ``reach`` keeps, ``[NEIGHBOURS]`` or
    ``[2 * NEIGHBOURS]``: 1..NEIGHBOURS, then for ``reach > NEIGHBOURS`` as many more spread evenly over
    ``NEIGHBOURS+1 .. reach`` (repeats where that range is shorter)."""
    if not NEIGHBOURS <= reach <= MAX_REACH:
        raise MeshsplatError(f"albedo prior: reach must be in {NEIGHBOURS}..{MAX_REACH}, got {reach}")
    near = np.arange(1, NEIGHBOURS + 1)
    if reach == NEIGHBOURS:
        return near
    far = np.linspace(NEIGHBOURS + 1, reach, NEIGHBOURS).round().astype(np.int64)
    return np.concatenate([near, far])


def albedo_neighbours(
    verts: torch.Tensor, faces: torch.Tensor, face: torch.Tensor, uv: torch.Tensor, reach: int = NEIGHBOURS
) -> torch.Tensor:
    """Indices ``[N,k]`` of each Gaussian's neighbours by their surface points on the mesh ``verts [V,3]``,
    ``faces [F,3]`` (embedding ``face [N]``, ``uv [N,2]``): the others of ranks :func:`neighbour_ranks` ``(reach)``,
    nearest first (``k`` = ``NEIGHBOURS``, twice that with ``reach > NEIGHBOURS``). Fewer Gaussians than a rank:
    the others, repeated. Exact (a k-d tree), deterministic."""
    from scipy.spatial import cKDTree

    ranks = neighbour_ranks(reach)
    n = int(face.shape[0])
    if n < 2:
        return torch.zeros(n, 0, dtype=torch.long, device=face.device)
    pts = surface_points(verts.detach(), faces, face, uv.detach()).double().cpu().numpy()
    k = min(int(ranks[-1]) + 1, n)
    _, idx = cKDTree(pts).query(pts, k=k, workers=max(1, torch.get_num_threads()))  # per point: thread-count free
    idx = np.asarray(idx, np.int64).reshape(n, k)
    others = idx != np.arange(n)[:, None]  # itself (usually first; elsewhere or absent where points coincide)
    others &= np.cumsum(others, axis=1) <= k - 1  # the k-1 nearest others of each row
    nb = idx[others].reshape(n, k - 1)[:, (ranks - 1) % (k - 1)]  # repeated past k - 1
    return torch.from_numpy(np.ascontiguousarray(nb)).to(face.device)


def albedo_smoothness(sh0: torch.Tensor, neighbours: torch.Tensor, compiled: bool | None = None) -> torch.Tensor:
    """The prior's value (a scalar) for the albedo of ``sh0 [N,1,3]`` (its DC band) and ``neighbours [N,k]``.

    ``compiled`` (default: on CPU when numba is available) computes it and its gradient with numba's kernels,
    2-3x faster than the torch path (``bench/albedo_prior_cost.py``); both agree to float rounding."""
    if sh0.ndim != 3 or sh0.shape[1:] != (1, 3) or neighbours.ndim != 2 or neighbours.shape[0] != sh0.shape[0]:
        raise MeshsplatError(
            f"albedo_smoothness: expected sh0 [N,1,3] and neighbours [N,k], got {list(sh0.shape)}, "
            f"{list(neighbours.shape)}"
        )
    if neighbours.numel() == 0:
        return sh0.sum() * 0.0
    lo, hi = int(neighbours.min()), int(neighbours.max())
    if lo < 0 or hi >= sh0.shape[0]:  # the compiled path does not check its reads
        raise MeshsplatError(f"albedo_smoothness: neighbour indices must be in 0..{sh0.shape[0] - 1}, got {lo}..{hi}")
    a = sh0[:, 0] * SH_C0 + 0.5  # [N,3]
    if compiled is None:
        compiled = sh0.device.type == "cpu" and numba_available()
    if compiled:
        return albedo_smoothness_compiled(a, neighbours, CHROMA_SIGMA)
    a_nb = gather_rows(a, neighbours)  # [N,k,3]; not a[neighbours], whose backward is not bit-reproducible
    with torch.no_grad():
        c = a.detach().clamp_min(1e-4)
        chroma = c / c.sum(-1, keepdim=True)
        c_nb = gather_rows(chroma, neighbours)
        w = torch.exp(-((chroma[:, None] - c_nb) ** 2).sum(-1) / CHROMA_SIGMA**2)  # [N,k]
    return (w[..., None] * (a[:, None] - a_nb).abs()).mean()
