"""Readers (and writers) for the capture layouts people already have.

Each format module is a ``protocol.CaptureFormat`` (checked for every registered format by a test):
``NAME``, ``DESCRIPTION``, ``SIGNATURE``, ``detect(root) -> bool``,
``read(root, model_dir=None, **options) -> AvatarDataset`` (lazy, validating, every problem of the
folder in one error) and ``write(dataset, out, overwrite=False, **options) -> Path`` (that layout from a
native dataset with driver parameters; used by ``meshsplat synth --format``). The readers' kit:
``_files`` (generic file helpers), ``_flame`` (FLAME posing). Adding a format touches one new module,
its docs page and ``FORMAT_NAMES`` below. Pages: ``docs/formats/``.
"""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path
from types import ModuleType
from typing import Any

from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.manifest import open_dataset
from meshsplat.errors import MeshsplatError

__all__ = ["FORMAT_NAMES", "format_module", "detect_format", "open_capture", "reader_options"]

# detection order: the most specific layouts first
FORMAT_NAMES = ("native", "meshseq", "vhap", "insta", "imavatar", "peoplesnapshot")


def format_module(name: str) -> ModuleType:
    """The module implementing capture format ``name``."""
    if name not in FORMAT_NAMES:
        raise MeshsplatError(f"format: {name!r} is not one of {', '.join(FORMAT_NAMES)}")
    return importlib.import_module(f"meshsplat.data.formats.{name}")


def detect_format(root: Path | str) -> str:
    """Name of the layout of the folder ``root`` (one line saying what was looked for if none fits)."""
    root = Path(root)
    if root.is_file() and root.name == "manifest.json":
        root = root.parent
    if root.exists() and not root.is_dir():
        raise MeshsplatError(f"{root} is a file, not a capture folder: give the folder that holds the capture")
    if not root.is_dir():
        raise MeshsplatError(f"capture folder not found: {root}")
    for name in FORMAT_NAMES:
        if format_module(name).detect(root):
            return name
    looked = "; ".join(f"{n}: {format_module(n).SIGNATURE}" for n in FORMAT_NAMES)
    raise MeshsplatError(f"{root}: not a capture layout meshsplat reads (looked for {looked})")


def open_capture(
    root: Path | str,
    format: str | None = None,
    model_dir: Path | str | None = None,
    downscale: float = 1,
    **options: Any,
) -> AvatarDataset:
    """Open a capture folder of any supported layout as an :class:`AvatarDataset` (``format`` auto-detected).

    ``downscale``: cameras and frames at ``1 / downscale`` of the recorded size, the same rule for every
    layout (``meshsplat.data.downscale``: ``round(W / N)``, K scaled per axis, area-averaged images)."""
    name = format or detect_format(root)
    reader = open_dataset if name == "native" else format_module(name).read
    accepted = inspect.signature(reader).parameters
    unknown = [k for k in options if k not in accepted]
    if unknown:
        raise MeshsplatError(
            f"{root}: the {name} layout has no reader option {', '.join(map(repr, unknown))} "
            f"(--{unknown[0].replace('_', '-')} applies to other layouts; docs/formats/)"
        )
    if name == "native":
        ds = open_dataset(root, **options)
    else:
        ds = format_module(name).read(Path(root), model_dir=model_dir, **options)
    return ds.set_downscale(downscale)


def reader_options(gender: str | None = None, shape: str | None = None) -> dict[str, Any]:
    """The reader options a command was given (``--gender``, ``--shape``; empty ones left out), for
    :func:`open_capture`; a layout whose reader lacks one refuses it in one line."""
    return {k: v for k, v in (("gender", gender), ("shape", shape)) if v}
