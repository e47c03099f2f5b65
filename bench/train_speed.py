"""Training time per iteration on the demo capture: today's default vs the code path before the
compiled rasterizer and the subject-crop losses, in the same run, at 1 and 2 threads.

    python bench/train_speed.py [--data DIR] [--iters 60] [--warmup 20] [--block 20] [--threads 1,2] [--quick]

Variants (both the quality preset on the demo's schedule, ``demo_train_config`` with the ``default``
demo sizes, same seed): ``before`` = ``backend=torch`` and ``loss.crop_to_subject=false`` (the path of
meshsplat before the numba backend and the crop), ``now`` = the defaults (``backend=auto``: numba on
CPU when installed; LPIPS on the subject's box). Per thread count, both trainers are warmed up, then
timed in alternating blocks so a change of the machine's load hits both alike. ``--data`` reuses a
generated demo dataset (``OUT/data`` of ``meshsplat demo``). Saves bench/results/train_speed-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from _machine import machine_info, results_path
from meshsplat.demo import PRESETS, _generate, demo_train_config
from meshsplat.train import Trainer

VARIANTS = {"before": ["backend=torch", "loss.crop_to_subject=false"], "now": []}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=None, help="a generated demo dataset to reuse")
    ap.add_argument("--iters", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--block", type=int, default=20)
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--out", type=Path, default=None, help="JSON path (default bench/results/train_speed-<host>.json)")
    ap.add_argument("--quick", action="store_true", help="20 timed iterations after 10 warm-up ones, blocks of 10")
    args = ap.parse_args()
    if args.quick:
        args.iters, args.warmup, args.block = 20, 10, 10
    tmp = Path(tempfile.mkdtemp(prefix="train_speed_"))
    data = args.data if args.data is not None else _generate(tmp / "data", PRESETS["default"], progress=False)
    rows = []
    for threads in [int(t) for t in args.threads.split(",")]:
        torch.set_num_threads(threads)
        trainers = {}
        for name, extra in VARIANTS.items():
            cfg = demo_train_config(data, tmp / f"{name}{threads}", PRESETS["default"], extra, progress=False)
            trainers[name] = Trainer(cfg)
            for _ in range(args.warmup):
                trainers[name].step()
        times: dict[str, list[float]] = {name: [] for name in trainers}
        done = 0
        while done < args.iters:
            n = min(args.block, args.iters - done)
            for name, tr in trainers.items():
                for _ in range(n):
                    t = time.perf_counter()
                    tr.step()
                    times[name].append(time.perf_counter() - t)
            done += n
        assert torch.get_num_threads() == threads, "a backend changed torch's thread count"
        for name, t in times.items():
            rows.append(
                {
                    "threads": threads,
                    "variant": name,
                    "median_s": statistics.median(t),
                    "mean_s": statistics.mean(t),
                    "gaussians": trainers[name].num_gaussians,
                }
            )
    print(f"{'threads':>7} {'variant':>7} {'median s':>9} {'mean s':>8} {'speed-up':>8}")
    for r in rows:
        base = next(b for b in rows if b["threads"] == r["threads"] and b["variant"] == "before")
        r["speedup_median"] = base["median_s"] / r["median_s"]
        print(
            f"{r['threads']:>7} {r['variant']:>7} {r['median_s']:9.4f} {r['mean_s']:8.4f} {r['speedup_median']:7.2f}x"
        )
    out = {"machine": machine_info(), "args": {k: str(v) for k, v in vars(args).items()}, "variants": VARIANTS}
    out["rows"] = rows
    path = args.out or results_path("train_speed")
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"saved {path}")


if __name__ == "__main__":
    main()
