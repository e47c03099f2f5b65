"""From a video to a viewable head avatar with the README's own commands, timed: track, train with a
time budget, view, then eval for the held-out metrics (not counted in the time).

    python bench/own_video_time.py VIDEO [--size 512] [--fps 15] [--minutes 8] [--work runs/bench-own-video]

Each command runs as a user would run it (`meshsplat ...` in a subprocess); the table gives wall time per
step and in all, and the held-out frames' metrics; bench/results/own_video_time-<host>.json keeps them
under ``<video stem>@<size>``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _machine import machine_info, results_path

# the console script installed beside this Python (as a user types it), else the one on PATH
MESHSPLAT = [
    str(Path(sys.executable).with_name("meshsplat"))
    if Path(sys.executable).with_name("meshsplat").exists()
    else "meshsplat"
]


def run(step: str, argv: list[str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run([*MESHSPLAT, *argv], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{step} failed:\n{proc.stderr[-2000:]}")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("video", type=Path)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--fps", type=float, default=15)
    ap.add_argument("--minutes", type=float, default=8)
    ap.add_argument("--work", type=Path, default=Path("runs/bench-own-video"))
    ap.add_argument("--name", default="own_video_time")
    args = ap.parse_args()
    if args.work.exists():
        shutil.rmtree(args.work)
    cap, run_dir, viewer = args.work / "capture", args.work / "run", args.work / "viewer"
    common = ["--no-progress"]
    times = {
        "track": run(
            "track",
            ["track", str(args.video), "--out", str(cap), "--size", str(args.size), "--fps", str(args.fps), *common],
        ),
        "train": run("train", ["train", str(cap), "--out", str(run_dir), "--minutes", str(args.minutes), *common]),
        "view": run("view", ["view", str(run_dir), "--out", str(viewer)]),
    }
    times["total"] = sum(times.values())
    run("eval", ["eval", str(run_dir), "--no-report", *common])
    metrics = json.loads((run_dir / "eval" / "metrics.json").read_text())["splits"]["test_frames"]
    path = results_path(args.name)
    results = json.loads(path.read_text()) if path.exists() else {}
    results["machine"] = machine_info()
    key = f"{args.video.stem}@{args.size}"
    results[key] = {"seconds": times, "minutes_budget": args.minutes, "fps": args.fps, "test_frames": metrics}
    path.write_text(json.dumps(results, indent=1))
    print(f"{'step':8s} {'wall s':>8s}")
    for k, v in times.items():
        print(f"{k:8s} {v:8.1f}")
    keys = ("psnr", "ssim", "lpips", "psnr_mask", "lpips_mask")
    print("held-out frames: " + ", ".join(f"{k} {metrics[k]:.4g}" for k in keys if metrics.get(k) is not None))
    print(f"saved {path}")


if __name__ == "__main__":
    main()
