"""meshsplat's own layout (docs/dataset-format.md): ``manifest.json`` + meshes + images."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.manifest import open_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.io.out_folder import empty_or_new_folder

NAME = "native"
DESCRIPTION = "meshsplat native dataset"
SIGNATURE = "manifest.json"


def detect(root: Path | str) -> bool:
    return (Path(root) / "manifest.json").is_file()


def read(root: Path | str, model_dir: Path | str | None = None, **options: Any) -> AvatarDataset:
    return open_dataset(root, **options)


def write(dataset: AvatarDataset, out: Path | str, overwrite: bool = False) -> Path:
    """Copy a native dataset folder (as written; nothing is re-encoded)."""
    if dataset.downscale != 1:  # the files are copied as recorded
        raise MeshsplatError(f"{NAME}: cannot copy a downscaled dataset; write it with meshsplat import --downscale")
    out = empty_or_new_folder(out, overwrite)
    shutil.copytree(dataset.root, out, dirs_exist_ok=True)
    return out
