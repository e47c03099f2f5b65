"""Same-code A/B of training settings on captures as they are (e.g. real videos tracked by ``meshsplat track``).

    python bench/recipe_ab.py --capture head=CAPTURE_DIR --capture body=CAPTURE_DIR \
        --variant now: --variant snap0:shading.key_snap_deg=0 --set pose_refine.polish_steps=0 --name key_snap_real

Every capture is trained once per variant with the demo's model and schedule shape (``meshsplat.demo``'s
``--preset`` sizes: 1,500 iterations by default) and the default recipe, then ``--set`` overrides common to all
variants, then the variant's own (``NAME:KEY=V,KEY=V``; ``NAME:`` alone is the recipe as it is). Scored by
``meshsplat eval`` on the capture's held-out splits and its training frames; the key light's fate (kept or folded,
its direction, the learned irradiance's direction) is read from the run's checkpoint. Prints a table and saves
bench/results/<name>-<host>.json; a rerun with ``--reuse`` keeps finished runs of the same config.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from _machine import machine_info, results_path
from key_light import _angle, _key

KEYS = ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", action="append", required=True, metavar="NAME=DIR", help="a capture (repeatable)")
    ap.add_argument("--variant", action="append", required=True, metavar="NAME:KEY=V[,KEY=V]", help="(repeatable)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=V", help="overrides common to every variant")
    ap.add_argument("--preset", default="default", choices=["default", "tiny"], help="sizes (meshsplat.demo.PRESETS)")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default="runs/bench-recipe-ab")
    ap.add_argument("--name", default="recipe_ab")
    ap.add_argument("--reuse", action="store_true", help="keep a finished run of the same config")
    args = ap.parse_args()
    if any("=" not in c for c in args.capture) or any(":" not in v for v in args.variant):
        ap.error("--capture takes NAME=DIR, --variant NAME:KEY=V,...")

    import torch

    from meshsplat.data import open_dataset
    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.eval import evaluate_run
    from meshsplat.train import Trainer

    torch.set_num_threads(args.threads)
    preset = PRESETS[args.preset]
    captures = {c.split("=", 1)[0]: Path(c.split("=", 1)[1]).resolve() for c in args.capture}
    variants = {v.split(":", 1)[0]: [x for x in v.split(":", 1)[1].split(",") if x] for v in args.variant}
    rows: dict = {}
    for case, data in captures.items():
        splits = [s for s in ("train", "test_frames", "test_views") if s in open_dataset(data).split_names]
        rows[case] = {}
        for variant, extra in variants.items():
            run = Path(args.work) / f"run_{case}-{preset.iterations}_{variant}"
            cfg = demo_train_config(data, run, preset, list(args.set) + extra, progress=False)
            if args.seed is not None:
                cfg.seed = args.seed
            done = run / "checkpoints" / f"ckpt_{cfg.iterations:08d}.pt"
            same = done.is_file() and json.loads((run / "config.json").read_text()) == json.loads(
                json.dumps(cfg.to_dict())
            )
            t0 = time.perf_counter()
            if not (args.reuse and same):
                if run.exists():
                    shutil.rmtree(run)
                Trainer(cfg).train()
            train_s = time.perf_counter() - t0
            m = evaluate_run(run, splits=splits, lpips_net="alex", device="cpu")
            key = _key(run, None)  # no true light on a real capture: the key against the learned irradiance
            key["found_vs_irradiance_deg"] = _angle(key["found"], key["irradiance"])
            rows[case][variant] = {
                "train_s": train_s if not (args.reuse and same) else None,
                "overrides": list(args.set) + extra,
                "splits": {s: {k: v.get(k) for k in KEYS} for s, v in m["splits"].items()},
                "key_light": key,
            }
            print(f"[{case}/{variant}] trained in {train_s:.0f} s", flush=True)

    f = lambda x, d: "-" if x is None else f"{x:.{d}f}"  # noqa: E731
    print(f"\n{preset.iterations} iterations; PSNR / LPIPS full image, then in the mask")
    print(f"{'capture':<20}{'variant':<12}{'split':<13}{'PSNR':>8}{'LPIPS':>8}{'PSNRm':>8}{'LPIPSm':>8}  key")
    for case, vs in rows.items():
        for name, r in vs.items():
            key = r["key_light"]
            for s, m in r["splits"].items():
                kinfo = f"  kept {key['kept']}, {f(key['found_vs_irradiance_deg'], 1)} deg" if s == "train" else ""
                print(
                    f"{case:<20}{name:<12}{s:<13}{f(m['psnr'], 2):>8}{f(m['lpips'], 4):>8}"
                    f"{f(m['psnr_mask'], 2):>8}{f(m['lpips_mask'], 4):>8}{kinfo}"
                )
    out = results_path(args.name)
    doc = {"machine": machine_info(), "preset": args.preset, "iterations": preset.iterations, "set": args.set}
    doc["captures"] = {k: str(v) for k, v in captures.items()}
    doc["cases"] = rows
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"saved {out}")


if __name__ == "__main__":
    main()
