"""Quality of the full method vs two ablations on the demo's dataset, in one run.

    python bench/quality.py                 # demo preset: CesiumMan 256px, 1500 iterations each
    python bench/quality.py --preset tiny   # seconds, to check the script

Variants (same data, same seed, same schedule):
  full        lifted optimization with walking on triangles (the method)
  no_walk     walking disabled: (u+du, v+dv) clipped to the embedding triangle (paper, Table A2)
  frozen      embedding frozen: no du, dv, d (paper, Fig. 7 "w/o trainable embedding")
  scale_area  the paper's pose scale (times the area ratio) instead of our sqrt_area default
  unfold      walking with the exact unfold mode instead of the paper's re-expression

Prints a table of PSNR / SSIM / LPIPS per test split and saves bench/results/quality-<host>.json.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from _machine import machine_info, results_path

VARIANTS = {
    "full": [],
    "no_walk": ["walk.enabled=false"],
    "frozen": ["model.freeze_embedding=true"],
    "scale_area": ["model.scale_mode=area"],
    "unfold": ["walk.mode=unfold"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--iters", type=int, default=None)
    ap.add_argument("--work", default="runs/bench-quality", help="scratch folder (dataset + runs)")
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--name", default="quality", help="results file bench/results/<name>-<host>.json")
    args = ap.parse_args()

    from dataclasses import replace

    from meshsplat.demo import PRESETS, _generate, demo_train_config
    from meshsplat.eval import evaluate_run
    from meshsplat.train import Trainer

    preset = PRESETS[args.preset]
    if args.iters:
        preset = replace(preset, iterations=args.iters)
    work = Path(args.work)
    data = _generate(work / "data", preset, progress=False)
    rows = {}
    for name in args.variants:
        cfg = demo_train_config(data, work / name, preset, VARIANTS[name], progress=False)
        t0 = time.perf_counter()
        trainer = Trainer(cfg, resume=True)
        trainer.train()
        train_s = time.perf_counter() - t0
        m = evaluate_run(work / name, report=False)
        rows[name] = {"train_s": train_s, "gaussians": trainer.num_gaussians,
                      "walked_total": getattr(trainer, "walked_total", None),
                      "splits": {s: {k: v[k] for k in ("psnr", "ssim", "lpips")} for s, v in m["splits"].items()}}
        print(f"[{name}] trained in {train_s:.0f} s", flush=True)

    splits = sorted({s for r in rows.values() for s in r["splits"]})
    print(f"\nquality on {args.preset} preset ({preset.iterations} iterations, {preset.resolution}px)")
    print(f"{'variant':<12}{'split':<14}{'PSNR':>8}{'SSIM':>8}{'LPIPS':>8}{'N':>8}{'train s':>9}")
    for name, r in rows.items():
        for s in splits:
            m = r["splits"].get(s, {})
            fmt = lambda x, d: "-" if x is None else f"{x:.{d}f}"  # noqa: E731
            print(f"{name:<12}{s:<14}{fmt(m.get('psnr'), 2):>8}{fmt(m.get('ssim'), 4):>8}"
                  f"{fmt(m.get('lpips'), 4):>8}{r['gaussians']:>8}{r['train_s']:>9.0f}")
    out = results_path(args.name)
    out.write_text(json.dumps({"machine": machine_info(), "preset": args.preset,
                               "iterations": preset.iterations, "resolution": preset.resolution,
                               "variants": rows}, indent=2) + "\n")
    print(f"saved {out}")


if __name__ == "__main__":
    main()
