"""A larger capture a user would bring: the stand-in SMPL body dancing the bundled AIST++ motion at 540²,
trained with today's default and with the code path before the compiled rasterizer and the subject crop
(``backend=torch``, ``loss.crop_to_subject=false``): wall time, seconds per iteration, metrics.

    python bench/train_body.py [--resolution 540] [--frames 100] [--iters 3000] [--variants now before]
                               [--threads 1] [--work runs/bench-body] [--name train_body]

The capture (``meshsplat synth smpl``, Lambert, 100 frames, one turning camera, 2 novel views, driving
mesh = the body) and the stand-in model files are generated once under ``--work`` and reused. Both
variants train the quality preset with the same seed on a schedule scaled to ``--iters``
(densification from 1/6 to 4/5 of the run every 100 iterations, at most 100k Gaussians, 20k at the
start, no opacity reset). Each finished run is recorded in bench/results/<name>-<host>.json under
``variant@iters`` (a rerun with other variants or lengths adds to the file), with its seconds per
iteration over the whole run and over its last 20% (after densification), and the held-out frames'
and novel views' metrics (full image and inside the mask).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import torch

from _machine import machine_info, results_path
from meshsplat.eval import evaluate_run
from meshsplat.render.backends import numba_available
from meshsplat.render.backends.numba_cpu import warm_up
from meshsplat.synth import synthesize
from meshsplat.synth.standin_models import write_standin_models
from meshsplat.train import Trainer, recipe_config
from meshsplat.train.config import apply_overrides

VARIANTS = {"before": ["backend=torch", "loss.crop_to_subject=false", "loss.lpips_every=1"], "now": []}
KEYS = ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")


def _schedule(iters: int) -> list[str]:
    return [
        f"strategy.refine_start_iter={iters // 6}",
        f"strategy.refine_stop_iter={iters * 4 // 5}",
        "strategy.refine_every=100",
        "strategy.reset_every=1000000",
        "strategy.max_gaussians=100000",
        "walk.every=100",
        f"checkpoint_every={max(iters // 4, 1)}",
        "preview_every=1000000",
        "log_every=50",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", type=int, default=540)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--iters", type=int, default=3000)
    ap.add_argument("--n-init", type=int, default=20_000)
    ap.add_argument("--until", type=int, default=None, help="stop at this iteration (speed only, no metrics)")
    ap.add_argument("--variants", nargs="+", default=["now", "before"], choices=sorted(VARIANTS))
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 on a shared machine)")
    ap.add_argument("--work", default="runs/bench-body", help="scratch folder (models, capture, runs)")
    ap.add_argument("--name", default="train_body", help="results file bench/results/<name>-<host>.json")
    args = ap.parse_args()

    torch.set_num_threads(args.threads)
    work = Path(args.work)
    models, data = work / "models", work / f"smpl{args.resolution}"
    if not (models / "smpl").is_dir():
        write_standin_models(models, kinds=("smpl",))
    if not (data / "manifest.json").is_file():
        t0 = time.perf_counter()
        synthesize("smpl", data, frames=args.frames, resolution=args.resolution, test_views=2, model_dir=models)
        print(f"capture: {args.frames} frames at {args.resolution}² in {time.perf_counter() - t0:.0f} s", flush=True)

    if "now" in args.variants and numba_available():
        t0 = time.perf_counter()
        warm_up()  # numba's compile (or cache load) is not part of any run's time
        print(f"numba kernels ready in {time.perf_counter() - t0:.0f} s", flush=True)
    out = results_path(args.name)
    record = json.loads(out.read_text()) if out.is_file() else {"runs": {}}
    for name in args.variants:
        cfg = recipe_config()
        cfg.data, cfg.out, cfg.model_dir = str(data), str(work / f"{name}{args.iters}"), str(models)
        cfg.iterations, cfg.model.n_init, cfg.progress, cfg.seed = args.iters, args.n_init, False, 0
        cfg = apply_overrides(cfg, _schedule(args.iters) + VARIANTS[name]).validate()
        trainer = Trainer(cfg)
        trainer.train(until=args.until)
        done = trainer.iteration
        with open(trainer.folder.log_path, newline="") as fh:
            log = [(int(r["iteration"]), float(r["time_s"])) for r in csv.DictReader(fh)]
        total = log[-1][1]
        tail = [row for row in log if row[0] >= done * 4 // 5]
        tail_rate = (tail[-1][1] - tail[0][1]) / max(tail[-1][0] - tail[0][0], 1)
        at = {it: t for it, t in log}
        m = evaluate_run(cfg.out, report=False) if done == args.iters else {"splits": {}}
        key = f"{name}@{args.iters}" + ("" if done == args.iters else f":until{done}")
        record["runs"][key] = {
            "variant": name,
            "overrides": VARIANTS[name],
            "iterations": args.iters,
            "stopped_at": done,
            "train_s": total,
            "s_per_iter": total / done,
            "time_at_s": {str(it): round(t, 2) for it, t in at.items() if it % 100 == 0},
            "s_per_iter_last20": tail_rate,
            "gaussians": trainer.num_gaussians,
            "splits": {s: {k: v.get(k) for k in KEYS} for s, v in m["splits"].items()},
        }
        record.update(
            machine=machine_info(),
            threads=args.threads,
            resolution=args.resolution,
            frames=args.frames,
            n_init=args.n_init,
            data=str(data),
        )
        out.write_text(json.dumps(record, indent=2) + "\n")
        print(f"[{key}] {total:.0f} s ({total / done:.3f} s/it)", flush=True)

    print(f"\nSMPL stand-in, {args.resolution}², {args.threads} thread(s); full image | inside the mask")
    print(
        f"{'run':<14}{'split':<12}{'PSNR':>7}{'SSIM':>7}{'LPIPS':>7} |{'PSNR':>7}{'LPIPS':>7}{'N':>8}{'s/it':>7}{'train s':>8}"
    )
    for key, r in record["runs"].items():
        if not r["splits"]:  # stopped early: speed only
            print(f"{key:<26}{'-':>21} |{'-':>14}{r['gaussians']:>8}{r['s_per_iter']:>7.3f}{r['train_s']:>8.0f}")
        for s, v in sorted(r["splits"].items()):
            print(
                f"{key:<14}{s:<12}{v['psnr']:>7.2f}{v['ssim']:>7.3f}{v['lpips']:>7.3f} |{v['psnr_mask']:>7.2f}"
                f"{v['lpips_mask']:>7.3f}{r['gaussians']:>8}{r['s_per_iter']:>7.3f}{r['train_s']:>8.0f}"
            )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
