"""Your own capture with your own mesh: images + cameras + a mesh sequence (docs/formats/meshseq.md).

Folder layout::

    cameras.json   {"cameras": {ID: {"K": 3x3, "viewmat": 4x4 world->camera OpenCV
                                     | "c2w_opengl": 4x4 camera->world OpenGL, "width": W, "height": H}},
                    "frames": [{"image": "images/0000.png", "camera": ID, "mesh": 0,
                                "mask": "masks/0000.png"}, ...],          (optional, see below)
                    "splits": {"train": [...], "test_frames": [...]}}     (optional; default all train)
    images/        the photos (PNG/JPEG)
    masks/         optional foreground masks, same stem as the image (.png)
    mesh.npz | mesh/ | mesh.glb    the mesh sequence: an npz (faces + vertices [T,V,3]), a folder of
                   OBJ/PLY frames, or a glTF (frames then give "time" in seconds and "clip" instead of "mesh")

Without ``frames``, the images in name order are the frames, all seen by the one camera, image ``i``
posed by mesh frame ``i``. Cameras and meshes share one world; the mesh is used in its own vertex
order (the first frame, or the npz's ``rest``, is the canonical mesh).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from meshsplat.camera import viewmat_from_opengl_c2w
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.formats._files import IMAGE_EXTS, find_file, read_json, whole_number
from meshsplat.data.manifest import Problems, build_dataset, inside_capture
from meshsplat.drivers.gltf import GltfDriver
from meshsplat.drivers.mesh_sequence import FRAMES_LAYOUT, NPZ_LAYOUT, read_mesh_sequence
from meshsplat.errors import MeshsplatError
from meshsplat.io.out_folder import empty_or_new_folder

__all__ = ["NAME", "DESCRIPTION", "SIGNATURE", "detect", "read", "write", "MESH_NAMES"]

NAME = "meshseq"
DESCRIPTION = "images + cameras.json + your own mesh sequence (mesh.npz, mesh/ OBJ/PLY frames or mesh.glb)"
SIGNATURE = "cameras.json + images/ + mesh.npz, mesh/ or mesh.glb"
MESH_NAMES = ("mesh.npz", "mesh", "mesh.glb", "mesh.gltf")
_L = f"{NAME} layout ({SIGNATURE})"


def _mesh_path(root: Path) -> Path | None:
    for name in MESH_NAMES:
        if (root / name).exists():
            return root / name
    return None


def detect(root: Path | str) -> bool:
    root = Path(root)
    return (root / "cameras.json").is_file() and _mesh_path(root) is not None


def _camera(cid: str, cam, problems: Problems):
    if not isinstance(cam, dict) or "K" not in cam or "width" not in cam or "height" not in cam:
        problems.add(f"cameras.json camera {cid!r}", "needs K, width, height and viewmat or c2w_opengl")
        return None
    try:
        if "viewmat" in cam:
            vm = np.asarray(cam["viewmat"], np.float64)
        elif "c2w_opengl" in cam:
            vm = viewmat_from_opengl_c2w(cam["c2w_opengl"])
        else:
            problems.add(f"cameras.json camera {cid!r}", "needs 'viewmat' (world->camera, OpenCV) or 'c2w_opengl'")
            return None
        return {
            "K": np.asarray(cam["K"], np.float64).tolist(),
            "viewmat": np.asarray(vm).tolist(),
            "width": whole_number(cam["width"], "width"),
            "height": whole_number(cam["height"], "height"),
        }
    except (ValueError, TypeError, MeshsplatError) as exc:
        problems.add(f"cameras.json camera {cid!r}", f"malformed ({exc})")
        return None


def _default_frames(root: Path, cameras: dict, problems: Problems) -> list[dict]:
    if len(cameras) != 1:
        problems.add(
            "cameras.json",
            f"no 'frames' list and {len(cameras)} cameras: list the frames "
            "(image, camera, mesh) when there is more than one camera",
        )
        return []
    cid = next(iter(cameras))
    imgs = (
        sorted(p for p in (root / "images").glob("*") if p.suffix.lower() in IMAGE_EXTS)
        if (root / "images").is_dir()
        else []
    )
    if not imgs:
        problems.add("images/", "no images found")
    frames = []
    for i, p in enumerate(imgs):
        rec = {"name": p.stem, "image": f"images/{p.name}", "camera": cid, "mesh": i}
        m = find_file(root, f"masks/{p.stem}", (".png",))
        if m:
            rec["mask"] = m
        frames.append(rec)
    return frames


def _gltf_meshes(path: Path, frames: list[dict], problems: Problems):
    drv = GltfDriver(path)
    rows: list[np.ndarray] = []
    keys: dict[tuple, int] = {}
    for i, rec in enumerate(frames):
        if "time" not in rec:
            problems.add(f"frame {i}", f"with {path.name} a frame needs 'time' (seconds) and optional 'clip'")
            rec["mesh"] = -1
            continue
        key = (rec.get("clip") or drv.clip, float(rec["time"]))
        if key not in keys:
            keys[key] = len(rows)
            rows.append(drv.vertices_at(key[1], key[0]).numpy())
        rec["mesh"] = keys[key]
    verts = np.stack(rows) if rows else np.zeros((0, drv.num_vertices, 3), np.float32)
    return drv.rest_vertices().numpy(), drv.faces.numpy(), verts


def read(
    root: Path | str,
    model_dir: Path | str | None = None,
    check_masks: bool = True,
    cache_size: int = 8,
    drop_bad_frames: bool = False,
    allow_outside: bool | None = None,
    **options: Any,
) -> AvatarDataset:
    """Open the folder (see the module docstring); every problem in one error naming the layout.
    ``allow_outside``: let cameras.json name files outside the folder, and the mesh sequence be a link out
    of it (default: ``MESHSPLAT_ALLOW_OUTSIDE_FILES=1``)."""
    root = Path(root)
    if options:
        raise MeshsplatError(f"{NAME}: unknown options {sorted(options)}")
    doc = read_json(root / "cameras.json")
    mpath = _mesh_path(root)
    if mpath is None:
        raise MeshsplatError(f"{root}: no mesh sequence ({', '.join(MESH_NAMES)}) for the {_L}")
    problems = Problems(root)
    if inside_capture(root, mpath.name, "mesh sequence", mpath.name, problems, allow_outside) is None:
        problems.raise_if_any()
    cams_in = doc.get("cameras")
    if not isinstance(cams_in, dict) or not cams_in:
        raise MeshsplatError(
            f"{root / 'cameras.json'}: needs a 'cameras' object (id -> K, viewmat, width, height); {_L}"
        )
    cameras = {str(k): c for k, c in ((str(k), _camera(str(k), v, problems)) for k, v in cams_in.items()) if c}
    frames = doc.get("frames")
    if frames is None:
        frames = _default_frames(root, cameras, problems)
    elif not isinstance(frames, list):
        raise MeshsplatError(f"{root / 'cameras.json'}: 'frames' must be a list of records; {_L}")
    frames = [dict(f) if isinstance(f, dict) else f for f in frames]
    for rec in frames:
        if isinstance(rec, dict) and "image" in rec:
            rec["image"] = find_file(root, str(rec["image"])) or str(rec["image"])
            rec.setdefault("name", Path(rec["image"]).stem)
    try:
        if mpath.suffix.lower() in (".glb", ".gltf"):
            canonical, faces, verts = _gltf_meshes(mpath, [f for f in frames if isinstance(f, dict)], problems)
            what = "glTF"
        else:
            seq = read_mesh_sequence(mpath, with_uvs=False)
            canonical = seq.rest if seq.rest is not None else seq.vertices[0]
            faces, verts = seq.faces, seq.vertices
            what = NPZ_LAYOUT if seq.layout == "npz" else FRAMES_LAYOUT
    except MeshsplatError as exc:
        raise MeshsplatError(f"{exc} [{_L}]") from None
    splits = doc.get("splits") or {"train": list(range(len(frames)))}
    manifest = {
        "cameras": cameras,
        "frames": frames,
        "vertices": mpath.name,
        "splits": splits,
        "meta": {
            "source_format": NAME,
            "source": str(root),
            "mesh": what,
            "attribution": str(doc.get("attribution", "")),
        },
    }
    return build_dataset(
        root,
        manifest,
        np.asarray(canonical, np.float32),
        np.asarray(faces, np.int64),
        np.asarray(verts, np.float32),
        problems,
        check_masks=check_masks,
        cache_size=cache_size,
        drop_bad_frames=drop_bad_frames,
        format_name=NAME,
        allow_outside=allow_outside,
    )


def write(dataset: AvatarDataset, out: Path | str, overwrite: bool = False) -> Path:
    """This layout from any dataset: images/, masks/, cameras.json (OpenCV viewmats) and mesh.npz."""
    import json
    import shutil

    if dataset.downscale != 1:  # the files are copied as recorded
        raise MeshsplatError(f"{NAME}: cannot copy a downscaled dataset; write it with meshsplat import --downscale")
    out = empty_or_new_folder(out, overwrite)
    (out / "images").mkdir(parents=True, exist_ok=True)
    cams = {}
    for cid in dataset.camera_ids:
        cam = dataset.camera(cid)
        cams[cid] = {
            "K": np.asarray(cam.K, np.float64).tolist(),
            "viewmat": np.asarray(cam.viewmat, np.float64).tolist(),
            "width": cam.width,
            "height": cam.height,
        }
    frames = []
    for i in range(len(dataset)):
        info = dataset.frame_info(i)
        img = Path(info["image"])
        shutil.copyfile(dataset.root / img, out / "images" / img.name)
        rec = {"image": f"images/{img.name}", "camera": info["camera"], "mesh": int(info["mesh"])}
        if info.get("mask") and info.get("mask_kind", "png") == "png":
            (out / "masks").mkdir(exist_ok=True)
            shutil.copyfile(dataset.root / info["mask"], out / "masks" / Path(info["mask"]).name)
            rec["mask"] = f"masks/{Path(info['mask']).name}"
        frames.append(rec)
    drv = dataset.driver()
    verts = np.stack([drv.vertices(r).numpy() for r in range(drv.num_frames)])
    np.savez(
        out / "mesh.npz",
        faces=dataset.faces.numpy().astype(np.int32),
        vertices=verts,
        rest=dataset.canonical_vertices.numpy(),
    )
    doc = {
        "cameras": cams,
        "frames": frames,
        "splits": {s: dataset.split(s) for s in dataset.split_names},
        "attribution": str(dataset.meta.get("attribution", "")),
    }
    (out / "cameras.json").write_text(json.dumps(doc, indent=1))
    return out
