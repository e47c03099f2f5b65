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
from meshsplat.mesh.trimesh import TriMesh

__all__ = ["WalkResult", "walk_on_triangles", "WALK_MODES"]

WALK_MODES = ("paper", "unfold")


class WalkResult(NamedTuple):
    face: torch.Tensor     # [N] long
    uv: torch.Tensor       # [N,2]
    changed: torch.Tensor  # [N] bool, face differs from the start face


def _clamp_bary(b: torch.Tensor) -> torch.Tensor:
    b = b.clamp(0.0, 1.0)
    return b / b.sum(-1, keepdim=True).clamp_min(1e-30)


def _tables(mesh: TriMesh, verts: torch.Tensor, dtype: torch.dtype, mode: str) -> dict:
    """Per half-edge ``h = 3*f + j`` tables, cached on the mesh per (verts version, dtype, mode).

    adj [3F]: neighbour face (-1 = wall: boundary, non-manifold, degenerate face on either side);
    src [3F,3]: for each corner of the neighbour, the corner of f it takes its weight from
    (the neighbour's far corner reads f's exit coordinate, which is 0);
    entry [3F]: the neighbour's far corner; rate_map [3F,3,3]: linear map of the remaining
    barycentric rates of f into the neighbour (paper re-expression or unfolding).
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
    same = faces[g, k] == faces                                   # orientation of the shared edge
    dst_j, dst_j1 = torch.where(same, k, k1), torch.where(same, k1, k)
    src = torch.empty(nf, 3, 3, dtype=torch.long, device=dev)
    src.scatter_(2, dst_j.unsqueeze(2), j.unsqueeze(2).contiguous())
    src.scatter_(2, dst_j1.unsqueeze(2), j1.unsqueeze(2))
    src.scatter_(2, k2.unsqueeze(2), i.unsqueeze(2))
    if mode == "paper":
        m = torch.zeros(nf, 3, 3, 3, dtype=dtype, device=dev)    # [F, j, row (g corner), col (f corner)]
        one = torch.ones(nf, 3, 1, 1, dtype=dtype, device=dev)
        for row, col, val in ((dst_j, j, 1), (dst_j1, j1, 1), (dst_j, i, 1), (dst_j1, i, 1), (k2, i, -1)):
            flat = (row * 3 + col).reshape(nf, 3, 1)
            m.view(nf, 3, 9).scatter_add_(2, flat, (val * one).reshape(nf, 3, 1))
    else:
        v = verts.detach().to(dtype)
        p = torch.stack(face_corners(v, faces), dim=1)                             # [F, corner, xyz]
        nrm = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
        n2 = (nrm * nrm).sum(-1, keepdim=True).clamp_min(torch.finfo(dtype).tiny)
        opp = p[:, [2, 0, 1]] - p[:, [1, 2, 0]]                                      # edge opposite corner c
        grad = torch.linalg.cross(nrm.unsqueeze(1).expand_as(opp), opp, dim=-1) / n2.unsqueeze(1)
        grad = torch.where(deg[:, None, None], torch.zeros_like(grad), grad)         # [F, corner, xyz]
        e = safe_normalize(p[:, [1, 2, 0]] - p)                                      # local edge j direction
        pin = safe_normalize(grad[:, [2, 0, 1]])                                     # inward normal of edge j
        pin_g = pin[g, k]                                                            # [F,3,xyz]
        rot = e.unsqueeze(-1) * e.unsqueeze(-2) - pin_g.unsqueeze(-1) * pin.unsqueeze(-2)   # [F,3,3,3]
        # rates in f -> 3D (sum_c rate_c p_c) -> rotate about the edge -> rates in g
        m = grad[g] @ rot @ p.transpose(-1, -2).unsqueeze(1)
    m = torch.where(wall[..., None, None], torch.zeros_like(m), m)
    out = {"adj": adj.reshape(-1), "src": src.reshape(-1, 3), "entry": k2.reshape(-1),
           "rate_map": m.reshape(-1, 3, 3), "deg": deg}
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
        raise MeshsplatError(f"face: indices must lie in [0, {mesh.num_faces}), got [{int(face.min())}, {int(face.max())}]")

    with torch.no_grad():
        return _walk(mesh, verts, face.long(), uv.detach(), step.detach().to(uv.dtype), mode, int(max_crossings), dev)


def _walk(mesh, verts, face0, uv, step, mode, max_crossings, dev) -> WalkResult:
    dtype = uv.dtype
    tb = _tables(mesh, verts, dtype, mode)
    adj, src, entry_t, rate_map = tb["adj"], tb["src"], tb["entry"], tb["rate_map"]
    b0 = _clamp_bary(torch.cat([uv, 1.0 - uv.sum(-1, keepdim=True)], -1))
    out_face, out_b = face0.clone(), b0.clone()
    tol = torch.finfo(dtype).eps ** 0.75  # relative: grazing rates below this count as zero
    inf = torch.tensor(float("inf"), dtype=dtype, device=dev)
    nxt = torch.tensor([1, 2, 0], device=dev)
    ar3 = torch.arange(3, device=dev)

    rate_all = torch.cat([step, -step.sum(-1, keepdim=True)], -1)                # barycentric rates
    if mode == "unfold":  # the 3D step is undefined on a degenerate face: it does not move
        rate_all = rate_all.masked_fill(tb["deg"][face0].unsqueeze(1), 0.0)
    idx = torch.nonzero(rate_all.abs().amax(-1) > 0).squeeze(1)
    f, b, rate = face0.index_select(0, idx), b0.index_select(0, idx), rate_all.index_select(0, idx)
    entry = torch.full_like(f, -1)

    def take(i, *xs):
        return [x.index_select(0, i) for x in xs]

    for rnd in range(max_crossings + 1):
        if idx.numel() == 0:
            break
        neg = (rate < -tol * rate.abs().amax(-1, keepdim=True)) & (ar3 != entry.unsqueeze(1))
        t, i_opp = torch.where(neg, b / -rate, inf).min(-1)
        inside = t >= 1.0
        ins = torch.nonzero(inside).squeeze(1)
        if ins.numel():
            sel, f_in, b_in, r_in = take(ins, idx, f, b, rate)
            out_face.index_copy_(0, sel, f_in)
            out_b.index_copy_(0, sel, _clamp_bary(b_in + r_in))
        if ins.numel() == idx.numel():
            break
        cr = torch.nonzero(~inside).squeeze(1)
        idx, f, b, rate, t, i_opp = take(cr, idx, f, b, rate, t, i_opp)
        b_exit = b + t.unsqueeze(1) * rate
        b_exit = _clamp_bary(b_exit.scatter(1, i_opp.unsqueeze(1), 0.0))
        h = f * 3 + nxt.index_select(0, i_opp)                                  # exit half-edge
        nb = adj.index_select(0, h)
        stop = nb < 0 if rnd < max_crossings else torch.ones_like(nb, dtype=torch.bool)
        st = torch.nonzero(stop).squeeze(1)
        if st.numel():
            sel, f_st, b_st = take(st, idx, f, b_exit)
            out_face.index_copy_(0, sel, f_st)
            out_b.index_copy_(0, sel, b_st)
        if st.numel() == idx.numel():
            break
        go = torch.nonzero(~stop).squeeze(1)
        idx, h, nb, b_exit, rate, t = take(go, idx, h, nb, b_exit, rate, t)
        rate = torch.bmm(rate_map.index_select(0, h), ((1.0 - t).unsqueeze(1) * rate).unsqueeze(-1)).squeeze(-1)
        b = torch.gather(b_exit, 1, src.index_select(0, h))
        f, entry = nb, entry_t.index_select(0, h)

    out_b = _clamp_bary(out_b)
    return WalkResult(out_face, out_b[:, :2].contiguous(), out_face != face0)
