"""Evaluate a trained run on its dataset's test splits (PSNR, SSIM, LPIPS; writes RUN/eval/).

Examples:
  meshsplat eval runs/cesium                       # all splits except "train", dataset from RUN/config.json
  meshsplat eval runs/cesium --splits test_views --max-frames 10 --background black
  meshsplat eval runs/body --fit-poses 100          # held-out SMPL poses fitted to their images first

Renders and ground truth share one background colour (ground truth composited through its mask);
writes metrics.json, samples_<split>.png (ground truth | render | error), curves.png and report.html.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from meshsplat.cli._guards import check_output_dir, check_range
from meshsplat.cli._options import (
    add_downscale_option,
    add_drop_bad_frames_option,
    add_render_options,
    add_run_argument,
    render_options,
)
from meshsplat.cli.threads import add_threads_argument, apply_threads
from meshsplat.errors import MeshsplatError
from meshsplat.eval import evaluate_run
from meshsplat.run_folder import TRACKED_POSES_FLAG, RunFolder

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_argument(parser)
    parser.add_argument("--splits", nargs="+", default=None, help="splits to evaluate (default: all but train)")
    parser.add_argument("--out", default=None, help="output folder (default RUN/eval)")
    parser.add_argument("--max-frames", type=int, default=None, help="at most this many frames per split")
    add_downscale_option(parser, "the run's (data_downscale in RUN/config.json)")
    add_render_options(parser)
    add_drop_bad_frames_option(parser)
    add_threads_argument(parser)
    parser.add_argument("--no-lpips", action="store_true", help="skip LPIPS")
    parser.add_argument("--no-report", action="store_true", help="only metrics.json (no figures, no HTML)")
    parser.add_argument(
        TRACKED_POSES_FLAG,
        action="store_true",
        help="render held-out views of training frames in the tracker's poses, not the poses training refined",
    )
    parser.add_argument(
        "--fit-poses",
        type=int,
        default=0,
        metavar="STEPS",
        help="fit the body/head-model pose of each held-out frame to its own test images for STEPS Adam steps, "
        "the avatar frozen, before scoring (the protocol of papers on monocular body captures: scores then "
        "measure appearance, not the tracker's pose error; not comparable with tracked-pose scores). "
        "Captures with SMPL/SMPL-X/FLAME parameters only; default 0: the tracker's poses",
    )
    parser.add_argument("--fit-poses-lr", type=float, default=1e-3, help="learning rate of --fit-poses (default 1e-3)")


def run(args: argparse.Namespace) -> int:
    check_range("--max-frames", args.max_frames, "eval --max-frames")
    if args.fit_poses < 0 or args.fit_poses > 100_000:
        raise MeshsplatError(f"--fit-poses: expected 0 to 100000 steps, got {args.fit_poses}")
    if not 0 < args.fit_poses_lr < 1:
        raise MeshsplatError(f"--fit-poses-lr: expected a rate in (0, 1), got {args.fit_poses_lr}")
    if args.out or Path(args.run).is_dir():
        check_output_dir(args.out if args.out else RunFolder(args.run).eval_dir)
    opts = render_options(args)
    apply_threads(args)

    m = evaluate_run(
        args.run,
        dataset=args.dataset,
        splits=args.splits,
        out_dir=args.out,
        max_frames_per_split=args.max_frames,
        background=opts.background or "white",
        device=opts.device,
        lpips_net=None if args.no_lpips else "alex",
        report=not args.no_report,
        backend=opts.backend,
        progress=opts.progress,
        drop_bad_frames=True if args.drop_bad_frames else None,
        downscale=args.downscale,
        allow_older_checkpoint=args.allow_older_checkpoint,
        refined_poses=not args.tracked_poses,
        fit_poses=args.fit_poses,
        fit_poses_lr=args.fit_poses_lr,
    )
    print(
        f"checkpoint {m['checkpoint']} (iteration {m['iteration']}, {m['n_gaussians']} Gaussians), "
        f"background {m['background']}"
        + (f", {m['refined_pose_frames']} frames in the poses training refined" if m.get("refined_pose_frames") else "")
        + (
            f", {m['fitted_pose_frames']} held-out frames in poses fitted to their own images ({args.fit_poses} steps)"
            if m.get("fit_poses")
            else ""
        )
    )

    def fmt(x: float | None, d: int) -> str:
        return "-" if x is None else f"{x:.{d}f}"

    print(f"{'':<23}{'full image':^25}{'subject (in mask)':^25}")
    print(
        f"{'split':<16}{'frames':>7}{'PSNR':>9}{'SSIM':>8}{'LPIPS':>8}{'PSNR':>9}{'SSIM':>8}{'LPIPS':>8}{'ms/frame':>10}"
    )
    for name, s in m["splits"].items():
        print(
            f"{name:<16}{s['n_frames']:>7}{fmt(s['psnr'], 2):>9}{fmt(s['ssim'], 3):>8}{fmt(s['lpips'], 3):>8}"
            f"{fmt(s.get('psnr_mask'), 2):>9}{fmt(s.get('ssim_mask'), 3):>8}{fmt(s.get('lpips_mask'), 3):>8}"
            f"{fmt(s['render_ms'], 1):>10}"
        )
    if m.get("lpips_note"):
        print(f"note: {m['lpips_note']}")
    print(f"wrote {m['files'].get('report', m['files']['metrics'])}")
    return 0
