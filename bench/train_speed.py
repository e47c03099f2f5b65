"""Training time per iteration on the demo capture: today's default vs the code path before the
compiled rasterizer and the subject-crop losses, in the same run, at 1 and 2 threads.

    python bench/train_speed.py [--data DIR] [--iters 60] [--warmup 20] [--block 20] [--threads 1,2]
                                [--lpips-every 4] [--quick] [--variants now,...]

A setting read once per process (``MESHSPLAT_LANE_VECTOR_WIDTH``) is compared by running ``--variants now`` in
alternating processes with and without it (bench/raster_cpu_lanes.md).

Variants (the quality preset on the demo's schedule, ``demo_train_config`` with the ``default`` demo
sizes, same seed): ``before`` = ``backend=torch``, ``loss.crop_to_subject=false``,
``loss.lpips_every=1`` and the torch shadow maps (the path of meshsplat before the numba backend, the crop
and the LPIPS cadence), ``numba_crop`` = the defaults but LPIPS on every iteration (the default before the cadence),
``now`` = the defaults (``backend=auto``: numba on CPU when installed; LPIPS on the subject's box, every
second iteration), ``now_lpips_bf16`` = ``now`` with LPIPS's backbone in bfloat16 (``loss.lpips_precision=bfloat16``),
``now_adam_default`` = ``now`` with torch's default Adam instead of its fused kernel (the default before
issue 47's eighth round; switched on the built trainer's optimizers), ``now_lpips<k>`` = ``now`` with
``loss.lpips_every=k`` for each k of
``--lpips-every`` (default none). (A variant ``now_torch_maps`` timed the key light's shadow maps in pure
torch against the compiled ones; since the trainer keeps each training frame's maps, they are built once per
frame and that variant was dropped.) Per thread count, every trainer is warmed up, then timed in
alternating blocks so a change of the machine's load hits all alike. An iteration with LPIPS costs
more than one without: besides the median and mean time per iteration, ``cycle_median_s`` is the
median over aligned groups of lcm(k) consecutive iterations of their mean
time (each group holds the same mix of iterations with and without LPIPS), the figure the speed-ups
``speedup_cycle`` compare. ``--data`` reuses a
generated demo dataset (``OUT/data`` of ``meshsplat demo``). Saves bench/results/train_speed-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import time
from pathlib import Path

import torch

from _machine import machine_info, results_path
from _shadow_maps import use_torch_maps
from meshsplat.demo import PRESETS, _generate, demo_train_config
from meshsplat.train import Trainer

VARIANTS = {
    "before": ["backend=torch", "loss.crop_to_subject=false", "loss.lpips_every=1"],
    "numba_crop": ["loss.lpips_every=1"],
    "now": [],
    "now_lpips_bf16": ["loss.lpips_precision=bfloat16"],  # LPIPS's backbone in bfloat16 (opt-in, issue 47)
    "now_adam_default": [],  # torch's default Adam (unfused), see AFTER_BUILD
}
TORCH_MAPS = {"before"}  # variants whose shadow maps are built by the torch path
CADENCES = {"before": 1, "numba_crop": 1, "now": 2, "now_lpips_bf16": 2, "now_adam_default": 2}  # loss.lpips_every


def _adam_unfused(trainer: Trainer) -> None:
    for opt in trainer.optimizers.values():
        for group in opt.param_groups:
            group["fused"] = None


AFTER_BUILD = {"now_adam_default": _adam_unfused}  # what a variant changes on the built trainer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=None, help="a generated demo dataset to reuse")
    ap.add_argument("--iters", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--block", type=int, default=20)
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--out", type=Path, default=None, help="JSON path (default bench/results/train_speed-<host>.json)")
    ap.add_argument("--lpips-every", default="", help="comma-separated other loss.lpips_every values to time too")
    ap.add_argument("--quick", action="store_true", help="24 timed iterations after 12 warm-up ones, blocks of 12")
    ap.add_argument("--variants", default="", help=f"comma-separated subset of {', '.join(VARIANTS)} (default: all)")
    args = ap.parse_args()
    if args.quick:
        args.iters, args.warmup, args.block = 24, 12, 12
    picked = [v for v in args.variants.split(",") if v]
    if unknown := set(picked) - set(VARIANTS):
        raise SystemExit(f"unknown variants {sorted(unknown)}: pick from {', '.join(VARIANTS)}")
    variants = {k: v for k, v in VARIANTS.items() if not picked or k in picked}
    cadences = [int(k) for k in args.lpips_every.split(",") if k.strip()]
    for k in cadences:
        variants[f"now_lpips{k}"] = [f"loss.lpips_every={k}"]
    cycle = math.lcm(*(CADENCES[k] for k in variants if k in CADENCES), *cadences)
    if args.warmup % cycle or args.block % cycle:
        raise SystemExit(f"--warmup and --block must be multiples of {cycle} (the lcm of --lpips-every)")
    tmp = Path(tempfile.mkdtemp(prefix="train_speed_"))
    data = args.data if args.data is not None else _generate(tmp / "data", PRESETS["default"], progress=False)
    rows = []
    for threads in [int(t) for t in args.threads.split(",")]:
        torch.set_num_threads(threads)
        trainers = {}
        for name, extra in variants.items():
            cfg = demo_train_config(data, tmp / f"{name}{threads}", PRESETS["default"], extra, progress=False)
            trainers[name] = Trainer(cfg)
            AFTER_BUILD.get(name, lambda tr: None)(trainers[name])
            use_torch_maps(name in TORCH_MAPS)
            for _ in range(args.warmup):
                trainers[name].step()
        times: dict[str, list[float]] = {name: [] for name in trainers}
        done = 0
        while done < args.iters:
            n = min(args.block, args.iters - done)
            for name, tr in trainers.items():
                use_torch_maps(name in TORCH_MAPS)
                for _ in range(n):
                    t = time.perf_counter()
                    tr.step()
                    times[name].append(time.perf_counter() - t)
            done += n
        use_torch_maps(False)
        assert torch.get_num_threads() == threads, "a backend changed torch's thread count"
        for name, t in times.items():
            rows.append(
                {
                    "threads": threads,
                    "variant": name,
                    "median_s": statistics.median(t),
                    "mean_s": statistics.mean(t),
                    "cycle_median_s": statistics.median(
                        statistics.mean(t[i : i + cycle]) for i in range(0, len(t) - cycle + 1, cycle)
                    ),
                    "cycle": cycle,
                    "gaussians": trainers[name].num_gaussians,
                }
            )
    print(f"{'threads':>7} {'variant':>11} {'median s':>9} {'mean s':>8} {'cycle s':>8} {'speed-up':>8} {'(cycle)':>8}")
    for r in rows:
        same = [b for b in rows if b["threads"] == r["threads"]]  # against `before`, else the first variant
        base = next((b for b in same if b["variant"] == "before"), same[0])
        r["speedup_median"] = base["median_s"] / r["median_s"]
        r["speedup_cycle"] = base["cycle_median_s"] / r["cycle_median_s"]
        print(
            f"{r['threads']:>7} {r['variant']:>11} {r['median_s']:9.4f} {r['mean_s']:8.4f} "
            f"{r['cycle_median_s']:8.4f} {r['speedup_median']:7.2f}x {r['speedup_cycle']:7.2f}x"
        )
    out = {"machine": machine_info(), "args": {k: str(v) for k, v in vars(args).items()}, "variants": variants}
    out["rows"] = rows
    path = args.out or results_path("train_speed")
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"saved {path}")


if __name__ == "__main__":
    main()
