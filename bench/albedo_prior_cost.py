"""What the albedo prior (albedo_prior.weight) costs a training iteration, by its reach (albedo_prior.reach).

    python bench/albedo_prior_cost.py                  # 12k Gaussians on RobotExpressive, reach 8 / 64
    python bench/albedo_prior_cost.py --reach 8 32 64 128
    python bench/albedo_prior_cost.py --tiny           # seconds, to check the script

Times, interleaved and in the same process (median of --repeats), the neighbour search
(``albedo_neighbours``: a k-d tree over the Gaussians' surface points, once every ``REFRESH_EVERY``
iterations in training) and the prior's value and gradient (``albedo_smoothness`` forward and backward,
every iteration; numba's compiled kernels, the default on CPU, and the torch path, the baseline), for Gaussians spread over a bundled glTF's rest mesh with random albedos. The
per-iteration share is the prior plus a search spread over ``REFRESH_EVERY`` iterations.
Saves bench/results/<name>-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

from _machine import machine_info, results_path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=12_000)
    ap.add_argument("--reach", type=int, nargs="+", default=[8, 64])
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--asset", default="RobotExpressive", help="a bundled glTF: CesiumMan, RobotExpressive")
    ap.add_argument("--name", default="albedo_prior_cost")
    ap.add_argument("--tiny", action="store_true")
    args = ap.parse_args()
    if args.tiny:
        args.gaussians, args.repeats = 1000, 3

    import torch

    from meshsplat._numba import numba_available
    from meshsplat.drivers import GltfDriver
    from meshsplat.embedding import sample_surface
    from meshsplat.mesh import TriMesh
    from meshsplat.paths import bundled_asset
    from meshsplat.train.albedo_prior import REFRESH_EVERY, albedo_neighbours, albedo_smoothness

    torch.set_num_threads(args.threads)
    drv = GltfDriver(bundled_asset(args.asset))
    mesh = TriMesh(drv.rest_vertices(), drv.faces)
    g = torch.Generator().manual_seed(0)
    face, uv = sample_surface(mesh.vertices, mesh.faces, args.gaussians, generator=g)
    sh0 = (torch.rand(args.gaussians, 1, 3, generator=g) - 0.5).requires_grad_(True)

    def search(reach: int) -> torch.Tensor:
        return albedo_neighbours(mesh.vertices, mesh.faces, face, uv, reach)

    compiled = numba_available()

    def prior(nb: torch.Tensor, fast: bool) -> None:
        sh0.grad = None
        albedo_smoothness(sh0, nb, compiled=fast).backward()

    neighbours = {r: search(r) for r in args.reach}  # also warms up
    for r in args.reach:
        prior(neighbours[r], compiled)  # compiles (or loads) the kernels
    times: dict[str, list[float]] = {f"{k}{r}": [] for r in args.reach for k in ("search", "prior", "torch")}
    for _ in range(args.repeats):
        for r in args.reach:  # interleaved
            t0 = time.perf_counter()
            search(r)
            t1 = time.perf_counter()
            prior(neighbours[r], compiled)
            t2 = time.perf_counter()
            prior(neighbours[r], False)
            t3 = time.perf_counter()
            times[f"search{r}"].append((t1 - t0) * 1e3)
            times[f"prior{r}"].append((t2 - t1) * 1e3)
            times[f"torch{r}"].append((t3 - t2) * 1e3)

    rows = []
    path = "numba" if compiled else "torch (numba not available)"
    print(
        f"{args.gaussians} Gaussians on {args.asset}, {args.threads} threads, median of {args.repeats} (ms); prior: {path}"
    )
    print(f"{'reach':>5} {'neighbours':>10} {'search':>8} {'prior+grad':>10} {'torch path':>10} {'per iteration':>13}")
    for r in args.reach:
        s, p = statistics.median(times[f"search{r}"]), statistics.median(times[f"prior{r}"])
        t = statistics.median(times[f"torch{r}"])
        row = {
            "reach": r,
            "neighbours": int(neighbours[r].shape[1]),
            "search_ms": s,
            "prior_ms": p,
            "prior_path": "numba" if compiled else "torch",
            "prior_torch_ms": t,
            "per_iteration_ms": p + s / REFRESH_EVERY,
        }
        rows.append(row)
        print(f"{r:>5} {row['neighbours']:>10} {s:>8.1f} {p:>10.2f} {t:>10.2f} {row['per_iteration_ms']:>13.2f}")
    out = results_path(args.name)
    out.write_text(json.dumps({"machine": machine_info(), "args": vars(args), "rows": rows}, indent=2) + "\n")
    print(f"saved {out}")


if __name__ == "__main__":
    main()
