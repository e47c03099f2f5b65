"""Where the numba backend's time goes: each stage timed on its own, and how much per-pixel work there is.

One camera, ``avatar_scene`` (default 50k Gaussians @ 512², as ``raster_cpu.py``'s middle case). Stages:
projection forward and backward (compiled), geometry (the depth ``argsort`` and entry order), binning (entry
records and tile lists), compositing forward, compositing backward (per-intersection gradient rows; both with
the lanes kernels, the default, and the scalar ones), and the scatter of those rows. Time: minimum and median
over repeats, CPU time of the process (``--threads 1`` on a shared machine: the least disturbed); shares are of
the default pipeline (lanes). Work: intersections, footprint pixels visited (forward), of which at already finished
pixels and below the 1/255 alpha threshold, contributions per pixel.

    python bench/raster_cpu_stages.py [--gaussians N] [--size S] [--threads T] [--repeats R] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from meshsplat.render._constants import ALPHA_THRESHOLD, MAX_EXTEND

HERE = Path(__file__).resolve().parent


def _count_visits(tile_ptr, isect, rec, xs, ys, width, height, tile, tiles_x):  # compiled below
    """The forward walk of every tile (its row spans, alpha in float64) counting instead of compositing:
    [pixels visited, of them at done pixels, below the alpha threshold, contributing; rows]."""
    out = np.zeros(5, np.int64)
    for t in range(tile_ptr.shape[0] - 1):
        tx0, ty0 = (t % tiles_x) * tile, (t // tiles_x) * tile
        tw, th = min(width, tx0 + tile) - tx0, min(height, ty0 + tile) - ty0
        trans = np.ones(tw * th)
        done = np.zeros(tw * th, np.bool_)
        for k in range(tile_ptr[t], tile_ptr[t + 1]):
            e = isect[k]
            # the record: mx, my, a, b, c, opacity, first and last row (numba_lanes' columns); the row-span terms
            mx, my, a, b, c, op = rec[e, 0], rec[e, 1], rec[e, 2], rec[e, 3], rec[e, 4], rec[e, 5]
            two_a_tau = 2.0 * a * min(max(math.log(op / ALPHA_THRESHOLD), 0.0), 0.5 * MAX_EXTEND * MAX_EXTEND)
            det = max(a * c - b * b, 1e-300)
            for y in range(max(int(rec[e, 6]), ty0), min(int(rec[e, 7]), ty0 + th - 1) + 1):
                out[4] += 1
                dy = my - (y + 0.5)
                disc = math.sqrt(max(two_a_tau - det * dy * dy, 0.0))
                x0 = max(np.ceil(mx - (-b * dy + disc) / a - 0.5 - 0.05), tx0)
                x1 = min(np.floor(mx - (-b * dy - disc) / a - 0.5 + 0.05), tx0 + tw - 1)
                for x in range(int(x0), int(x1) + 1):
                    q = (y - ty0) * tw + x - tx0
                    out[0] += 1
                    if done[q]:
                        out[1] += 1
                        continue
                    dx = mx - xs[x]
                    alpha = min(op * math.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)), 0.999)
                    if alpha < 1.0 / 255.0:
                        out[2] += 1
                        continue
                    if trans[q] * (1.0 - alpha) <= 1e-4:
                        done[q] = True
                        continue
                    trans[q] *= 1.0 - alpha
                    out[3] += 1
    return out


def _timed(fn, repeats: int) -> tuple[float, float]:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        ts.append(time.process_time() - t0)
    return min(ts), statistics.median(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=50_000)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    sys.path.insert(0, str(HERE))
    import numba

    from _machine import machine_info, results_path
    from _raster_scenes import avatar_scene
    from meshsplat.render.backends import numba_cpu as nc
    from meshsplat.render.projection import Projection

    n, size = args.gaussians, args.size
    sc = avatar_scene(n, size)
    k = nc._kernels()
    nc.warm_up()
    arrs = [sc[x].contiguous().numpy() for x in ("means", "quats", "scales", "opacities")]
    cams = [sc[x].double().contiguous().numpy() for x in ("viewmats", "Ks")]
    rng = np.random.default_rng(0)
    stages: dict[str, tuple[float, float]] = {}
    proj_args = (*arrs, *cams, float(size), float(size), 0.01, 1e10)
    stages["projection forward"] = _timed(lambda: k.project(*proj_args), args.repeats)
    m2, con, depth, radii, vis = k.project(*proj_args)
    v = [rng.standard_normal(x.shape) for x in (m2, con, depth)]
    bwd_args = (*arrs[:3], *cams, float(size), float(size), vis, *v)
    stages["projection backward"] = _timed(lambda: k.project_backward(*bwd_args), args.repeats)
    proj = Projection(
        means2d=torch.from_numpy(m2).float(), conics=torch.from_numpy(con).float(),
        depths=torch.from_numpy(depth).float(), radii=torch.from_numpy(radii), visible=torch.from_numpy(vis),
    )  # fmt: skip
    stages["geometry (depth argsort)"] = _timed(lambda: nc._Geometry(proj, n, True, size, size, 16), args.repeats)
    geo = nc._Geometry(proj, n, True, size, size, 16)
    stages["binning"] = _timed(lambda: geo.bin(sc["opacities"], sc["colors"]), args.repeats)
    bg = sc["backgrounds"].numpy()
    stages["compositing forward (scalar)"] = _timed(lambda: k.forward(*geo.args(bg)), args.repeats)
    stages["compositing forward (lanes)"] = _timed(lambda: k.forward_lanes(*geo.args(bg)), args.repeats)
    _, t_final, n_contrib = k.forward(*geo.args(bg))
    g_out = rng.standard_normal((size * size, 3)).astype(np.float32)
    g_alpha = rng.standard_normal(size * size).astype(np.float32)
    bwd = (*geo.args(bg), g_out, g_alpha, t_final, n_contrib)
    stages["compositing backward (scalar)"] = _timed(lambda: k.backward(*bwd), args.repeats)
    stages["compositing backward (lanes)"] = _timed(lambda: k.backward_lanes(*bwd), args.repeats)
    rows = k.backward(*bwd)
    stages["scatter"] = _timed(
        lambda: k.scatter(geo.isect, rows, geo.slot, geo.visible, geo.flat.shape[0], True, n, 1, geo.xs), args.repeats
    )
    count = numba.njit(_count_visits)
    visited, at_done, below, contributed, n_rows = (
        int(x) for x in count(geo.tile_ptr, geo.isect, geo.rec, geo.xs, geo.ys, size, size, 16, geo.tiles_x)
    )
    total = sum(m for name, (m, _) in stages.items() if "(scalar)" not in name)
    print(f"{n} Gaussians @ {size}², {args.threads} thread(s)")
    print(f"{'stage':>30} {'min ms':>8} {'median ms':>10} {'share':>6}")
    for name, (lo, med) in stages.items():
        share = "" if "(scalar)" in name else f"{lo / total:6.1%}"
        print(f"{name:>30} {lo * 1e3:8.1f} {med * 1e3:10.1f} {share}")
    n_isect = int(geo.isect.shape[0])
    work = {
        "visible": int(vis.sum()),
        "intersections": n_isect,
        "rows": n_rows,
        "visited": visited,
        "visited_per_intersection": visited / max(n_isect, 1),
        "at_done_pixels": at_done,
        "below_threshold": below,
        "contributed": contributed,
        "contributions_per_pixel": contributed / (size * size),
    }
    print(", ".join(f"{key} {val:.3g}" if isinstance(val, float) else f"{key} {val}" for key, val in work.items()))
    out = args.out or results_path("raster_cpu_stages")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "machine": machine_info(),
                "gaussians": n,
                "size": size,
                "repeats": args.repeats,
                "stages_s": {name: {"min": lo, "median": med} for name, (lo, med) in stages.items()},
                "work": work,
            },
            indent=2,
        )
    )
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
