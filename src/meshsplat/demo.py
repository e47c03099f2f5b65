"""The end-to-end demo: synthesize a CesiumMan capture, train an avatar on it, evaluate, render, export.

    from meshsplat.demo import run_demo
    summary = run_demo("runs/demo")                  # what `make demo` runs (a few minutes on 2 CPU cores)
    summary = run_demo("/tmp/d", preset="tiny")      # seconds; used by the end-to-end test

Everything lands under one folder::

    OUT/data/        the generated dataset (native format) + contact_sheet.png
    OUT/run/         training run (config.json, checkpoints/, log.csv, previews/)
    OUT/run/eval/    metrics.json, report.html, report PNGs (held-out frames and novel views)
    OUT/animation/   the avatar driven by the unseen part of the walk, from an orbiting camera (MP4 + PNGs)
    OUT/export/      avatar.ply (standard 3DGS), embedding.json, canonical_mesh.obj
    OUT/summary.json what the demo printed at the end

Asset: CesiumMan (CC-BY 4.0, (c) 2017 Cesium), bundled (``meshsplat/assets/gltf``).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat._device import resolve_device
from meshsplat._numba import numba_available
from meshsplat.animate import render_animation
from meshsplat.camera import orbit_cameras
from meshsplat.data import AvatarDataset, open_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.eval import evaluate_run
from meshsplat.export import export_avatar
from meshsplat.paths import asset
from meshsplat.run_folder import RunFolder, load_avatar
from meshsplat.synth import contact_sheet, synthesize
from meshsplat.train import DEFAULT_RECIPE, TrainConfig, Trainer, apply_overrides, recipe_config
from meshsplat.train.cpu_kernels import start_compiling_early, stop_compiling_early, uses_cpu_kernels

__all__ = ["DemoPreset", "PRESETS", "run_demo", "demo_train_config", "continuous_frames"]


@dataclass(frozen=True)
class DemoPreset:
    """Sizes of one demo run. ``overrides`` are TrainConfig ``key=value`` overrides (its schedule);
    the model comes from a training recipe (``meshsplat.train.recipes``)."""

    frames: int
    resolution: int
    test_views: int
    iterations: int
    n_init: int
    animation_frames: int
    overrides: tuple[str, ...] = field(default_factory=tuple)


# Densification, walking and the lr decay are scaled to the short schedules; the paper's 30k-iteration
# schedule is the TrainConfig default. Opacity reset is off in short runs (it needs thousands of
# iterations to recover).
PRESETS: dict[str, DemoPreset] = {
    "default": DemoPreset(
        frames=100,
        resolution=256,
        test_views=2,
        iterations=1500,
        n_init=10_000,
        animation_frames=30,
        overrides=(
            "strategy.refine_start_iter=300",
            "strategy.refine_stop_iter=1200",
            "strategy.refine_every=100",
            "strategy.reset_every=100000",
            "strategy.max_gaussians=40000",
            "walk.every=100",
            "preview_every=250",
            "checkpoint_every=250",
            "log_every=10",
        ),
    ),
    "tiny": DemoPreset(
        frames=12,
        resolution=64,
        test_views=1,
        iterations=60,
        n_init=1500,
        animation_frames=4,
        overrides=(
            "strategy.refine_start_iter=20",
            "strategy.refine_stop_iter=50",
            "strategy.refine_every=20",
            "strategy.reset_every=100000",
            "walk.every=20",
            "preview_every=30",
            "checkpoint_every=30",
            "log_every=5",
        ),
    ),
}


def demo_train_config(
    data: Path,
    out: Path,
    sizes: DemoPreset,
    extra: list[str] | None = None,
    progress: bool = True,
    recipe: str = DEFAULT_RECIPE,
) -> TrainConfig:
    """The TrainConfig the demo trains with: the model of training recipe ``recipe`` (``quality``,
    or ``paper``: the published method), the schedule of ``sizes``, then ``extra`` (bench variants)."""
    cfg = recipe_config(recipe)
    cfg.data, cfg.out, cfg.device, cfg.progress = str(data), str(out), "auto", progress
    cfg.iterations, cfg.model.n_init = sizes.iterations, sizes.n_init
    return apply_overrides(cfg, list(sizes.overrides) + list(extra or [])).validate()


def continuous_frames(ds: AvatarDataset, n: int, split: str = "test_frames") -> list[int]:
    """Up to ``n`` frame indices playing one continuous motion: the frames of ``split`` (default the
    held-out end of the walk; else the training frames) of one clip, one per pose, in time order."""
    ids = ds.split(split) if split in ds.split_names and ds.split(split) else ds.split("train")
    if not ids:
        ids = list(range(len(ds)))
    infos = [(i, ds.frame_info(i)) for i in ids]
    clip = infos[0][1].get("clip")
    seen, out = set(), []
    same_clip = [(i, f) for i, f in infos if f.get("clip") == clip]
    for i, info in sorted(same_clip, key=lambda x: (x[1].get("time") or 0.0, x[0])):
        if info["mesh"] not in seen:
            seen.add(info["mesh"])
            out.append(i)
    if len(out) > n:
        out = [out[k] for k in np.linspace(0, len(out) - 1, n).round().astype(int)]
    return out


def _generate(data_dir: Path, preset: DemoPreset, progress: bool) -> Path:
    if (data_dir / "manifest.json").exists():
        return data_dir  # reuse a dataset from an earlier (interrupted) demo run
    synthesize(
        asset("gltf/CesiumMan.glb"),
        data_dir,
        rig="monocular-turn",
        frames=preset.frames,
        resolution=preset.resolution,
        test_views=preset.test_views,
        driver_smooth=5,
        progress=progress,
        overwrite=True,
    )
    contact_sheet(open_dataset(data_dir), data_dir / "contact_sheet.png")
    return data_dir


def _compile_while_rendering(cfg: TrainConfig, data_dir: Path) -> bool:
    """Start compiling the training's CPU kernels in one worker process while the capture renders on one thread
    (when training will run them on two or more threads and the dataset is still to make)."""
    if (data_dir / "manifest.json").exists() or not numba_available():
        return False
    if not uses_cpu_kernels(resolve_device(cfg.device), cfg.backend):
        return False
    return start_compiling_early(torch.get_num_threads())


def run_demo(
    out_dir: str | Path = "runs/demo", preset: str = "default", progress: bool = True, iterations: int | None = None
) -> dict[str, Any]:
    """Run the whole pipeline into ``out_dir``; returns (and writes) the summary. Resumes training
    from the last checkpoint if an earlier demo in the same folder was interrupted."""
    if preset not in PRESETS:
        raise MeshsplatError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
    p = PRESETS[preset]
    if iterations is not None:
        p = replace(p, iterations=int(iterations))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    def stage(name: str):
        if progress:
            print(f"[demo] {name}", flush=True)
        return time.perf_counter()

    run = RunFolder(out / "run")
    cfg = demo_train_config(out / "data", run.root, p, progress=progress)
    t = stage(f"1/5 generating a CesiumMan dataset ({p.frames} frames, {p.resolution}px) in {out / 'data'}")
    try:
        if _compile_while_rendering(cfg, out / "data") and progress:
            print("compiling the CPU kernels in another process meanwhile (once after an install)", flush=True)
        data = _generate(out / "data", p, progress)
        timings["synth_s"] = time.perf_counter() - t

        t = stage(f"2/5 training {p.iterations} iterations on {run.root}")
        trainer = Trainer(cfg, resume=True)
        trainer.train()
        timings["train_s"] = time.perf_counter() - t
    finally:
        stop_compiling_early()  # (taken by the training unless it never started)

    t = stage("3/5 evaluating held-out frames and novel views")
    metrics = evaluate_run(run.root)
    timings["eval_s"] = time.perf_counter() - t

    t = stage("4/5 rendering the unseen part of the walk from an orbiting camera")
    avatar = load_avatar(run.root)
    ds = open_dataset(data)
    verts = [ds.vertices(i) for i in continuous_frames(ds, p.animation_frames)]
    cams = orbit_cameras(verts, p.resolution, p.resolution, num_frames=len(verts), orbit_deg=360.0, elevation_deg=15.0)
    anim = render_animation(avatar, verts, cams, out / "animation", fps=12.0, name="avatar_orbit")
    timings["render_s"] = time.perf_counter() - t

    t = stage("5/5 exporting .ply, embedding JSON and canonical mesh")
    exp = export_avatar(avatar, out / "export", source=str(run.root), iteration=trainer.iteration)
    timings["export_s"] = time.perf_counter() - t

    summary = {
        "preset": preset,
        "asset": "CesiumMan (CC-BY 4.0, (c) 2017 Cesium)",
        "iterations": trainer.iteration,
        "gaussians": avatar.num_gaussians,
        "metrics": {
            name: {k: s.get(k) for k in ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")}
            for name, s in metrics.get("splits", {}).items()
        },
        "timings_s": {k: round(v, 1) for k, v in timings.items()},
        "outputs": {
            "dataset": str(data),
            "contact_sheet": str(data / "contact_sheet.png"),
            "run": str(run.root),
            "report": str(run.eval_dir / "report.html"),
            "animation": str(anim.mp4 or (out / "animation" / "frames")),
            "export": str(exp.folder),
        },
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
