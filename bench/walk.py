"""Benchmark walk_on_triangles: 100k embeddings on a ~10k-face closed mesh, three step sizes, both modes.

Baseline: the plain per-point reference (meshsplat.embedding._walk_reference) on the first 2,000
points of the same data, in the same run; the table shows points/s of both and the speed-up.

Usage: python bench/walk.py [--quick] [--out bench/results/walk-<host>.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from _machine import machine_info, results_path
from meshsplat.embedding import WALK_MODES, sample_surface, walk_on_triangles
from meshsplat.embedding._walk_reference import walk_on_triangles_reference
from meshsplat.mesh import TriMesh


def bench_mesh(quick: bool) -> TriMesh:
    """Closed, deformed UV sphere: 10,400 faces of mixed shape and size (quick: 1,200)."""
    s = trimesh.creation.uv_sphere(count=[21, 31] if quick else [51, 51])
    v = s.vertices * (1 + 0.15 * np.sin(3 * s.vertices[:, :1]) * np.cos(2 * s.vertices[:, 1:2]))
    return TriMesh(torch.tensor(v, dtype=torch.float32), torch.tensor(s.faces))


def timed(fn, repeats: int, device: torch.device) -> list[float]:
    out = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="tiny run (smoke test)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    n, repeats = (5000, 3) if args.quick else (100_000, 15)
    n_ref, ref_repeats = (200, 1) if args.quick else (2000, 3)
    mesh = bench_mesh(args.quick)
    # mean edge length in barycentric units is ~1: steps of 0.1 stay inside, ~1 cross 1-2 edges, ~5 cross several
    sizes = {"small (inside)": 0.1, "medium (1-2 edges)": 1.0, "large (several)": 5.0}
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    gen = torch.Generator().manual_seed(0)
    face, uv = sample_surface(mesh.vertices, mesh.faces, n, generator=gen)
    direction = torch.nn.functional.normalize(torch.randn(n, 2, generator=gen), dim=1)
    rows = []
    for dev in devices:
        verts, f, u = mesh.vertices.to(dev), face.to(dev), uv.to(dev)
        for mode in WALK_MODES:
            for label, size in sizes.items():
                step = (direction * size * torch.rand(n, 1, generator=gen)).to(dev)
                res = walk_on_triangles(mesh, verts, f, u, step, mode=mode)  # warm-up
                times = timed(lambda a=(mesh, verts, f, u, step), m=mode: walk_on_triangles(*a, mode=m), repeats, dev)
                med = statistics.median(times)
                row = {
                    "device": dev.type,
                    "mode": mode,
                    "step": label,
                    "step_size": size,
                    "n": n,
                    "faces": mesh.num_faces,
                    "median_ms": med,
                    "min_ms": min(times),
                    "points_per_s": n / (med / 1e3),
                    "changed_frac": float(res.changed.float().mean()),
                }
                if dev.type == "cpu":  # per-point Python reference on a subset, same points
                    args_ref = (mesh, verts, f[:n_ref], u[:n_ref], step[:n_ref])
                    ref_times = timed(
                        lambda a=args_ref, m=mode: walk_on_triangles_reference(*a, mode=m), ref_repeats, dev
                    )
                    ref_med = statistics.median(ref_times)
                    row.update(ref_n=n_ref, ref_median_ms=ref_med, ref_points_per_s=n_ref / (ref_med / 1e3))
                    row["speedup_vs_ref"] = row["points_per_s"] / row["ref_points_per_s"]
                rows.append(row)
    print(
        f"walk_on_triangles: N={n}, F={mesh.num_faces}, repeats={repeats} (median); "
        f"reference: N={n_ref}, repeats={ref_repeats}; torch threads={torch.get_num_threads()}, "
        f"load avg {machine_info().get('load_avg_1m', float('nan')):.2f}"
    )
    print(
        f"{'device':6} {'mode':6} {'step':20} {'median ms':>10} {'Mpts/s':>8} {'changed':>8} "
        f"{'ref kpts/s':>10} {'speed-up':>9}"
    )
    for r in rows:
        ref = (
            f"{r['ref_points_per_s'] / 1e3:10.2f} {r['speedup_vs_ref']:8.0f}x"
            if "ref_points_per_s" in r
            else f"{'-':>10} {'-':>9}"
        )
        print(
            f"{r['device']:6} {r['mode']:6} {r['step']:20} {r['median_ms']:10.2f} "
            f"{r['points_per_s'] / 1e6:8.2f} {r['changed_frac']:8.3f} {ref}"
        )
    out = Path(args.out) if args.out else results_path("walk")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps({"bench": "walk", "quick": args.quick, "machine": machine_info(), "rows": rows}, indent=2)
    )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
