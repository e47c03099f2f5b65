"""Walking on triangles: move embedded points by a barycentric step across faces.

All points move in parallel (vectorized torch, CPU or CUDA); the Python loop runs
only over crossing rounds, each on the points that are still moving. Per round a
point either ends inside its face or leaves through the edge its segment hits
first, enters the neighbour across that edge and carries the remaining step:

- ``paper``: Algorithm 1 of SplattingAvatar. The remainder is re-expressed in
  barycentric coordinates as if both triangles were halves of one parallelogram
  (two right triangles on a shared hypotenuse): with exit through the edge
  opposite corner ``i``, the rates become ``(δ_j + δ_i, δ_j' + δ_i, -δ_i)`` for the
  shared corners and the neighbour's opposite corner. Shape-agnostic, as in the paper.
- ``unfold``: geometrically exact. The remaining 3D displacement is rotated about
  the shared edge into the neighbour's plane, so on a flat mesh the walk follows
  the straight 3D segment whatever the triangulation.

A point stops on the edge at boundary edges, non-manifold edges, edges of
degenerate faces, and after ``max_crossings`` crossings. Outputs are always a
valid face and barycentrics in [0, 1] summing to 1.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from meshsplat._checks import check_same_device, check_tensor
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import degenerate_faces, face_corners, safe_normalize
from meshsplat.mesh.tri_mesh import TriMesh

__all__ = ["WalkResult", "walk_on_triangles", "WALK_MODES"]

WALK_MODES = ("paper", "unfold")


class WalkResult(NamedTuple):
    face: torch.Tensor  # [N] long
    uv: torch.Tensor  # [N,2]
    changed: torch.Tensor  # [N] bool, face differs from the start face


def _clamp_bary_t(b: torch.Tensor) -> torch.Tensor:
    """Barycentrics ``[3, n]`` clamped to [0, 1] and renormalized to sum 1."""
    b = b.clamp(0.0, 1.0)
    return b.div_(b.sum(0).clamp_min_(1e-30))


def _tables(mesh: TriMesh, verts: torch.Tensor, dtype: torch.dtype, mode: str) -> dict:
    """Per half-edge ``h = 3*f + j`` tables, cached on the mesh per (verts version, dtype, mode).

    adj [3F]: neighbour face (-1 = wall: boundary, non-manifold, degenerate face on either side);
    src_t [3,3F]: for each corner of the neighbour, the corner of f it takes its weight from
    (the neighbour's far corner reads f's exit coordinate, which is 0);
    allow_t [3,3F]: 0 at the neighbour's far corner (no exit back through the entry edge), else 1;
    rate_map_t [9,3F]: row-major 3x3 linear map of the remaining barycentric rates of f into
    the neighbour (paper re-expression or unfolding).
    """
    key = ("walk", mode, str(verts.device), dtype, verts.data_ptr(), verts._version, tuple(verts.shape))
    cache = mesh.__dict__.setdefault("_walk_cache", {})
    if key in cache:
        return cache[key]
    cache.clear()
    dev = verts.device
    faces = mesh._on("faces", dev)
    nf = faces.shape[0]
    adj = mesh._on("face_adj", dev)
    k = mesh._on("adj_local", dev).clamp_min(0)
    deg = degenerate_faces(verts, faces)
    wall = (adj < 0) | deg.unsqueeze(1) | deg[adj.clamp_min(0)]
    adj = torch.where(wall, torch.full_like(adj, -1), adj)
    g = adj.clamp_min(0)
    j = torch.arange(3, device=dev).expand(nf, 3)
    j1, i = (j + 1) % 3, (j + 2) % 3
    k1, k2 = (k + 1) % 3, (k + 2) % 3
    same = faces[g, k] == faces  # orientation of the shared edge
    dst_j, dst_j1 = torch.where(same, k, k1), torch.where(same, k1, k)
    src = torch.empty(nf, 3, 3, dtype=torch.long, device=dev)
    src.scatter_(2, dst_j.unsqueeze(2), j.unsqueeze(2).contiguous())
    src.scatter_(2, dst_j1.unsqueeze(2), j1.unsqueeze(2))
    src.scatter_(2, k2.unsqueeze(2), i.unsqueeze(2))
    if mode == "paper":
        m = torch.zeros(nf, 3, 3, 3, dtype=dtype, device=dev)  # [F, j, row (g corner), col (f corner)]
        one = torch.ones(nf, 3, 1, 1, dtype=dtype, device=dev)
        for row, col, val in ((dst_j, j, 1), (dst_j1, j1, 1), (dst_j, i, 1), (dst_j1, i, 1), (k2, i, -1)):
            flat = (row * 3 + col).reshape(nf, 3, 1)
            m.view(nf, 3, 9).scatter_add_(2, flat, (val * one).reshape(nf, 3, 1))
    else:
        v = verts.detach().to(dtype)
        p = torch.stack(face_corners(v, faces), dim=1)  # [F, corner, xyz]
        nrm = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
        n2 = (nrm * nrm).sum(-1, keepdim=True).clamp_min(torch.finfo(dtype).tiny)
        opp = p[:, [2, 0, 1]] - p[:, [1, 2, 0]]  # edge opposite corner c
        grad = torch.linalg.cross(nrm.unsqueeze(1).expand_as(opp), opp, dim=-1) / n2.unsqueeze(1)
        grad = torch.where(deg[:, None, None], torch.zeros_like(grad), grad)  # [F, corner, xyz]
        e = safe_normalize(p[:, [1, 2, 0]] - p)  # local edge j direction
        pin = safe_normalize(grad[:, [2, 0, 1]])  # inward normal of edge j
        pin_g = pin[g, k]  # [F,3,xyz]
        rot = e.unsqueeze(-1) * e.unsqueeze(-2) - pin_g.unsqueeze(-1) * pin.unsqueeze(-2)  # [F,3,3,3]
        # rates in f -> 3D (sum_c rate_c p_c) -> rotate about the edge -> rates in g
        m = grad[g] @ rot @ p.transpose(-1, -2).unsqueeze(1)
    m = torch.where(wall[..., None, None], torch.zeros_like(m), m)
    allow = torch.ones(nf, 3, 3, dtype=dtype, device=dev)
    allow.scatter_(2, k2.unsqueeze(2), 0.0)
    # corner-major copies for the walk: [3, 3F] / [9, 3F]
    out = {
        "adj": adj.reshape(-1),
        "src_t": src.reshape(-1, 3).t().contiguous(),
        "allow_t": allow.reshape(-1, 3).t().contiguous(),
        "rate_map_t": m.reshape(-1, 9).t().contiguous(),
        "deg": deg,
        "any_deg": bool(deg.any()),
    }
    cache[key] = out
    return out


def walk_on_triangles(
    mesh: TriMesh,
    verts: torch.Tensor,
    face: torch.Tensor,
    uv: torch.Tensor,
    step: torch.Tensor,
    mode: str = "paper",
    max_crossings: int = 64,
) -> WalkResult:
    """Move each point ``(face [N], uv [N,2])`` by ``step [N,2]`` = (du, dv) in its start face.

    verts [V,3] gives the geometry (``unfold`` uses it; ``paper`` only uses it to find
    degenerate faces). Returns :class:`WalkResult` with face [N], uv [N,2] in uv's dtype,
    changed [N] bool.
    """
    if not isinstance(mesh, TriMesh):
        raise MeshsplatError(f"mesh: expected a TriMesh, got {type(mesh).__name__}")
    if mode not in WALK_MODES:
        raise MeshsplatError(f"mode: expected one of {WALK_MODES}, got {mode!r}")
    if int(max_crossings) < 0:
        raise MeshsplatError(f"max_crossings: expected >= 0, got {max_crossings}")
    dims: dict[str, int] = {}
    check_tensor("verts", verts, "V,3", {"V": mesh.num_vertices}, dtype="float", finite=True)
    check_tensor("face", face, "N", dims, dtype="int")
    check_tensor("uv", uv, "N,2", dims, dtype="float", finite=True)
    check_tensor("step", step, "N,2", dims, dtype="float", finite=True)
    dev = check_same_device(verts=verts, face=face, uv=uv, step=step)
    if face.numel() and (int(face.min()) < 0 or int(face.max()) >= mesh.num_faces):
        raise MeshsplatError(
            f"face: indices must lie in [0, {mesh.num_faces}), got [{int(face.min())}, {int(face.max())}]"
        )

    with torch.no_grad():
        return _walk(mesh, verts, face.long(), uv.detach(), step.detach().to(uv.dtype), mode, int(max_crossings), dev)


def _walk(
    mesh: TriMesh,
    verts: torch.Tensor,
    face0: torch.Tensor,
    uv: torch.Tensor,
    step: torch.Tensor,
    mode: str,
    max_crossings: int,
    dev: torch.device,
) -> WalkResult:
    """Rounds over the moving points, corner-major ``[3, n]`` layout (contiguous per corner).

    Branch-free arithmetic replaces masks where torch's CPU kernels are slow on random
    masks (``where``, ``min`` with indices, bool casts); one compaction per round.
    """
    dtype = uv.dtype
    tb = _tables(mesh, verts, dtype, mode)
    adj, src_t, allow_t, map_t = tb["adj"], tb["src_t"], tb["allow_t"], tb["rate_map_t"]
    tol = torch.finfo(dtype).eps ** 0.75  # relative: grazing rates below this count as zero
    u, v = uv.unbind(1)
    b = _clamp_bary_t(torch.stack([u, v, 1.0 - (u + v)]))  # [3, N]
    du, dv = step.unbind(1)
    r = torch.stack([du, dv, -(du + dv)])  # barycentric rates [3, N]
    if mode == "unfold" and tb["any_deg"]:  # the 3D step is undefined on a degenerate face: it does not move
        r = r.masked_fill(tb["deg"][face0].unsqueeze(0), 0.0)
    f, idx, allow = face0, None, None
    out_face, out_b = face0, b
    for rnd in range(max_crossings + 1):
        # candidate exit corners: rate clearly negative (and not the corner we entered opposite to)
        neg = (r.abs().amax(0) * -tol - r).sign_().clamp_min_(0.0)  # 1.0 where r < -tol*max|r|
        if allow is not None:
            neg.mul_(allow)
        other = 1.0 - neg
        # t_c = b_c / -r_c for candidates, b_c + 2 >= 2 (never an exit before t = 1) otherwise
        t3 = b.add(other, alpha=2.0).div_(torch.addcmul(other, neg, r, value=-1.0))
        t = t3.amin(0)
        cross = t < 1.0
        first = (t - t3).sign_().add_(1.0)  # 1.0 at the minimum
        first[1].mul_(1.0 - first[0])  # ties: first index wins
        first[2] = 1.0 - first[0] - first[1]
        b_end = torch.addcmul(b, r, t.clamp_max(1.0))  # inside: b + r; else exit point
        b_end.mul_(1.0 - first * cross.to(dtype))  # exit coordinate := 0
        b_end = _clamp_bary_t(b_end)
        h = f * 3 + (first[0] + 2.0 * first[1]).long()  # exit half-edge (edge (i+1)%3)
        nb = adj.index_select(0, h)
        keep = None if rnd == max_crossings else torch.nonzero(cross & (nb >= 0)).squeeze(1)
        n = f.shape[0]
        if keep is None or keep.numel() < n or n == 0:  # someone stops here: record all (movers are overwritten later)
            if idx is None:
                out_face, out_b = face0.clone(), b_end
            else:
                out_face.index_copy_(0, idx, f)
                out_b.index_copy_(1, idx, b_end)
            if keep is None or keep.numel() == 0:
                break
            idx = keep if idx is None else idx.index_select(0, keep)
            h, f = h.index_select(0, keep), nb.index_select(0, keep)
            r, t, b_end = r.index_select(1, keep), t.index_select(0, keep), b_end.index_select(1, keep)
        else:  # everyone crosses: no compaction
            f = nb
            if idx is None:
                idx, out_face, out_b = torch.arange(n, device=dev), face0.clone(), b_end
        m = map_t.index_select(1, h).view(3, 3, -1)  # [row, col, n]
        r = (m * (r * (1.0 - t)).unsqueeze(0)).sum(1)  # remaining rates, re-expressed
        b = b_end.gather(0, src_t.index_select(1, h))
        allow = allow_t.index_select(1, h)
    return WalkResult(out_face, out_b[:2].t().contiguous(), out_face != face0)
