"""What a capture format module is: the :class:`CaptureFormat` protocol, checked for every registered format.

A format is a module with ``NAME`` (its registry name), ``DESCRIPTION`` (one line), ``SIGNATURE`` (the
files that identify it, quoted when detection fails), ``detect(root) -> bool``,
``read(root, model_dir=None, **options) -> AvatarDataset`` (lazy, validating: every problem of the folder
in one error, as strict as the native reader) and ``write(dataset, out, overwrite=False, **options) -> Path``
(the layout from a native dataset). Optional: ``WRITE_MODEL`` (``"flame"``/``"smpl"``: the body model whose
parameters ``write`` stores) and ``WRITE_RIGS`` (the synth rigs whose captures the layout can hold), which
``synth --format`` checks before rendering. :func:`format_problems` says how a module falls short.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from meshsplat.data.dataset import AvatarDataset

__all__ = ["CaptureFormat", "format_problems"]


@runtime_checkable
class CaptureFormat(Protocol):
    """A capture format module (see the module docstring)."""

    NAME: str
    DESCRIPTION: str
    SIGNATURE: str

    def detect(self, root: Path | str) -> bool: ...

    def read(self, root: Path | str, model_dir: Path | str | None = None, **options: Any) -> AvatarDataset: ...

    def write(self, dataset: AvatarDataset, out: Path | str, overwrite: bool = False, **options: Any) -> Path: ...


def _params(fn: Any) -> list[inspect.Parameter]:
    return list(inspect.signature(fn).parameters.values())


def format_problems(module: Any, name: str) -> list[str]:
    """How ``module`` (registered as ``name``) falls short of :class:`CaptureFormat` (empty when it fits)."""
    out = []
    for attr in ("NAME", "DESCRIPTION", "SIGNATURE"):
        value = getattr(module, attr, None)
        if not isinstance(value, str) or not value.strip() or "\n" in value:
            out.append(f"{attr} must be a one-line string, got {value!r}")
    if getattr(module, "NAME", name) != name:
        out.append(f"NAME is {module.NAME!r}, registered as {name!r}")
    for fn_name in ("detect", "read", "write"):
        if not callable(getattr(module, fn_name, None)):
            out.append(f"{fn_name}() is missing")
    if out:
        return out
    names = [p.name for p in _params(module.detect)]
    if names[:1] != ["root"] or len([p for p in _params(module.detect) if p.default is p.empty]) != 1:
        out.append(f"detect(root) takes one argument, got ({', '.join(names)})")
    read = {p.name: p for p in _params(module.read)}
    if list(read)[:1] != ["root"] or "model_dir" not in read or read["model_dir"].default is not None:
        out.append(f"read(root, model_dir=None, ...), got ({', '.join(read)})")
    write = {p.name: p for p in _params(module.write)}
    if list(write)[:2] != ["dataset", "out"] or write.get("overwrite") is None:
        out.append(f"write(dataset, out, overwrite=False, ...), got ({', '.join(write)})")
    elif write["overwrite"].default is not False:
        out.append("write(): overwrite must default to False")
    model = getattr(module, "WRITE_MODEL", None)
    if model not in (None, "flame", "smpl", "smplx"):
        out.append(f"WRITE_MODEL must be 'flame', 'smpl', 'smplx' or absent, got {model!r}")
    rigs = getattr(module, "WRITE_RIGS", None)
    if rigs is not None and not (isinstance(rigs, tuple) and all(isinstance(r, str) for r in rigs)):
        out.append(f"WRITE_RIGS must be a tuple of rig names, got {rigs!r}")
    if not isinstance(module, CaptureFormat):
        out.append("does not satisfy the CaptureFormat protocol")
    return out
