"""Rasterizer benchmark: forward+backward time and peak memory of the torch backend on CPU.

Cases (one camera, avatar-like upper-body framing, footprints ~5-25 px):
2k Gaussians @ 128x128, 10k @ 256x256, 50k @ 512x512; plus the brute-force dense
reference on the smallest case (time ratio), and custom-backward vs autograd.

Time: median over repeats of one forward + backward (after a warm-up run).
Memory: each case runs in a fresh subprocess; peak = resource.getrusage ru_maxrss
after the runs minus the RSS measured just before the first render (scene built,
torch imported), i.e. the extra resident memory the renderer needed.

    python bench/raster.py [--quick] [--threads N] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
CASES = [(2_000, 128), (10_000, 256), (50_000, 512)]
TARGETS = {(10_000, 256): (1.5, 1024), (50_000, 512): (15.0, 4096)}  # seconds, MiB


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _maxrss_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_case(n: int, size: int, repeats: int, mode: str) -> dict:
    """Runs in the child process."""
    import torch

    sys.path.insert(0, str(HERE))
    from _raster_scenes import avatar_scene
    from meshsplat.render import rasterize
    from meshsplat.render.backends._dense_reference import rasterize_dense

    scene = avatar_scene(n, size)
    names = ("means", "quats", "scales", "opacities", "colors")
    params = {k: (v.clone().requires_grad_(True) if k in names else v) for k, v in scene.items()}

    def step():
        if mode == "dense":
            colors, alphas = rasterize_dense(**params)
            info = {}
        else:
            out = rasterize(**params, backend="torch", grad_mode=mode)
            colors, alphas, info = out.colors, out.alphas, out.meta
        loss = (colors - 0.5).abs().mean() + alphas.mean()
        t0 = time.perf_counter()
        loss.backward()
        return time.perf_counter() - t0, info, alphas

    base_rss = _rss_mib()
    times, bwd = [], []
    for i in range(repeats + 1):
        for p in params.values():
            if isinstance(p, torch.Tensor):
                p.grad = None
        t0 = time.perf_counter()
        tb, info, alphas = step()
        if i > 0:  # first run is a warm-up
            times.append(time.perf_counter() - t0)
            bwd.append(tb)
    return {
        "gaussians": n,
        "size": size,
        "mode": mode,
        "fwd_bwd_s": statistics.median(times),
        "bwd_s": statistics.median(bwd),
        "peak_extra_mib": max(0.0, _maxrss_mib() - base_rss),
        "pairs": int(info.get("n_pairs", 0)),
        "visible": int(info["visible"].sum()) if "visible" in info else None,
        "coverage": float((alphas.detach() > 0.5).float().mean()),
        "threads": torch.get_num_threads(),
    }


def _spawn(n, size, repeats, mode, threads) -> dict:
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    cmd = [sys.executable, __file__, "--child", f"{n},{size},{repeats},{mode}"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if res.returncode != 0:
        raise SystemExit(f"case {n}@{size} ({mode}) failed:\n{res.stderr}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repeats, skip the 50k case")
    ap.add_argument("--threads", type=int, default=0, help="OMP_NUM_THREADS for the cases (0: torch default)")
    ap.add_argument("--no-autograd", action="store_true", help="skip the autograd-backward comparison")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        n, size, repeats, mode = args.child.split(",")
        print(json.dumps(run_case(int(n), int(size), int(repeats), mode)))
        return 0

    repeats = 3 if args.quick else 7
    cases = CASES[:2] if args.quick else CASES
    rows = [_spawn(n, s, repeats, "custom", args.threads) for n, s in cases]
    if not args.no_autograd:
        rows += [_spawn(n, s, repeats, "autograd", args.threads) for n, s in cases[:2]]
    dense = _spawn(CASES[0][0], CASES[0][1], 1, "dense", args.threads)
    rows.append(dense)

    print(f"{'case':>14} {'mode':>9} {'fwd+bwd s':>10} {'bwd s':>8} {'peak MiB':>9} {'pairs':>9} {'cover':>6}  target")
    for r in rows:
        tgt = TARGETS.get((r["gaussians"], r["size"])) if r["mode"] == "custom" else None
        ok = "" if tgt is None else ("ok" if r["fwd_bwd_s"] < tgt[0] and r["peak_extra_mib"] < tgt[1] else "MISSED")
        tgt_s = "" if tgt is None else f"<{tgt[0]}s <{tgt[1]}MiB {ok}"
        print(
            f"{r['gaussians']:>7}@{r['size']:<6} {r['mode']:>9} {r['fwd_bwd_s']:>10.3f} {r['bwd_s']:>8.3f} "
            f"{r['peak_extra_mib']:>9.0f} {r['pairs']:>9} {r['coverage']:>6.2f}  {tgt_s}"
        )
    fast_small = next(r for r in rows if r["mode"] == "custom" and r["size"] == CASES[0][1])
    ratio = dense["fwd_bwd_s"] / fast_small["fwd_bwd_s"]
    print(f"dense reference / torch backend on {CASES[0][0]}@{CASES[0][1]}: {ratio:.0f}x slower")
    for n, s in cases[:2]:
        auto = [r for r in rows if r["mode"] == "autograd" and r["size"] == s]
        cust = [r for r in rows if r["mode"] == "custom" and r["size"] == s]
        if auto and cust:
            print(
                f"autograd backward / custom backward at {n}@{s}: "
                f"{auto[0]['bwd_s'] / cust[0]['bwd_s']:.2f}x (fwd+bwd {auto[0]['fwd_bwd_s'] / cust[0]['fwd_bwd_s']:.2f}x)"
            )

    sys.path.insert(0, str(HERE))
    from _machine import machine_info  # shared by the bench scripts

    info = machine_info()
    out = args.out or HERE / "results" / f"raster-{info['hostname']}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "machine": info,
                "quick": args.quick,
                "dense_ratio": ratio,
                "memory_method": "ru_maxrss delta in a fresh subprocess per case",
                "results": rows,
            },
            indent=2,
        )
    )
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
