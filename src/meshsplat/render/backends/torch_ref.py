"""Pure-PyTorch Gaussian rasterizer (CPU or any device), gsplat 1.5.3 conventions.

Pipeline:
1. ``project_gaussians`` (autograd, O(C*N)).
2. Visible (camera, Gaussian) entries sorted by camera then depth.
3. Exact footprints: for every entry and pixel row, the x-range where
   ``opacity * exp(-sigma) >= 1/255`` (closed form, float64), i.e. "row spans".
   This is the opacity-aware 3-sigma ellipse, tighter than its bounding box.
4. Rows are grouped into bands holding at most ``pair_budget`` (pixel, entry)
   pairs, which bounds memory. Per band: expand spans into flat pairs, stable-sort
   by pixel (depth order is kept), evaluate alpha, per-pixel exclusive
   transmittance by a segmented cumulative sum of ``log(1 - alpha)`` (float64),
   drop pairs after T would reach 1e-4, scatter-add colours.
5. Backward (custom ``autograd.Function``, default): reuses the saved per-pair
   alpha, T, footprint offsets and gathered colours/conics, gets the "later splats"
   sums from one more segmented cumsum and scatters all per-Gaussian gradients with
   a single ``index_add_``. Measured on one CPU thread (10k Gaussians, 256 px):
   backward 1.4x and forward+backward 1.2x faster than letting autograd
   differentiate the same single-pass compositing (``grad_mode="autograd"``), whose
   backward walks ~30 P-sized nodes (gathers, where, cumsum, index_add).
   Where alpha is clamped at 0.999 the pair passes no gradient (as gsplat's kernel).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meshsplat.errors import MeshsplatError
from meshsplat.render._constants import (
    ALPHA_MAX,
    ALPHA_THRESHOLD,
    DEPTH_ALPHA_MIN,
    LOG_TRANSMITTANCE_MIN,
    MAX_EXTEND,
    PIXEL_CENTER,
    SPAN_MARGIN,
)
from meshsplat.render.projection import Projection, project_gaussians
from meshsplat.render.types import RenderOutput

__all__ = [
    "rasterize_torch",
    "sorted_entries",
    "finish_render",
    "render_output",
    "SortedEntries",
    "DEFAULT_PAIR_BUDGET",
    "DEFAULT_SAVED_PAIR_LIMIT",
]

DEFAULT_PAIR_BUDGET = 2_000_000  # (pixel, Gaussian) candidate pairs per band
DEFAULT_SAVED_PAIR_LIMIT = 16_000_000  # pairs kept for backward (~61 B each); later bands recompute


@dataclass
class _Plan:
    """No-grad geometry shared by forward and backward."""

    width: int
    height: int
    n_cams: int
    span_entry: torch.Tensor  # [S] entry index, spans ordered by (global row, depth)
    span_row: torch.Tensor  # [S] global row = cam * H + y
    span_x0: torch.Tensor  # [S]
    span_w: torch.Tensor  # [S] pixels in the span
    span_ptr: list  # band b uses spans [span_ptr[b], span_ptr[b+1])
    bands: list  # [(r0, r1)] global rows
    saved_pair_limit: int = DEFAULT_SAVED_PAIR_LIMIT


def _row_spans(m2: torch.Tensor, con: torch.Tensor, op: torch.Tensor, cam: torch.Tensor, W: int, H: int):
    """Per (entry, row) x-ranges of the alpha >= 1/255 ellipse (float64). Inputs detached."""
    dev = m2.device
    mx, my = m2.double().unbind(1)
    a, b, c = con.double().unbind(1)
    tau = torch.log(op.double() / ALPHA_THRESHOLD).clamp(0.0, 0.5 * MAX_EXTEND**2)
    det = (a * c - b * b).clamp_min(1e-300)
    ry = torch.sqrt(2.0 * tau * a / det)
    y0 = torch.ceil(my - ry - PIXEL_CENTER - SPAN_MARGIN).clamp(0, H)
    y1 = torch.floor(my + ry - PIXEL_CENTER + SPAN_MARGIN).clamp(-1, H - 1)
    nrows = (y1 - y0 + 1).clamp_min(0).long()
    total = int(nrows.sum())
    entry = torch.repeat_interleave(torch.arange(m2.shape[0], device=dev), nrows, output_size=total)
    first = (torch.cumsum(nrows, 0) - nrows).double()
    per = torch.stack([mx, my, a, b, 2.0 * a * tau, det, y0 - first, cam.double() * H], 1)
    mx, my, a, b, two_a_tau, det, y_off, row0 = torch.repeat_interleave(per, nrows, dim=0, output_size=total).unbind(1)
    y = y_off + torch.arange(total, device=dev, dtype=torch.float64)  # y0 + (i - first)
    dy = my - (y + PIXEL_CENTER)
    # 0.5 a dx^2 + b dy dx + 0.5 c dy^2 <= tau  ->  dx in [lo, hi]
    disc = (two_a_tau - det * dy * dy).clamp_min(0.0).sqrt()
    dx_lo = (-b * dy - disc) / a
    dx_hi = (-b * dy + disc) / a
    x0 = torch.ceil(mx - dx_hi - PIXEL_CENTER - SPAN_MARGIN).clamp(0, W)
    x1 = torch.floor(mx - dx_lo - PIXEL_CENTER + SPAN_MARGIN).clamp(-1, W - 1)
    w = x1 - x0 + 1
    keep = (w > 0).nonzero().squeeze(1)
    entry = entry.index_select(0, keep)
    row = (row0 + y).index_select(0, keep).long()
    x0, w = x0.index_select(0, keep).long(), w.index_select(0, keep).long()
    order = torch.sort(row, stable=True).indices  # entries are depth-ordered: stays so per row
    return entry[order], row[order], x0[order], w[order]


def _make_plan(m2, con, op, cam, W, H, C, budget) -> _Plan:
    entry, row, x0, w = _row_spans(m2, con, op, cam, W, H)
    n_rows = C * H
    per_row = torch.zeros(n_rows, dtype=torch.long, device=w.device).index_add_(0, row, w)
    cum_rows = torch.cumsum(per_row, 0).cpu()
    bands, r0, done = [], 0, 0
    while r0 < n_rows:
        r1 = int(torch.searchsorted(cum_rows, done + budget, right=True))
        r1 = min(max(r1, r0 + 1), n_rows)
        bands.append((r0, r1))
        done = int(cum_rows[r1 - 1])
        r0 = r1
    edges = torch.tensor([r for r, _ in bands] + [n_rows], dtype=torch.long)
    span_ptr = torch.searchsorted(row.cpu(), edges).tolist()
    return _Plan(W, H, C, entry, row, x0, w, span_ptr, bands)


def _band_pairs(plan: _Plan, b: int):
    """Sorted (pixel-in-band, entry) pairs of band b, depth order inside each pixel."""
    s0, s1 = plan.span_ptr[b], plan.span_ptr[b + 1]
    r0 = plan.bands[b][0]
    w = plan.span_w[s0:s1]
    dev = w.device
    total = int(w.sum()) if s1 > s0 else 0
    if total == 0:
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return empty, empty
    # pixel of the i-th pair = (row - r0) * W + x0 + (i - first pair of its span)
    base = (plan.span_row[s0:s1] - r0) * plan.width + plan.span_x0[s0:s1] - (torch.cumsum(w, 0) - w)
    key = torch.repeat_interleave(base.to(torch.int32), w, output_size=total)
    key += torch.arange(total, dtype=torch.int32, device=dev)
    entry = torch.repeat_interleave(plan.span_entry[s0:s1].to(torch.int32), w, output_size=total)
    pix, order = torch.sort(key, stable=True)  # int32 radix sort; stable keeps depth order
    return pix.long(), entry.index_select(0, order).long()


def _pixel_coords(plan: _Plan, b: int, pix: torch.Tensor, dtype):
    """Camera-local pixel-centre coordinates of band pixels (a band row lies in one camera)."""
    r0, r1 = plan.bands[b]
    dev = pix.device
    xs = torch.arange(plan.width, device=dev, dtype=dtype) + PIXEL_CENTER
    ys = torch.remainder(torch.arange(r0, r1, device=dev), plan.height).to(dtype) + PIXEL_CENTER
    px_tab = xs.repeat(r1 - r0)
    py_tab = ys.repeat_interleave(plan.width)
    return px_tab.index_select(0, pix), py_tab.index_select(0, pix)


def _seg_exclusive_prefix(vals: torch.Tensor, pix: torch.Tensor, npix: int):
    """Inclusive prefix sum (float64) of vals inside each pixel run (pairs sorted by pixel)."""
    counts = torch.bincount(pix, minlength=npix)
    if vals.shape[0] == 0:
        return vals.double(), counts
    csum = torch.cumsum(vals, 0, dtype=torch.float64)
    starts = (torch.cumsum(counts, 0) - counts).clamp_max(vals.shape[0] - 1)
    base = torch.where(counts > 0, csum[starts] - vals[starts].double(), torch.zeros_like(csum[starts]))
    return csum - base.index_select(0, pix), counts


def _band_bg(plan: _Plan, b: int, bg: torch.Tensor | None, D: int, dtype, dev):
    r0, r1 = plan.bands[b]
    if bg is None:
        return None
    cams = torch.div(torch.arange(r0, r1, device=dev), plan.height, rounding_mode="floor")
    return bg[cams][:, None, :].expand(r1 - r0, plan.width, D).reshape(-1, D)


def _band_forward(plan, b, params, colors_t, bg):
    """Composite band b. params [6,M] rows (mx, my, a, b, c, opacity), colors_t [D,M]."""
    r0, r1 = plan.bands[b]
    npix = (r1 - r0) * plan.width
    dtype, dev = params.dtype, params.device
    D = colors_t.shape[0]
    pix, entry = _band_pairs(plan, b)
    px, py = _pixel_coords(plan, b, pix, dtype)
    mx, my, ca, cb, cc, op = (params[k].index_select(0, entry) for k in range(6))
    dx, dy = mx - px, my - py
    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    vis = torch.exp(-sigma)
    raw = op * vis
    alpha = raw.clamp(max=ALPHA_MAX)
    ok = (alpha >= ALPHA_THRESHOLD) & (sigma >= 0)
    alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
    log1m = torch.log1p(-alpha)
    incl, _ = _seg_exclusive_prefix(log1m, pix, npix)
    keep = ok & (incl > LOG_TRANSMITTANCE_MIN)
    n_keep = int(keep.sum())
    if n_keep < 0.8 * keep.shape[0]:  # compact; otherwise dropped pairs just get alpha = 0
        idx = keep.nonzero().squeeze(1)
        pix, entry, alpha, vis, dx, dy, log1m, incl, raw, ca, cb, cc = (
            t.index_select(0, idx) for t in (pix, entry, alpha, vis, dx, dy, log1m, incl, raw, ca, cb, cc)
        )
    elif n_keep < keep.shape[0]:
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        log1m = torch.where(keep, log1m, torch.zeros_like(log1m))
    trans = torch.exp(incl - log1m).to(dtype)
    log_tf = torch.zeros(npix, dtype=torch.float64, device=dev).index_add_(0, pix, log1m.double())
    t_final = torch.exp(log_tf).to(dtype)
    weight = alpha * trans
    cp = colors_t.index_select(1, entry)  # [D, P]
    out = torch.zeros(D, npix, dtype=dtype, device=dev).index_add_(1, pix, cp * weight).t()
    bg_pix = _band_bg(plan, b, bg, D, dtype, dev)
    if bg_pix is not None:
        out = out + t_final[:, None] * bg_pix
    saved = (pix, entry, alpha, trans, vis, dx, dy, raw > ALPHA_MAX, t_final, cp, ca, cb, cc)
    return out, 1.0 - t_final, saved


def _band_backward(plan, b, saved, params, colors_t, bg, g_col, g_alpha, grad_acc, grad_bg):
    """Accumulate d(loss)/d(params, colors, bg) of band b into grad_acc [6+D, M] / grad_bg [C, D]."""
    pix, entry, alpha, trans, vis, dx, dy, clamped, t_final, cp, ca, cb, cc = saved
    r0, r1 = plan.bands[b]
    npix = (r1 - r0) * plan.width
    dtype, dev = params.dtype, params.device
    D = colors_t.shape[0]
    bg_pix = _band_bg(plan, b, bg, D, dtype, dev)
    extra = -g_alpha * t_final  # d(alpha_out)/d(alpha_i) = T_final / (1 - alpha_i)
    if bg_pix is not None:
        extra = extra + t_final * (bg_pix * g_col).sum(1)
        if grad_bg is not None:
            cams = torch.div(torch.arange(r0, r1, device=dev), plan.height, rounding_mode="floor")
            per_row = (t_final[:, None] * g_col).reshape(r1 - r0, plan.width, D).sum(1)
            grad_bg.index_add_(0, cams, per_row)
    if pix.shape[0] == 0:
        return
    gp = g_col.t().contiguous().index_select(1, pix)  # [D, P]
    cg = (gp * cp).sum(0)
    weight = alpha * trans
    wc = weight * cg
    incl, _ = _seg_exclusive_prefix(wc, pix, npix)
    seg_total = torch.zeros(npix, dtype=torch.float64, device=dev).index_add_(0, pix, wc.double())
    # later splats' colour (suffix) + background and alpha terms, per pair
    later = ((seg_total + extra.double()).index_select(0, pix) - incl).to(dtype)
    v_alpha = trans * cg - later / (1.0 - alpha)
    # no gradient for dropped pairs (alpha = 0) nor, as in gsplat, through the 0.999 clamp
    v_alpha = torch.where((alpha > 0) & ~clamped, v_alpha, torch.zeros_like(v_alpha))
    v_op = vis * v_alpha
    v_sigma = -alpha * v_alpha
    rows = torch.empty(6 + D, pix.shape[0], dtype=dtype, device=dev)
    rows[0] = v_sigma * (ca * dx + cb * dy)
    rows[1] = v_sigma * (cb * dx + cc * dy)
    rows[2] = 0.5 * v_sigma * dx * dx
    rows[3] = v_sigma * dx * dy
    rows[4] = 0.5 * v_sigma * dy * dy
    rows[5] = v_op
    rows[6:] = gp * weight
    grad_acc.index_add_(1, entry, rows)


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, bg, plan: _Plan):
        params = torch.cat([means2d.t(), conics.t(), opacities[None]], 0).contiguous()  # [6, M]
        colors_t = colors.t().contiguous()
        D = colors.shape[1]
        C, H, W = plan.n_cams, plan.height, plan.width
        out = torch.empty(C * H * W, D, dtype=colors.dtype, device=colors.device)
        alpha = torch.empty(C * H * W, dtype=colors.dtype, device=colors.device)
        saved_all, n_saved, n_pairs = [], 0, 0
        for b, (r0, r1) in enumerate(plan.bands):
            o, a, saved = _band_forward(plan, b, params, colors_t, bg)
            out[r0 * W : r1 * W] = o
            alpha[r0 * W : r1 * W] = a
            n = int(saved[0].shape[0])
            n_pairs += n
            keep = n_saved + n <= plan.saved_pair_limit
            n_saved += n if keep else 0
            saved_all.append(saved if keep else None)  # None: recomputed in backward
        ctx.plan, ctx.saved_all = plan, saved_all
        ctx.has_bg = bg is not None
        ctx.save_for_backward(params, colors_t, bg if bg is not None else torch.empty(0))
        ctx.n_pairs = n_pairs
        return out.reshape(C, H, W, D), alpha.reshape(C, H, W, 1)

    @staticmethod
    def backward(ctx, g_out, g_alpha):
        params, colors_t, bg = ctx.saved_tensors
        bg = bg if ctx.has_bg else None
        plan = ctx.plan
        W, D = plan.width, colors_t.shape[0]
        dtype, dev = colors_t.dtype, colors_t.device
        n_pix = plan.n_cams * plan.height * W
        zero = torch.zeros(1, dtype=dtype, device=dev)
        g_out = zero.expand(n_pix, D) if g_out is None else g_out.reshape(n_pix, D)
        g_alpha = zero.expand(n_pix) if g_alpha is None else g_alpha.reshape(n_pix)
        grad_acc = torch.zeros(6 + D, params.shape[1], dtype=dtype, device=dev)
        grad_bg = torch.zeros_like(bg) if (bg is not None and ctx.needs_input_grad[4]) else None
        for b, (r0, r1) in enumerate(plan.bands):
            saved = ctx.saved_all[b]
            if saved is None:
                saved = _band_forward(plan, b, params, colors_t, bg)[2]
            _band_backward(
                plan,
                b,
                saved,
                params,
                colors_t,
                bg,
                g_out[r0 * W : r1 * W],
                g_alpha[r0 * W : r1 * W],
                grad_acc,
                grad_bg,
            )
        return (grad_acc[0:2].t(), grad_acc[2:5].t(), grad_acc[5], grad_acc[6:].t(), grad_bg, None)


def _composite_autograd(means2d, conics, opacities, colors, bg, plan: _Plan):
    """The same single-pass compositing with differentiable ops only (for measurement/tests)."""
    params = torch.cat([means2d.t(), conics.t(), opacities[None]], 0)
    D = colors.shape[1]
    C, H, W = plan.n_cams, plan.height, plan.width
    outs, alphas = [], []
    for b in range(len(plan.bands)):
        npix = (plan.bands[b][1] - plan.bands[b][0]) * W
        pix, entry = _band_pairs(plan, b)
        px, py = _pixel_coords(plan, b, pix, params.dtype)
        mx, my, ca, cb, cc, op = (params[k].index_select(0, entry) for k in range(6))
        dx, dy = mx - px, my - py
        sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
        alpha = (op * torch.exp(-sigma)).clamp(max=ALPHA_MAX)
        ok = (alpha.detach() >= ALPHA_THRESHOLD) & (sigma.detach() >= 0)
        alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
        log1m = torch.log1p(-alpha)
        incl, _ = _seg_exclusive_prefix(log1m, pix, npix)
        keep = (ok & (incl.detach() > LOG_TRANSMITTANCE_MIN)).nonzero().squeeze(1)
        pix, entry, alpha, log1m, incl = (t.index_select(0, keep) for t in (pix, entry, alpha, log1m, incl))
        weight = alpha * torch.exp(incl - log1m).to(alpha.dtype)
        out = torch.zeros(npix, D, dtype=colors.dtype, device=colors.device)
        out = out.index_add(0, pix, colors.index_select(0, entry) * weight[:, None])
        log_tf = torch.zeros(npix, dtype=torch.float64, device=colors.device).index_add(0, pix, log1m.double())
        t_final = torch.exp(log_tf).to(colors.dtype)
        bg_pix = _band_bg(plan, b, bg, D, colors.dtype, colors.device)
        if bg_pix is not None:
            out = out + t_final[:, None] * bg_pix
        outs.append(out)
        alphas.append(1.0 - t_final)
    return torch.cat(outs).reshape(C, H, W, D), torch.cat(alphas).reshape(C, H, W, 1)


@dataclass
class SortedEntries:
    """Visible (camera, Gaussian) entries in compositing order, shared by the CPU backends.

    Entries are sorted by camera, then by camera ``z`` with ties kept in Gaussian index order
    (stable sort): every backend composites in exactly this order. ``m2 [M,2]``, ``con [M,3]``,
    ``op [M]``, ``col [M,D]`` are differentiable gathers of the projection; ``cam [M]`` int64.
    ``bg`` is ``backgrounds`` with a zero depth channel appended in ``RGB+ED`` mode.
    """

    proj: Projection
    means2d: torch.Tensor
    m2: torch.Tensor
    con: torch.Tensor
    op: torch.Tensor
    col: torch.Tensor
    cam: torch.Tensor
    bg: torch.Tensor | None
    n_cams: int
    width: int
    height: int


def sorted_entries(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    backgrounds: torch.Tensor | None,
    render_mode: str,
) -> SortedEntries:
    """Project (autograd) and gather the visible entries in compositing order (see :class:`SortedEntries`)."""
    C, N = viewmats.shape[0], means.shape[0]
    proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    cols = colors if colors.dim() == 3 else colors[None].expand(C, N, colors.shape[-1])
    bg = backgrounds
    if render_mode == "RGB+ED":
        cols = torch.cat([cols, proj.depths[..., None]], dim=-1)
        if bg is not None:
            bg = torch.cat([bg, torch.zeros_like(bg[:, :1])], dim=-1)
    D = cols.shape[-1]

    with torch.no_grad():
        key = torch.where(proj.visible, proj.depths.detach(), torch.full_like(proj.depths, float("inf")))
        order = torch.argsort(key, dim=1, stable=True)
        flat = (order + torch.arange(C, device=order.device)[:, None] * N)[proj.visible.gather(1, order)]
        cam = torch.div(flat, N, rounding_mode="floor")
    m2 = means2d.reshape(C * N, 2).index_select(0, flat)
    con = proj.conics.reshape(C * N, 3).index_select(0, flat)
    op = opacities.index_select(0, flat - cam * N)
    col = cols.reshape(C * N, D).index_select(0, flat)
    return SortedEntries(proj, means2d, m2, con, op, col, cam, bg, C, int(width), int(height))


def finish_render(
    ent: SortedEntries, img: torch.Tensor, alpha: torch.Tensor, render_mode: str, backend: str
) -> RenderOutput:
    """Expected depth for ``RGB+ED`` and the ``meta`` dict (the contract of :func:`meshsplat.render.rasterize`)."""
    return render_output(ent.proj, ent.means2d, ent.n_cams, ent.width, ent.height, img, alpha, render_mode, backend)


def render_output(
    proj: Projection,
    means2d: torch.Tensor,
    n_cams: int,
    width: int,
    height: int,
    img: torch.Tensor,
    alpha: torch.Tensor,
    render_mode: str,
    backend: str,
) -> RenderOutput:
    """:func:`finish_render` from the projection itself (backends that do not build :class:`SortedEntries`)."""
    if render_mode == "RGB+ED":
        img = torch.cat([img[..., :-1], img[..., -1:] / alpha.clamp_min(DEPTH_ALPHA_MIN)], dim=-1)
    meta = {
        "means2d": means2d,
        "radii": proj.radii,
        "depths": proj.depths,
        "conics": proj.conics,
        "visible": proj.visible,
        "width": width,
        "height": height,
        "n_cameras": n_cams,
        "backend": backend,
    }
    return RenderOutput(img, alpha, meta)


def rasterize_torch(
    *,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
    pair_budget: int | None = None,
    grad_mode: str = "custom",
    saved_pair_limit: int | None = None,
) -> RenderOutput:
    """Render C cameras; arguments as :func:`meshsplat.render.rasterize` (validated there).

    colors may be [N,D] or per camera [C,N,D]. ``pair_budget`` caps the
    (pixel, Gaussian) pairs processed at once (default 2M, ~100 B each while
    compositing); ``saved_pair_limit`` caps the pairs kept for backward (default 16M,
    ~61 B each; bands beyond it are recomputed in backward); ``grad_mode`` "custom"
    (default) or "autograd".
    """
    W, H = int(width), int(height)
    ent = sorted_entries(
        means, quats, scales, opacities, colors, viewmats, Ks, W, H, near_plane, far_plane, backgrounds, render_mode
    )
    plan = _make_plan(
        ent.m2.detach(),
        ent.con.detach(),
        ent.op.detach(),
        ent.cam,
        W,
        H,
        ent.n_cams,
        int(pair_budget or DEFAULT_PAIR_BUDGET),
    )
    if saved_pair_limit is not None:
        plan.saved_pair_limit = int(saved_pair_limit)

    if grad_mode == "custom":
        img, alpha = _Composite.apply(ent.m2, ent.con, ent.op, ent.col, ent.bg, plan)
    elif grad_mode == "autograd":
        img, alpha = _composite_autograd(ent.m2, ent.con, ent.op, ent.col, ent.bg, plan)
    else:
        raise MeshsplatError(f"grad_mode must be 'custom' or 'autograd', got {grad_mode!r}")
    out = finish_render(ent, img, alpha, render_mode, "torch")
    out.meta["n_pairs"] = int(plan.span_w.sum())  # candidate (pixel, Gaussian) pairs in footprints
    return out
