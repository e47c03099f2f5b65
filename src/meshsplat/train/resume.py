"""Safe resuming: which checkpoint to continue from, which config changes a resume may make,
and stopping on SIGINT/SIGTERM at an iteration boundary.

Rules (nothing is lost or silently wrong):
- a run folder whose checkpoints cannot all be read is never resumed, cleaned or overwritten:
  the error names every unreadable file and why;
- a fresh run refuses a folder that already holds checkpoints (that would delete them);
- resuming compares the new config with the checkpoint's: changes listed in ``SAFE_CHANGES`` are
  applied (and reported), any other change is refused, naming the keys and both values.
"""

from __future__ import annotations

import hashlib
import json
import random
import signal
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat.data.dataset import AvatarDataset
from meshsplat.errors import MeshsplatError
from meshsplat.io.atomic import write_text_atomic
from meshsplat.io.checkpoint import load_checkpoint
from meshsplat.run_folder import RunFolder, capture_identity, identity_differences

__all__ = [
    "SAFE_CHANGES",
    "load_resume_checkpoint",
    "refuse_existing_run",
    "config_changes",
    "TrainingInterrupted",
    "StopOnSignal",
    "check_resume_config",
    "signal_name",
    "capture_rng",
    "restore_rng",
    "check_same_capture",
    "write_identity",
]

# Keys a resumed run may change: where data/outputs live, how it runs and reports, how long it runs (the pose
# polish comes after the last iteration: a finished run resumed with it fits its poses, the avatar as it is).
SAFE_CHANGES = frozenset(
    {
        "pose_refine.polish_steps",
        "pose_refine.polish_lr",
        "pose_refine.polish_min_gain",
        "data",
        "data_format",
        "model_dir",
        "out",
        "iterations",
        "device",
        "backend",
        "progress",
        "log_every",
        "preview_every",
        "checkpoint_every",
        "checkpoint_every_s",
        "keep_checkpoints",
    }
)


def load_resume_checkpoint(run: RunFolder, map_location: str | torch.device = "cpu") -> tuple[Path, dict] | None:
    """``(path, state)`` of the newest checkpoint of ``run``, or None when there is none.

    Every ``ckpt_*.pt`` must load: otherwise one MeshsplatError names each unreadable file,
    and nothing is deleted (a run that resumed past a bad file would later prune or overwrite it).
    """
    ckpt_dir = run.checkpoint_dir
    ckpts = run.checkpoints()
    if not ckpts:
        return None
    loaded, bad = None, []
    for _, p in reversed(ckpts):
        try:
            state = load_checkpoint(p, map_location)
        except MeshsplatError as exc:
            bad.append(f"{p.name}: {_reason(exc, p)}")
            continue
        if loaded is None:
            loaded = (p, state)
    if bad:
        good = f"; the newest readable one is {loaded[0].name}" if loaded else "; none is readable"
        raise MeshsplatError(
            f"cannot resume: {len(bad)} of {len(ckpts)} checkpoint(s) in {ckpt_dir} are unreadable "
            f"({'; '.join(bad)}){good}. Nothing was changed: move the bad file(s) out of the "
            "folder to resume from the rest, or train into a new --out"
        )
    return loaded


def _reason(exc: MeshsplatError, path: Path) -> str:
    msg = str(exc)
    quoted = repr(str(path))
    return msg.replace(f"checkpoint {quoted} ", "").replace(quoted, "").strip() or msg


def refuse_existing_run(run: RunFolder) -> None:
    """A fresh run must not reuse a folder holding checkpoints (it would prune them)."""
    found = [p for _, p in run.checkpoints()]
    if found:
        raise MeshsplatError(
            f"{run.root} already holds a run ({len(found)} checkpoint(s), newest "
            f"{found[-1].name}); continue it with --resume, or choose another --out"
        )


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def config_changes(old: dict, new: dict) -> tuple[list[str], list[str]]:
    """``(safe, refused)``: ``"key: old -> new"`` for each differing key present in both configs."""
    a, b = _flatten(old), _flatten(new)
    safe: list[str] = []
    refused: list[str] = []
    for k in sorted(set(a) & set(b)):
        if a[k] != b[k]:
            (safe if k in SAFE_CHANGES else refused).append(f"{k}: {a[k]!r} -> {b[k]!r}")
    return safe, refused


def check_resume_config(old: dict, new: dict, ckpt: Path) -> list[str]:
    """Raise when ``new`` changes anything but ``SAFE_CHANGES``; returns the safe changes."""
    safe, refused = config_changes(old if isinstance(old, dict) else {}, new)
    if refused:
        raise MeshsplatError(
            f"cannot resume from {ckpt.name} with a changed config ({'; '.join(refused)}): these "
            f"change the model or its training. Only {', '.join(sorted(SAFE_CHANGES))} may change on "
            "resume; drop the overrides, or start a new run with another --out"
        )
    return [c for c in safe if not c.startswith(("data:", "out:", "progress:"))]


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped by SIGINT/SIGTERM after writing a checkpoint (``checkpoint``)."""

    def __init__(self, message: str, signum: int, checkpoint: Path | None) -> None:
        super().__init__(message)
        self.signum, self.checkpoint = signum, checkpoint


class StopOnSignal:
    """While active (main thread only), SIGINT/SIGTERM only set ``signum``: the loop finishes its
    iteration and checkpoints. A second signal interrupts at once."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __enter__(self) -> StopOnSignal:
        self.signum: int | None = None
        self._old = {}
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._old[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum

    def __exit__(self, *exc) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)


def capture_rng(generators: dict[str, torch.Generator], device: torch.device) -> dict[str, Any]:
    """Every random state a run draws from, for a checkpoint: torch CPU (and CUDA on ``device``), numpy's
    legacy global state, python's ``random``, and the run's own ``generators`` (by name)."""
    np_state: Any = np.random.get_state()  # the legacy tuple
    rng = {
        "torch": torch.get_rng_state(),
        "numpy": [
            np_state[0],
            torch.from_numpy(np_state[1].astype(np.int64)),
            int(np_state[2]),
            int(np_state[3]),
            float(np_state[4]),
        ],
        "python": random.getstate(),
        **{name: gen.get_state() for name, gen in generators.items()},
    }
    if device.type == "cuda":
        rng["cuda"] = torch.cuda.get_rng_state(device)
    return rng


def restore_rng(rng: dict[str, Any], names: tuple[str, ...], device: torch.device) -> dict[str, torch.Generator]:
    """Set the global generators from ``capture_rng``'s dict; returns the run's own generators ``names``."""
    torch.set_rng_state(rng["torch"])
    n = rng["numpy"]
    np.random.set_state((n[0], n[1].numpy().astype(np.uint32), n[2], n[3], n[4]))
    random.setstate(_tuplify(rng["python"]))
    if device.type == "cuda" and "cuda" in rng:
        torch.cuda.set_rng_state(rng["cuda"], device)
    gens = {}
    for name in names:
        gens[name] = torch.Generator()
        gens[name].set_state(rng[name])
    return gens


def _tuplify(x):
    return tuple(_tuplify(v) for v in x) if isinstance(x, (list, tuple)) else x


def check_same_capture(run: RunFolder, dataset: AvatarDataset, data: str) -> None:
    """On resume: the capture is the one the run was trained on (``RUN/run.json``; runs without it pass)."""
    old = run.identity()
    if not isinstance(old, dict) or not isinstance(old.get("capture"), dict):
        return
    differ = identity_differences(old["capture"], capture_identity(dataset))
    if differ:
        raise MeshsplatError(
            f"cannot resume {run.root}: it was trained on {old.get('data', 'another capture')}, and "
            f"{data} is another capture ({', '.join(differ)} differ); resume with the run's own "
            "capture, or train this one into a new --out"
        )


def write_identity(run: RunFolder, config: dict[str, Any], dataset: AvatarDataset, resumed: bool) -> None:
    """``RUN/run.json``: the capture this run trains and a digest of its recipe (every config key but those a
    resume may change); kept on resume."""
    if resumed and run.identity_path.is_file():
        return
    recipe = {k: v for k, v in config.items() if k not in SAFE_CHANGES}
    record = {
        "data": config["data"],
        "data_format": dataset.format_name,
        "capture": capture_identity(dataset),
        "recipe": hashlib.sha256(json.dumps(recipe, sort_keys=True, default=str).encode()).hexdigest()[:16],
    }
    write_text_atomic(run.identity_path, json.dumps(record, indent=1) + "\n")
