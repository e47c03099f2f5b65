"""CPU rasterizer benchmark: the compiled numba backend (compositing with pixels in SIMD lanes, the default, and
the scalar kernels, ``MESHSPLAT_RASTER_KERNEL=scalar``) vs the torch backend, forward + backward.

Cases (one camera, avatar-like upper-body framing): 10k Gaussians @ 256x256, 50k @ 512x512,
200k @ 1080x1080, 500k @ 512x512 (``--quick``: the first only).

Time: median over repeats of forward, backward and forward + backward (after one warm-up run), wall clock and
CPU time of the process (``time.process_time``); with ``--rounds R`` every (case, variant) child runs R times,
the variants interleaved within each round, and the median over the rounds' medians is reported. Variants:
numba (the default lane kernels), numba-scalar, numba-llvmwidth (the lane kernels at LLVM's own vector width),
numba-w4/-w8/-w16 (at that forced width), torch. Work: pixel
visits, the pixels of the entries' exact footprints in the tiles they touch that the scalar forward walks (from
``raster_cpu_stages.py``'s count), so "ns / visit" = forward + backward CPU time over visits.
Memory: each (case, backend) runs in a fresh subprocess; peak = resource.getrusage ru_maxrss after the
runs minus the RSS just before the first render (scene built, numba kernels already loaded from the
on-disk cache, so compilation memory is not counted), i.e. the extra resident memory the renderer needed.
Compile time: a child with an empty NUMBA_CACHE_DIR times ``warm_up()`` (float32 + float64 kernels,
cold compile), a second child with the same directory times it again (kernels loaded from the cache).

    python bench/raster_cpu.py [--quick] [--cases 0,1] [--threads N] [--repeats R] [--rounds R] [--no-compile]
                               [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
CASES = [(10_000, 256), (50_000, 512), (200_000, 1080), (500_000, 512)]
# numba: the default (lanes) compositing kernels; numba-llvmwidth: the same kernels at LLVM's own vector width
# (MESHSPLAT_LANE_VECTOR_WIDTH=0, compiled without the disk cache: what AVX2-only hosts ran before the width was set)
VARIANTS = ("numba", "numba-scalar", "numba-llvmwidth", "torch")


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _maxrss_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _pixel_visits(scene: dict) -> int:
    """Footprint pixels the scalar forward walks (``raster_cpu_stages._count_visits``) for a scene's one camera."""
    import numba

    from _raster_scenes import binned_geometry
    from meshsplat.render.backends import numba_cpu as nc
    from raster_cpu_stages import _count_visits

    geo = binned_geometry(scene)
    counts = numba.njit(_count_visits)(
        geo.tile_ptr, geo.isect, geo.rec, geo.xs, geo.ys, scene["width"], scene["height"], nc.TILE_SIZE, geo.tiles_x
    )
    return int(counts[0])


def _lane_width() -> int:
    from meshsplat.render.backends.numba_lanes import lane_vector_width

    return lane_vector_width()


def run_case(n: int, size: int, repeats: int, variant: str, threads: int) -> dict:
    """Runs in the child process."""
    import torch

    backend = "numba" if variant.startswith("numba") else "torch"
    os.environ["MESHSPLAT_RASTER_KERNEL"] = "scalar" if variant == "numba-scalar" else "lanes"
    if variant == "numba-llvmwidth":
        os.environ["MESHSPLAT_LANE_VECTOR_WIDTH"] = "0"
    elif variant.startswith("numba-w"):  # numba-w4, -w8, -w16: the lane kernels at that forced width
        os.environ["MESHSPLAT_LANE_VECTOR_WIDTH"] = variant.removeprefix("numba-w")

    if threads:
        torch.set_num_threads(threads)
    sys.path.insert(0, str(HERE))
    from _raster_scenes import avatar_scene
    from meshsplat.render import rasterize
    from meshsplat.render.backends.numba_cpu import warm_up

    if backend == "numba":
        warm_up()  # from the on-disk cache (the parent compiled it); not part of the measurement
    scene = avatar_scene(n, size)
    names = ("means", "quats", "scales", "opacities", "colors", "backgrounds")
    params = {k: (v.clone().requires_grad_(True) if k in names else v) for k, v in scene.items()}
    base_rss = _rss_mib()
    fwd, bwd, total, cpu = [], [], [], []
    for i in range(repeats + 1):
        for p in params.values():
            if isinstance(p, torch.Tensor):
                p.grad = None
        c0 = time.process_time()
        t0 = time.perf_counter()
        out = rasterize(**params, backend=backend)
        loss = (out.colors - 0.5).abs().mean() + out.alphas.mean()
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        c2 = time.process_time()
        if i > 0:  # the first run is a warm-up
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
            total.append(t2 - t0)
            cpu.append(c2 - c0)
    return {
        "gaussians": n,
        "size": size,
        "backend": variant,
        "kernel": out.meta.get("kernel", ""),
        "lane_vector_width": _lane_width() if backend == "numba" else None,  # 0: LLVM's own
        "fwd_bwd_cpu_s": statistics.median(cpu),
        "pixel_visits": _pixel_visits(scene) if backend == "numba" else 0,
        "fwd_s": statistics.median(fwd),
        "bwd_s": statistics.median(bwd),
        "fwd_bwd_s": statistics.median(total),
        "peak_extra_mib": max(0.0, _maxrss_mib() - base_rss),
        "visible": int(out.meta["visible"].sum()),
        "coverage": float((out.alphas.detach() > 0.5).float().mean()),
        "threads": torch.get_num_threads(),
    }


def compile_child() -> dict:
    """Runs in the child process: time of warm_up() (cold compile or cache load, per NUMBA_CACHE_DIR)."""
    t0 = time.perf_counter()
    import numba  # noqa: F401

    t1 = time.perf_counter()
    from meshsplat.render.backends.numba_cpu import warm_up

    warm_up()
    return {"import_numba_s": t1 - t0, "warm_up_s": time.perf_counter() - t1}


def _child(args: list[str], env_extra: dict | None = None) -> dict:
    env = dict(os.environ, **(env_extra or {}))
    res = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, env=env, check=False)
    if res.returncode != 0:
        raise SystemExit(f"child {args} failed:\n{res.stderr}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def measure_compile() -> dict:
    with tempfile.TemporaryDirectory() as cache:
        env = {"NUMBA_CACHE_DIR": cache}
        cold = _child(["--compile-child"], env)
        warm = _child(["--compile-child"], env)
    return {
        "cold_s": cold["warm_up_s"],
        "cached_s": warm["warm_up_s"],
        "import_numba_s": warm["import_numba_s"],
        "what": "warm_up(): float32 + float64 forward and backward kernels",
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="only the smallest case")
    ap.add_argument("--cases", default="", help="comma-separated indices into the cases (default: all)")
    ap.add_argument("--threads", type=int, default=0, help="torch (and so numba) threads (0: torch default)")
    ap.add_argument("--repeats", type=int, default=0, help="timed runs per case (default 7, --quick 3)")
    ap.add_argument("--rounds", type=int, default=1, help="children per (case, variant), variants interleaved")
    ap.add_argument(
        "--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}, numba-w4/8/16"
    )
    ap.add_argument("--no-compile", action="store_true", help="skip the compile-time measurement")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--compile-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.compile_child:
        print(json.dumps(compile_child()))
        return 0
    if args.child:
        n, size, repeats, backend, threads = args.child.split(",")
        print(json.dumps(run_case(int(n), int(size), int(repeats), backend, int(threads))))
        return 0

    repeats = args.repeats or (3 if args.quick else 7)
    cases = CASES[:1] if args.quick else CASES
    if args.cases:
        cases = [CASES[int(i)] for i in args.cases.split(",")]
    compile_info = None if args.no_compile else measure_compile()
    _child(["--compile-child"])  # fill the default on-disk cache the cases load from
    variants = args.variants.split(",")
    rows = []
    for n, s in cases:
        runs: dict[str, list[dict]] = {v: [] for v in variants}
        for rnd in range(args.rounds):  # interleaved; every other round in reverse order
            for v in variants if rnd % 2 == 0 else variants[::-1]:
                runs[v].append(_child(["--child", f"{n},{s},{repeats},{v},{args.threads}"]))
        for rs in runs.values():
            row = dict(rs[0])
            for key in ("fwd_s", "bwd_s", "fwd_bwd_s", "fwd_bwd_cpu_s", "peak_extra_mib"):
                row[key] = statistics.median(r[key] for r in rs)
            row["rounds_fwd_bwd_s"] = [r["fwd_bwd_s"] for r in rs]
            rows.append(row)
    visits = {(r["gaussians"], r["size"]): r["pixel_visits"] for r in rows if r["pixel_visits"]}
    for r in rows:
        r["pixel_visits"] = visits.get((r["gaussians"], r["size"]), 0)

    print(
        f"{'case':>14} {'variant':>12} {'fwd s':>8} {'bwd s':>8} {'fwd+bwd s':>10} {'cpu s':>8} {'ns/visit':>9} "
        f"{'peak MiB':>9} {'vs torch':>9}"
    )
    for r in rows:
        ref = next((x for x in rows if x["backend"] == "torch" and x["size"] == r["size"]
                    and x["gaussians"] == r["gaussians"]), None)  # fmt: skip
        speed = f"{ref['fwd_bwd_s'] / r['fwd_bwd_s']:8.2f}x" if ref else "       -"
        ns = 1e9 * r["fwd_bwd_cpu_s"] / r["pixel_visits"] if r["pixel_visits"] else float("nan")
        print(
            f"{r['gaussians']:>7}@{r['size']:<6} {r['backend']:>12} {r['fwd_s']:>8.3f} {r['bwd_s']:>8.3f} "
            f"{r['fwd_bwd_s']:>10.3f} {r['fwd_bwd_cpu_s']:>8.3f} {ns:>9.1f} {r['peak_extra_mib']:>9.0f} {speed}"
        )
    if compile_info:
        print(
            f"numba compile (float32+float64, fwd+bwd): cold {compile_info['cold_s']:.1f} s, "
            f"from cache {compile_info['cached_s']:.2f} s (+ import numba {compile_info['import_numba_s']:.2f} s)"
        )

    sys.path.insert(0, str(HERE))
    from _machine import machine_info  # shared by the bench scripts

    info = machine_info()
    out = args.out or HERE / "results" / f"raster_cpu-{info['hostname']}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "machine": info,
                "quick": args.quick,
                "repeats": repeats,
                "rounds": args.rounds,
                "compile": compile_info,
                "memory_method": "ru_maxrss delta in a fresh subprocess per (case, backend), kernels preloaded",
                "results": rows,
            },
            indent=2,
        )
    )
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
