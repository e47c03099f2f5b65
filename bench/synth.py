"""Benchmark: generate CesiumMan frames with meshsplat.synth; prints seconds and saves JSON.

Default 100 training frames at 512x512 (goal < 60 s on a 2-core CPU); ``--quick``: 12 frames at 128.
Results: bench/results/synth-<hostname>.json.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from _machine import machine_info, results_path
from meshsplat.data import open_dataset
from meshsplat.synth import synthesize


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--resolution", type=int, default=None)
    args = ap.parse_args()
    frames = args.frames or (12 if args.quick else 100)
    res = args.resolution or (128 if args.quick else 512)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        out = synthesize("CesiumMan", Path(tmp) / "ds", frames=frames, resolution=res, test_frames=0, test_views=0)
        secs = time.perf_counter() - t0
        n = len(open_dataset(out, check_masks=False))
    result = {
        "benchmark": "synth",
        "asset": "CesiumMan",
        "frames": n,
        "resolution": res,
        "seconds": round(secs, 2),
        "seconds_per_frame": round(secs / n, 4),
        "goal_seconds_100_frames_512": 60,
        "machine": machine_info(),
        "quick": bool(args.quick),
    }
    print(f"synth: {n} frames of CesiumMan at {res}x{res} in {secs:.1f} s ({secs / n * 1000:.0f} ms/frame)")
    results_path("synth").write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
