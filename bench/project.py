"""Benchmark project_to_surface: 100k points (|d| up to 2% of the bbox diagonal) onto a ~10k-face mesh.

Usage: python bench/project.py [--quick] [--out bench/results/project-<host>.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from _machine import machine_info, results_path
from meshsplat.embedding import embed, project_to_surface, sample_surface
from meshsplat.mesh import MeshPose
from walk import bench_mesh


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="tiny run (smoke test)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    n = 5000 if args.quick else 100_000
    mesh = bench_mesh(args.quick)
    pose = MeshPose.canonical(mesh)
    diag = mesh.bbox_diagonal()
    gen = torch.Generator().manual_seed(0)
    face, uv = sample_surface(mesh.vertices, mesh.faces, n, generator=gen)
    d = (2 * torch.rand(n, generator=gen) - 1) * 0.02 * diag
    x, _ = embed(pose, face, uv, d)
    rows = []
    for k, n_starts in ((8, 1), (8, 2)):
        t0 = time.perf_counter()
        f2, uv2, d2 = project_to_surface(mesh, mesh.vertices, x, k=k, n_starts=n_starts)
        dt = time.perf_counter() - t0
        x2, _ = embed(pose, f2, uv2, d2)
        err = (x2 - x).norm(dim=1) / diag
        rows.append(
            {
                "k": k,
                "n_starts": n_starts,
                "n": n,
                "faces": mesh.num_faces,
                "seconds": dt,
                "points_per_s": n / dt,
                "frac_err_below_1e-4_diag": float((err < 1e-4).float().mean()),
                "median_rel_err": float(err.median()),
                "max_rel_err": float(err.max()),
                "nan": bool(torch.isnan(err).any()),
            }
        )
    print(f"project_to_surface: N={n}, F={mesh.num_faces}")
    print(f"{'k':>3} {'starts':>6} {'seconds':>8} {'kpts/s':>8} {'<1e-4 diag':>11} {'median err':>11}")
    for r in rows:
        print(
            f"{r['k']:3d} {r['n_starts']:6d} {r['seconds']:8.2f} {r['points_per_s'] / 1e3:8.1f} "
            f"{r['frac_err_below_1e-4_diag']:11.4f} {r['median_rel_err']:11.2e}"
        )
    out = Path(args.out) if args.out else results_path("project")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps({"bench": "project", "quick": args.quick, "machine": machine_info(), "rows": rows}, indent=2)
    )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
