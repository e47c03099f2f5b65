"""PeopleSnapshot test protocol: the same trained avatar evaluated with each split posed by its own
parameter file (``shape="per_split"``, InstantAvatar / SplattingAvatar) and with the train betas for
every frame (``shape="train"``).

A stand-in SMPL capture in the PeopleSnapshot layout whose images have one true shape B. As with the
released refined files, each split's file carries its own betas: the test file B (the shape its images
show), the train file B + delta (its refinement drifted). One training run (train frames use the train
file either way), two evaluations. Results: bench/results/protocol-<machine>.json.

    python bench/protocol.py [--iters 300] [--resolution 128] [--frames 40]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from _machine import machine_info, results_path
from meshsplat.data import open_dataset
from meshsplat.data.formats import peoplesnapshot as ps
from meshsplat.demo import PRESETS, demo_train_config
from meshsplat.eval import evaluate_run
from meshsplat.synth import synthesize
from meshsplat.synth.standin_models import write_standin_models
from meshsplat.train import Trainer

KEYS = ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")
DELTA = np.array([0.31, -0.2, 0.15, 0, 0, 0, 0, 0, 0, 0], np.float32)  # train file's drift (max 0.31, as issue)


def _split_files(root: Path) -> None:
    """poses/anim_nerf_{train,test}.npz from poses.npz rows: train betas B + DELTA, test betas B."""
    cfg = json.loads((root / "config.json").read_text())
    with np.load(root / "poses.npz") as z:
        betas, thetas, transl = z["betas"].reshape(1, -1), z["thetas"], z["transl"]
    (root / "poses").mkdir(exist_ok=True)
    for split, b in (("train", betas + DELTA), ("test", betas)):
        r = cfg[split]
        rows = list(range(r["start"], r["end"] + 1, r.get("skip", 1)))
        np.savez(
            root / "poses" / f"anim_nerf_{split}.npz",
            betas=b.astype(np.float32),
            global_orient=thetas[rows, :3],
            body_pose=thetas[rows, 3:],
            transl=transl[rows],
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iters", type=int, default=300)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--work", default="runs/bench-protocol")
    args = ap.parse_args()
    work = Path(args.work)
    models = work / "models"
    if not (models / "smpl").is_dir():
        write_standin_models(models)
    native, data = work / "native", work / "peoplesnapshot"
    if not (native / "manifest.json").is_file():
        synthesize("smpl", native, frames=args.frames, resolution=args.resolution, test_views=0, model_dir=models)
    if not data.is_dir():
        ps.write(open_dataset(native), data)
        _split_files(data)
    run = work / "run"
    preset = PRESETS["default"]
    cfg = demo_train_config(data, run, preset, progress=False)
    cfg.iterations = args.iters
    cfg.model_dir = str(models)
    t0 = time.perf_counter()
    Trainer(cfg, resume=True).train()
    train_s = time.perf_counter() - t0
    rows = {}
    for shape in ps.SHAPE_MODES:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = ps.read(data, model_dir=models, shape=shape)
        m = evaluate_run(run, dataset=ds, report=False, out_dir=work / f"eval_{shape}")
        rows[shape] = {k: m["splits"]["test_frames"].get(k) for k in KEYS}
        rows[shape]["betas"] = ds.meta["betas"]
        print(shape, json.dumps(rows[shape]), flush=True)
    out = {
        "machine": machine_info(),
        "iterations": args.iters,
        "resolution": args.resolution,
        "frames": args.frames,
        "train_s": train_s,
        "delta_betas": DELTA.tolist(),
        "results": rows,
    }
    path = results_path("protocol")
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(path)


if __name__ == "__main__":
    main()
