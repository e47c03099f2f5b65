"""What checking every frame's mask at the door costs (``data.camera_check``, issue 44).

    python bench/camera_check_cost.py                # 170 CesiumMan frames at 540 px (PeopleSnapshot-sized)
    python bench/camera_check_cost.py --frames 24 --resolution 128   # seconds

Synthesizes one capture, then opens it alternately with the masks checked (every frame: the mask decoded,
pooled and the mesh projected onto it; the reader's own checks, which decode every mask for emptiness,
included) and with ``check_masks=False`` (geometry only), ``--repeats`` times each, one thread. Prints the
medians and the difference per frame; saves bench/results/camera_check_cost-<host>.json.
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
from meshsplat.data import open_dataset
from meshsplat.synth import synthesize


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=170)
    ap.add_argument("--resolution", type=int, default=540)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        root = synthesize(
            "CesiumMan", Path(tmp) / "ds", frames=args.frames, resolution=args.resolution, test_frames=0, test_views=0
        )
        n = len(open_dataset(root))
        times: dict[str, list[float]] = {"masks": [], "geometry": []}
        for _ in range(args.repeats):
            for name, masks in (("masks", True), ("geometry", False)):
                t0 = time.perf_counter()
                open_dataset(root, check_masks=masks)
                times[name].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in times.items()}
    per_frame_ms = 1000 * (med["masks"] - med["geometry"]) / n
    print(
        f"{n} frames at {args.resolution} px: open with every mask checked {med['masks'] * 1000:.0f} ms, "
        f"geometry only {med['geometry'] * 1000:.0f} ms (medians of {args.repeats}): {per_frame_ms:.1f} ms a frame"
    )
    out = results_path("camera_check_cost")
    out.write_text(
        json.dumps(
            {
                "machine": machine_info(),
                "frames": n,
                "resolution": args.resolution,
                "repeats": args.repeats,
                "seconds": times,
                "median_s": med,
                "masks_ms_per_frame": per_frame_ms,
            },
            indent=2,
        )
        + "\n"
    )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
