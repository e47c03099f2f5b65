"""Quality of the method's variants and options on one capture, in one run (same data, seed, schedule).

    python bench/quality.py                                 # demo: CesiumMan 256px, 1500 iterations each
    python bench/quality.py --preset tiny                   # seconds, to check the script
    python bench/quality.py --resolution 128 --iters 400 --variants paper shading   # quick screening
    python bench/quality.py --asset RobotExpressive --variants paper default        # novel poses (test_clip:
                                                            # Walking -> Wave, Dance)

Variants (a training preset plus TrainConfig overrides, on top of the demo preset's short schedule;
all but ``default`` start from the ``paper`` preset):
  paper         the paper-faithful baseline: one colour per Gaussian, colours from the first frame
                (what the demo trained with before the quality preset; ``full`` is an alias)
  no_walk       walking disabled: (u+du, v+dv) clipped to the embedding triangle (paper, Table A2)
  frozen        embedding frozen: no du, dv, d (paper, Fig. 7 "w/o trainable embedding")
  scale_area    the paper's pose scale (times the area ratio) instead of our sqrt_area default
  unfold        walking with the exact unfold mode instead of the paper's re-expression
  shading       pose-dependent shading: albedo x learned SH irradiance of the posed Phong normal
  shading_axis  the same, shading the Gaussian's shortest axis instead of the Phong normal
  sh1_world     SH degree 1, view direction in world space (the published code)
  sh1_triangle  SH degree 1, view direction in the embedding triangle's frame
  init_multi    initial colours averaged over 8 training frames (facing the camera, in the mask)
  mask_loss     + 0.1 |rendered alpha - mask|
  antialiased   opacity compensated for the rasterizer's 0.3 px^2 low-pass (gsplat "antialiased")
  dens_low      densification threshold grow_grad2d 1e-4 instead of 2e-4 (the subject is a small target)
  lr_color      colour learning rate 1e-2 instead of 2.5e-3 (short runs)
  default       the ``quality`` training preset (the default of meshsplat train and the demo)
  lpips_every2  ``default`` with LPIPS on every 2nd iteration, twice its weight (loss.lpips_every=2)
  lpips_every4  ``default`` with LPIPS on every 4th iteration, 4x its weight
  lpips_every4_unscaled  every 4th iteration at the plain weight (lambda_lpips 0.01 / 4 x 4): a quarter of
                the mean LPIPS weight, to compare with the scaled one under Adam
  no_lpips      ``default`` without LPIPS (lambda_lpips=0): the bound of what skipping LPIPS can cost
  lpips_fp32    ``default`` with LPIPS's backbone in float32 (loss.lpips_precision=float32)
  lpips_bf16    ``default`` with LPIPS's backbone in bfloat16 (loss.lpips_precision=bfloat16, ~2x faster on CPUs
                with native bf16)

Prints full-image and subject (inside the mask) PSNR / SSIM / LPIPS per test split and saves
bench/results/<name>-<host>.json after every variant (a rerun resumes finished variants' runs).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from _machine import machine_info, results_path

# name -> (training preset, TrainConfig overrides on top of it)
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "paper": ("paper", []),
    "full": ("paper", []),
    "no_walk": ("paper", ["walk.enabled=false"]),
    "frozen": ("paper", ["model.freeze_embedding=true"]),
    "scale_area": ("paper", ["model.scale_mode=area"]),
    "unfold": ("paper", ["walk.mode=unfold"]),
    "shading": ("paper", ["shading.enabled=true"]),
    "shading_axis": ("paper", ["shading.enabled=true", "shading.normal=axis"]),
    "sh1_world": ("paper", ["model.sh_degree=1"]),
    "sh1_triangle": ("paper", ["model.sh_degree=1", "model.sh_frame=triangle"]),
    "init_multi": ("paper", ["model.init_color_frames=8"]),
    "mask_loss": ("paper", ["mask_loss.weight=0.1"]),
    "antialiased": ("paper", ["model.antialiased=true"]),
    "dens_low": ("paper", ["strategy.grow_grad2d=1e-4"]),
    "lr_color": ("paper", ["optim.lr_color=1e-2"]),
    "default": ("quality", []),
    "lpips_every2": ("quality", ["loss.lpips_every=2"]),
    "lpips_every4": ("quality", ["loss.lpips_every=4"]),
    "lpips_every4_unscaled": ("quality", ["loss.lpips_every=4", "loss.lambda_lpips=0.0025"]),
    "no_lpips": ("quality", ["loss.lambda_lpips=0"]),
    "lpips_fp32": ("quality", ["loss.lpips_precision=float32"]),
    "lpips_bf16": ("quality", ["loss.lpips_precision=bfloat16"]),
}
KEYS = ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask", "psnr_crop", "ssim_crop", "lpips_crop")


def _dataset(args, preset, work: Path) -> Path:
    from meshsplat.demo import _generate

    if args.asset == "CesiumMan" and args.resolution is None and args.frames is None:
        return _generate(work / "data", preset, progress=False)
    from meshsplat.paths import asset
    from meshsplat.synth import synthesize

    data = work / "data"
    if not (data / "manifest.json").exists():
        synthesize(
            asset(f"gltf/{args.asset}.glb"),
            data,
            rig="monocular-turn",
            frames=preset.frames,
            resolution=preset.resolution,
            test_views=preset.test_views,
            driver_smooth=5,
            clip=args.clip,
            test_clips=args.test_clips,
            overwrite=True,
        )
    return data


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--iters", type=int, default=None)
    ap.add_argument("--resolution", type=int, default=None, help="override the preset's image size")
    ap.add_argument("--frames", type=int, default=None, help="override the preset's training frames")
    ap.add_argument("--asset", default="CesiumMan", help="shared glTF asset (CesiumMan, RobotExpressive)")
    ap.add_argument("--clip", default=None, help="training clip (RobotExpressive: Walking)")
    ap.add_argument("--test-clips", nargs="*", default=None, help="novel-pose clips (split test_clip)")
    ap.add_argument("--work", default=None, help="scratch folder (dataset + runs)")
    ap.add_argument(
        "--variants", nargs="*", default=["paper", "no_walk", "frozen", "shading", "default"], choices=list(VARIANTS)
    )
    ap.add_argument("--set", nargs="*", default=[], help="extra TrainConfig overrides for every variant")
    ap.add_argument("--name", default="quality", help="results file bench/results/<name>-<host>.json")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 on a shared machine)")
    args = ap.parse_args()

    from dataclasses import replace

    import torch

    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.eval import evaluate_run
    from meshsplat.train import Trainer

    torch.set_num_threads(args.threads)
    preset = PRESETS[args.preset]
    if args.iters:
        preset = replace(preset, iterations=args.iters)
    if args.resolution:
        preset = replace(preset, resolution=args.resolution)
    if args.frames:
        preset = replace(preset, frames=args.frames)
    work = Path(args.work or f"runs/bench-{args.name}")
    data = _dataset(args, preset, work)
    out = results_path(args.name)
    rows = {}
    for name in args.variants:
        train_preset, overrides = VARIANTS[name]
        cfg = demo_train_config(data, work / name, preset, overrides + args.set, progress=False, recipe=train_preset)
        c0 = time.process_time()
        t0 = time.perf_counter()
        trainer = Trainer(cfg, resume=True)
        trainer.train()
        train_s = time.perf_counter() - t0
        cpu_s = time.process_time() - c0
        m = evaluate_run(work / name, report=True)
        rows[name] = {
            "train_s": train_s,
            "train_cpu_s": cpu_s,
            "gaussians": trainer.num_gaussians,
            "preset": train_preset,
            "overrides": overrides + args.set,
            "walked_total": getattr(trainer, "walked_total", None),
            "splits": {s: {k: v.get(k) for k in KEYS} for s, v in m["splits"].items()},
        }
        print(f"[{name}] trained in {train_s:.0f} s", flush=True)
        out.write_text(
            json.dumps(
                {
                    "machine": machine_info(),
                    "preset": args.preset,
                    "asset": args.asset,
                    "clip": args.clip,
                    "test_clips": args.test_clips,
                    "data": str(data),
                    "iterations": preset.iterations,
                    "resolution": preset.resolution,
                    "frames": preset.frames,
                    "variants": rows,
                },
                indent=2,
            )
            + "\n"
        )

    splits = sorted({s for r in rows.values() for s in r["splits"]})
    fmt = lambda x, d: "-" if x is None else f"{x:.{d}f}"  # noqa: E731
    print(f"\n{args.asset}, {preset.iterations} iterations, {preset.resolution}px; full image | inside the mask")
    print(
        f"{'variant':<22}{'split':<12}{'PSNR':>7}{'SSIM':>7}{'LPIPS':>7} |{'PSNR':>7}{'SSIM':>7}{'LPIPS':>7}"
        f"{'N':>7}{'train s':>8}"
    )
    for name, r in rows.items():
        for s in splits:
            m = r["splits"].get(s, {})
            print(
                f"{name:<22}{s:<12}{fmt(m.get('psnr'), 2):>7}{fmt(m.get('ssim'), 3):>7}{fmt(m.get('lpips'), 3):>7} |"
                f"{fmt(m.get('psnr_mask'), 2):>7}{fmt(m.get('ssim_mask'), 3):>7}{fmt(m.get('lpips_mask'), 3):>7}"
                f"{r['gaussians']:>7}{r['train_s']:>8.0f}"
            )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
