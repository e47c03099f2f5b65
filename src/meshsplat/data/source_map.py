"""How a dataset's driving (canonical) mesh derives from the asset it was rendered from.

``source_map.npz`` (written by ``meshsplat synth`` next to ``manifest.json`` and copied into each
training run) holds ``source_index [V]`` (the asset vertex that lends canonical vertex ``i`` its
motion: seams welded and vertices reordered, or the nearest vertex of a smoothed/decimated mesh),
``source_rest [Vs,3]`` and ``source_faces [Fs,3]`` (the asset's rest mesh in the dataset's y-up
world), ``rotation [3,3]`` (asset axes -> world), ``exact`` (canonical rest equals the asset rest at
``source_index``), ``smooth`` and ``decimate``. With it, vertex sequences in the asset's own order
and every clip of the asset drive the avatar (:mod:`meshsplat.animation.avatar_match`).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npz
from meshsplat.mesh.geometry import vertex_quaternions
from meshsplat.mesh.quaternion import quat_to_matrix

__all__ = ["SourceMap", "read_source_map", "copy_source_map", "FILE_NAME"]

FILE_NAME = "source_map.npz"


@dataclass
class SourceMap:
    source_index: np.ndarray
    source_rest: np.ndarray
    source_faces: np.ndarray
    rotation: np.ndarray
    exact: bool
    smooth: int = 0
    decimate: float = 1.0
    path: Path | None = None

    @property
    def num_source_vertices(self) -> int:
        return int(self.source_rest.shape[0])

    def to_world(self, verts: torch.Tensor) -> torch.Tensor:
        """Asset-axes vertices ``[..., Vs, 3]`` to the dataset's world."""
        return verts @ torch.as_tensor(self.rotation, dtype=verts.dtype).T

    def to_canonical(self, frame: torch.Tensor, canonical: torch.Tensor) -> torch.Tensor:
        """A world-space frame ``[Vs,3]`` of the asset's mesh as the canonical mesh ``[V,3]``: the
        index picks each canonical vertex; a smoothed/decimated vertex keeps its rest offset from its
        asset vertex, turned by that vertex's rotation (rest -> frame)."""
        idx = torch.from_numpy(self.source_index)
        out = frame[idx]
        if not self.exact:
            rest = torch.from_numpy(self.source_rest).to(frame)
            q = vertex_quaternions(rest, frame, torch.from_numpy(self.source_faces).long())[idx]
            offset = canonical.to(frame) - rest[idx]
            out = out + (quat_to_matrix(q) @ offset[..., None])[..., 0]
        return out


def read_source_map(folder: Path | str) -> SourceMap | None:
    """The source map in ``folder`` (dataset or run), or None when there is none."""
    p = Path(folder) / FILE_NAME
    if not p.is_file():
        return None
    try:
        d = read_npz(p, "source map")
    except MeshsplatError as exc:
        raise MeshsplatError(f"{exc}; delete it to go without") from None
    need = ("source_index", "source_rest", "source_faces", "rotation", "exact")
    if any(k not in d for k in need):
        raise MeshsplatError(f"{p}: source map lacks {[k for k in need if k not in d]}; delete it to go without")
    return SourceMap(
        d["source_index"].astype(np.int64),
        d["source_rest"].astype(np.float32),
        d["source_faces"].astype(np.int64),
        d["rotation"].astype(np.float64),
        bool(d["exact"]),
        int(d.get("smooth", 0)),
        float(d.get("decimate", 1.0)),
        p,
    )


def copy_source_map(dataset_root: Path | str, run_dir: Path | str) -> Path | None:
    """Copy the dataset's source map into the run folder (so the run alone can be animated)."""
    src = Path(dataset_root) / FILE_NAME
    if not src.is_file():
        return None
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    return Path(shutil.copyfile(src, Path(run_dir) / FILE_NAME))
