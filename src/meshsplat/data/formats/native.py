"""meshsplat's own layout (docs/dataset-format.md): ``manifest.json`` + meshes + images."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.manifest import open_dataset
from meshsplat.errors import MeshsplatError

NAME = "native"
DESCRIPTION = "meshsplat native dataset"
SIGNATURE = "manifest.json"


def detect(root: Path | str) -> bool:
    return (Path(root) / "manifest.json").is_file()


def read(root: Path | str, model_dir: Path | str | None = None, **options: Any) -> AvatarDataset:
    return open_dataset(root, **options)


def write(dataset: AvatarDataset, out: Path | str, overwrite: bool = False) -> Path:
    """Copy a native dataset folder (as written; nothing is re-encoded)."""
    out = Path(out)
    if dataset.downscale != 1:  # the files are copied as recorded
        raise MeshsplatError(f"{NAME}: cannot copy a downscaled dataset; write it with meshsplat import --downscale")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise MeshsplatError(f"{out}: exists and is not empty (pass --overwrite)")
    shutil.copytree(dataset.root, out, dirs_exist_ok=True)
    return out
