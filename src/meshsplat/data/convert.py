"""Converting any opened capture (:func:`meshsplat.data.formats.open_capture`) to the native format."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.writer import DatasetWriter
from meshsplat.errors import MeshsplatError
from meshsplat.io.out_folder import empty_or_new_folder

__all__ = ["write_native"]

_RECORD_KEYS = ("name", "image", "mask", "mask_kind", "camera", "mesh", "clip", "time")


def _safe_name(name: str, taken: set[str]) -> str:
    base = re.sub(r"[^A-Za-z0-9._-]", "_", str(name)).strip(".") or "frame"
    out, k = base, 1
    while out in taken:
        out, k = f"{base}_{k}", k + 1
    taken.add(out)
    return out


def write_native(
    dataset: AvatarDataset,
    out: Path | str,
    overwrite: bool = False,
    progress: Callable[[int, int], object] | None = None,
) -> Path:
    """Write ``dataset`` as a native dataset at ``out``: PNG images, PNG masks (npy / alpha masks are
    converted), the same cameras, meshes (row for row), frames, splits and driver parameters. A
    dataset opened with ``downscale`` is written at that size (meta ``downscale`` records the factor).

    ``progress``: optional callable ``(done, total)``. Returns the folder.
    """
    out = empty_or_new_folder(out, overwrite)
    if out.resolve() == Path(dataset.root).resolve():
        raise MeshsplatError(f"{out}: is the capture folder itself; choose another output folder")
    meta = {**dataset.meta, "imported_from": str(dataset.root), "source_format": dataset.format_name}
    if dataset.downscale != 1:
        meta["downscale"] = dataset.downscale  # images, masks and K at 1/downscale of the capture's
    w = DatasetWriter(out, dataset.canonical_vertices, dataset.faces, overwrite=True, meta=meta)
    for cid in dataset.camera_ids:
        cam = dataset.camera(cid)
        w.add_camera(cid, cam.K, cam.viewmat, cam.width, cam.height)
    drv = dataset.driver()
    for r in range(drv.num_frames):
        w.add_mesh(drv.vertices(r))
    taken: set[str] = set()
    for i in range(len(dataset)):
        info = dataset.frame_info(i)
        fr = dataset[i]
        extra = {k: v for k, v in info.items() if k not in _RECORD_KEYS}
        w.add_frame(
            fr.image,
            fr.camera_id,
            mesh=int(info["mesh"]),
            mask=fr.mask,
            name=_safe_name(fr.name, taken),
            clip=fr.clip,
            time=fr.time,
            extra=extra or None,
        )
        if progress is not None:
            progress(i + 1, len(dataset))
    for name in dataset.split_names:
        w.set_split(name, dataset.split(name))
    driver_info = dataset.driver_info
    if driver_info is not None and dataset.driver_params is not None:
        w.set_driver({k: v for k, v in driver_info.items() if k != "params"}, dataset.driver_params)
    return w.close()
