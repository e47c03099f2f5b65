"""Run the end-to-end demo: synthesize CesiumMan, train, evaluate, render, export.

Writes everything under --out (default runs/demo) and prints a summary. Re-running the same
command resumes an interrupted demo from its last checkpoint.
"""

from __future__ import annotations

import argparse

from meshsplat.cli.threads import add_threads_argument, apply_threads
from meshsplat.demo import PRESETS, run_demo


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="runs/demo", help="output folder (default: runs/demo)")
    parser.add_argument(
        "--preset",
        default="default",
        choices=sorted(PRESETS),
        help="size of the run: default (a few minutes on 2 CPU cores) or tiny (seconds)",
    )
    parser.add_argument("--iters", type=int, default=None, help="override the number of training iterations")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    add_threads_argument(parser)


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.4f}" if x < 1 else f"{x:.2f}"


def run(args: argparse.Namespace) -> int:
    apply_threads(args)
    s = run_demo(args.out, preset=args.preset, progress=not args.quiet, iterations=args.iters)
    print()
    print(f"meshsplat demo — {s['asset']}")
    print(f"  trained {s['iterations']} iterations, {s['gaussians']} Gaussians")
    print(f"  {'':<14}{'full image':^24}{'subject (in mask)':^24}")
    print(f"  {'split':<14}{'PSNR':>8}{'SSIM':>8}{'LPIPS':>8}{'PSNR':>8}{'SSIM':>8}{'LPIPS':>8}")
    for name, m in s["metrics"].items():
        print(
            f"  {name:<14}{_fmt(m['psnr']):>8}{_fmt(m['ssim']):>8}{_fmt(m['lpips']):>8}"
            f"{_fmt(m.get('psnr_mask')):>8}{_fmt(m.get('ssim_mask')):>8}{_fmt(m.get('lpips_mask')):>8}"
        )
    print("  time (s): " + ", ".join(f"{k[:-2]} {v}" for k, v in s["timings_s"].items()))
    for k, v in s["outputs"].items():
        print(f"  {k:<14}{v}")
    return 0
