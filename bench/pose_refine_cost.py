"""What pose refinement (on by default for body/head-model captures) costs in training time.

    python bench/pose_refine_cost.py                       # demo sizes: 256², 100 frames, 1500 iterations
    python bench/pose_refine_cost.py --data DIR --model-dir MODELS --repeats 2
    python bench/pose_refine_cost.py --tiny                # seconds, to check the script

Trains the default (``quality`` preset, the demo's schedule as ``bench/quality_pbr.py`` scales it) on an
SMPL capture with tracking noise twice per repeat, without and with pose refinement
(``pose_refine.enabled=false`` / ``true``), in the order off, on, on, off, ... so a change of the machine's
load and one-off costs of the first run hit both alike, and prints the training seconds of every run, their
medians and the ratio. Without ``--data`` it synthesizes the stand-in SMPL body dancing the bundled
AIST++ motion (Lambert renderer, ``--pose-noise`` radians). Saves bench/results/<name>-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from _machine import machine_info, results_path
from quality_pbr import _schedule


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None, help="an SMPL/FLAME capture (default: synthesized)")
    ap.add_argument("--model-dir", type=Path, default=None, help="its model files (default: stand-in files)")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--iters", type=int, default=1500)
    ap.add_argument("--n-init", type=int, default=10_000)
    ap.add_argument("--pose-noise", type=float, default=0.03)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--tiny", action="store_true", help="32 px, 6 frames, 30 iterations, 500 Gaussians")
    ap.add_argument("--name", default="pose_refine_cost")
    args = ap.parse_args()
    if args.tiny:
        args.frames, args.resolution, args.iters, args.n_init = 6, 32, 30, 500

    import torch

    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.synth import synthesize
    from meshsplat.synth.standin_models import write_standin_models
    from meshsplat.train import Trainer

    torch.set_num_threads(args.threads)
    work = Path(tempfile.mkdtemp(prefix="pose_refine_cost-"))
    models = args.model_dir or write_standin_models(work / "models")
    data = args.data
    if data is None:
        data = synthesize(
            "smpl",
            work / "data",
            frames=args.frames,
            resolution=args.resolution,
            model_dir=models,
            pose_noise=args.pose_noise,
            threads=args.threads,
        )
    sizes = replace(PRESETS["default"], iterations=args.iters, n_init=args.n_init, overrides=_schedule(args.iters))
    runs: dict[str, list[float]] = {"off": [], "on": []}
    notes: dict[str, str | None] = {}
    for rep in range(args.repeats):
        order = (("off", "false"), ("on", "true"))
        for tag, auto in order if rep % 2 == 0 else order[::-1]:  # off, on, on, off, ...: first-run costs spread
            out = work / f"run-{tag}-{rep}"
            overrides = [f"model_dir={models}", f"pose_refine.enabled={auto}"]
            cfg = demo_train_config(Path(data), out, sizes, overrides, progress=False)
            t0 = time.perf_counter()
            trainer = Trainer(cfg)
            trainer.train()
            runs[tag].append(time.perf_counter() - t0)
            notes[tag] = trainer.pose_refine_note
            print(f"repeat {rep} refinement {tag}: {runs[tag][-1]:.1f} s", flush=True)
    med = {k: statistics.median(v) for k, v in runs.items()}
    print(f"\n{'refinement':<12}{'runs (s)':<28}{'median (s)':>12}")
    for k, v in runs.items():
        print(f"{k:<12}{' / '.join(f'{x:.1f}' for x in v):<28}{med[k]:>12.1f}")
    print(f"ratio on / off: {med['on'] / med['off']:.2f}x ({notes['on']})")
    out = results_path(args.name)
    doc = {
        "machine": machine_info(),
        "args": {k: str(v) for k, v in vars(args).items()},
        "train_s": runs,
        "median_s": med,
        "ratio": med["on"] / med["off"],
        "notes": notes,
    }
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"saved {out}")


if __name__ == "__main__":
    main()
