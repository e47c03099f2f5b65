"""INSTA head captures (instant-ngp style, from metrical-tracker): the tracked meshes drive the avatar.

``transforms_{train,val,test}.json`` (top-level ``w h cx cy fl_x fl_y``; per frame ``transform_matrix``
camera->world, ``file_path`` images/<id>.png, ``mesh_path`` meshes/<id>.obj), ``canonical.obj``. No FLAME
file is needed: every frame's OBJ is read (vertices only after the first; same topology required).
INSTA's ``transform_matrix`` is the inverse of metrical-tracker's OpenCV world->camera, i.e. camera->world
in OpenCV axes; VHAP's mesh export writes the same layout with OpenGL axes (``camera_convention``).
Page: docs/formats/insta.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np

from meshsplat.camera import K_from_focal, opengl_c2w_from_viewmat, viewmat_from_opengl_c2w
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.formats._files import (
    alpha_frames,
    find_file,
    frame_pixels,
    mask_choice,
    merge_transform_frames,
    natural_key,
    not_a_path,
    obj_vertices,
    prepare_out,
    save_png,
    tail_split,
    transforms_files,
    whole_number,
    write_json,
)
from meshsplat.data.formats._flame import check_in_front
from meshsplat.data.manifest import Problems, build_dataset, inside_capture
from meshsplat.errors import MeshsplatError
from meshsplat.io.obj import read_obj, write_obj

__all__ = ["NAME", "DESCRIPTION", "SIGNATURE", "detect", "read", "write", "CONVENTIONS", "VAL_FRAMES"]

NAME = "insta"
DESCRIPTION = "INSTA head capture: transforms_*.json + meshes/*.obj + canonical.obj (tracked meshes)"
SIGNATURE = "transforms_train.json (or transforms.json) + meshes/ or canonical.obj"
CONVENTIONS = ("auto", "opencv", "opengl")
SPLIT_FILES = {"train": "train", "test": "test_frames", "val": "val"}  # INSTA file -> meshsplat split
VAL_FRAMES = 20  # INSTA's transforms_val.json: the last 20 frames (of the test frames)
MASK_FOLDERS = ("masks", "mask", "fg_masks")


def detect(root: Path | str) -> bool:
    root = Path(root)
    has_json = (root / "transforms_train.json").is_file() or (root / "transforms.json").is_file()
    return has_json and ((root / "meshes").is_dir() or (root / "canonical.obj").is_file())


def _files(root: Path) -> list[tuple[str | None, Path]]:
    found = transforms_files(root)
    out: list[tuple[str | None, Path]] = []
    if (root / "transforms.json").is_file():
        out.append((None, root / "transforms.json"))
    for name in [*SPLIT_FILES, *sorted(found)]:
        if name in found and not name.startswith("backup") and SPLIT_FILES.get(name, name) not in [s for s, _ in out]:
            out.append((SPLIT_FILES.get(name, name), found[name]))
    return out


def _camera(fr: dict, top: dict, convention: str):

    def get(k: str) -> Any:
        return fr[k] if k in fr else top[k]

    def has(k: str) -> bool:
        return k in fr or k in top

    fx = float(get("fl_x") if has("fl_x") else get("fl_y"))
    fy = float(get("fl_y") if has("fl_y") else fx)
    w, h = whole_number(get("w"), "w"), whole_number(get("h"), "h")
    K = K_from_focal(fx, fy, float(get("cx")) if has("cx") else w / 2, float(get("cy")) if has("cy") else h / 2)
    c2w = np.asarray(fr["transform_matrix"], np.float64)
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0, 0, 0, 1]])
    if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
        raise MeshsplatError(f"transform_matrix must be a finite 4x4 matrix, got shape {list(c2w.shape)}")
    vm = viewmat_from_opengl_c2w(c2w) if convention == "opengl" else np.linalg.inv(c2w)
    return K, vm, w, h


def read(
    root: Path | str,
    model_dir: Path | str | None = None,
    camera_convention: str = "auto",
    mask: str = "auto",
    test_frames: int | None = None,
    check_masks: bool = True,
    cache_size: int = 8,
    drop_bad_frames: bool = False,
    allow_outside: bool | None = None,
) -> AvatarDataset:
    """Open an INSTA folder. ``camera_convention``: auto (OpenGL when the frames carry VHAP's
    ``timestep_index``, else INSTA's OpenCV) | opencv | opengl; ``mask``: auto (per-frame ``mask_path`` /
    ``fg_mask_path``, else RGBA alpha, else a masks/, mask/ or fg_masks/ folder) | alpha | folder | none;
    ``test_frames``: only for a folder without split files (default: last 350, or 20% when <= 350 frames).
    ``model_dir`` is not needed (the meshes are stored); ``allow_outside``: let the JSON name files outside the
    folder (default: ``MESHSPLAT_ALLOW_OUTSIDE_FILES=1``)."""
    root = Path(root)
    mask = mask_choice(mask)
    if camera_convention not in CONVENTIONS:
        raise MeshsplatError(f"camera_convention: expected one of {list(CONVENTIONS)}, got {camera_convention!r}")
    files = _files(root)
    if not files:
        raise MeshsplatError(f"{root}: no transforms.json or transforms_train.json")
    problems = Problems(root)
    merged, splits, _ = merge_transform_frames(files, problems)
    items = [(fr, top) for fr, top, _ in merged]
    has_splits = any(s is not None for s, _ in files)
    # capture order (INSTA lists frames as its worker pool finishes them): natural order of the image path
    order = sorted(
        range(len(items)),
        key=lambda j: natural_key(str(items[j][0].get("file_path", "")) if isinstance(items[j][0], dict) else ""),
    )
    new = {old: n for n, old in enumerate(order)}
    items = [items[j] for j in order]
    splits = {k: sorted(new[j] for j in v) for k, v in splits.items()}
    if has_splits and test_frames is not None:
        raise MeshsplatError(
            f"{root}: test_frames applies to a folder with only transforms.json; this one has "
            "split files (transforms_train.json ...), which set the test frames"
        )
    if not has_splits:
        train, test = tail_split(len(items), test_frames)
        splits = {"train": train, "test_frames": test}

    convention = camera_convention
    if convention == "auto":
        vhap_made = any(isinstance(fr, dict) and "timestep_index" in fr for fr, _ in items[:1])
        convention = "opengl" if vhap_made else "opencv"

    cameras: dict[str, dict] = {}
    cam_of: dict[tuple, str] = {}
    frames: list[dict] = []
    mesh_row: dict[str, int] = {}
    mesh_paths: list[tuple[str, str]] = []
    for i, (fr, top) in enumerate(items):
        where = f"frame {i}"
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            problems.add(where, "needs 'file_path'")
            continue
        where = f"frame {i} ({fr['file_path']!r})"
        bad = not_a_path(fr, ("mesh_path", "mask_path", "fg_mask_path"))
        if bad:
            problems.add(where, bad)
            continue
        try:
            K, vm, w, h = _camera(fr, top, convention)
        except (KeyError, TypeError, ValueError, MeshsplatError, np.linalg.LinAlgError) as exc:
            problems.add(where, f"needs transform_matrix and fl_x/fl_y/cx/cy/w/h ({exc})")
            continue
        key = (w, h, tuple(np.round(K, 9).ravel()), tuple(np.round(vm, 12).ravel()))
        if key not in cam_of:
            cam_of[key] = str(len(cam_of))
            cameras[cam_of[key]] = {"K": K.tolist(), "viewmat": vm.tolist(), "width": w, "height": h}
        image = find_file(root, fr["file_path"]) or fr["file_path"]
        mp = fr.get("mesh_path") or _derived_mesh_path(fr["file_path"])
        mp = find_file(root, mp, (".obj",)) or mp
        if mp not in mesh_row:
            mesh_row[mp] = len(mesh_paths)
            mesh_paths.append((mp, where))
        rec = {"name": Path(image).stem, "image": image, "camera": cam_of[key], "mesh": mesh_row[mp]}
        explicit = fr.get("mask_path") or fr.get("fg_mask_path")
        if explicit:
            rec["mask"] = find_file(root, explicit) or explicit
        frames.append(rec)

    kind = _assign_masks(root, mask, frames, problems)
    canonical, faces, verts = _meshes(root, mesh_paths, problems, allow_outside)
    hint = (
        "INSTA's transform_matrix is camera->world in OpenCV axes, VHAP's in OpenGL axes; pass "
        f"camera_convention='{'opengl' if convention == 'opencv' else 'opencv'}' if this capture uses the other"
    )
    if verts is not None and len(verts) == len(mesh_paths):
        check_in_front(cameras, frames, verts, problems, hint)
    manifest = {
        "cameras": cameras,
        "frames": frames,
        "vertices": "meshes/*.obj",
        "splits": splits,
        "meta": {
            "source_format": NAME,
            "source": str(root),
            "camera_convention": convention,
            "mask": kind,
            "canonical": "canonical.obj" if (root / "canonical.obj").is_file() else "first frame's mesh",
        },
    }
    return build_dataset(
        root,
        manifest,
        canonical,
        faces,
        verts,
        problems,
        check_masks=check_masks,
        cache_size=cache_size,
        drop_bad_frames=drop_bad_frames,
        format_name=NAME,
        allow_outside=allow_outside,
    )


def _derived_mesh_path(file_path: str) -> str:
    """INSTA's rule when a frame has no ``mesh_path``: images/<id>.png -> meshes/<id>.obj."""
    p = Path(file_path.replace("\\", "/"))
    parts = ["meshes" if q == "images" else q for q in p.parts]
    return str(Path(*parts).with_suffix(".obj").as_posix())


def _assign_masks(root: Path, mode: str, frames: list[dict], problems: Problems) -> str:
    if mode == "none" or not frames:
        for r in frames:
            r.pop("mask", None)
        return "none"
    explicit = all("mask" in r for r in frames)
    images = [r["image"] for r in frames]
    if mode == "alpha":
        alpha_frames(root, images, problems, required=True)
    if mode == "alpha" or (mode == "auto" and not explicit and alpha_frames(root, images, problems)):
        for r in frames:
            r.pop("mask", None)
            r["mask_kind"] = "alpha"
        return "alpha"
    if explicit:
        return "file"
    folder = next((d for d in MASK_FOLDERS if (root / d).is_dir()), None)
    if folder is None:
        if mode == "folder":
            raise MeshsplatError(f"{root}: mask='folder' but none of {list(MASK_FOLDERS)} exists")
        for r in frames:
            r.pop("mask", None)
        return "none"
    for i, r in enumerate(frames):
        if "mask" in r:
            continue
        m = find_file(root, f"{folder}/{r['name']}", (".png", ".jpg", ".npy"))
        if m is None:
            problems.add(f"frame {i} ({r['name']!r})", f"mask {folder}/{r['name']}.png is missing")
            continue
        r["mask"] = m
        if m.endswith(".npy"):
            r["mask_kind"] = "npy"
    return "folder"


def _meshes(root: Path, mesh_paths: list[tuple[str, str]], problems: Problems, allow_outside: bool | None):
    """Canonical ``[V,3]``, faces ``[F,3]`` and every frame's vertices ``[T,V,3]`` (None on failure)."""
    canon_path = root / "canonical.obj"
    first = mesh_paths[0][0] if mesh_paths else None
    if (
        first is not None
        and not canon_path.is_file()
        and inside_capture(root, first, "mesh", mesh_paths[0][1], problems, allow_outside) is None
    ):
        return None, None, None
    ref = canon_path if canon_path.is_file() else (root / first if first is not None else None)
    if ref is None or not ref.is_file():
        problems.add("canonical.obj", "missing (and no frame mesh to take the topology from)")
        return None, None, None
    try:
        m = read_obj(ref)
    except MeshsplatError as exc:
        problems.add(ref.name, str(exc))
        return None, None, None
    canonical, faces = m.vertices.double().numpy(), m.faces.numpy()
    V, F = len(canonical), len(faces)
    verts = np.empty((len(mesh_paths), V, 3), np.float32)
    ok = True
    for r, (rel, where) in enumerate(mesh_paths):
        if inside_capture(root, rel, "mesh", where, problems, allow_outside) is None:
            ok = False
            continue
        p = root / rel
        if not p.is_file():
            problems.add(where, f"mesh {rel} is missing")
            ok = False
            continue
        try:
            v, nf = obj_vertices(p)
        except MeshsplatError as exc:
            problems.add(where, str(exc))
            ok = False
            continue
        if v.shape[0] != V or nf not in (0, F):
            problems.add(
                where,
                f"mesh {rel} has {v.shape[0]} vertices / {nf} faces, {ref.name} has {V} / {F} "
                "(every frame needs the same topology)",
            )
            ok = False
            continue
        verts[r] = v
    return canonical, faces, verts if ok else None


# ---------------------------------------------------------------- writing
def write(dataset: AvatarDataset, out: Path | str, overwrite: bool = False, camera_convention: str = "opencv") -> Path:
    """Write an INSTA folder: ``meshes/<row>.obj`` per mesh row, ``canonical.obj``, ``images/``, ``masks/``
    (when the dataset has masks), ``transforms.json`` (every frame) and ``transforms_{train,test,val}.json``
    (``train``, ``test_frames``, the last 20 test frames as INSTA does); other splits go to
    ``transforms_<name>.json``. Intrinsics of the first frame at top level, per frame where they differ."""
    if camera_convention not in ("opencv", "opengl"):
        raise MeshsplatError(f"camera_convention: expected 'opencv' or 'opengl', got {camera_convention!r}")
    out = prepare_out(out, overwrite, ("transforms*.json",))
    cams = dataset.manifest["cameras"]
    faces = dataset.faces
    write_obj(out / "canonical.obj", dataset.canonical_vertices, faces)
    first_of: dict[int, int] = {}
    for i in range(len(dataset)):
        first_of.setdefault(int(dataset.frame_info(i)["mesh"]), i)
    for r, i in sorted(first_of.items()):
        write_obj(out / "meshes" / f"{r:05d}.obj", dataset.vertices(i), faces)
    top: dict[str, Any] | None = None
    records = []
    for i in range(len(dataset)):
        info = dataset.frame_info(i)
        cam = cams[str(info["camera"])]
        K, vm = np.asarray(cam["K"], np.float64), np.asarray(cam["viewmat"], np.float64)
        intr = {
            "w": int(cam["width"]),
            "h": int(cam["height"]),
            "cx": K[0, 2],
            "cy": K[1, 2],
            "fl_x": K[0, 0],
            "fl_y": K[1, 1],
        }
        if top is None:
            top = {
                **intr,
                "camera_angle_x": 2 * np.arctan(intr["w"] / (2 * K[0, 0])),
                "camera_angle_y": 2 * np.arctan(intr["h"] / (2 * K[1, 1])),
            }
        c2w = opengl_c2w_from_viewmat(vm) if camera_convention == "opengl" else np.linalg.inv(vm)
        fid = f"{i:05d}"
        rec = {
            "transform_matrix": c2w.tolist(),
            "file_path": f"images/{fid}.png",
            "mesh_path": f"meshes/{int(info['mesh']):05d}.obj",
        }
        rec.update({k: v for k, v in intr.items() if top[k] != v})
        rgb, m = frame_pixels(dataset, i)
        save_png(out / "images" / f"{fid}.png", rgb)
        if m is not None:
            save_png(out / "masks" / f"{fid}.png", m)
        records.append(rec)
    top = cast("dict[str, Any]", top)  # set by the first frame
    write_json(out / "transforms.json", {**top, "frames": records})
    names = dataset.split_names
    test = dataset.split("test_frames") if "test_frames" in names else []
    files = {"train": dataset.split("train") if "train" in names else [], "test": test, "val": test[-VAL_FRAMES:]}
    files.update({n: dataset.split(n) for n in names if n not in ("train", "test_frames", "val")})
    for name, idx in files.items():
        write_json(out / f"transforms_{name}.json", {**top, "frames": [records[i] for i in idx]})
    return out
