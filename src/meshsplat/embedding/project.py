"""Project 3D points onto the Phong surface of a mesh: find (face, uv, d) with
``P(face, uv) + d * n(face, uv) ≈ x`` (least squares), as used by densify-split.

1. Candidates: the ``k`` faces with the nearest centroids (scipy cKDTree), scored by
   exact point-triangle distance, chunked so memory stays bounded.
2. From the best ``n_starts`` candidates, a few damped Gauss-Newton steps on (u, v, d);
   when uv leaves the triangle the step is walked across faces (``unfold`` walk).
3. The start with the smallest residual wins.
"""

from __future__ import annotations

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat.embedding.barycentric import barycentric_weights
from meshsplat.embedding.walk import walk_on_triangles
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import face_corners, safe_normalize, vertex_normals
from meshsplat.mesh.tri_mesh import TriMesh

__all__ = ["project_to_surface", "closest_point_on_triangles"]


def _seg_closest(x: torch.Tensor, p: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest point parameter s in [0,1] on segments p->q, and squared distance."""
    e = q - p
    s = ((x - p) * e).sum(-1) / (e * e).sum(-1).clamp_min(1e-300)
    s = s.clamp(0.0, 1.0)
    diff = p + s.unsqueeze(-1) * e - x
    return s, (diff * diff).sum(-1)


def closest_point_on_triangles(
    x: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact closest point of ``x [...,3]`` on triangles ``(a, b, c) [...,3]``.

    Returns ``(dist2 [...], w [...,3])`` with barycentric weights of a, b, c.
    Works for degenerate triangles (falls back to the edges).
    """
    e0, e1, xa = b - a, c - a, x - a
    d00, d01, d11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
    d20, d21 = (xa * e0).sum(-1), (xa * e1).sum(-1)
    den = d00 * d11 - d01 * d01
    ok = den > 1e-12 * d00 * d11
    den = torch.where(ok, den, torch.ones_like(den))
    wb = (d11 * d20 - d01 * d21) / den
    wc = (d00 * d21 - d01 * d20) / den
    wa = 1.0 - wb - wc
    inside = ok & (wa >= 0) & (wb >= 0) & (wc >= 0)
    proj = wa.unsqueeze(-1) * a + wb.unsqueeze(-1) * b + wc.unsqueeze(-1) * c
    dplane = ((proj - x) ** 2).sum(-1)
    s_ab, d_ab = _seg_closest(x, a, b)
    s_bc, d_bc = _seg_closest(x, b, c)
    s_ca, d_ca = _seg_closest(x, c, a)
    z = torch.zeros_like(s_ab)
    cands_d = torch.stack([torch.where(inside, dplane, torch.full_like(dplane, float("inf"))), d_ab, d_bc, d_ca], -1)
    cands_w = torch.stack(
        [
            torch.stack([wa, wb, wc], -1),
            torch.stack([1 - s_ab, s_ab, z], -1),
            torch.stack([z, 1 - s_bc, s_bc], -1),
            torch.stack([s_ca, z, 1 - s_ca], -1),
        ],
        -2,
    )
    best = cands_d.argmin(-1)
    dist2 = torch.gather(cands_d, -1, best.unsqueeze(-1)).squeeze(-1)
    w = torch.gather(cands_w, -2, best[..., None, None].expand(best.shape + (1, 3))).squeeze(-2)
    return dist2, w


def _candidates(
    points: torch.Tensor, verts: torch.Tensor, faces: torch.Tensor, k: int, n_starts: int, chunk: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Best ``n_starts`` faces per point (by exact distance among the k nearest centroids)."""
    from scipy.spatial import cKDTree

    a, b, c = face_corners(verts, faces)
    cent = ((a + b + c) / 3.0).cpu().numpy()
    tree = cKDTree(cent)
    k = min(k, faces.shape[0])
    n_starts = min(n_starts, k)
    pts_np = points.cpu().numpy()
    out_f, out_w = [], []
    for s in range(0, points.shape[0], chunk):
        _, cand = tree.query(pts_np[s : s + chunk], k=k)
        cand = torch.as_tensor(np.asarray(cand).reshape(-1, k), device=points.device, dtype=torch.long)
        x = points[s : s + chunk].unsqueeze(1)
        d2, w = closest_point_on_triangles(x, a[cand], b[cand], c[cand])
        order = d2.argsort(-1)[:, :n_starts]
        out_f.append(torch.gather(cand, 1, order))
        out_w.append(torch.gather(w, 1, order.unsqueeze(-1).expand(-1, -1, 3)))
    return torch.cat(out_f), torch.cat(out_w)


def _residual(
    verts: torch.Tensor,
    vn: torch.Tensor,
    faces: torch.Tensor,
    f: torch.Tensor,
    uv: torch.Tensor,
    d: torch.Tensor,
    x: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    fc = faces[f]
    w = barycentric_weights(uv).unsqueeze(-1)
    pv, nv = verts[fc], vn[fc]  # [M,3,3]
    p = (w * pv).sum(1)
    nint = (w * nv).sum(1)
    n = safe_normalize(nint)
    return p + d.unsqueeze(-1) * n - x, p, pv, nv, nint, n


def project_to_surface(
    mesh: TriMesh,
    verts: torch.Tensor,
    points: torch.Tensor,
    k: int = 8,
    iters: int = 10,
    n_starts: int = 2,
    chunk: int = 32768,
    normal_weighting: str = "area",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Embed ``points [M,3]`` on the mesh posed by ``verts [V,3]``: ``(face [M], uv [M,2], d [M])``.

    The normals are ``vertex_normals(verts, faces, normal_weighting)``, as in ``MeshPose``,
    so ``embed(MeshPose.from_vertices(mesh, verts), face, uv, d)`` reproduces the points.
    uv and d come back in points' dtype; internal arithmetic is float64.
    """
    if not isinstance(mesh, TriMesh):
        raise MeshsplatError(f"mesh: expected a TriMesh, got {type(mesh).__name__}")
    check_tensor("verts", verts, "V,3", {"V": mesh.num_vertices}, dtype="float", finite=True)
    check_tensor("points", points, "M,3", dtype="float", finite=True)
    if k < 1 or n_starts < 1 or chunk < 1 or iters < 0:
        raise MeshsplatError("project_to_surface: k, n_starts and chunk must be >= 1 and iters >= 0")
    out_dtype = points.dtype
    dev = points.device
    m = points.shape[0]
    if m == 0:
        return (torch.zeros(0, dtype=torch.long, device=dev), points.new_zeros(0, 2), points.new_zeros(0))
    with torch.no_grad():
        v = verts.detach().to(dev, torch.float64)
        x = points.detach().to(torch.float64)
        faces = mesh._on("faces", dev)
        vn = vertex_normals(v, faces, normal_weighting)
        cand_f, cand_w = _candidates(x, v, faces, k, n_starts, chunk)
        s = cand_f.shape[1]
        f = cand_f.reshape(-1)
        uv = cand_w.reshape(-1, 3)[:, :2].contiguous()
        xs = x.repeat_interleave(s, 0)
        d = torch.zeros(f.shape[0], dtype=torch.float64, device=dev)
        r, *_, n = _residual(v, vn, faces, f, uv, d, xs)
        d = -(r * n).sum(-1)  # initial displacement along n
        eye = torch.eye(3, dtype=torch.float64, device=dev)
        for _ in range(iters):
            r, _p, pv, nv, nint, n = _residual(v, vn, faces, f, uv, d, xs)
            proj = (eye - n.unsqueeze(-1) * n.unsqueeze(-2)) / nint.norm(dim=-1).clamp_min(1e-12)[:, None, None]
            dn_du = (proj @ (nv[:, 0] - nv[:, 2]).unsqueeze(-1)).squeeze(-1)
            dn_dv = (proj @ (nv[:, 1] - nv[:, 2]).unsqueeze(-1)).squeeze(-1)
            ju = pv[:, 0] - pv[:, 2] + d.unsqueeze(-1) * dn_du
            jv = pv[:, 1] - pv[:, 2] + d.unsqueeze(-1) * dn_dv
            jac = torch.stack([ju, jv, n], -1)  # [M,3,3]
            jtj = jac.transpose(-1, -2) @ jac
            lam = 1e-9 * jtj.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-30)
            delta = torch.linalg.solve(
                jtj + lam[:, None, None] * eye, -(jac.transpose(-1, -2) @ r.unsqueeze(-1))
            ).squeeze(-1)
            delta = torch.nan_to_num(delta).clamp(-4.0, 4.0)
            if bool(delta[:, :2].abs().max() < 1e-13):
                d = d + delta[:, 2]
                break
            res = walk_on_triangles(mesh, v, f, uv, delta[:, :2].contiguous(), mode="unfold", max_crossings=16)
            f, uv = res.face, res.uv
            d = d + delta[:, 2]
        r, *_ = _residual(v, vn, faces, f, uv, d, xs)
        err = (r * r).sum(-1).reshape(m, s)
        best = err.argmin(1)
        pick = torch.arange(m, device=dev) * s + best
        return f[pick], uv[pick].to(out_dtype), d[pick].to(out_dtype)
