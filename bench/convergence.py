"""Time to quality: subject PSNR against iterations and CPU minutes, out to the paper's 30,000 iterations.

    python bench/convergence.py                      # demo capture (CesiumMan 256 px), paper schedule, 30k
    python bench/convergence.py --iters 3000         # a shorter curve
    python bench/convergence.py --preset tiny --iters 200 --points 50 100 200   # seconds, to check

Trains ONE run of a training preset (``--train-preset``, default ``paper``: the paper-faithful model)
on the TrainConfig schedule (the 30k-iteration densification schedule, opacity reset, lr decay to
30k) plus any ``--set key=value`` overrides, on the demo's
dataset, and at log-spaced iterations evaluates a few held-out frames of each test split (subject
PSNR/SSIM inside the mask, full-image PSNR; no LPIPS, to keep the points cheap). The curve is written
to ``bench/results/<name>-<host>.json`` after every point, with the CPU seconds this process has
used, and the run keeps checkpoints: rerunning the same command resumes where it stopped (the
points already measured are kept). ``--plot`` draws the curve (matplotlib) next to the JSON.

The saved curve (``results/convergence-vm.json``) was measured before the strategy keys took gsplat's
names and units, with the screen-size prune at the paper code's 20 px; to reproduce it with today's
default (0.15 of the image), pass ``--set strategy.prune_scale2d=0.078125`` (20 px at 256 px).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from _machine import machine_info, results_path

# Points avoid the paper schedule's opacity resets (every 3000 iterations up to 15,000), right after which
# the avatar is nearly transparent; ``since_reset`` records how long ago the last one was.
DEFAULT_POINTS = (100, 200, 300, 500, 750, 1000, 1500, 2000, 2900, 5000, 7500, 10_000, 14_500, 20_000, 30_000)


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def measure(trainer, dataset, frames: int) -> dict:
    from meshsplat.eval.evaluate import evaluate_avatar

    res, _ = evaluate_avatar(
        trainer.avatar(), dataset, max_frames_per_split=frames, lpips_net=None, samples_per_split=0
    )
    keys = ("psnr", "ssim", "psnr_mask", "ssim_mask", "psnr_crop")
    return {s: {k: v.get(k) for k in keys} for s, v in res["splits"].items()}


def plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = [p for p in doc["points"] if p.get("since_reset") != 0]  # right after an opacity reset: not shown
    splits = sorted({s for p in pts for s in p["splits"]})
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for j, s in enumerate(splits):
        col = f"C{j}"
        xs = [p["iteration"] for p in pts]
        cm = [p["cpu_s"] / 60.0 for p in pts]
        ys = [p["splits"][s]["psnr_mask"] for p in pts]
        axes[0].plot(xs, ys, "o-", color=col, label=f"{s} (mask)")
        axes[1].plot(cm, ys, "o-", color=col, label=f"{s} (mask)")
        ys = [p["splits"][s]["psnr"] for p in pts]
        axes[0].plot(xs, ys, "x--", color=col, alpha=0.5, label=f"{s} (full image)")
        axes[1].plot(cm, ys, "x--", color=col, alpha=0.5)
    axes[0].set_xscale("log")
    axes[0].set_xlabel("iteration")
    axes[1].set_xlabel("CPU minutes (this process)")
    for ax in axes:
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"time to quality: {doc['data_desc']}, paper schedule to {doc['iterations']} it")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="default", help="demo preset whose dataset is used")
    ap.add_argument("--iters", type=int, default=30_000)
    ap.add_argument("--points", type=int, nargs="*", default=list(DEFAULT_POINTS))
    ap.add_argument("--frames", type=int, default=4, help="held-out frames per split at each point")
    ap.add_argument(
        "--train-preset",
        default="paper",
        choices=("paper", "quality"),
        help="training preset (meshsplat.train.recipes; default paper)",
    )
    ap.add_argument("--set", nargs="*", default=[], help="TrainConfig overrides key=value")
    ap.add_argument("--work", default="runs/bench-convergence")
    ap.add_argument("--data", default="runs/bench-quality/data", help="dataset folder (generated if missing)")
    ap.add_argument("--name", default="convergence")
    ap.add_argument("--plot", action="store_true")
    ap.add_argument("--plot-only", action="store_true", help="redraw the plot from the saved JSON and exit")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 on a shared machine)")
    args = ap.parse_args()

    if args.plot_only:
        out = results_path(args.name)
        plot(json.loads(out.read_text()), out.with_suffix(".png"))
        return

    import torch

    torch.set_num_threads(args.threads)

    from meshsplat.data import open_dataset
    from meshsplat.demo import PRESETS, _generate
    from meshsplat.train import Trainer, apply_overrides, recipe_config

    preset = PRESETS[args.preset]
    data = _generate(Path(args.data), preset, progress=False)
    ckpt_every = max(1, min(1000, args.iters // 10))
    cfg = recipe_config(args.train_preset)
    cfg.data, cfg.out, cfg.iterations, cfg.progress = str(data), str(Path(args.work) / "run"), args.iters, False
    cfg.log_every, cfg.preview_every, cfg.checkpoint_every, cfg.keep_checkpoints = 100, 10**9, ckpt_every, 2
    cfg.model.n_init = preset.n_init
    cfg = apply_overrides(cfg, args.set).validate()
    out = results_path(args.name)
    doc = {"points": []}
    if out.exists():
        doc = json.loads(out.read_text())
    trainer = Trainer(cfg, resume=True)
    ds = open_dataset(data)
    done = {p["iteration"] for p in doc["points"]}
    doc.update(
        {
            "data": str(data),
            "data_desc": f"CesiumMan {preset.resolution}px {preset.frames} frames",
            "iterations": args.iters,
            "train_preset": args.train_preset,
            "overrides": args.set,
            "config": cfg.to_dict(),
            "frames_per_split": args.frames,
            "machine": machine_info(),
            "note": "cpu_s / wall_s: process CPU and wall seconds of training (evaluation excluded), "
            "summed over resumed sessions",
        }
    )
    cpu_train = doc.get("cpu_s_total", 0.0)
    wall_train = doc.get("wall_s_total", 0.0)
    last = max((p["iteration"] for p in doc["points"]), default=0)
    if trainer.iteration > last and last:  # resumed past the last point: add its rate for the gap
        cpu_train += (trainer.iteration - last) * cpu_train / last
        wall_train += (trainer.iteration - last) * wall_train / last
    elif trainer.iteration and not doc["points"]:
        print(f"resuming at {trainer.iteration} without a curve file: CPU time before is unknown")
    for target in sorted(p for p in args.points if p <= args.iters):
        if target <= trainer.iteration:
            continue
        c0, w0 = _cpu_s(), time.perf_counter()
        trainer.train(until=target)
        cpu_train += _cpu_s() - c0
        wall_train += time.perf_counter() - w0
        if target in done:
            continue
        splits = measure(trainer, ds, args.frames)
        st = cfg.strategy
        resets = [r for r in range(st.reset_every, min(trainer.iteration, st.refine_stop_iter) + 1, st.reset_every)]
        doc["points"].append(
            {
                "iteration": trainer.iteration,
                "cpu_s": cpu_train,
                "wall_s": wall_train,
                "since_reset": trainer.iteration - resets[-1] if resets else None,
                "gaussians": trainer.num_gaussians,
                "splits": splits,
                "load_avg_1m": os.getloadavg()[0],
            }
        )
        doc["cpu_s_total"], doc["wall_s_total"] = cpu_train, wall_train
        doc["cpu_s_per_iteration"] = cpu_train / max(1, trainer.iteration)
        tmp = out.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(doc, indent=1) + "\n")
        tmp.replace(out)
        msg = "  ".join(f"{s}: {v['psnr_mask']:.2f} mask / {v['psnr']:.2f} full" for s, v in splits.items())
        print(
            f"it {trainer.iteration:>6}  cpu {cpu_train / 60:7.1f} min  N {trainer.num_gaussians:>6}  {msg}", flush=True
        )
        if args.plot:
            plot(doc, out.with_suffix(".png"))
    print(f"saved {out}")


if __name__ == "__main__":
    main()
