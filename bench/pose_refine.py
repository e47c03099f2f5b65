"""Pose refinement on an exactly tracked capture and on a noisy one, in one run (issue 44).

    python bench/pose_refine.py                      # demo sizes: 256 px, 100 frames, 1500 iterations a run
    python bench/pose_refine.py --preset tiny         # seconds, to check the script
    python bench/pose_refine.py --resolution 128 --frames 40 --iters 600   # what fits a shared 2-core box

Two synthetic SMPL captures (stand-in body model, AIST++ dance, one turning camera, ``meshsplat synth``):
``exact``, whose stored (tracked) parameters are the ones the images show, and ``noisy``, the same capture
with ``--pose-noise`` (every joint's tracked rotation off by that many radians, the images exact). Each is
trained three times with the demo's schedule and seed: refinement ``off``; the ``old`` refiner (one Adam
over every training frame's offsets, stepped every iteration: frames not drawn move on stale momentum, the
refiner before issue 44, rebuilt here); and the ``new`` one (``PoseRefiner``: a lazy per-frame Adam, with the
default recipe's settings, its guarded polish at half the run and at the end included); ``prev`` (only when named)
is the lazy Adam with the defaults before issue 44's third round (lr 3e-4, no evidence gate, no start, no depth
rule); ``off``, ``old`` and ``prev`` have no polish. ``--with NAME:KEY=V,...`` adds ``new`` with overrides. ``--subject flame``: the stand-in FLAME head
instead (jaw, neck and expressions per frame), its captures and runs named ``flame-...``. ``--polish
NAME:KEY=V,...`` (repeatable) adds the run of variant ``--polish-base`` (one trained without the polish), copied
and resumed with those ``pose_refine.polish_*`` settings: its poses fitted after the last iteration, the avatar as
it is (no retraining). ``--capture NAME=DIR`` adds a capture as it is, e.g. a real video tracked by ``meshsplat
track`` (``--cases`` may be empty). ``--pictures``: one training frame and one held-out view per case, the truth
beside every variant, in bench/reports/images/<results name>_<case>_<split>.png.
Prints PSNR/SSIM in full and in the mask on the training frames (in their refined poses, as ``eval`` and
``render --split train`` use them), held-out views of training frames (refined poses) and held-out frames
(tracked poses); and, on the exact capture, how far the refined training meshes ended from the true ones.
Saves bench/results/pose_refine-<host>.json and a bar chart next to it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from _machine import machine_info, results_path

KEYS = ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")
SPLITS = ("train", "test_views", "test_frames")
OLD_LR = 3e-4  # the old refiner's default rate
NO_POLISH = ["pose_refine.polish_steps=0", "pose_refine.polish_lr=1e-3", "pose_refine.polish_mid=0"]


class StaleAdamRefiner:
    """The refiner before issue 44: one ``torch.optim.Adam`` over all rows' offsets, stepped every iteration
    (rows not in the batch keep moving on their old moments). Wraps a ``PoseRefiner``; bench-only."""

    def __init__(self, new) -> None:
        self.__dict__.update(new.__dict__)
        self._new = new
        self.optimizer = torch.optim.Adam(list(new.offsets.values()), lr=new.lr, eps=1e-15)

    def step(self, mesh_rows) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def __getattr__(self, name):
        attr = getattr(type(self._new), name)
        return attr.__get__(self) if hasattr(attr, "__get__") else attr


def _same_config(run: Path, cfg) -> bool:
    """Whether ``run`` was trained with ``cfg`` (every key but the paths, which its name holds). A key added to a
    section since the run was trained counts as the same when ``cfg`` has its default (which keeps the
    behaviour from before the key)."""
    from meshsplat.train.config import TrainConfig

    old = json.loads((run / "config.json").read_text())
    new = json.loads(json.dumps(cfg.to_dict()))
    default = json.loads(json.dumps(TrainConfig().to_dict()))
    for k, v in new.items():
        if k in ("out", "data", "model_dir"):
            continue
        was = old.get(k)
        if isinstance(v, dict) and isinstance(was, dict):
            added = {kk: vv for kk, vv in v.items() if kk not in was}
            if any(default.get(k, {}).get(kk) != vv for kk, vv in added.items()):
                return False
            v = {kk: vv for kk, vv in v.items() if kk in was}
        if was != v:
            return False
    return True


def mesh_drift(run: Path) -> dict:
    """Distance per vertex between the refined training meshes and the stored (here: true) ones."""
    from meshsplat.run_folder import load_run

    lr = load_run(run, "cpu")
    tracked, refined = lr.open_dataset(refined_poses=False), lr.open_dataset()
    d = []
    for i in tracked.split("train"):
        d.append((refined.vertices(i) - tracked.vertices(i)).norm(dim=-1))
    dist = torch.stack(d)
    return {"mean_mm": 1000 * float(dist.mean()), "max_mm": 1000 * float(dist.max())}


def chart(rows: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    for ax, case in zip(axes, ("exact", "noisy"), strict=True):
        if case not in rows:
            continue
        variants = list(rows[case])
        width = 0.8 / len(variants)
        for k, v in enumerate(variants):
            vals = [rows[case][v]["splits"].get(s, {}).get("psnr_mask") or 0.0 for s in SPLITS]
            ax.bar(np.arange(len(SPLITS)) + (k - (len(variants) - 1) / 2) * width, vals, width, label=v)
        ax.set_xticks(range(len(SPLITS)), SPLITS)
        ax.set_title(f"{case} poses")
        ax.set_ylabel("PSNR in mask (dB)")
        lo = min(rows[case][v]["splits"][s]["psnr_mask"] for v in variants for s in SPLITS)
        ax.set_ylim(lo - 2, None)
    axes[0].legend(title="refinement", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=80)


def strips(runs: dict[str, dict[str, Path]], prefix: Path) -> list[Path]:
    """Per case and split (training frames in their refined poses, held-out views): one frame, the ground truth
    then every variant's render on white, cropped to the subject; ``<prefix>_<case>_<split>.png``."""
    from _sheets import label_sheet
    from meshsplat.metrics.subject import subject_box
    from meshsplat.render.background import composite
    from meshsplat.run_folder import load_run

    white = torch.ones(3)
    written = []
    for case, variants in runs.items():
        loaded = {v: load_run(run) for v, run in variants.items()}
        datasets = {v: r.open_dataset() for v, r in loaded.items()}
        first = next(iter(datasets.values()))
        for split in ("train", "test_views"):
            ids = first.split(split) if split in first.split_names else []
            if not ids:
                continue
            i = ids[len(ids) // 2]
            fr = first[i]
            tiles = [("truth", composite(fr.image, fr.mask, white))]
            with torch.no_grad():
                for v, ds in datasets.items():
                    f = ds[i]
                    tiles.append((v, loaded[v].avatar.render(f.vertices, f.camera, white).image.clamp(0, 1)))
            h, w = fr.image.shape[:2]
            y0, y1, x0, x1 = (subject_box(fr.mask, pad=0.05) if fr.mask is not None else None) or (0, h, 0, w)
            sheet = label_sheet([[(label, t[y0:y1, x0:x1]) for label, t in tiles]], max(1, 256 // (y1 - y0)))
            out = Path(f"{prefix}_{case}_{split}.png")
            out.parent.mkdir(parents=True, exist_ok=True)
            sheet.save(out)
            written.append(out)
    return written


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="default", choices=["default", "tiny"], help="sizes (meshsplat.demo.PRESETS)")
    ap.add_argument("--iters", type=int, default=None)
    ap.add_argument("--resolution", type=int, default=None)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--n-init", type=int, default=None)
    ap.add_argument("--pose-noise", type=float, default=0.05, help="radians (default 0.05 = 2.9 deg)")
    ap.add_argument(
        "--new-lrs", type=float, nargs="*", default=[], help="also the new refiner at these pose_refine.lr (new_lr<x>)"
    )
    ap.add_argument(
        "--with",
        dest="extra_variants",
        action="append",
        default=[],
        metavar="NAME:KEY=V[,KEY=V]",
        help="also the new refiner with these config overrides, e.g. late:pose_refine.start=0.3 (repeatable)",
    )
    ap.add_argument(
        "--polish",
        action="append",
        default=[],
        metavar="NAME:KEY=V[,KEY=V]",
        help="also the finished --polish-base run resumed with these pose_refine.polish_* settings (repeatable)",
    )
    ap.add_argument("--polish-base", default="new", help="the variant --polish resumes (trained without the polish)")
    ap.add_argument("--seed", type=int, default=None, help="training seed (default: the config's)")
    ap.add_argument("--prior", type=float, default=None, help="pose_refine.prior of the new refiner variants")
    ap.add_argument("--name", default=None, help="results file bench/results/<name>-<host>.json")
    ap.add_argument("--work", default="runs/bench-pose-refine")
    ap.add_argument("--pictures", action="store_true", help="eval writes its report with sample images per split")
    ap.add_argument("--reuse", action="store_true", help="keep a finished run of the same config (no retraining)")
    ap.add_argument("--cases", nargs="*", default=["exact", "noisy"], choices=["exact", "noisy"])
    ap.add_argument(
        "--capture",
        action="append",
        default=[],
        metavar="NAME=DIR",
        help="also a capture as it is (e.g. a video tracked by `meshsplat track`), its case called NAME (repeatable)",
    )
    ap.add_argument("--variants", nargs="*", default=["off", "old", "new"], choices=["off", "old", "prev", "new"])
    ap.add_argument("--subject", default="smpl", choices=["smpl", "flame"], help="the stand-in body or head model")
    args = ap.parse_args()

    from meshsplat.data import open_dataset
    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.eval import evaluate_run
    from meshsplat.synth import synthesize
    from meshsplat.synth.standin_models import write_standin_models
    from meshsplat.train import Trainer

    preset = PRESETS[args.preset]
    for field, value in (("iterations", args.iters), ("resolution", args.resolution), ("frames", args.frames)):
        if value:
            preset = replace(preset, **{field: value})
    if args.n_init:
        preset = replace(preset, n_init=args.n_init)
    work = Path(args.work)
    models = work / "models"
    if not (models / args.subject).is_dir():
        write_standin_models(models, kinds=(args.subject,))
    rows: dict = {}
    runs: dict[str, dict[str, Path]] = {}
    tag = "" if args.subject == "smpl" else f"{args.subject}-"  # the SMPL captures keep their names
    captures = {c.split("=", 1)[0]: Path(c.split("=", 1)[1]).resolve() for c in args.capture if "=" in c}
    if len(captures) != len(args.capture):
        ap.error("--capture takes NAME=DIR")
    for case in args.cases + list(captures):
        data = captures.get(case, work / f"{tag}{case}-{preset.resolution}-{preset.frames}")
        if case not in captures and not (data / "manifest.json").is_file():
            synthesize(
                args.subject,
                data,
                rig="monocular-turn",
                frames=preset.frames,
                resolution=preset.resolution,
                test_views=1,
                model_dir=models,
                pose_noise=args.pose_noise if case == "noisy" else 0.0,
                overwrite=True,
            )
        rows[case] = {}
        named = dict(v.split(":", 1) for v in args.extra_variants)
        polish = dict(v.split(":", 1) for v in args.polish)
        base = args.polish_base
        if polish and base not in args.variants + list(named):
            ap.error(f"--polish resumes the run of variant {base!r}: name it in --variants or --with")
        for variant in args.variants + [f"new_lr{x:g}" for x in args.new_lrs] + list(named) + list(polish):
            run = work / f"run_{tag}{case}-{preset.resolution}-{preset.frames}-{preset.iterations}_{variant}"
            extra = (
                ["pose_refine.enabled=false"]
                if variant == "off"
                else ["pose_refine.enabled=true", "pose_refine.required=true"]
            )
            if variant in ("off", "old", "prev"):  # no polish (issue 44's fifth round): off's keys as they were
                extra += NO_POLISH
            if variant in ("old", "prev"):  # the settings before issue 44's third round (prev: its lazy Adam)
                extra += [f"pose_refine.lr={OLD_LR}", "pose_refine.evidence=0", "pose_refine.start=0"]
                extra.append("pose_refine.keep_depth=false")
            elif variant.startswith("new_lr"):
                extra.append(f"pose_refine.lr={variant[len('new_lr') :]}")
            if variant in named:
                extra += named[variant].split(",")
            if variant in polish:
                extra += polish[variant].split(",")
            if (variant.startswith("new") or variant in named) and args.prior is not None:
                extra.append(f"pose_refine.prior={args.prior}")
            cfg = demo_train_config(data, run, preset, extra, progress=False)
            cfg.model_dir = str(models)
            if args.seed is not None:
                cfg.seed = args.seed
            done = run / "checkpoints" / f"ckpt_{cfg.iterations:08d}.pt"
            t0 = time.perf_counter()
            counts = None
            if args.reuse and done.is_file() and _same_config(run, cfg):
                print(f"[{case}/{variant}] reusing {run.name}", flush=True)
                trainer = None
            elif variant in polish:  # the new run, its poses polished: resumed past its last iteration
                if run.exists():
                    shutil.rmtree(run)
                shutil.copytree(run.parent / (run.name[: -len(variant)] + base), run)
                trainer = Trainer(cfg, resume=True)
                trainer.train()
                counts = trainer.component("pose_refine").polish_counts  # type: ignore[attr-defined]
                print(f"[{case}/{variant}] polish: {counts}", flush=True)
            else:
                if run.exists():
                    shutil.rmtree(run)
                trainer = Trainer(cfg)
                if variant == "old":
                    refine = trainer.component("pose_refine")
                    refine.refiner = StaleAdamRefiner(refine.refiner)  # type: ignore[attr-defined]
                trainer.train()
            train_s = time.perf_counter() - t0
            splits = [s for s in SPLITS if s in open_dataset(data).split_names]  # a real capture: no test_views
            m = evaluate_run(run, splits=splits, report=args.pictures, lpips_net=None, device="cpu")
            rec: dict = {
                "train_s": train_s,
                "gaussians": trainer.num_gaussians if trainer else None,
                "splits": {s: {k: v.get(k) for k in KEYS} for s, v in m["splits"].items()},
            }
            if counts is not None:
                rec["polish"] = counts
            if variant != "off" and case == "exact":
                rec["mesh_drift"] = mesh_drift(run)
            rows[case][variant] = rec
            runs.setdefault(case, {})[variant] = run
            print(f"[{case}/{variant}] trained in {train_s:.0f} s", flush=True)

    f = lambda x, d: "-" if x is None else f"{x:.{d}f}"  # noqa: E731
    print(
        f"\npose refinement, {preset.iterations} iterations, {preset.resolution} px, {preset.frames} frames, "
        f"noisy case {args.pose_noise} rad"
    )
    print(f"{'case':<7}{'refiner':<9}{'split':<13}{'PSNR':>8}{'SSIM':>8}{'PSNRm':>8}{'SSIMm':>8}  drift mm")
    for case, variants in rows.items():
        for name, r in variants.items():
            drift = r.get("mesh_drift")
            for s in SPLITS:
                m = r["splits"].get(s)
                if m is None:
                    continue
                extra = f"  {drift['mean_mm']:.2f} (max {drift['max_mm']:.2f})" if drift and s == "train" else ""
                print(
                    f"{case:<7}{name:<9}{s:<13}{f(m['psnr'], 2):>8}{f(m['ssim'], 4):>8}"
                    f"{f(m['psnr_mask'], 2):>8}{f(m['ssim_mask'], 4):>8}{extra}"
                )
    out = results_path(args.name or ("pose_refine" if args.preset == "default" else f"pose_refine-{args.preset}"))
    out.write_text(
        json.dumps(
            {
                "machine": machine_info(),
                "preset": args.preset,
                "iterations": preset.iterations,
                "resolution": preset.resolution,
                "frames": preset.frames,
                "n_init": preset.n_init,
                "pose_noise_rad": args.pose_noise,
                "lr_new_extra": args.new_lrs,
                "prior_new": args.prior,
                "with": args.extra_variants,
                "polish": args.polish,
                "seed": args.seed,
                "lr_old": OLD_LR,
                "cases": rows,
            },
            indent=2,
        )
        + "\n"
    )
    if {"off", "old", "new"} <= set(args.variants):
        chart(rows, out.with_suffix(".png"))
    if args.pictures:
        for f in strips(runs, Path(__file__).parent / "reports" / "images" / out.stem.replace("-", "_")):
            print(f"picture {f}")
    print(f"saved {out}")


if __name__ == "__main__":
    main()
