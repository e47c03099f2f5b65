"""Bring-your-own-mesh check: a procedural z-up creature in centimetres (and the same in metres),
through the command line a user runs: synth -> train -> eval -> render by the asset's own sequence.

Default: 60 training frames at 128 px, 400 iterations, 1 thread (a few minutes per unit on 2 cores);
``--quick``: 12 frames at 64 px, 60 iterations. Prints the metrics and the last logged loss/scale of
both units; saves bench/results/own_mesh-<hostname>.json. The creature is tests/_creature.py.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _creature import write_creature_npz
from _machine import machine_info, results_path
from meshsplat.cli.main import main as cli

TRAIN_SET = (
    "strategy.refine_start_iter=100",
    "strategy.refine_stop_iter=350",
    "strategy.refine_every=50",
    "strategy.reset_every=100000",
    "walk.every=50",
    "preview_every=200",
    "checkpoint_every=200",
    "log_every=20",
    "model.n_init=6000",
)


def _run(cmd: list[str]) -> None:
    rc = cli(cmd)
    if rc != 0:
        raise SystemExit(f"meshsplat {' '.join(cmd)} exited {rc}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--keep", default=None, help="work folder to keep (default: a temporary one)")
    args = ap.parse_args()
    frames, res, iters = (12, 64, 60) if args.quick else (60, 128, 400)
    work = Path(args.keep or tempfile.mkdtemp(prefix="meshsplat-own-"))
    work.mkdir(parents=True, exist_ok=True)
    cm = write_creature_npz(work / "creature.npz", frames_per_clip=48)
    d = dict(np.load(cm))
    d["vertices"] = d["vertices"] * 0.01
    np.savez(work / "creature_m.npz", **d)
    out = {"machine": machine_info(), "frames": frames, "resolution": res, "iterations": iters, "units": {}}
    for unit, asset in (("cm", cm), ("m", work / "creature_m.npz")):
        ds, run = work / f"ds_{unit}", work / f"run_{unit}"
        t = time.perf_counter()
        _run(
            [
                "synth",
                str(asset),
                "--out",
                str(ds),
                "--resolution",
                str(res),
                "--frames",
                str(frames),
                "--threads",
                "1",
                "--overwrite",
            ]
        )
        t_synth = time.perf_counter() - t
        t = time.perf_counter()
        train = ["train", str(ds), "--out", str(run), "--iters", str(iters), "--threads", "1", "--no-progress"]
        for s in TRAIN_SET:
            train += ["--set", s]
        _run(train)
        t_train = time.perf_counter() - t
        _run(["eval", str(run), "--threads", "1", "--no-progress"])
        metrics = json.loads((run / "eval" / "metrics.json").read_text())
        with open(run / "log.csv") as fh:
            last = list(csv.DictReader(fh))[-1]
        out["units"][unit] = {
            "synth_s": round(t_synth, 1),
            "train_s": round(t_train, 1),
            "last_loss": float(last["loss"]),
            "last_scale": float(last["scale"]),
            "splits": {
                k: {m: v.get(m) for m in ("psnr", "ssim", "lpips", "psnr_mask", "n_frames")}
                for k, v in metrics["splits"].items()
            },
        }
    _run(
        [
            "render",
            str(work / "run_cm"),
            "--animation",
            "vertices",
            str(cm),
            "--size",
            f"{res}x{res}",
            "--orbit",
            "90",
            "--no-mp4",
            "--no-progress",
            "--threads",
            "1",
            "--out",
            str(work / "anim"),
        ]
    )
    print(f"\n{'unit':<5}{'split':<13}{'PSNR':>7}{'SSIM':>7}{'LPIPS':>7}  last loss / scale")
    for unit, r in out["units"].items():
        for k, s in r["splits"].items():
            print(
                f"{unit:<5}{k:<13}{s['psnr']:>7.2f}{s['ssim']:>7.3f}{(s['lpips'] or 0):>7.3f}"
                f"  {r['last_loss']:.4g} / {r['last_scale']:.4g}"
            )
    path = results_path("own_mesh")
    path.write_text(json.dumps(out, indent=1))
    print(f"saved {path}; work folder {work}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
