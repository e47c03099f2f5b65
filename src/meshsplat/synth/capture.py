"""Synthetic captures in other layouts: generate a native dataset, then write it with a format's ``write``."""

from __future__ import annotations

import inspect
import shutil
import tempfile
from pathlib import Path
from typing import Any

from meshsplat.data.formats import FORMAT_NAMES, format_module
from meshsplat.data.manifest import open_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.io.out_folder import empty_or_new_folder
from meshsplat.synth.body_source import MODEL_SOURCES
from meshsplat.synth.generate import SynthSpec, synthesize

__all__ = ["synth_capture"]


def synth_capture(
    asset: Path | str,
    out: Path | str,
    format: str = "native",
    native_dir: Path | str | None = None,
    overwrite: bool = False,
    write_options: dict | None = None,
    spec: SynthSpec | None = None,
    **generate_options: Any,
) -> Path:
    """Render ``asset`` as ``spec`` says, ``generate_options`` as for :func:`meshsplat.synth.synthesize` (its
    run options, or ``SynthSpec`` fields overriding ``spec``), and write it at ``out`` in ``format``.

    For a format other than ``native`` the native dataset goes to ``native_dir`` (kept) or a temporary
    folder (removed), and ``format_module(format).write(dataset, out, **write_options)`` converts it.
    """
    if format not in FORMAT_NAMES:
        raise MeshsplatError(f"format: {format!r} is not one of {', '.join(FORMAT_NAMES)}")
    out = empty_or_new_folder(out, overwrite)  # an existing capture (or anything else) only with overwrite
    if native_dir is not None:
        empty_or_new_folder(native_dir, overwrite)
    if format == "native":
        return synthesize(asset, out, spec, overwrite=overwrite, **generate_options)
    try:
        module = format_module(format)
        writer = module.write
    except (ImportError, AttributeError):
        raise MeshsplatError(f"format {format!r}: this installation has no writer for it") from None
    _check_fits(module, format, asset, str(generate_options.get("rig", (spec or SynthSpec()).rig)))
    tmp = None
    if native_dir is None:
        tmp = tempfile.mkdtemp(prefix="meshsplat-synth-")
        native_dir = Path(tmp) / "native"
    try:
        native = synthesize(asset, native_dir, spec, overwrite=overwrite, **generate_options)
        opts = dict(write_options or {})
        params = inspect.signature(writer).parameters
        if "overwrite" in params or any(p.kind == p.VAR_KEYWORD for p in params.values()):
            opts["overwrite"] = overwrite
        return writer(open_dataset(native), out, **opts)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def _check_fits(module: Any, format: str, asset: Path | str, rig: str) -> None:
    """Before rendering: the layout can hold what ``asset`` and ``rig`` make (its model, its cameras)."""
    need = getattr(module, "WRITE_MODEL", None)
    kind = str(asset).lower() if not Path(asset).exists() and str(asset).lower() in MODEL_SOURCES else None
    if need is not None and kind != need:
        has = f"the {kind.upper()} model" if kind else f"{asset}, not a {need.upper()} model"
        raise MeshsplatError(
            f"--format {format} stores {need.upper()} parameters but the asset is {has}; synthesize from "
            f"'{need}' (model files from --model-dir), or write --format native or meshseq"
        )
    rigs = getattr(module, "WRITE_RIGS", None)
    if rigs is not None and rig not in rigs:
        raise MeshsplatError(f"--format {format} holds one fixed camera; use --rig {' or '.join(rigs)}, not {rig}")
