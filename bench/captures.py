"""Real-capture layouts end to end: the same synthetic capture, native and written in each layout.

    python bench/captures.py                 # demo sizes: 256 px, 1500 iterations per run
    python bench/captures.py --preset tiny   # seconds, to check the script

Stand-in SMPL / FLAME model files (meshsplat.synth.standin_models: a CesiumMan-derived body and an
ICT-derived head, not the licensed models) drive three synthetic captures: a body turning in front of
one camera (AIST++ dance poses), a talking head in front of one camera, and the head seen by a
multi-view rig. Each is trained natively and from every layout it can be written in
(body: peoplesnapshot; head: imavatar, insta; multi-view head: vhap) with the same schedule and seed.
Equal metrics prove the readers' conventions (cameras, pose layouts, scale, masks) match the writer's.

Prints format | detected as | frames | train s | PSNR/SSIM/LPIPS (full image and in the subject's
mask) on the held-out frames, and saves bench/results/captures-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

from _machine import machine_info, results_path

CAPTURES = {  # name -> (model, rig, layouts)
    "body": ("smpl", "monocular-turn", ["peoplesnapshot"]),
    "head": ("flame", "monocular-turn", ["imavatar", "insta"]),
    "head_mv": ("flame", "multiview", ["vhap"]),
}
KEYS = ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="default", choices=["default", "tiny"])
    ap.add_argument("--iters", type=int, default=None)
    ap.add_argument("--work", default="runs/bench-captures")
    ap.add_argument("--captures", nargs="*", default=list(CAPTURES), choices=list(CAPTURES))
    args = ap.parse_args()

    from meshsplat.data import open_dataset
    from meshsplat.data.formats import detect_format, format_module
    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.eval import evaluate_run
    from meshsplat.synth import synthesize
    from meshsplat.synth.standin_models import write_standin_models
    from meshsplat.train import Trainer

    preset = PRESETS[args.preset]
    if args.iters:
        preset = replace(preset, iterations=args.iters)
    work = Path(args.work)
    models = work / "models"
    if not (models / "flame").is_dir():
        write_standin_models(models)
    rows = []
    for cap in args.captures:
        kind, rig, layouts = CAPTURES[cap]
        native = work / cap / "native"
        if not (native / "manifest.json").is_file():
            t0 = time.perf_counter()
            synthesize(
                kind,
                native,
                rig=rig,
                frames=preset.frames,
                resolution=preset.resolution,
                test_views=0 if rig == "monocular-turn" else 1,
                model_dir=models,
                overwrite=True,
            )
            print(f"[{cap}] synthesized in {time.perf_counter() - t0:.0f} s", flush=True)
        for layout in ["native"] + layouts:
            data = native if layout == "native" else work / cap / layout
            if layout != "native" and not data.is_dir():
                format_module(layout).write(open_dataset(native), data)
            detected = detect_format(data)
            run = work / cap / f"run_{layout}"
            cfg = demo_train_config(data, run, preset, progress=False)
            cfg.model_dir = str(models)
            t0 = time.perf_counter()
            trainer = Trainer(cfg, resume=True)
            n_frames = len(trainer.dataset)
            trainer.train()
            train_s = time.perf_counter() - t0
            m = evaluate_run(run, report=False)
            split = "test_frames" if "test_frames" in m["splits"] else sorted(m["splits"])[0]
            res = {k: m["splits"][split].get(k) for k in KEYS}
            rows.append(
                {
                    "capture": cap,
                    "layout": layout,
                    "detected": detected,
                    "frames": n_frames,
                    "train_frames": len(trainer.train_ids),
                    "split": split,
                    "train_s": train_s,
                    "gaussians": trainer.num_gaussians,
                    **res,
                }
            )
            print(
                f"[{cap}/{layout}] {train_s:.0f} s, {split} PSNR {res['psnr']:.2f} / mask {res['psnr_mask']:.2f}",
                flush=True,
            )

    f = lambda x, d: "-" if x is None else f"{x:.{d}f}"  # noqa: E731
    print(f"\ncaptures, {args.preset} preset ({preset.iterations} iterations, {preset.resolution} px), held-out frames")
    print(
        f"{'capture':<9}{'layout':<16}{'detected':<16}{'frames':>7}{'train s':>9}"
        f"{'PSNR':>8}{'SSIM':>8}{'LPIPS':>8}{'PSNRm':>8}{'SSIMm':>8}{'LPIPSm':>8}"
    )
    for r in rows:
        print(
            f"{r['capture']:<9}{r['layout']:<16}{r['detected']:<16}{r['frames']:>7}{r['train_s']:>9.0f}"
            f"{f(r['psnr'], 2):>8}{f(r['ssim'], 4):>8}{f(r['lpips'], 4):>8}"
            f"{f(r['psnr_mask'], 2):>8}{f(r['ssim_mask'], 4):>8}{f(r['lpips_mask'], 4):>8}"
        )
    out = results_path("captures" if args.preset == "default" else f"captures-{args.preset}")
    out.write_text(
        json.dumps(
            {
                "machine": machine_info(),
                "preset": args.preset,
                "iterations": preset.iterations,
                "resolution": preset.resolution,
                "rows": rows,
            },
            indent=2,
        )
        + "\n"
    )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
