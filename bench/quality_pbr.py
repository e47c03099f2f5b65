"""Quality on path-traced captures (shadows that move with pose, gloss, imperfect tracking), in one run.

    python bench/quality_pbr.py                                   # 3 captures x (paper, default), small sizes
    python bench/quality_pbr.py --captures cesium --variants default_v12 default
    python bench/quality_pbr.py --renderer lambert --captures cesium   # the same on today's Lambert renders
    python bench/quality_pbr.py --tiny                            # seconds, to check the script
    python bench/quality_pbr.py --captures cesium --variants default default_occl --seed 1   # another seed

Captures (``meshsplat synth --renderer pbr``, monocular turn; glTF driving meshes Taubin-smoothed 5
iterations like the demo's):
  cesium  CesiumMan (the demo's capture): held-out frames and views
  robot   RobotExpressive trained on Walking, tested on Wave and Dance (novel poses: test_clip)
  smpl    the stand-in SMPL body dancing the bundled AIST++ motion, tracked poses off by --pose-noise
  robot_dance  the robot trained on Dance, tested on Walking and Wave (only when named: --captures robot_dance)

Scoring: path-traced captures are scored against the same frames rendered again with ``--ref-spp``
samples per pixel (default 256; the training capture has ``--spp``, 32): Monte Carlo noise in the
references would otherwise cap every model's score (``capture_vs_ref`` in the JSON: the noisy capture's
own subject PSNR against the references).

Variants: those of bench/quality.py (``paper``, ``default``, ...) plus candidates on top of the
default (``quality``) preset listed in EXTRA. Metrics per test split, mean over frames: full-image and
subject PSNR on white, subject PSNR on black, subject LPIPS (white), and the error budget on black:
the share of squared error in the silhouette band (2 px either side of the mask's edge), the interior
and the outside (``meshsplat.metrics.budget``); in the band, the mean |rendered alpha - mask| and its
sign (``a-m`` > 0: the avatar spills over the edge) and the driving mesh's own coverage error
(``|mesh-m|``: what a smoothed or mis-posed tracked mesh alone costs at the edge). A rerun with the same
arguments reuses the captures and finished runs and scores them again. Saves bench/results/<name>-<host>.json after every run.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

from _machine import machine_info, results_path
from quality import VARIANTS

# The quality recipe's history before the format reset (config versions 1-14 of the pre-release): at version v,
# each key of CHANGED_AFTER[v] still had this value. Frozen: the rows of bench/reports/quality_pbr.md name them.
CHANGED_AFTER: dict[int, dict[str, object]] = {
    1: {"shading.enabled": False, "model.init_color_frames": 1, "optim.lr_color": 2.5e-3},
    2: {"loss.crop_to_subject": False},
    3: {"loss.lpips_every": 1},
    4: {"shading.occlusion": "none"},
    5: {"pose_refine.enabled": False},
    6: {"shading.lr": 5e-3},
    7: {"shading.key_soft": 0.0},
    8: {"shading.grid": 64, "shading.key_soft": 8.0},
    9: {"albedo_prior.enabled": False},
    10: {"albedo_prior.reach": 8},
    11: {"strategy.grow_grad2d": 2e-4},
    12: {"mask_loss.enabled": False},
    13: {"offset_bound.enabled": False},
}


def version_defaults(version: int) -> list[str]:
    """Overrides giving the pre-release config ``version``'s default: each key changed since, at its value then
    (for a key changed twice, the earliest value)."""
    values: dict = {}
    for v in range(max(CHANGED_AFTER), version - 1, -1):
        values.update(CHANGED_AFTER.get(v, {}))
    return [f"{k}={str(val).lower() if isinstance(val, bool) else val}" for k, val in values.items()]


EXTRA: dict[str, tuple[str, list[str]]] = {
    "default_mask": ("quality", ["mask_loss.weight=0.1"]),  # the default's value since config version 13
    "default_v12": ("quality", version_defaults(12)),  # config version 12's default (no mask loss)
    "default_v13": ("quality", version_defaults(13)),  # config version 13's default (offsets unbounded)
    "default_aa": ("quality", ["model.antialiased=true"]),
    "default_sh1tri": ("quality", ["model.sh_degree=1", "model.sh_frame=triangle"]),
    "default_axis": ("quality", ["shading.normal=axis"]),
    "default_occl": ("quality", ["shading.occlusion=directions"]),
    "default_spec": ("quality", ["shading.specular=sh2"]),
    "default_spec_occl": ("quality", ["shading.specular=sh2", "shading.occlusion=directions"]),
    "default_key": ("quality", ["shading.occlusion=key"]),
    # the default before shading.occlusion=key and pose refinement
    "default_nokey": ("quality", ["shading.occlusion=none", "pose_refine.enabled=false"]),
    "default_norefine": ("quality", ["pose_refine.enabled=false"]),  # the key light without pose refinement
    "default_key150": ("quality", ["shading.key_iter=150"]),  # a shorter search
    "default_key_spec": ("quality", ["shading.occlusion=key", "shading.specular=sh2"]),
    "default_lrdecay": ("quality", ["optim.lr_color_final=1e-3"]),
    "default_lrdecay3e-4": ("quality", ["optim.lr_color_final=3e-4"]),
    # the lighting's learning rate; 5e-3 was the default before config version 7, 5e-2 is the default now
    "default_lr5e-3": ("quality", ["shading.lr=5e-3"]),
    "default_lrsh2e-2": ("quality", ["shading.lr=2e-2"]),
    "default_lrsh5e-2": ("quality", ["shading.lr=5e-2"]),
    # the key's shadow: hard (one map) up to config version 7, soft (8 degrees) since 8. quality_pbr_*_soft8*-vm.json
    # compare default_lrsh5e-2, trained while it meant the hard key (default_hard today), with default_lrsh5e-2_soft8
    "default_hard": ("quality", ["shading.key_soft=0"]),
    "default_lrsh5e-2_soft8": ("quality", ["shading.lr=5e-2", "shading.key_soft=8"]),
    "default_lrsh1e-1": ("quality", ["shading.lr=1e-1"]),
    "default_soft4": ("quality", ["shading.key_soft=4"]),  # the soft key's radius
    "default_soft12": ("quality", ["shading.key_soft=12"]),
    "default_grid96": ("quality", ["shading.grid=96"]),  # finer shadow maps
    "default_grid128": ("quality", ["shading.grid=128"]),
    "default_soft16": ("quality", ["shading.key_soft=16"]),
    "default_g96s12": ("quality", ["shading.grid=96", "shading.key_soft=12"]),
    # the two halves of config version 9's change, each alone (today's preset has grid 96 and 12 degrees)
    "default_g96s8": ("quality", ["shading.grid=96", "shading.key_soft=8"]),
    "default_g64s12": ("quality", ["shading.grid=64", "shading.key_soft=12"]),
    "default_v8": ("quality", ["shading.grid=64", "shading.key_soft=8", "albedo_prior.weight=0"]),
    # config version 9's default (no albedo prior; the rows named default_g96s12 were trained as it); the prior's weight
    "default_v9": ("quality", ["albedo_prior.weight=0"]),
    "default_albedo0.05": ("quality", ["albedo_prior.weight=0.05"]),
    "default_albedo0.1": ("quality", ["albedo_prior.weight=0.1"]),  # today's default, in a folder of its own
    "default_albedo0.2": ("quality", ["albedo_prior.weight=0.2"]),
    "default_albedo0.3": ("quality", ["albedo_prior.weight=0.3"]),
    "default_albedo0.4": ("quality", ["albedo_prior.weight=0.4"]),
    # config version 10's default (the albedo prior's 8 nearest neighbours only)
    "default_reach8": ("quality", ["albedo_prior.reach=8"]),
    "default_reach32": ("quality", ["albedo_prior.reach=32"]),
    "default_reach128": ("quality", ["albedo_prior.reach=128"]),
    "default_reach256": ("quality", ["albedo_prior.reach=256"]),
    # a lower densification threshold (more Gaussians where the gradient is); 1e-4 is the default since config
    # version 12, so the variants above (each today's default with one key changed) densify at 1e-4 from then on
    "default_dens1e-4": ("quality", ["strategy.grow_grad2d=1e-4"]),
    "default_v11": ("quality", version_defaults(11)),  # config version 11's default
    # config version 4's default, the one issue 26 started from: every key changed since set back
    "default_v4": ("quality", version_defaults(4)),
    "default_dens5e-5": ("quality", ["strategy.grow_grad2d=5e-5"]),
    # D-SSIM in the loss (3DGS's 0.2)
    "default_ssim0.2": ("quality", ["loss.lambda_ssim=0.2"]),
    "default_ssim0.2_dens3e-4": ("quality", ["loss.lambda_ssim=0.2", "strategy.grow_grad2d=3e-4"]),
    # the optimiser at the demo's short budget: faster embedding / scale learning, denser refinement steps
    "default_lremb2x": ("quality", ["optim.lr_embedding=3.2e-4", "optim.lr_embedding_final=3.2e-6"]),
    "default_lrscale1e-2": ("quality", ["optim.lr_scale=1e-2"]),
    "default_every50": ("quality", ["strategy.refine_every=50"]),
    "default_lremb4x": ("quality", ["optim.lr_embedding=6.4e-4", "optim.lr_embedding_final=6.4e-6"]),
    "default_mask0.3": ("quality", ["mask_loss.weight=0.3"]),
    "default_lremb2x_mask": (
        "quality",
        ["optim.lr_embedding=3.2e-4", "optim.lr_embedding_final=3.2e-6", "mask_loss.weight=0.1"],
    ),
    "default_lremb2x_mask_scale": (
        "quality",
        ["optim.lr_embedding=3.2e-4", "optim.lr_embedding_final=3.2e-6", "mask_loss.weight=0.1", "optim.lr_scale=1e-2"],
    ),
}
ALL = {**VARIANTS, **EXTRA}
CAPTURES = {
    "cesium": {"asset": "CesiumMan", "driver_smooth": 5},
    "robot": {"asset": "RobotExpressive", "driver_smooth": 5, "clip": "Walking", "test_clips": ["Wave", "Dance"]},
    "smpl": {"asset": "smpl"},
    # the same robot trained on the clip with the most varied motion (issue 26's novel-pose goal; not run by default)
    "robot_dance": {"asset": "RobotExpressive", "driver_smooth": 5, "clip": "Dance", "test_clips": ["Walking", "Wave"]},
}
DEFAULT_CAPTURES = ["cesium", "robot", "smpl"]


def _schedule(iterations: int) -> tuple[str, ...]:
    """The demo's short schedule (refine 300..1200 of 1500) scaled to ``iterations``."""
    s = iterations / 1500
    every = max(10, round(100 * s))
    return (
        f"strategy.refine_start_iter={round(300 * s)}",
        f"strategy.refine_stop_iter={round(1200 * s)}",
        f"strategy.refine_every={every}",
        "strategy.reset_every=100000",
        "strategy.max_gaussians=40000",
        f"walk.every={every}",
        f"checkpoint_every={iterations}",
        f"preview_every={iterations}",
        "log_every=10",
    )


def _capture(name: str, args, work: Path, spp: int | None = None) -> Path:
    """The capture ``name`` (``spp``: samples per pixel, default ``args.spp``; another count renders the
    held-out frames only, same names, cameras and poses, with less noise: the low-noise references)."""
    from meshsplat.synth import synthesize
    from meshsplat.synth.pbr import PbrSettings

    spp = args.spp if spp is None else spp
    data = work / (f"data-{name}-{args.renderer}" + (f"-spp{spp}" if spp != args.spp else ""))
    if (data / "manifest.json").exists():
        return data
    spec = dict(CAPTURES[name])
    asset = spec.pop("asset")
    extra: dict = {}
    if asset == "smpl":
        extra = {"model_dir": _model_dir(name, work), "pose_noise": args.pose_noise}
    synthesize(
        asset,
        data,
        rig="monocular-turn",
        frames=args.frames,
        resolution=args.resolution,
        test_frames=args.test_frames,
        test_views=2,
        test_view_frames=max(2, args.test_frames // 2),
        renderer=args.renderer,
        pbr=PbrSettings(spp=spp),
        overwrite=True,
        splits=None if spp == args.spp else [s for s in _planned_splits(name) if s != "train"],
        **spec,
        **extra,
    )
    return data


def _model_dir(name: str, work: Path) -> Path | None:
    """The body-model files of capture ``name`` (the stand-in SMPL files, written once), None for a mesh asset.
    Training is given them as a user gives ``--model-dir``: the default then refines the tracked poses."""
    if CAPTURES[name]["asset"] != "smpl":
        return None
    from meshsplat.synth.standin_models import write_standin_models

    folder = work / "standin_models"
    return folder if (folder / "smpl").is_dir() else write_standin_models(folder)


def _planned_splits(name: str) -> list[str]:
    return ["train", "test_frames", "test_views"] + (["test_clip"] if CAPTURES[name].get("test_clips") else [])


def _mesh_coverage(verts, faces, cam, s: int = 2):
    """Pixel coverage ``[H,W,1]`` of the driving mesh (``s`` x ``s`` supersampled): the silhouette the
    tracked mesh itself would give."""
    from meshsplat.synth.raster import rasterize_triangles

    vm, K = cam.viewmat.float(), cam.K.float().clone()
    K[:2] *= s
    frags = rasterize_triangles(verts.float() @ vm[:3, :3].T + vm[:3, 3], faces, K, cam.width * s, cam.height * s)
    return frags.mask.float().view(cam.height, s, cam.width, s).mean((1, 3))[..., None]


_FITTED: dict = {}


def _fitted_poses(run: Path, loaded, ds, steps: int, lr: float) -> dict:
    """Driving meshes of ``ds``'s held-out frames fitted to their images for ``steps`` steps with the run's
    avatar frozen (``meshsplat eval --fit-poses``); empty for 0 steps. Kept per run for the picture."""
    if not steps:
        return {}
    key = (str(run), steps, lr)
    if key not in _FITTED:
        import torch

        from meshsplat.eval.fit_poses import fit_test_poses

        ids = [i for split in ds.split_names if split != "train" for i in ds.split(split)]
        mdir = loaded.model_dir()
        _FITTED[key] = fit_test_poses(loaded.avatar, ds, ids, steps, lr, str(mdir) if mdir else None, torch.ones(3))
    return _FITTED[key]


def _score(run: Path, data: Path, ref: Path, fit_poses: int = 0, fit_lr: float = 1e-3) -> dict:
    """Per split of ``data``: mean metrics over its frames and the error budget (summed squared error per
    region), against the images and masks of the same frames in ``ref`` (the low-noise references; may
    be ``data`` itself). ``fit_poses`` > 0: held-out frames are scored in poses fitted for that many steps
    to the capture's own test images, the avatar frozen (as ``meshsplat eval --fit-poses``)."""
    import torch

    from meshsplat.data import open_dataset
    from meshsplat.metrics import lpips, lpips_available, psnr
    from meshsplat.metrics.budget import BUDGET_REGIONS, error_budget, silhouette_regions
    from meshsplat.metrics.subject import subject_metrics
    from meshsplat.render.background import composite
    from meshsplat.run_folder import load_run

    loaded = load_run(run)
    avatar = loaded.avatar
    # held-out views of training frames in the poses training refined, if it did (as meshsplat eval)
    ds, refs = loaded.open_dataset(data), open_dataset(ref)
    by_name = {refs.frame_info(j)["name"]: j for j in range(len(refs))}
    white, black = torch.ones(3), torch.zeros(3)
    fitted = _fitted_poses(run, loaded, ds, fit_poses, fit_lr)
    ds = ds.with_meshes(fitted)
    lp = (lambda a, b: lpips(a, b)) if lpips_available("alex") else None
    out = {}
    for split in [s for s in ds.split_names if s != "train"]:
        rows, sse = [], dict.fromkeys(BUDGET_REGIONS, 0.0)
        for i in ds.split(split):
            target = refs[by_name[ds.frame_info(i)["name"]]]
            fr = replace(ds[i], image=target.image, mask=target.mask)
            row = {}
            band = silhouette_regions(fr.mask)["band"]
            mesh_cov = _mesh_coverage(fr.vertices, ds.faces, fr.camera)
            # silhouette diagnostics in the band: the avatar's alpha and the driving mesh's coverage vs the mask
            row["mesh_band_abs"] = float((mesh_cov - fr.mask)[band].abs().mean())
            for tag, bg in (("w", white), ("b", black)):
                with torch.no_grad():
                    rendered = avatar.render(fr.vertices, fr.camera, bg)
                img = rendered.image.float().clamp(0, 1)
                if tag == "b":
                    d = (rendered.alpha.float() - fr.mask)[band]
                    row["alpha_band_abs"], row["alpha_band_bias"] = float(d.abs().mean()), float(d.mean())
                gt = composite(fr.image, fr.mask, bg)
                sub = subject_metrics(img, gt, fr.mask, lp if tag == "w" else None)
                row[f"psnr_{tag}"] = float(psnr(img, gt))
                row[f"psnr_mask_{tag}"] = sub["psnr_mask"]
                if tag == "w":
                    row["lpips_mask"] = sub["lpips_mask"]
                else:
                    b = error_budget(img, gt, fr.mask)
                    for r in BUDGET_REGIONS:
                        sse[r] += b[f"sse_{r}"]
            rows.append(row)
        total = sum(sse.values()) or 1.0
        mean = {k: sum(r[k] for r in rows if r[k] is not None) / len(rows) for k in rows[0]}
        out[split] = {**mean, **{f"share_{r}": sse[r] / total for r in BUDGET_REGIONS}, "frames": len(rows)}
        out[split]["fitted_pose_frames"] = sum(int(ds.frame_info(i)["mesh"]) in fitted for i in ds.split(split))
    return out


def _picture(
    runs: dict[str, Path], data: Path, ref: Path, out: Path, frames: int = 2, fit_poses: int = 0, fit_lr: float = 1e-3
) -> None:
    """Per held-out frame (``frames`` of each test split): reference | each run | the last run's squared
    error on black, silhouette band in red, interior in green (brighter = larger), as a PNG. Held-out
    frames in fitted poses with ``fit_poses`` (as ``_score``)."""
    import numpy as np
    import torch
    from PIL import Image

    from meshsplat.data import open_dataset
    from meshsplat.metrics.budget import silhouette_regions
    from meshsplat.render.background import composite
    from meshsplat.run_folder import load_run

    loaded = {name: load_run(r) for name, r in runs.items()}
    sets = {name: lr.open_dataset(data) for name, lr in loaded.items()}  # each run's refined poses, if any
    sets = {
        name: ds.with_meshes(_fitted_poses(runs[name], loaded[name], ds, fit_poses, fit_lr))
        for name, ds in sets.items()
    }
    ds, refs = open_dataset(data), open_dataset(ref)
    by_name = {refs.frame_info(j)["name"]: j for j in range(len(refs))}
    rows = []
    for split in [s for s in ds.split_names if s != "train"]:
        for i in ds.split(split)[:frames]:
            fr, target = ds[i], refs[by_name[ds.frame_info(i)["name"]]]
            black = torch.zeros(3)
            gt = composite(target.image, target.mask, black)
            tiles = [gt]
            for name, lr in loaded.items():
                with torch.no_grad():
                    rendered = lr.avatar.render(sets[name].vertices(i), fr.camera, black)
                tiles.append(rendered.image.float().clamp(0, 1))
            err = (tiles[-1] - gt).pow(2).sum(-1).sqrt().clamp(0, 1)
            reg = silhouette_regions(target.mask)
            tiles.append(torch.stack([err * reg["band"], err * reg["interior"], torch.zeros_like(err)], -1))
            rows.append(torch.cat(tiles, 1))
    img = (torch.cat(rows, 0).numpy() * 255 + 0.5).astype(np.uint8)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).save(out)


def _noise(data: Path, ref: Path) -> dict:
    """Subject PSNR (white) of the capture's own test images against the low-noise references: the
    ceiling a model scored against the noisy capture would have had."""
    import torch

    from meshsplat.data import open_dataset
    from meshsplat.metrics.subject import subject_metrics
    from meshsplat.render.background import composite

    a, b = open_dataset(data), open_dataset(ref)
    by_name = {b.frame_info(j)["name"]: j for j in range(len(b))}
    out = {}
    for split in [s for s in a.split_names if s != "train"]:
        vals = []
        for i in a.split(split):
            fa, fb = a[i], b[by_name[a.frame_info(i)["name"]]]
            white = torch.ones(3)
            vals.append(
                subject_metrics(composite(fa.image, fa.mask, white), composite(fb.image, fb.mask, white), fb.mask)[
                    "psnr_mask"
                ]
            )
        out[split] = round(sum(vals) / len(vals), 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--captures", nargs="*", default=DEFAULT_CAPTURES, choices=list(CAPTURES))
    ap.add_argument("--variants", nargs="*", default=["paper", "default"], choices=list(ALL))
    ap.add_argument("--renderer", default="pbr", choices=("pbr", "lambert"))
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--test-frames", type=int, default=8)
    ap.add_argument("--iters", type=int, default=600)
    ap.add_argument("--spp", type=int, default=32, help="samples per pixel of the training capture")
    ap.add_argument(
        "--ref-spp",
        type=int,
        default=256,
        help="pbr: score against the same frames rendered with this many spp (0: the capture)",
    )
    ap.add_argument("--pose-noise", type=float, default=0.03, help="smpl capture: tracking error (radians)")
    ap.add_argument("--n-init", type=int, default=5000)
    ap.add_argument("--tiny", action="store_true", help="seconds: 32 px, 4 frames, 30 iterations, 4 spp")
    ap.add_argument("--work", default=None)
    ap.add_argument("--name", default="quality_pbr")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--picture", default=None, help="PNG per capture: reference | variants | error budget (name gets -<capture>)"
    )
    ap.add_argument("--seed", type=int, default=0, help="training seed; not 0: rows and runs named VARIANT_sSEED")
    ap.add_argument(
        "--fit-poses",
        type=int,
        default=0,
        help="score held-out frames in poses fitted to their own images for this many steps (as meshsplat eval "
        "--fit-poses; captures with body-model parameters: smpl)",
    )
    ap.add_argument("--fit-poses-lr", type=float, default=1e-3)
    args = ap.parse_args()
    if args.tiny:
        args.resolution, args.frames, args.test_frames, args.iters, args.spp, args.n_init = 32, 4, 2, 30, 4, 500

    import torch

    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.train import Trainer

    torch.set_num_threads(args.threads)
    sizes = replace(
        PRESETS["default"],
        frames=args.frames,
        resolution=args.resolution,
        iterations=args.iters,
        n_init=args.n_init,
        overrides=_schedule(args.iters),
    )
    work = Path(args.work or f"runs/bench-{args.name}")
    out = results_path(args.name)
    rows: dict = {}
    previous = json.loads(out.read_text()) if out.exists() else {}  # this run rewrites it as it goes
    for cap in args.captures:
        t0 = time.perf_counter()
        data = _capture(cap, args, work)
        manifest = json.loads((data / "manifest.json").read_text())
        meta = manifest.get("meta", {})
        rows[cap] = {"synth_s_per_frame": meta.get("seconds_per_frame"), "renderer": meta.get("renderer"), "runs": {}}
        print(f"[{cap}] capture ready ({time.perf_counter() - t0:.0f} s)", flush=True)
        ref = data
        if args.renderer == "pbr" and args.ref_spp and args.ref_spp != args.spp:
            ref = _capture(cap, args, work, spp=args.ref_spp)
            ref_meta = json.loads((ref / "manifest.json").read_text()).get("meta", {})
            rows[cap]["ref_spp"] = args.ref_spp
            rows[cap]["ref_s_per_frame"] = ref_meta.get("seconds_per_frame")
            rows[cap]["capture_vs_ref"] = _noise(data, ref)
            print(
                f"[{cap}] references ready ({args.ref_spp} spp); capture vs references: {rows[cap]['capture_vs_ref']}"
            )
        for variant in args.variants:
            preset, overrides = ALL[variant]
            name = variant if args.seed == 0 else f"{variant}_s{args.seed}"  # the run's folder and its row
            overrides = list(overrides) + ([f"seed={args.seed}"] if args.seed else [])
            if _model_dir(cap, work) is not None:
                overrides.append(f"model_dir={_model_dir(cap, work)}")
            run = work / f"{cap}-{args.renderer}-{name}"
            cfg = demo_train_config(data, run, sizes, overrides, progress=False, recipe=preset)
            t0 = time.perf_counter()
            trainer = Trainer(cfg, resume=True)
            finished = trainer.iteration >= cfg.iterations
            trainer.train()
            train_s = time.perf_counter() - t0
            if finished:  # a rerun only scores again: keep the training time measured before
                before = previous.get("captures", {}).get(cap, {}).get("runs", {}).get(name, {})
                train_s = before.get("train_s", train_s)
            rows[cap]["runs"][name] = {
                "preset": preset,
                "overrides": overrides,
                "train_s": train_s,
                "gaussians": trainer.num_gaussians,
                "splits": _score(run, data, ref, args.fit_poses if _model_dir(cap, work) else 0, args.fit_poses_lr),
            }
            print(f"[{cap}/{name}] trained in {train_s:.0f} s", flush=True)
            out.write_text(
                json.dumps({"machine": machine_info(), "args": vars(args), "captures": rows}, indent=2) + "\n"
            )

        if args.picture:
            pic = Path(args.picture)
            pic = pic.with_name(f"{pic.stem}-{cap}{pic.suffix}")
            names = [v if args.seed == 0 else f"{v}_s{args.seed}" for v in args.variants]
            steps = args.fit_poses if _model_dir(cap, work) else 0
            _picture(
                {n: work / f"{cap}-{args.renderer}-{n}" for n in names}, data, ref, pic, 2, steps, args.fit_poses_lr
            )
            print(f"[{cap}] picture: {pic}")

    print(f"\n{args.renderer} captures, {args.iters} iterations, {args.resolution}px, {args.spp} spp")
    hdr = f"{'capture':<8}{'variant':<18}{'split':<12}{'PSNR':>7}{'mask/w':>8}{'mask/b':>8}{'LPIPSm':>8}"
    print(hdr + f"{'band%':>7}{'int%':>6}{'out%':>6}{'|a-m|':>7}{'a-m':>7}{'|mesh-m|':>9}")
    for cap, r in rows.items():
        for name, v in r["runs"].items():
            for split, m in v["splits"].items():
                print(
                    f"{cap:<8}{name:<18}{split:<12}{m['psnr_w']:>7.2f}{m['psnr_mask_w']:>8.2f}{m['psnr_mask_b']:>8.2f}"
                    f"{(m['lpips_mask'] or float('nan')):>8.3f}{100 * m['share_band']:>7.0f}"
                    f"{100 * m['share_interior']:>6.0f}{100 * m['share_outside']:>6.0f}"
                    f"{m['alpha_band_abs']:>7.3f}{m['alpha_band_bias']:>7.3f}{m['mesh_band_abs']:>9.3f}"
                )
    print(f"saved {out}")


if __name__ == "__main__":
    main()
