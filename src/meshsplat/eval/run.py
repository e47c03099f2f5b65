"""Open a training run folder: newest valid checkpoint -> Avatar, its iteration, the run config.

Run layout (written by ``meshsplat.train``): ``RUN/config.json``, ``RUN/checkpoints/ckpt_*.pt``,
``RUN/log.csv``, ``RUN/previews/``. A checkpoint file may be given instead of the folder.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from meshsplat._device import resolve_device
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.avatar import Avatar

__all__ = ["LoadedRun", "load_run", "run_dataset_path", "open_run_dataset"]


@dataclass
class LoadedRun:
    """``avatar`` of the newest valid checkpoint of ``run_dir``; ``config`` is the run's config dict."""

    run_dir: Path
    checkpoint: Path
    iteration: int | None
    avatar: Avatar
    config: dict[str, Any] = field(default_factory=dict)


def load_run(run: str | Path, device: str | torch.device | None = "cpu") -> LoadedRun:
    """Load the avatar of a run folder (newest valid ``checkpoints/ckpt_*.pt``) or of one checkpoint file."""
    from meshsplat.io.checkpoint import load_run_checkpoint

    path = Path(run)
    ckpt, state = load_run_checkpoint(path)
    if path.is_dir():
        run_dir = path
    else:
        run_dir = path.parent.parent if path.parent.name == "checkpoints" else path.parent
    if not isinstance(state, dict) or "avatar" not in state:
        raise MeshsplatError(f"{ckpt}: checkpoint holds no avatar")
    avatar = Avatar.from_state_dict(state["avatar"], resolve_device(device))
    config: dict[str, Any] = {}
    cfg_path = run_dir / "config.json"
    if cfg_path.is_file():
        try:
            config = json.loads(cfg_path.read_text())
        except (ValueError, UnicodeDecodeError) as exc:
            raise MeshsplatError(f"{cfg_path}: not valid JSON ({exc})") from None
    elif isinstance(state.get("config"), dict):
        config = dict(state["config"])
    if not isinstance(config, dict):
        raise MeshsplatError(f"{cfg_path}: expected a JSON object, got {type(config).__name__}")
    it = state.get("iteration")
    if it is not None and (isinstance(it, bool) or not isinstance(it, int) or it < 0):
        raise MeshsplatError(f"{ckpt}: 'iteration' must be a non-negative integer, got {it!r}")
    return LoadedRun(run_dir, Path(ckpt), int(it) if it is not None else None, avatar, config)


def run_dataset_path(run: LoadedRun, dataset: str | Path | None = None) -> Path:
    """``dataset`` if given, else the ``data`` entry of the run's config. Runs store it absolute;
    a relative one (older runs) is tried from the current folder, then from the run folder."""
    if dataset is not None:
        return Path(dataset)
    data = run.config.get("data")
    if not data or not isinstance(data, str):
        raise MeshsplatError(f"{run.run_dir}: config.json names no dataset; pass --dataset PATH")
    p = Path(data)
    if not p.exists() and not p.is_absolute() and (run.run_dir / p).exists():
        p = run.run_dir / p
    if not p.exists():
        raise MeshsplatError(f"the run's dataset {data} (from {run.run_dir / 'config.json'}) is not there: was it "
                             "moved or deleted? Pass --dataset PATH")
    return p


def open_run_dataset(run: LoadedRun, dataset: str | Path | None = None, model_dir: str | Path | None = None,
                     check_masks: bool = True):
    """The run's capture (any layout, as recorded in its config), or ``dataset`` if given.

    ``model_dir`` (SMPL/FLAME files) defaults to the run's ``model_dir``, then ``$MESHSPLAT_MODEL_DIR``.
    """
    from meshsplat.data.formats import open_capture

    path = run_dataset_path(run, dataset)
    fmt = run.config.get("data_format") or None if dataset is None else None
    mdir = model_dir if model_dir is not None else (run.config.get("model_dir") or None)
    return open_capture(path, format=fmt, model_dir=mdir, check_masks=check_masks)
