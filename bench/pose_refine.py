"""Pose refinement on a capture whose tracked parameters are wrong by a known amount.

    python bench/pose_refine.py                 # demo sizes: 256 px, 1500 iterations per run
    python bench/pose_refine.py --preset tiny   # seconds, to check the script

A synthetic SMPL capture (stand-in body model, AIST++ dance, one camera) is trained three times with
the same schedule and seed: with the true parameters; with the training frames' parameters perturbed
by Gaussian noise (``--pose-noise`` radians on every joint and the global orientation, ``--transl-noise``
of the body height on the translation), as a tracker would leave them; and the perturbed capture
with ``--refine-pose``. Test frames keep their true parameters. Prints PSNR/SSIM/LPIPS on the held-out
frames (full image and in the mask) and the parameter error before/after refinement; saves
bench/results/pose_refine-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from _machine import machine_info, results_path

KEYS = ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")


def perturb(native: Path, out: Path, models: Path, pose_noise: float, transl_noise: float, seed: int = 0) -> dict:
    """Copy ``native`` to ``out`` with the training frames' SMPL parameters perturbed (meshes re-posed)."""
    import torch

    from meshsplat.data import open_dataset
    from meshsplat.drivers.body_models import BodyModel

    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(native, out)
    ds = open_dataset(out)
    rows = sorted({int(ds.frame_info(i)["mesh"]) for i in ds.split("train")})
    params = {k: v.copy() for k, v in ds.driver_params.items()}
    rng = np.random.default_rng(seed)
    height = float(np.ptp(ds.canonical_vertices.numpy()[:, 1]))
    for k, sigma in (("global_orient", pose_noise), ("body_pose", pose_noise), ("transl", transl_noise * height)):
        params[k][rows] += rng.normal(0.0, sigma, size=params[k][rows].shape).astype(np.float32)
    info = ds.driver_info
    model = BodyModel(info["type"], models, gender=info.get("gender", "neutral"))
    verts = np.load(out / "vertices.npy")
    with torch.no_grad():
        sub = {k: (v[rows] if k in ds.per_frame_param_names else v) for k, v in params.items()}
        verts[rows] = model.forward(sub).vertices.numpy()
    np.save(out / "vertices.npy", verts)
    np.savez(out / info["params"], **params)
    return {"rows": rows, "params": params}


def param_error(a: dict, b: dict, rows: list[int]) -> dict:
    """Mean absolute difference per parameter over ``rows`` (radians / model units)."""
    return {k: float(np.abs(a[k][rows] - b[k][rows]).mean()) for k in ("global_orient", "body_pose", "transl")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="default", choices=["default", "tiny"])
    ap.add_argument("--iters", type=int, default=None)
    ap.add_argument("--pose-noise", type=float, default=0.05, help="radians (default 0.05 = 2.9 deg)")
    ap.add_argument("--transl-noise", type=float, default=0.01, help="fraction of the body height")
    ap.add_argument("--lr", type=float, default=None, help="pose_refine.lr (default: the config's)")
    ap.add_argument("--name", default=None, help="results file bench/results/<name>-<host>.json")
    ap.add_argument("--work", default="runs/bench-pose-refine")
    ap.add_argument(
        "--variants",
        nargs="*",
        default=["true", "perturbed", "perturbed+refine"],
        choices=["true", "perturbed", "perturbed+refine"],
    )
    args = ap.parse_args()

    from meshsplat.data import open_dataset
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
    if not (models / "smpl").is_dir():
        write_standin_models(models, kinds=("smpl",))
    native = work / "true"
    if not (native / "manifest.json").is_file():
        synthesize(
            "smpl",
            native,
            rig="monocular-turn",
            frames=preset.frames,
            resolution=preset.resolution,
            test_views=0,
            model_dir=models,
            overwrite=True,
        )
    noisy = work / "perturbed"
    pert = perturb(native, noisy, models, args.pose_noise, args.transl_noise)
    true_params = open_dataset(native).driver_params

    rows = {}
    variants = {"true": (native, False), "perturbed": (noisy, False), "perturbed+refine": (noisy, True)}
    variants = {k: v for k, v in variants.items() if k in args.variants}
    for name, (data, refine) in variants.items():
        run = work / f"run_{name}"
        if run.exists():
            shutil.rmtree(run)
        extra = ["pose_refine.enabled=true"] if refine else []
        if refine and args.lr:
            extra.append(f"pose_refine.lr={args.lr}")
        cfg = demo_train_config(data, run, preset, extra, progress=False)
        cfg.model_dir = str(models)
        t0 = time.perf_counter()
        trainer = Trainer(cfg)
        trainer.train()
        train_s = time.perf_counter() - t0
        m = evaluate_run(run, report=False)
        rec = {
            "train_s": train_s,
            "gaussians": trainer.num_gaussians,
            "splits": {s: {k: v.get(k) for k in KEYS} for s, v in m["splits"].items()},
        }
        if refine:
            refined = dict(np.load(run / "refined_params.npz"))
            order = {int(r): j for j, r in enumerate(refined["mesh_rows"])}
            full = {k: pert["params"][k].copy() for k in ("global_orient", "body_pose", "transl")}
            for k in full:
                for r, j in order.items():
                    full[k][r] = refined[k][j]
            rec["param_error_after"] = param_error(full, true_params, pert["rows"])
        rows[name] = rec
        print(f"[{name}] trained in {train_s:.0f} s", flush=True)
    before = param_error(pert["params"], true_params, pert["rows"])

    f = lambda x, d: "-" if x is None else f"{x:.{d}f}"  # noqa: E731
    print(
        f"\npose refinement, {args.preset} preset ({preset.iterations} iterations, {preset.resolution} px), "
        f"noise {args.pose_noise} rad / {args.transl_noise} x height"
    )
    print(f"{'variant':<18}{'split':<13}{'PSNR':>8}{'SSIM':>8}{'LPIPS':>8}{'PSNRm':>8}{'SSIMm':>8}{'LPIPSm':>8}")
    for name, r in rows.items():
        for s, m in r["splits"].items():
            print(
                f"{name:<18}{s:<13}{f(m['psnr'], 2):>8}{f(m['ssim'], 4):>8}{f(m['lpips'], 4):>8}"
                f"{f(m['psnr_mask'], 2):>8}{f(m['ssim_mask'], 4):>8}{f(m['lpips_mask'], 4):>8}"
            )
    print("mean |param - true| on training frames: before " + json.dumps({k: round(v, 5) for k, v in before.items()}))
    if "perturbed+refine" in rows:
        print(
            "                                        after  "
            + json.dumps({k: round(v, 5) for k, v in rows["perturbed+refine"]["param_error_after"].items()})
        )
    out = results_path(args.name or ("pose_refine" if args.preset == "default" else f"pose_refine-{args.preset}"))
    out.write_text(
        json.dumps(
            {
                "machine": machine_info(),
                "preset": args.preset,
                "iterations": preset.iterations,
                "pose_noise_rad": args.pose_noise,
                "transl_noise_height": args.transl_noise,
                "param_error_before": before,
                "variants": rows,
            },
            indent=2,
        )
        + "\n"
    )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
