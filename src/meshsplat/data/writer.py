"""Writing datasets in the native format (see docs/dataset-format.md)."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import Any, cast

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat.errors import MeshsplatError
from meshsplat.io.images import float_to_uint8, write_png

__all__ = ["DatasetWriter", "write_dataset", "FORMAT_NAME", "FORMAT_VERSION"]

FORMAT_NAME = "meshsplat-dataset"
FORMAT_VERSION = 1


_MESHES_PARTIAL = ".vertices.npy.partial"  # posed meshes as they are added (raw float32 rows), until close()


def _np(x, dtype=np.float32) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


class DatasetWriter:
    """Streams frames to ``root``: images and masks are written at once, meshes and the manifest
    on :meth:`close` (atomic manifest write). Use as a context manager.

    ``canonical_vertices [V,3]``, ``faces [F,3]``: the rest (canonical) driving mesh. ``backdrop [3]``:
    the uniform colour the images were rendered over (manifest key ``backdrop``; the loader recovers
    the subject's colour at soft mask edges from it), or None for images as a camera recorded them.
    """

    def __init__(
        self,
        root: Path | str,
        canonical_vertices: torch.Tensor | ArrayLike,
        faces: torch.Tensor | ArrayLike,
        overwrite: bool = False,
        meta: dict | None = None,
        backdrop: tuple[float, float, float] | list[float] | None = None,
    ) -> None:
        self.root = Path(root)
        if (self.root / "manifest.json").exists() and not overwrite:
            raise MeshsplatError(f"{self.root}: a dataset already exists here (pass overwrite=True)")
        (self.root / "images").mkdir(parents=True, exist_ok=True)
        self.canonical = _np(canonical_vertices)
        self.faces = _np(faces, np.int32)
        if self.canonical.ndim != 2 or self.canonical.shape[1] != 3:
            raise MeshsplatError(f"canonical_vertices: expected shape [V,3], got {list(self.canonical.shape)}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise MeshsplatError(f"faces: expected shape [F,3], got {list(self.faces.shape)}")
        self.meta = dict(meta or {})
        self.backdrop = None if backdrop is None else [float(x) for x in backdrop]
        self.cameras: dict[str, dict] = {}
        self.frames: list[dict] = []
        self._mesh_count = 0  # posed meshes streamed to _MESHES_PARTIAL (memory bounded in their number)
        self._mesh_file: Any = None
        self.splits: dict[str, list[int]] = {}
        self.driver: dict | None = None
        self.driver_params: dict[str, np.ndarray] | None = None
        self.source_map: dict[str, np.ndarray] | None = None

    def set_source_map(
        self,
        source_index: torch.Tensor | ArrayLike,
        source_rest: torch.Tensor | ArrayLike,
        source_faces: torch.Tensor | ArrayLike,
        rotation: torch.Tensor | ArrayLike | None = None,
        exact: bool = True,
        smooth: int = 0,
        decimate: float | None = None,
    ) -> None:
        """Record how the driving mesh derives from the asset (``source_map.npz``, see
        :mod:`meshsplat.data.source_map`): ``source_index [V]`` asset vertex of each canonical vertex,
        ``source_rest [Vs,3]`` / ``source_faces [Fs,3]`` the asset's rest mesh in this dataset's world,
        ``rotation [3,3]`` asset axes -> world, ``exact`` (canonical rest == asset rest at the index),
        and the Taubin ``smooth`` iterations / ``decimate`` ratio applied."""
        idx = _np(source_index, np.int64).reshape(-1)
        rest = _np(source_rest)
        if idx.shape[0] != self.canonical.shape[0] or idx.min() < 0 or idx.max() >= rest.shape[0]:
            raise MeshsplatError(
                f"source_index: expected {self.canonical.shape[0]} indices into {rest.shape[0]} asset vertices"
            )
        self.source_map = {
            "source_index": idx,
            "source_rest": rest,
            "source_faces": _np(source_faces, np.int64),
            "rotation": _np(np.eye(3) if rotation is None else rotation, np.float64),
            "exact": np.asarray(bool(exact)),
            "smooth": np.asarray(int(smooth)),
            "decimate": np.asarray(1.0 if decimate is None else float(decimate)),
        }

    def set_driver(self, record: dict, params: dict) -> None:
        """Store the body/head model parameters the meshes were posed with (``driver_params.npz``).

        ``record``: ``{"type": "smpl"|"smplx"|"flame", "gender", ...}``; ``params``: name -> array,
        per-frame arrays with one row per mesh added with :meth:`add_mesh` (checked on close).
        """
        self.driver = {**dict(record), "params": "driver_params.npz"}
        self.driver_params = {k: _np(v) for k, v in params.items()}

    def add_camera(
        self,
        camera_id: str | int,
        K: torch.Tensor | ArrayLike,
        viewmat: torch.Tensor | ArrayLike,
        width: int,
        height: int,
    ) -> str:
        """Register a camera: ``K [3,3]``, world->camera ``viewmat [4,4]`` (OpenCV axes)."""
        cid = str(camera_id)
        self.cameras[cid] = {
            "K": _np(K, np.float64).tolist(),
            "viewmat": _np(viewmat, np.float64).tolist(),
            "width": int(width),
            "height": int(height),
        }
        return cid

    def add_mesh(self, vertices: torch.Tensor | ArrayLike) -> int:
        """Store one posed driving mesh ``[V,3]``; returns its index (frames may share it)."""
        v = _np(vertices)
        if v.shape != self.canonical.shape:
            raise MeshsplatError(f"vertices: expected shape {list(self.canonical.shape)}, got {list(v.shape)}")
        if self._mesh_file is None:
            self._mesh_file = open(self.root / _MESHES_PARTIAL, "wb")  # noqa: SIM115 - closed in close()
        self._mesh_file.write(np.ascontiguousarray(v, "<f4").tobytes())
        self._mesh_count += 1
        return self._mesh_count - 1

    def add_frame(
        self,
        image: torch.Tensor | ArrayLike,
        camera_id: str | int,
        vertices: torch.Tensor | ArrayLike | None = None,
        mesh: int | None = None,
        mask: torch.Tensor | ArrayLike | None = None,
        name: str | None = None,
        clip: str | None = None,
        time: float | None = None,
        extra: dict | None = None,
    ) -> int:
        """Write one frame: ``image [H,W,3]`` (uint8 or float in [0,1]), optional ``mask [H,W]|[H,W,1]``;
        the driving mesh is ``vertices [V,3]`` or an index from :meth:`add_mesh`. Returns the frame index."""
        cid = str(camera_id)
        if cid not in self.cameras:
            raise MeshsplatError(f"camera_id: {cid!r} was not added with add_camera")
        if (vertices is None) == (mesh is None):
            raise MeshsplatError("add_frame: pass exactly one of vertices or mesh")
        if mesh is None:
            assert vertices is not None  # exactly one of the two, checked above
            mesh = self.add_mesh(vertices)
        elif not 0 <= mesh < self._mesh_count:
            raise MeshsplatError(f"mesh: index {mesh} out of range (have {self._mesh_count})")
        index = len(self.frames)
        name = name or f"{index:06d}"
        img = float_to_uint8(image)
        cam = self.cameras[cid]
        if img.ndim != 3 or img.shape[2] != 3 or img.shape[:2] != (cam["height"], cam["width"]):
            raise MeshsplatError(f"image: expected [{cam['height']},{cam['width']},3], got {list(img.shape)}")
        rec: dict[str, Any] = {"name": name, "image": f"images/{name}.png", "camera": cid, "mesh": int(mesh)}
        write_png(self.root / rec["image"], img)
        if mask is not None:
            (self.root / "masks").mkdir(exist_ok=True)
            m = float_to_uint8(mask)
            rec["mask"] = f"masks/{name}.png"
            write_png(self.root / rec["mask"], m.reshape(cam["height"], cam["width"]))
        if clip is not None:
            rec["clip"] = clip
        if time is not None:
            rec["time"] = float(time)
        if extra:
            rec.update(extra)
        self.frames.append(rec)
        return index

    def set_split(self, name: str, indices: Iterable[int] | np.ndarray | torch.Tensor) -> None:
        idx = [int(i) for i in indices]
        bad = [i for i in idx if not 0 <= i < len(self.frames)]
        if bad:
            raise MeshsplatError(f"split {name!r}: frame indices out of range: {bad[:5]}")
        self.splits[name] = idx

    def close(self) -> Path:
        if not self.frames:
            raise MeshsplatError("DatasetWriter: no frames were added")
        np.savez(self.root / "canonical.npz", vertices=self.canonical, faces=self.faces)
        self._write_meshes()
        splits = dict(self.splits)
        splits.setdefault("train", list(range(len(self.frames))))
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "canonical": "canonical.npz",
            "vertices": "vertices.npy",
            "num_vertices": int(self.canonical.shape[0]),
            "num_faces": int(self.faces.shape[0]),
            "cameras": self.cameras,
            "frames": self.frames,
            "splits": splits,
            "meta": self.meta,
        }
        if self.backdrop is not None:
            manifest["backdrop"] = self.backdrop
        if self.driver is not None and self.driver_params is not None:
            per_frame = self.driver.get(
                "per_frame", [k for k, v in self.driver_params.items() if v.ndim == 2 and len(v) == self._mesh_count]
            )
            bad = [k for k in per_frame if len(self.driver_params[k]) != self._mesh_count]
            if bad:
                raise MeshsplatError(f"driver params {bad}: expected one row per mesh ({self._mesh_count})")
            self.driver["per_frame"] = list(per_frame)
            # cast: the savez stub would match a keyword array against allow_pickle
            np.savez(self.root / "driver_params.npz", **cast("dict[str, Any]", self.driver_params))
            manifest["driver"] = self.driver
        if self.source_map is not None:
            np.savez(self.root / "source_map.npz", **cast("dict[str, Any]", self.source_map))
            manifest["source_map"] = "source_map.npz"
        tmp = self.root / "manifest.json.tmp"
        tmp.write_text(json.dumps(manifest, indent=1))
        os.replace(tmp, self.root / "manifest.json")
        return self.root

    def _write_meshes(self) -> None:
        """``vertices.npy [T,V,3]`` float32 from the streamed rows (the bytes ``np.save`` writes), a chunk at a time."""
        if self._mesh_file is not None:
            self._mesh_file.close()
            self._mesh_file = None
        partial = self.root / _MESHES_PARTIAL
        shape = (self._mesh_count, *self.canonical.shape)
        with open(self.root / "vertices.npy", "wb") as out:
            np.lib.format.write_array_header_1_0(out, {"descr": "<f4", "fortran_order": False, "shape": shape})
            if self._mesh_count:
                with open(partial, "rb") as rows:
                    shutil.copyfileobj(rows, out, 16 * 2**20)
        partial.unlink(missing_ok=True)

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        elif self._mesh_file is not None:  # a failed write leaves no half-streamed meshes behind
            self._mesh_file.close()
            self._mesh_file = None
            (self.root / _MESHES_PARTIAL).unlink(missing_ok=True)


def write_dataset(
    root: Path | str,
    canonical_vertices: torch.Tensor | ArrayLike,
    faces: torch.Tensor | ArrayLike,
    cameras: dict,
    frames: list[dict],
    splits: dict | None = None,
    overwrite: bool = False,
    meta: dict | None = None,
) -> Path:
    """One-call writer. ``cameras``: id -> dict(K, viewmat, width, height); ``frames``: dicts with
    ``image``, ``camera_id``, ``vertices`` and optional ``mask``, ``name``, ``clip``, ``time``."""
    w = DatasetWriter(root, canonical_vertices, faces, overwrite=overwrite, meta=meta)
    for cid, cam in cameras.items():
        w.add_camera(cid, cam["K"], cam["viewmat"], cam["width"], cam["height"])
    for fr in frames:
        w.add_frame(
            fr["image"],
            fr["camera_id"],
            vertices=fr.get("vertices"),
            mesh=fr.get("mesh"),
            mask=fr.get("mask"),
            name=fr.get("name"),
            clip=fr.get("clip"),
            time=fr.get("time"),
        )
    for k, v in (splits or {}).items():
        w.set_split(k, v)
    return w.close()
