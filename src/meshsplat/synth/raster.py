"""Vectorized triangle rasterizer (PyTorch, CPU or GPU) with a z-buffer and perspective-correct
barycentrics, plus texture sampling and Lambert shading for the ground-truth generator.

Candidates are (triangle, pixel) pairs inside each triangle's pixel bounding box, processed in
chunks; the nearest surface per pixel is chosen with ``scatter_reduce(amin)`` on depth. Pixel
centres sit at ``+0.5`` (OpenCV pinhole ``K``, camera looks along +z). Triangles with a vertex
closer than ``near`` are dropped (no clipping); both faces of a triangle are drawn.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meshsplat._checks import check_tensor
from meshsplat.errors import MeshsplatError

__all__ = ["Fragments", "rasterize_triangles", "interpolate", "sample_texture", "vertex_normals", "lambert"]


@dataclass
class Fragments:
    """Per-pixel result: ``face [H,W]`` long (-1 = background), ``bary [H,W,3]`` perspective-correct
    weights of the face's corners (a, b, c), ``depth [H,W]`` camera z (inf = background)."""

    face: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        return self.face >= 0


def rasterize_triangles(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = 1e-3,
    chunk: int = 1 << 21,
) -> Fragments:
    """Rasterize ``verts_cam [V,3]`` (camera space, OpenCV axes) with ``faces [F,3]`` through ``K [3,3]``."""
    dims: dict[str, int] = {}
    check_tensor("verts_cam", verts_cam, "V,3", dims, dtype="float")
    check_tensor("faces", faces, "F,3", dtype="int")
    check_tensor("K", K, "3,3", dtype="float")
    if width <= 0 or height <= 0:
        raise MeshsplatError(f"width/height: expected positive, got {width}x{height}")
    dev = verts_cam.device
    v = verts_cam.float()
    z = v[:, 2]
    uvw = v @ K.to(v).T
    xy = uvw[:, :2] / uvw[:, 2:3].clamp_min(1e-12)
    f = faces.long()
    keep = (z[f] > near).all(1)
    tri = xy[f]  # [F, 3, 2]
    area = (tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1]) - (tri[:, 1, 1] - tri[:, 0, 1]) * (
        tri[:, 2, 0] - tri[:, 0, 0]
    )
    lo = torch.ceil(tri.amin(1) - 0.5)
    hi = torch.floor(tri.amax(1) - 0.5)
    lo = torch.maximum(lo, torch.zeros(2, device=dev))
    hi = torch.minimum(hi, torch.tensor([width - 1.0, height - 1.0], device=dev))
    keep &= (area.abs() > 1e-12) & (hi >= lo).all(1)
    ids = torch.nonzero(keep).squeeze(1)
    lo, hi = lo[ids].long(), hi[ids].long()
    bw = hi[:, 0] - lo[:, 0] + 1
    count = bw * (hi[:, 1] - lo[:, 1] + 1)

    keys, depths, fids, barys = [], [], [], []
    csum = torch.cumsum(count, 0)
    start = 0
    while start < ids.numel():
        base = int(csum[start - 1]) if start > 0 else 0
        stop = int(torch.searchsorted(csum, torch.tensor(base + chunk, device=dev), right=True))
        stop = max(stop, start + 1)
        sl = slice(start, stop)
        cnt = count[sl]
        local = torch.repeat_interleave(torch.arange(stop - start, device=dev), cnt)
        off = torch.arange(int(cnt.sum()), device=dev) - (torch.cumsum(cnt, 0) - cnt)[local]
        t = ids[sl][local]
        px = lo[sl, 0][local] + off % bw[sl][local]
        py = lo[sl, 1][local] + torch.div(off, bw[sl][local], rounding_mode="floor")
        p = torch.stack([px + 0.5, py + 0.5], 1).float()
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        w0 = (b[:, 0] - p[:, 0]) * (c[:, 1] - p[:, 1]) - (b[:, 1] - p[:, 1]) * (c[:, 0] - p[:, 0])
        w1 = (c[:, 0] - p[:, 0]) * (a[:, 1] - p[:, 1]) - (c[:, 1] - p[:, 1]) * (a[:, 0] - p[:, 0])
        w2 = (a[:, 0] - p[:, 0]) * (b[:, 1] - p[:, 1]) - (a[:, 1] - p[:, 1]) * (b[:, 0] - p[:, 0])
        bs = torch.stack([w0, w1, w2], 1) / area[t, None]
        inside = (bs >= 0).all(1)
        t, bs = t[inside], bs[inside]
        key = py[inside] * width + px[inside]
        lz = bs / z[f[t]]
        s = lz.sum(1)
        keys.append(key)
        depths.append(1.0 / s)
        fids.append(t)
        barys.append(lz / s[:, None])
        start = stop

    npx = width * height
    face = torch.full((npx,), -1, dtype=torch.long, device=dev)
    depth = torch.full((npx,), float("inf"), device=dev)
    bary = torch.zeros(npx, 3, device=dev)
    if keys:
        key, dep, fid, bar = torch.cat(keys), torch.cat(depths), torch.cat(fids), torch.cat(barys)
        if key.numel():
            depth.scatter_reduce_(0, key, dep, reduce="amin")
            win = dep <= depth[key]
            cand = torch.nonzero(win).squeeze(1)
            best = torch.full((npx,), -1, dtype=torch.long, device=dev)
            best.scatter_reduce_(0, key[cand], cand, reduce="amax")
            hit = best >= 0
            face[hit] = fid[best[hit]]
            bary[hit] = bar[best[hit]]
    return Fragments(face.view(height, width), bary.view(height, width, 3), depth.view(height, width))


def interpolate(frags: Fragments, faces: torch.Tensor, attr: torch.Tensor) -> torch.Tensor:
    """Interpolate per-vertex ``attr [V,D]`` at covered pixels: ``[H,W,D]`` (zeros on background)."""
    h, w = frags.face.shape
    out = torch.zeros(h, w, attr.shape[1], dtype=attr.dtype, device=attr.device)
    m = frags.mask
    corners = attr[faces[frags.face[m]]]  # [P, 3, D]
    out[m] = (frags.bary[m].to(attr.dtype)[..., None] * corners).sum(1)
    return out


def sample_texture(tex: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of ``tex [Ht,Wt,C]`` at glTF UVs ``uv [P,2]`` (origin top-left, repeat wrap)."""
    ht, wt = tex.shape[:2]
    x = uv[:, 0] * wt - 0.5
    y = uv[:, 1] * ht - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.long(), y0.long()
    xa, xb = x0 % wt, (x0 + 1) % wt
    ya, yb = y0 % ht, (y0 + 1) % ht
    return (1 - fy) * ((1 - fx) * tex[ya, xa] + fx * tex[ya, xb]) + fy * ((1 - fx) * tex[yb, xa] + fx * tex[yb, xb])


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor, weld: torch.Tensor | None = None) -> torch.Tensor:
    """Area-weighted unit vertex normals ``[V,3]``; ``weld [V]`` (group id per vertex) shares normals
    across duplicated seam vertices."""
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    fn = torch.linalg.cross(v1 - v0, v2 - v0)
    ids = faces if weld is None else weld[faces]
    size = verts.shape[0] if weld is None else int(weld.max()) + 1
    n = torch.zeros(size, 3, dtype=verts.dtype, device=verts.device)
    n.index_add_(0, ids.reshape(-1), fn.repeat_interleave(3, 0))
    if weld is not None:
        n = n[weld]
    return n / n.norm(dim=1, keepdim=True).clamp_min(1e-12)


def lambert(
    albedo: torch.Tensor,
    normal: torch.Tensor,
    view_pos: torch.Tensor,
    light_dir: torch.Tensor,
    ambient: float = 0.4,
    diffuse: float = 0.6,
) -> torch.Tensor:
    """Lambert shading ``[P,3]``: normals are flipped to face the viewer (points ``view_pos [P,3]`` in
    camera space); ``light_dir [3]`` points from the surface towards the light, in camera space."""
    n = normal / normal.norm(dim=1, keepdim=True).clamp_min(1e-12)
    n = torch.where(((n * view_pos).sum(1, keepdim=True) > 0), -n, n)
    ndl = (n * light_dir).sum(1, keepdim=True).clamp_min(0)
    return (albedo * (ambient + diffuse * ndl)).clamp(0, 1)
