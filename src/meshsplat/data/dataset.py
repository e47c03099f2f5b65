"""The lazy dataset of the native format (docs/dataset-format.md): :class:`AvatarDataset` and its :class:`Frame`.

A dataset is validated when it is opened (``meshsplat.data.manifest``: ``open_dataset``, ``build_dataset``,
the one validation path of every reader) and then hands out frames lazily.
"""

from __future__ import annotations

import copy
import warnings
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from meshsplat.camera import Camera, capture_front, capture_up
from meshsplat.data.downscale import check_downscale, downscale_frame, downscaled_size, scale_intrinsics
from meshsplat.drivers.base import SequenceDriver
from meshsplat.drivers.body_models import BodyModel, model_from_record
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.io.arrays import read_npy
from meshsplat.io.images import MASK_READINGS, png_max, read_image, read_mask

__all__ = ["Frame", "AvatarDataset", "MASK_KINDS", "DROP_FLAG"]

DROP_FLAG = "--drop-bad-frames"  # the command-line flag (reader option drop_bad_frames=True) named by refusals

MASK_KINDS = ("png", "npy", "alpha")  # a mask file (any image), a numpy array, the image's 4th channel


@dataclass
class Frame:
    """One training/test view: ``image [H,W,3]`` float32 in [0,1], ``mask [H,W,1]`` float32 or None,
    its ``camera`` (:class:`~meshsplat.camera.Camera`: ``viewmat``, ``K``, ``width``, ``height``),
    driving ``vertices [V,3]``."""

    image: torch.Tensor
    mask: torch.Tensor | None
    camera: Camera
    vertices: torch.Tensor
    index: int
    name: str
    camera_id: str
    clip: str | None = None
    time: float | None = None


class AvatarDataset:
    """A validated dataset; frames load lazily (``cache_size`` most recent kept in memory)."""

    def __init__(
        self,
        root: Path,
        manifest: dict,
        canonical: np.ndarray,
        faces: np.ndarray,
        vertices: np.ndarray,
        cameras: dict,
        cache_size: int = 8,
        driver_params: dict[str, np.ndarray] | None = None,
        format_name: str = "native",
    ) -> None:
        self.root = root
        self.manifest = manifest
        self.format_name = format_name
        self.driver_params = driver_params
        self.canonical_vertices = torch.from_numpy(canonical.astype(np.float32))
        self.faces = torch.from_numpy(faces.astype(np.int64))
        self._verts = vertices
        self._cameras = cameras  # id -> (K, viewmat, width, height)
        self._frames = manifest["frames"]
        self._splits = {k: [int(i) for i in v] for k, v in manifest.get("splits", {}).items()}
        self._cache: OrderedDict[int, Frame] = OrderedDict()
        self._cache_size = int(cache_size)
        self._replaced: dict[int, np.ndarray] = {}  # mesh row -> vertices [V,3] set by with_meshes
        self.downscale = 1.0  # set_downscale: cameras and frames at 1/downscale of the recorded size
        backdrop = manifest.get("backdrop")
        self.backdrop = None if backdrop is None else torch.tensor(backdrop, dtype=torch.float32)

    def set_downscale(self, factor: float) -> AvatarDataset:
        """Hand out cameras and frames at ``1 / factor`` of the recorded size (``meshsplat.data.downscale``:
        size ``round(W / factor)``, K scaled per axis, area-averaged images and soft masks); 1 = as
        recorded. A factor below 1 or above any camera's smaller side is one MeshsplatError. Returns self."""
        sizes = {cid: (w, h) for cid, (_, _, w, h) in self._cameras.items()}
        self.downscale = check_downscale(factor, sizes)
        self._cache.clear()
        return self

    def __len__(self) -> int:
        return len(self._frames)

    def largest_image_side(self, ids: list[int] | None = None) -> int:
        """The largest image side (pixels) among the cameras of frames ``ids`` (default: the 'train' split;
        all cameras when it names none): what screen radii in fractions of the image size are relative to."""
        ids = self.split("train") if ids is None else ids
        cams = {self.frame_info(i)["camera"] for i in ids} or set(self.camera_ids)
        return max(max(self.camera(c).width, self.camera(c).height) for c in cams)

    @property
    def split_names(self) -> list[str]:
        return list(self._splits)

    @property
    def meta(self) -> dict:
        return dict(self.manifest.get("meta") or {})

    @property
    def driver_info(self) -> dict | None:
        """The body/head model record (``type``, ``gender``, ...) when the meshes come from one."""
        d = self.manifest.get("driver")
        return dict(d) if isinstance(d, dict) else None

    @property
    def per_frame_param_names(self) -> list[str]:
        """Driver parameters with one row per mesh (the rest, e.g. ``betas``, are shared)."""
        if self.driver_params is None:
            return []
        info = self.driver_info or {}
        if "per_frame" in info:
            return [k for k in info["per_frame"] if k in self.driver_params]
        n = self._verts.shape[0] if self._verts is not None else -1
        return [
            k
            for k, v in self.driver_params.items()
            if k not in ("betas", "static_offset") and v.ndim == 2 and v.shape[0] == n
        ]

    def frame_params(self, i: int) -> dict[str, np.ndarray] | None:
        """Model parameters of frame ``i`` (per-frame rows ``[1,k]``, shared ones as stored)."""
        if self.driver_params is None or self.driver_info is None:
            return None
        row = self._frames[self._index(i)]["mesh"]
        per_frame = set(self.per_frame_param_names)
        return {k: (v[row : row + 1] if k in per_frame else v) for k, v in self.driver_params.items()}

    @property
    def up(self) -> torch.Tensor:
        """The world's up direction ``[3]`` as the cameras see it (``camera.capture_up``): the mean of the
        cameras' up vectors, snapped to a world axis; what default and orbit cameras turn about."""
        return torch.from_numpy(capture_up([vm for _, vm, _, _ in self._cameras.values()])).float()

    @property
    def front(self) -> torch.Tensor:
        """Where orbit cameras start (azimuth 0) ``[3]``: the first frame's camera side of the subject, level
        (``camera.capture_front``)."""
        rec = self._frames[0]
        center = np.asarray(self._mesh(rec["mesh"]), np.float64).mean(0)
        return torch.from_numpy(capture_front(self._cameras[str(rec["camera"])][1], center, self.up.double())).float()

    @property
    def dropped_frames(self) -> list[str]:
        """Names of the frames left out by ``drop_bad_frames`` (their cameras do not see the subject)."""
        return list((self.manifest.get("meta") or {}).get("dropped_frames", []))

    @property
    def num_vertices(self) -> int:
        return int(self.canonical_vertices.shape[0])

    @property
    def camera_ids(self) -> list[str]:
        return list(self._cameras)

    def split(self, name: str) -> list[int]:
        if name not in self._splits:
            raise MeshsplatError(f"split: {name!r} not in {self.split_names}")
        return list(self._splits[name])

    def frame_info(self, i: int) -> dict:
        """Manifest record of frame ``i`` (no image decoding)."""
        return dict(self._frames[self._index(i)])

    def camera(self, camera_id: str | int, size: tuple[int, int] | None = None) -> Camera:
        """The camera ``camera_id`` (one of ``camera_ids``), float32 tensors on the CPU; resized to
        ``size = (W, H)`` when given."""
        if str(camera_id) not in self._cameras:
            ids = self.camera_ids
            shown = ", ".join(ids[:20]) + (" ..." if len(ids) > 20 else "")
            raise MeshsplatError(f"camera: {camera_id!r} is not a camera of {self.root} (cameras: {shown})")
        K, vm, w, h = self._cameras[str(camera_id)]
        if self.downscale != 1:
            w2, h2 = downscaled_size(w, h, self.downscale)
            K, w, h = scale_intrinsics(K, w, h, w2, h2), w2, h2
        cam = Camera(torch.from_numpy(vm.astype(np.float32)), torch.from_numpy(K.astype(np.float32)), w, h)
        return cam.resized(*size) if size is not None and tuple(size) != (w, h) else cam

    def frame_camera(self, i: int) -> Camera:
        """The camera of frame ``i`` without loading its image."""
        return self.camera(self._frames[self._index(i)]["camera"])

    def vertices(self, i: int) -> torch.Tensor:
        """Driving vertices ``[V,3]`` of frame ``i`` without loading its image."""
        rec = self._frames[self._index(i)]
        return torch.from_numpy(np.array(self._mesh(rec["mesh"]), dtype=np.float32))

    def _mesh(self, row: int) -> np.ndarray:
        """Driving vertices ``[V,3]`` of mesh ``row``: the replaced ones (``with_meshes``), else the stored."""
        hit = self._replaced.get(int(row))
        return self._verts[row] if hit is None else hit

    @property
    def replaced_meshes(self) -> frozenset[int]:
        """Mesh rows whose vertices ``with_meshes`` replaced."""
        return frozenset(self._replaced)

    def body_model(self, model_dir: str | Path | None, device: torch.device | str = "cpu") -> BodyModel:
        """The body/head model whose parameters (``driver_params``) drive this capture's meshes, from the
        model files in ``model_dir`` (else ``$MESHSPLAT_MODEL_DIR``); one line when the capture has none."""
        info = self.driver_info
        if info is None or self.driver_params is None:
            raise MeshsplatError(
                f"{self.root} has no body/head model parameters ({self.format_name} layout): "
                "its meshes are not driven by SMPL/SMPL-X/FLAME parameters"
            )
        return model_from_record(info, model_dir, device)

    def with_meshes(self, meshes: dict[int, np.ndarray]) -> AvatarDataset:
        """A copy whose driving meshes ``row -> vertices [V,3]`` replace the stored ones (e.g. a run's refined
        training poses); images, cameras, splits and the stored meshes are shared (only the replaced rows
        are held)."""
        shape = (self.num_vertices, 3)
        for row, v in meshes.items():
            if not 0 <= int(row) < self._verts.shape[0] or tuple(np.shape(v)) != shape:
                raise MeshsplatError(
                    f"with_meshes: mesh row {row} with shape {list(np.shape(v))}; expected a row in "
                    f"[0, {self._verts.shape[0]}) and [{shape[0]}, 3]"
                )
        out = copy.copy(self)
        out._replaced = {**self._replaced, **{int(r): np.asarray(v, dtype=np.float32) for r, v in meshes.items()}}
        out._cache = OrderedDict()
        return out

    def driver(self) -> SequenceDriver:
        """All meshes as a :class:`SequenceDriver` (rest = canonical); replaced rows as replaced."""
        verts = self._verts
        if self._replaced:  # a copy only here: frames read the replaced rows one by one (_mesh)
            verts = np.array(verts, dtype=np.float32)
            for row, v in self._replaced.items():
                verts[row] = v
        return SequenceDriver(verts, self.faces, rest=self.canonical_vertices)

    def _index(self, i: int) -> int:
        n = len(self._frames)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        return i % n

    def __getitem__(self, i: int) -> Frame:
        i = self._index(int(i))
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        rec = self._frames[i]
        arr = read_image(self.root / rec["image"], 3)
        img = torch.from_numpy(arr.astype(np.float32)).div_(png_max(arr))
        mask = self._load_mask(rec)
        if self.backdrop is not None and mask is not None:
            img = remove_backdrop(img, mask, self.backdrop)
        camera = self.camera(rec["camera"])
        if self.downscale != 1:
            img, mask = downscale_frame(img, mask, camera.width, camera.height)
        fr = Frame(
            img,
            mask,
            camera,
            self.vertices(i),
            i,
            rec["name"],
            str(rec["camera"]),
            rec.get("clip"),
            rec.get("time"),
        )
        if self._cache_size > 0:
            self._cache[i] = fr
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return fr

    def _load_mask(self, rec: dict) -> torch.Tensor | None:
        kind = rec.get("mask_kind", "png")
        if kind == "alpha":
            return torch.from_numpy(read_image(self.root / rec["image"], 4)[..., 3:]).float().div_(255.0)
        if not rec.get("mask"):
            return None
        if kind == "npy":
            return torch.from_numpy(_read_npy_mask(self.root / rec["mask"]))
        mask, how = read_mask(self.root / rec["mask"])  # alpha mattes, 0/1 label maps, grey; EXIF upright
        if how != "grey":  # say what was understood (one message per folder)
            folder = (self.root / rec["mask"]).parent
            warnings.warn(f"{folder}: masks read from {MASK_READINGS[how]}", MeshsplatWarning, stacklevel=2)
        return torch.from_numpy(mask)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]


def remove_backdrop(image: torch.Tensor, mask: torch.Tensor, backdrop: torch.Tensor) -> torch.Tensor:
    """The subject's own colour ``[H,W,3]`` from ``image [H,W,3]`` recorded over a uniform ``backdrop [3]``
    (``image = colour * mask + backdrop * (1 - mask)``, ``mask [H,W,1]``): at the subject's soft edge the
    recorded pixel mixes in the backdrop, which ``composite(image, mask, bg)`` would keep; with the
    colour instead, the composite over any ``bg`` is exactly ``colour * mask + bg * (1 - mask)``.
    Where the mask is 0 the image is kept; values are clamped to [0, 1] (8-bit rounding at tiny masks)."""
    covered = mask > 0
    colour = (image - backdrop * (1 - mask)) / torch.where(covered, mask, torch.ones_like(mask))
    return torch.where(covered, colour.clamp_(0.0, 1.0), image)


def _read_npy_mask(path: Path) -> np.ndarray:
    """Mask ``[H,W,1]`` float32 in [0,1] from an ``.npy`` of 0/1, bool or 0-255 values."""
    a = np.squeeze(np.asarray(read_npy(path, "mask array")))
    if a.ndim != 2 or (not np.issubdtype(a.dtype, np.number) and a.dtype != bool):
        raise MeshsplatError(f"{path}: expected a numeric [H,W] mask array, got {a.dtype} {list(a.shape)}")
    a = a.astype(np.float32)
    if a.max(initial=0.0) > 1.0:
        a = a / 255.0
    return np.clip(a, 0.0, 1.0)[..., None]
