"""Losses where the subject is: time per training iteration with ``loss.crop_to_subject`` off and on.

    python bench/loss_crop.py [--data DIR] [--iters 100] [--warmup 20] [--block 25] [--threads 1]

The demo's training (CesiumMan, 100 frames at 256², ``demo_train_config`` with the ``default`` demo
sizes, the quality preset): two trainers with the same seed, one with the key off and one with it on,
each warmed up for ``--warmup`` iterations, then timed over ``--iters`` iterations in alternating
blocks of ``--block`` (so a change in the machine's load hits both alike). Reports the mean and median
seconds per iteration, the crop boxes seen (area share, distinct shapes) and, on the frames of the
last block, how the area-scaled crop LPIPS compares with the full-frame LPIPS the paper optimises
(value ratio, and cosine / norm ratio of their gradients with respect to the render) and what one
LPIPS forward + backward costs on each (min over 5 repeats). ``--data``
reuses a generated demo dataset (``OUT/data`` of ``meshsplat demo``); without it one is generated.
Saves bench/results/loss_crop-<host>.json.
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


def _lpips_agreement(trainer, frames: list[int]) -> dict:
    """Full-frame LPIPS vs area-scaled crop LPIPS (and their gradients w.r.t. the render) on ``frames``."""
    from meshsplat.train.losses import subject_crop

    perceptual = trainer.perceptual
    cfg = trainer.cfg.loss
    ratios, cosines, norms = [], [], []
    for idx in frames:
        _, mask, _, _ = trainer._frame(idx)
        out, gt = trainer.render_frame(idx, torch.full((3,), 0.5))
        render = out.image.detach().clamp(0, 1).requires_grad_(True)
        full = perceptual(render, gt)
        (g_full,) = torch.autograd.grad(full, render)
        crop = subject_crop(mask, out.alpha, cfg.crop_margin)
        if crop is None:
            continue
        cropped = crop.area_fraction * perceptual(crop(render), crop(gt))
        (g_crop,) = torch.autograd.grad(cropped, render)
        ratios.append(float(cropped.detach()) / float(full.detach()))
        cosines.append(float(torch.nn.functional.cosine_similarity(g_full.flatten(), g_crop.flatten(), dim=0)))
        norms.append(float(g_crop.norm() / g_full.norm()))
    return {
        "frames": len(ratios),
        "value_ratio_mean": statistics.mean(ratios),
        "value_ratio_min": min(ratios),
        "value_ratio_max": max(ratios),
        "grad_cosine_mean": statistics.mean(cosines),
        "grad_cosine_min": min(cosines),
        "grad_norm_ratio_mean": statistics.mean(norms),
    }


def _lpips_cost(trainer, frames: list[int], repeats: int) -> dict:
    """Seconds of one LPIPS forward + backward on the full frame and on the crop, min over ``repeats``
    (the least disturbed run: the machine is shared), mean over ``frames``."""
    from meshsplat.train.losses import subject_crop

    perceptual = trainer.perceptual
    full_s, crop_s = [], []
    for idx in frames:
        _, mask, _, _ = trainer._frame(idx)
        with torch.no_grad():
            out, gt = trainer.render_frame(idx, torch.full((3,), 0.5))
        crop = subject_crop(mask, out.alpha, trainer.cfg.loss.crop_margin)
        for cut, acc in ((lambda x: x, full_s), (crop, crop_s)):
            best = float("inf")
            for _ in range(repeats):
                render = out.image.detach().clamp(0, 1).requires_grad_(True)
                t = time.perf_counter()
                perceptual(cut(render), cut(gt)).backward()
                best = min(best, time.perf_counter() - t)
            acc.append(best)
    return {"full_s": statistics.mean(full_s), "crop_s": statistics.mean(crop_s), "frames": len(frames)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=None, help="a generated demo dataset to reuse")
    ap.add_argument("--iters", type=int, default=100)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--block", type=int, default=25)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--name", default="loss_crop")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from meshsplat.demo import PRESETS, _generate, demo_train_config
    from meshsplat.train import Trainer
    from meshsplat.train.losses import subject_crop

    tmp = Path(tempfile.mkdtemp(prefix="loss_crop_"))
    data = args.data if args.data is not None else _generate(tmp / "data", PRESETS["default"], progress=False)
    trainers, times, boxes = {}, {}, {}
    for name, on in (("off", "false"), ("on", "true")):
        cfg = demo_train_config(data, tmp / name, PRESETS["default"], [f"loss.crop_to_subject={on}"], progress=False)
        trainers[name] = Trainer(cfg)
        times[name], boxes[name] = [], []
    for tr in trainers.values():  # warm-up: numba kernels, LPIPS, the frame cache
        for _ in range(args.warmup):
            tr.step()
    # the numba backend's first render raises torch's (OpenMP) thread count to numba's pool size: set it back
    torch.set_num_threads(args.threads)
    done = 0
    while done < args.iters:
        n = min(args.block, args.iters - done)
        for name, tr in trainers.items():
            for _ in range(n):
                t = time.perf_counter()
                tr.step()
                times[name].append(time.perf_counter() - t)
        done += n

    threads_timed = torch.get_num_threads()
    on = trainers["on"]
    frames = [on.train_ids[int(i)] for i in on.order[: min(len(on.order), args.block)]]
    for idx in on.train_ids:  # the boxes the on-trainer's current model gives on every training frame
        _, mask, _, _ = on._frame(idx)
        with torch.no_grad():
            out, _ = on.render_frame(idx, torch.zeros(3))
        box = subject_crop(mask, out.alpha, on.cfg.loss.crop_margin)
        boxes["on"].append(None if box is None else (box.h, box.w, box.area_fraction))
    agreement = _lpips_agreement(on, frames)
    cost = _lpips_cost(on, frames[:10], repeats=5)

    seen = [b for b in boxes["on"] if b is not None]
    rows = {}
    for name in trainers:
        t = times[name]
        rows[name] = {
            "mean_s": statistics.mean(t),
            "median_s": statistics.median(t),
            "gaussians_end": trainers[name].num_gaussians,
        }
    speedup = rows["off"]["mean_s"] / rows["on"]["mean_s"]
    result = {
        "machine": machine_info(),
        "args": {k: str(v) for k, v in vars(args).items()},
        "iterations_timed": args.iters,
        "torch_threads_while_timed": threads_timed,
        "per_iteration": rows,
        "speedup_mean": speedup,
        "speedup_median": rows["off"]["median_s"] / rows["on"]["median_s"],
        "crop": {
            "frames": len(boxes["on"]),
            "full_frame": len(boxes["on"]) - len(seen),
            "area_share_mean": statistics.mean(b[2] for b in seen) if seen else 1.0,
            "shapes": sorted({f"{b[0]}x{b[1]}" for b in seen}),
        },
        "lpips_crop_vs_full": agreement,
        "lpips_fwd_bwd": cost,
    }
    print(f"{'crop':<5} {'mean s/it':>10} {'median s/it':>12} {'Gaussians':>10}")
    for name, r in rows.items():
        print(f"{name:<5} {r['mean_s']:>10.4f} {r['median_s']:>12.4f} {r['gaussians_end']:>10}")
    print(
        f"speed-up (mean): {speedup:.2f}x; crop area share {result['crop']['area_share_mean']:.3f}, "
        f"shapes {result['crop']['shapes']}"
    )
    print(
        f"LPIPS forward + backward (min of 5, mean of {cost['frames']} frames): full frame {cost['full_s'] * 1e3:.1f} ms, "
        f"crop {cost['crop_s'] * 1e3:.1f} ms"
    )
    print("area-scaled crop LPIPS vs full-frame LPIPS:", json.dumps(agreement))
    print("load (1 min):", result["machine"].get("load_avg_1m"))
    path = results_path(args.name)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"saved {path}")


if __name__ == "__main__":
    main()
