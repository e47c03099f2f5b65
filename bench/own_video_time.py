"""From a video to a viewable avatar with the README's own commands, timed: track, train with a time budget,
view; then, not counted in the time, eval for the held-out metrics and (bodies) the bundled AIST++ dance
rendered, with a picture of its frames and a check that the body stands upright in them.

    python bench/own_video_time.py VIDEO [--size 512] [--fps 15] [--minutes 8] [--work runs/bench-own-video]
    python bench/own_video_time.py VIDEO --subject body --fps 12 --minutes 14    # a body: issue 45's 20 minutes

Each command runs as a user would run it (`meshsplat ...` in a subprocess); the table gives wall time per
step and in all, and the held-out frames' metrics; bench/results/own_video_time-<host>.json keeps them
under ``<video stem>@<size>`` (``<video stem>@<size>-body`` for bodies).
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
    ap.add_argument("--subject", choices=["head", "body"], default="head")
    args = ap.parse_args()
    if args.work.exists():
        shutil.rmtree(args.work)
    cap, run_dir, viewer = args.work / "capture", args.work / "run", args.work / "viewer"
    common = ["--no-progress"]
    times = {
        "track": run(
            "track",
            [
                "track",
                str(args.video),
                "--out",
                str(cap),
                "--size",
                str(args.size),
                "--fps",
                str(args.fps),
                "--subject",
                args.subject,
                *common,
            ],
        ),
        "train": run("train", ["train", str(cap), "--out", str(run_dir), "--minutes", str(args.minutes), *common]),
        "view": run("view", ["view", str(run_dir), "--out", str(viewer)]),
    }
    times["total"] = sum(times.values())
    run("eval", ["eval", str(run_dir), "--no-report", *common])
    metrics = json.loads((run_dir / "eval" / "metrics.json").read_text())["splits"]["test_frames"]
    dance = dance_check(run_dir, args.work / "dance", args.size) if args.subject == "body" else None
    path = results_path(args.name)
    results = json.loads(path.read_text()) if path.exists() else {}
    results["machine"] = machine_info()
    key = f"{args.video.stem}@{args.size}" + ("-body" if args.subject == "body" else "")
    results[key] = {"seconds": times, "minutes_budget": args.minutes, "fps": args.fps, "test_frames": metrics}
    if dance:
        results[key]["dance"] = dance
    path.write_text(json.dumps(results, indent=1))
    print(f"{'step':8s} {'wall s':>8s}")
    for k, v in times.items():
        print(f"{k:8s} {v:8.1f}")
    keys = ("psnr", "ssim", "lpips", "psnr_mask", "lpips_mask")
    print("held-out frames: " + ", ".join(f"{k} {metrics[k]:.4g}" for k in keys if metrics.get(k) is not None))
    if dance:
        print(
            f"AIST++ dance: {dance['frames']} frames rendered in {dance['seconds']:.0f} s, upright in "
            f"{dance['upright_frames']} (subject taller than wide, head above hips); picture {dance['picture']}"
        )
    print(f"saved {path}")


def dance_check(run_dir: Path, out: Path, size: int) -> dict:
    """Render the bundled AIST++ dance on the body avatar (the orbit camera ``render`` chooses, no flags) and
    count the frames that stand upright: the subject taller than wide, or (arms out) its top tenth, the head,
    narrower than its middle."""
    import numpy as np
    from PIL import Image

    argv = ["render", str(run_dir), "--animation", "motion", "aist_demo", "--frames", "48"]
    argv += ["--size", f"{size}x{size}", "--background", "black", "--no-mp4", "--out", str(out), "--no-progress"]
    seconds = run("render", argv)
    frames = sorted((out / "frames").glob("*.png"))
    upright = 0
    for f in frames:
        fg = np.asarray(Image.open(f).convert("RGB"), np.float32).max(-1) > 8  # foreground on black
        widths, cols = fg.sum(1), np.nonzero(fg.any(0))[0]
        rows = np.nonzero(widths)[0]
        if not len(rows):
            continue
        top, h = rows[0], rows[-1] - rows[0] + 1
        head = widths[top : top + max(1, h // 10)].max()
        middle = widths[top + 4 * h // 10 : top + 6 * h // 10 + 1].max()
        upright += int(h > 1.2 * (cols[-1] - cols[0] + 1) or head < middle)
    picks = [frames[i] for i in np.linspace(0, len(frames) - 1, 6).astype(int)] if frames else []
    sheet = Image.new("RGB", (len(picks) * 160, 160))
    for k, f in enumerate(picks):
        sheet.paste(Image.open(f).convert("RGB").resize((160, 160)), (k * 160, 0))
    picture = out / "dance_sheet.png"
    sheet.save(picture)
    return {"frames": len(frames), "upright_frames": upright, "seconds": seconds, "picture": str(picture)}


if __name__ == "__main__":
    main()
