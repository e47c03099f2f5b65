"""Atomic training checkpoints.

A checkpoint is ``torch.save({"format": FORMAT_TAG, "version": FORMAT_VERSION, "state": state})``
written to a temporary file in the target folder, flushed, fsynced and moved into place
with ``os.replace``: a reader sees either the previous file or the complete new one.
``state`` may hold tensors, dicts, lists, tuples, numbers, strings, bytes and None (numpy
arrays must be converted to tensors); it is loaded with ``torch.load(weights_only=True)``.

A folder of checkpoints names them ``ckpt_<step:08d>.pt`` (:func:`checkpoint_path`); where a run keeps
that folder and which checkpoint a run is read from is ``meshsplat.run_folder``'s business.
"""

from __future__ import annotations

import io
import os
import pickle
import re
from pathlib import Path

import torch

from meshsplat.errors import MeshsplatError, os_error_text
from meshsplat.io.atomic import atomic_write

__all__ = [
    "FORMAT_TAG",
    "FORMAT_VERSION",
    "save_checkpoint",
    "load_checkpoint",
    "checkpoint_path",
    "list_checkpoints",
    "prune_checkpoints",
    "remove_stray_tmp",
]

FORMAT_TAG = "meshsplat-checkpoint"
FORMAT_VERSION = 1
_NAME = re.compile(r"^ckpt_(\d+)\.pt$")
_TMP = re.compile(r"^\.ckpt_\d+\.pt\..+\.tmp$")  # left behind by a process killed while writing
_PLAIN = (bool, int, float, complex, str, bytes, type(None), torch.dtype, torch.device, torch.Size)


def _check_state(obj, where: str = "state") -> None:
    if isinstance(obj, (torch.Tensor, *_PLAIN)):
        return
    if isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, (str, int, float, bool, type(None))):
                raise MeshsplatError(f"{where}: key {k!r} of type {type(k).__name__} is not storable")
            _check_state(v, f"{where}[{k!r}]")
        return
    if isinstance(obj, (list, tuple, set, frozenset)):
        for i, v in enumerate(obj):
            _check_state(v, f"{where}[{i}]")
        return
    hint = " (convert numpy arrays with torch.from_numpy)" if type(obj).__module__.startswith("numpy") else ""
    raise MeshsplatError(f"{where}: type {type(obj).__name__} cannot be stored in a checkpoint{hint}")


def save_checkpoint(path: str | os.PathLike, state: dict, keep_last: int | None = None) -> Path:
    """Write ``state`` atomically to ``path``; with ``keep_last`` prune older ``ckpt_*.pt`` siblings."""
    if not isinstance(state, dict):
        raise MeshsplatError(f"state: expected a dict, got {type(state).__name__}")
    _check_state(state)
    path = Path(path)
    buf = io.BytesIO()  # serialise first: write errors then come from our own write() as OSError
    torch.save({"format": FORMAT_TAG, "version": FORMAT_VERSION, "state": state}, buf)
    try:
        with atomic_write(path) as fh:
            fh.write(buf.getbuffer())
    except OSError as exc:
        raise MeshsplatError(
            f"cannot write checkpoint {path}: {os_error_text(exc)}; earlier checkpoints are untouched"
        ) from None
    remove_stray_tmp(path.parent)
    if keep_last is not None:
        prune_checkpoints(path.parent, keep_last)
    return path


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    """Load the ``state`` dict saved by :func:`save_checkpoint`; clear errors for bad files."""
    path = Path(path)
    if not path.is_file():
        raise MeshsplatError(f"checkpoint {str(path)!r} not found")
    try:
        open(path, "rb").close()
    except OSError as exc:
        raise MeshsplatError(f"checkpoint {str(path)!r} cannot be read: {os_error_text(exc)}") from None
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        text = str(exc)
        if "unsupported global" in text.lower():
            raise MeshsplatError(
                f"checkpoint {str(path)!r} holds Python code or objects, not just data; it was "
                "not loaded (meshsplat never runs code from a file)"
            ) from None
        # torch's refusal text advises weights_only=False: never relay that; keep only its reason
        reason = (
            next((ln.strip() for ln in text.split("WeightsUnpickler error:")[-1].splitlines() if ln.strip()), "")
            if "WeightsUnpickler error:" in text
            else ("unsupported content" if "weights_only" in text else _first_line(exc))
        )
        raise MeshsplatError(
            f"checkpoint {str(path)!r} is corrupt or truncated, or not a checkpoint ({reason[:120]}); it was not loaded"
        ) from None
    except Exception as exc:  # noqa: BLE001 - truncated zip, garbage: one clear line
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MeshsplatError(f"checkpoint {str(path)!r} is corrupt or truncated ({first[:200]})") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT_TAG:
        raise MeshsplatError(f"checkpoint {str(path)!r} is not a meshsplat checkpoint")
    if blob.get("version") != FORMAT_VERSION:
        raise MeshsplatError(
            f"checkpoint {str(path)!r} has format version {blob.get('version')!r}; "
            f"this meshsplat reads version {FORMAT_VERSION}"
        )
    state = blob.get("state")
    if not isinstance(state, dict):
        raise MeshsplatError(f"checkpoint {str(path)!r} holds no state dict")
    return state


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else type(exc).__name__


def remove_stray_tmp(folder: str | os.PathLike) -> list[Path]:
    """Delete temporary checkpoint files (``.ckpt_*.pt.*.tmp``) left by a killed writer."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    gone = []
    for p in folder.iterdir():
        if _TMP.match(p.name) and p.is_file():
            p.unlink(missing_ok=True)
            gone.append(p)
    return gone


def checkpoint_path(folder: str | os.PathLike, step: int) -> Path:
    """``folder/ckpt_<step:08d>.pt``."""
    if int(step) < 0:
        raise MeshsplatError(f"step: expected a non-negative integer, got {step}")
    return Path(folder) / f"ckpt_{int(step):08d}.pt"


def list_checkpoints(folder: str | os.PathLike) -> list[tuple[int, Path]]:
    """``(step, path)`` of ``ckpt_*.pt`` files in ``folder``, oldest first (not validated)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = []
    for p in folder.iterdir():
        m = _NAME.match(p.name)
        if m and p.is_file():
            found.append((int(m.group(1)), p))
    return sorted(found)


def prune_checkpoints(folder: str | os.PathLike, keep_last: int) -> list[Path]:
    """Delete all but the ``keep_last`` newest ``ckpt_*.pt``; returns the deleted paths."""
    if keep_last < 1:
        raise MeshsplatError(f"keep_last: expected >= 1, got {keep_last}")
    ckpts = list_checkpoints(folder)
    doomed = [p for _, p in ckpts[:-keep_last]]
    for p in doomed:
        p.unlink(missing_ok=True)
    return doomed
