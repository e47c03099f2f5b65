"""Real full-body videos through `meshsplat track --subject body` + train + eval, scored on held-out later
frames.

    python bench/track_bodies.py VIDEO_DIR [--size 256] [--iters 1500] [--fps 12] [--max-frames 150]
                                 [--work runs/bench-track-bodies] [--clips a b] [--name track_bodies]

For each video in VIDEO_DIR (``*.mp4 *.mov *.webm *.mkv``; sources and licences in its SOURCES.md; the
videos are not in the repository, bench/reports/track_bodies.md says where they come from):

1. ``track``: the body tracker writes the capture (first 80% of the frames train, the last 20% are held
   out: later poses); its 2D keypoint reprojection error (train and held-out frames), the part of the
   person matte beyond the body model (loose clothing, hair) and the tracking time are recorded.
2. ``train``: the default recipe with pose refinement (on by default for tracked bodies) at ``--iters``
   (densification from 1/5 to 4/5), through the command line, timed.
3. ``eval``: the held-out frames (tracked poses) rendered and scored against the photograph: in the
   person matte and on the full image with the photograph composited by its matte, on white and on
   black (PSNR, SSIM; LPIPS when its weights are installed); eval's picture (photograph | render |
   error) is copied to bench/results/<name>-<clip>-<background>.png.
4. where the error is, on black (``meshsplat.metrics.budget``): the share of the held-out frames' squared error
   in the silhouette band (2 px either side of the mask's edge), the interior and outside; and the part of
   the mask's weight on near-white pixels (every channel within 0.08 of 1): on a white studio background
   that is background the person matte took in (between the legs, halos), elsewhere white clothes count too.

``--reuse`` scores the capture and run already in ``--work`` (no tracking or training; times are not kept).

Prints a table and writes bench/results/<name>-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from _machine import RESULTS, machine_info, results_path
from meshsplat.track.body_capture import track_body
from meshsplat.track.clip import TrackSettings

VIDEO_SUFFIXES = (".mp4", ".mov", ".webm", ".mkv", ".avi")


def _meshsplat(*argv: str) -> None:
    subprocess.run([sys.executable, "-m", "meshsplat.cli.main", *argv], check=True)


def train(capture: Path, run: Path, iters: int, threads: int) -> float:
    if run.exists():
        shutil.rmtree(run)
    sets = [
        f"strategy.refine_start_iter={iters // 5}",
        f"strategy.refine_stop_iter={iters * 4 // 5}",
        "strategy.refine_every=100",
        "strategy.max_gaussians=40000",
        "preview_every=1000000",
        f"checkpoint_every={iters}",
        "model.n_init=10000",
    ]
    argv = ["train", str(capture), "--out", str(run), "--iters", str(iters), "--no-progress"]
    argv += ["--threads", str(threads)]
    for s in sets:
        argv += ["--set", s]
    t0 = time.perf_counter()
    _meshsplat(*argv)
    return time.perf_counter() - t0


def evaluate(run: Path, background: str) -> dict:
    _meshsplat("eval", str(run), "--background", background, "--no-progress", "--splits", "test_frames")
    m = json.loads((run / "eval" / "metrics.json").read_text())["splits"]["test_frames"]
    return {k: m.get(k) for k in ("n_frames", "psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")}


def where_the_error_is(capture: Path, run: Path) -> dict:
    """The held-out frames (tracked poses) on black: the error's shares by region of the mask, and the mask's
    weight on near-white pixels (all held-out and training frames)."""
    import torch

    from meshsplat.data import open_dataset
    from meshsplat.metrics.budget import BUDGET_REGIONS, error_budget
    from meshsplat.render.background import composite
    from meshsplat.run_folder import load_run

    loaded = load_run(run)
    ds = loaded.open_dataset(capture)
    black = torch.zeros(3)
    sse = dict.fromkeys(BUDGET_REGIONS, 0.0)
    for i in ds.split("test_frames"):
        fr = ds[i]
        with torch.no_grad():
            img = loaded.avatar.render(fr.vertices, fr.camera, black).image.float().clamp(0, 1)
        b = error_budget(img, composite(fr.image, fr.mask, black), fr.mask)
        for r in BUDGET_REGIONS:
            sse[r] += b[f"sse_{r}"]
    total = sum(sse.values()) or 1.0
    plain = open_dataset(capture)
    white = [
        float((fr.mask[..., 0] * ((1 - fr.image).abs().amax(-1) < 0.08)).sum() / fr.mask.sum().clamp_min(1e-6))
        for fr in (plain[i] for i in range(len(plain)))
    ]
    return {
        **{f"share_{r}": sse[r] / total for r in BUDGET_REGIONS},
        "mask_on_near_white": float(np.mean(white)),
        "mask_on_near_white_max": float(np.max(white)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("videos", type=Path)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--iters", type=int, default=1500)
    ap.add_argument("--fps", type=float, default=12.0)
    ap.add_argument("--max-frames", type=int, default=150)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("runs/bench-track-bodies"))
    ap.add_argument("--clips", nargs="*", default=None)
    ap.add_argument("--name", default="track_bodies")
    ap.add_argument("--reuse", action="store_true", help="score the captures and runs already in --work")
    args = ap.parse_args()
    videos = sorted(p for p in args.videos.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if args.clips:
        videos = [v for v in videos if v.stem in args.clips]
    rows = []
    for video in videos:
        work = args.work / video.stem
        cap, run = work / "capture", work / "run"
        if args.reuse:
            splits = json.loads((cap / "manifest.json").read_text())["splits"]
            n_train, n_test = len(splits["train"]), len(splits["test_frames"])
            row: dict = {"clip": video.stem, "frames": n_train + n_test, "train": n_train, "test": n_test}
        else:
            settings = TrackSettings(size=args.size, fps=args.fps, max_frames=args.max_frames, overwrite=True)
            t0 = time.perf_counter()
            res = track_body(video, cap, settings)
            t_track = time.perf_counter() - t0
            t_train = train(cap, run, args.iters, args.threads)
            n_train = res.train
            row = {
                "clip": video.stem,
                "frames": res.frames,
                "train": res.train,
                "test": res.test,
                "dropped": len(res.dropped),
                "track_s": t_track,
                "track_stages_s": res.seconds,
                "train_s": t_train,
                "notes": res.notes,
            }
        fit = np.load(cap / "body_fit.npz")
        err = fit["error_px"]
        row["keypoint_px_train"] = float(err[:n_train].mean())
        row["keypoint_px_test"] = float(err[n_train:].mean())
        row["outside_body"] = float(fit["outside_body"].mean())
        for bg in ("white", "black"):
            row[bg] = evaluate(run, bg)
            sample = run / "eval" / "samples_test_frames.png"
            if sample.exists():
                RESULTS.mkdir(exist_ok=True)
                shutil.copy(sample, RESULTS / f"{args.name}-{video.stem}-{bg}.png")
        row["error_black"] = where_the_error_is(cap, run)
        rows.append(row)
        print(json.dumps(row, indent=1))
    print(
        f"{'clip':34s} {'frames':>6s} {'kp px tr/te':>12s} {'outside':>8s} {'PSNR w/b':>12s} {'mask w/b':>12s} "
        f"{'band/int/out':>14s} {'white':>6s} {'track s':>8s} {'train s':>8s}"
    )
    for r in rows:
        w, b, e = r["white"], r["black"], r["error_black"]
        shares = f"{e['share_band']:.2f}/{e['share_interior']:.2f}/{e['share_outside']:.2f}"
        print(
            f"{r['clip']:34s} {r['frames']:6d} {r['keypoint_px_train']:5.1f}/{r['keypoint_px_test']:5.1f} "
            f"{100 * r['outside_body']:7.1f}% {w['psnr']:5.2f}/{b['psnr']:5.2f} {w['psnr_mask']:5.2f}/{b['psnr_mask']:5.2f} "
            f"{shares:>14s} {100 * e['mask_on_near_white']:5.1f}% {r.get('track_s', float('nan')):8.1f} "
            f"{r.get('train_s', float('nan')):8.1f}"
        )
    out = results_path(args.name)
    out.write_text(
        json.dumps(
            {"machine": machine_info(), "args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=1
        )
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
