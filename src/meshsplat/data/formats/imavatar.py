"""IMavatar / DECA head captures (the layout SplattingAvatar trains its head subjects on).

``flame_params.json`` (normalised intrinsics with fx < 0, 100 shape coefficients, per frame an
OpenGL-style world->camera ``world_mat [3,4]``, ``expression [50]``, ``pose [15]``) plus ``image/<k>.png``
(RGBA: the alpha is the matte) or RGB images with a ``mask/`` folder. The head is DECA's FLAME scaled
x4, without translation. Page: docs/formats/imavatar.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from meshsplat.camera import K_from_focal, K_from_integer_centers, K_from_normalized, K_to_integer_centers
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.formats._files import (
    alpha_frames,
    find_file,
    fit_out,
    frame_pixels,
    mask_choice,
    prepare_out,
    read_json,
    save_png,
    tail_split,
    write_json,
)
from meshsplat.data.formats._flame import (
    check_in_front,
    fit_coeffs,
    flame_driver_record,
    flame_model,
    flame_rows,
    pose_model,
)
from meshsplat.data.manifest import Problems, build_dataset, inside_capture
from meshsplat.drivers.body_models import join_flame_pose15, split_flame_pose15
from meshsplat.errors import MeshsplatError
from meshsplat.io.images import image_size

__all__ = [
    "NAME",
    "DESCRIPTION",
    "SIGNATURE",
    "detect",
    "read",
    "write",
    "viewmat_from_world_mat",
    "world_mat_from_viewmat",
    "K_from_intrinsics",
    "DECA_SCALE",
]

NAME = "imavatar"
DESCRIPTION = "IMavatar/DECA head capture: flame_params.json + image/ (FLAME x4, OpenGL world_mat)"
SIGNATURE = "flame_params.json"
WRITE_MODEL = "flame"  # write() stores FLAME parameters: only FLAME-posed datasets can be written
DECA_SCALE = 4.0  # DECA/IMavatar scale FLAME's template, shape and pose blendshapes by 4
NUM_SHAPE, NUM_EXPRESSION = 100, 50
_FLIP_YZ = np.diag([1.0, -1.0, -1.0])  # OpenGL camera axes <-> OpenCV camera axes
_PER_FRAME = ["global_orient", "neck_pose", "jaw_pose", "leye_pose", "reye_pose", "expression"]

_HINT = (
    "world_mat must be an OpenGL-style world->camera matrix (camera looks down -z, as DECA writes it); "
    "check the capture's camera convention"
)


def _placeholder_K(w: float, h: float) -> np.ndarray:
    """Intrinsics standing in for bad ones (reported once), so the rest of the capture is still checked."""
    return K_from_focal(w, h, w / 2, h / 2)


def detect(root: Path | str) -> bool:
    return (Path(root) / "flame_params.json").is_file()


def viewmat_from_world_mat(world_mat: ArrayLike | None) -> np.ndarray:
    """OpenCV world->camera ``[4,4]`` from IMavatar's ``world_mat [3,4]`` (or ``[4,4]``): negate rows 1, 2."""
    a = np.asarray(world_mat, np.float64)
    if a.shape == (4, 4):
        a = a[:3]
    if a.shape != (3, 4) or not np.isfinite(a).all():
        raise MeshsplatError(f"world_mat: expected a finite 3x4 matrix, got shape {list(a.shape)}")
    vm = np.eye(4)
    vm[:3] = _FLIP_YZ @ a
    return vm


def world_mat_from_viewmat(viewmat: ArrayLike) -> np.ndarray:
    """Inverse of :func:`viewmat_from_world_mat`: ``[3,4]``."""
    return _FLIP_YZ @ np.asarray(viewmat, np.float64)[:3]


def K_from_intrinsics(intr: ArrayLike | None, width: int, height: int) -> np.ndarray:
    """``K`` from IMavatar's ``[fx/W, fy/H, cx/W, cy/H]`` (signs dropped; values > 1 are the older pixel
    units on a 512-pixel base, as IMavatar's own reader treats them), in meshsplat's pixel-centre
    convention: IMavatar casts its rays through integer pixel coordinates (``code/datasets/real_dataset.py``
    ``uv = np.mgrid[...]``), so its principal point moves by +0.5 pixel (``meshsplat.camera``)."""
    try:
        a = np.asarray(intr, np.float64).reshape(-1)
        got = f"shape {list(np.shape(cast(ArrayLike, intr)))}"
    except (TypeError, ValueError):
        a, got = np.full(1, np.nan), f"{type(intr).__name__} {str(intr)[:60]!r}"  # not numbers
    if a.shape != (4,) or not np.isfinite(a).all():
        raise MeshsplatError(f"intrinsics: expected 4 finite numbers [fx/W, fy/H, cx/W, cy/H], got {got}")
    if abs(a[3]) > 1:
        a = a / 512.0
    return K_from_integer_centers(K_from_normalized(a, width, height))


def _image_candidates(file_path: str) -> list[str]:
    p = file_path.replace("\\", "/")
    while p.startswith("./"):
        p = p[2:]
    out = [p]
    for a, b in (("image/", "images/"), ("images/", "image/")):
        if p.startswith(a):
            out.append(b + p[len(a) :])
        elif f"/{a}" in p:
            out.append(p.replace(f"/{a}", f"/{b}"))
    return out


def _vector(fr: dict, key: str, where: str, problems: Problems, length: int | None = None) -> np.ndarray | None:
    try:
        a = np.asarray(fr[key], np.float64).reshape(-1)
    except (KeyError, TypeError, ValueError):
        problems.add(where, f"needs a numeric list {key!r}")
        return None
    if length is not None and a.shape != (length,):
        problems.add(where, f"{key} must have {length} numbers, got {a.size}")
        return None
    if not np.isfinite(a).all():
        problems.add(where, f"{key} contains NaN/Inf")
        return None
    return a


def read(
    root: Path | str,
    model_dir: Path | str | None = None,
    test_frames: int | None = None,
    mask: str = "auto",
    flame_version: str | None = None,
    check_masks: bool = True,
    cache_size: int = 8,
    drop_bad_frames: bool = False,
    allow_outside: bool | None = None,
) -> AvatarDataset:
    """Open an IMavatar folder. ``test_frames``: how many final frames are test frames (default: 350, or
    the last 20% of captures with <= 350 frames); ``mask``: auto | alpha | folder | none;
    ``flame_version``: default the file's ``flame_version`` key, else "2020" (DECA's FLAME); ``allow_outside``:
    let ``file_path`` name images outside the folder (default: ``MESHSPLAT_ALLOW_OUTSIDE_FILES=1``)."""
    root = Path(root)
    mask = mask_choice(mask)
    data = read_json(root / "flame_params.json")
    problems = Problems(root)
    items = data.get("frames")
    if not isinstance(items, list) or not items:
        raise MeshsplatError(f"{root / 'flame_params.json'}: 'frames' must be a non-empty list")
    shape = _vector(data, "shape_params", "flame_params.json", problems)
    intr = data.get("intrinsics")

    names, images, viewmats, poses, exprs = [], [], [], [], []
    for j, fr in enumerate(items):
        where = f"frame {j}"
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            problems.add(where, "needs 'file_path' (\"./image/<k>\")")
            continue
        where = f"frame {j} ({fr['file_path']!r})"
        cands = _image_candidates(fr["file_path"])
        rel = next((r for r in (find_file(root, c) for c in cands) if r), cands[0] + ".png")
        try:
            vm = viewmat_from_world_mat(fr.get("world_mat"))
        except (MeshsplatError, TypeError, ValueError) as exc:
            problems.add(where, str(exc))
            vm = None
        pose = _vector(fr, "pose", where, problems, 15)
        expr = _vector(fr, "expression", where, problems)
        names.append(Path(rel).stem)
        images.append(rel)
        viewmats.append(vm)
        poses.append(pose)
        exprs.append(expr)
    lengths = {e.size for e in exprs if e is not None}
    if len(lengths) > 1:
        problems.add("flame_params.json", f"expression vectors differ in length between frames ({sorted(lengths)})")

    scratch = Problems(root)  # outside images are reported by build_dataset, with every other frame file
    first = next(
        (
            root / r
            for r in images
            if inside_capture(root, r, "image", "", scratch, allow_outside) and (root / r).is_file()
        ),
        None,
    )
    if first is None:
        problems.add("image/", "no frame image found (looked for image/<k>.png and images/<k>.png)")
        problems.raise_if_any()
    assert first is not None  # raise_if_any raised
    width, height = image_size(first)
    K = None
    try:
        K = K_from_intrinsics(intr, width, height)
    except MeshsplatError as exc:
        problems.add("flame_params.json", str(exc))

    kind = _mask_kind(root, mask, images, problems)
    cameras, frames = {}, []
    for j, (name, rel, vm) in enumerate(zip(names, images, viewmats, strict=True)):
        cameras[name] = {
            "K": (K if K is not None else _placeholder_K(width, height)).tolist(),
            "viewmat": (vm if vm is not None else np.eye(4)).tolist(),
            "width": width,
            "height": height,
        }
        rec = {"name": name, "image": rel, "camera": name, "mesh": j}
        if kind == "alpha":
            rec["mask_kind"] = "alpha"
        elif kind == "folder":
            m = find_file(root, f"mask/{name}") or find_file(root, f"masks/{name}")
            if m is None:
                problems.add(f"frame {j} ({name!r})", f"mask file mask/{name}.png is missing")
            else:
                rec["mask"] = m
        frames.append(rec)

    version = str(flame_version or data.get("flame_version", "2020"))
    model = flame_model(model_dir, version, DECA_SCALE, problems)
    verts = canonical = faces = params = None
    parsed = (
        all(p is not None for p in poses)
        and all(e is not None for e in exprs)
        and shape is not None
        and len(lengths) <= 1
        and len(poses) == len(items)
    )
    if model is not None and parsed:
        assert shape is not None  # part of parsed
        pose = np.stack(cast("list[np.ndarray]", poses))
        params = {
            "betas": fit_coeffs("shape_params", shape, model.num_betas, problems),
            **split_flame_pose15(pose),
            "expression": fit_coeffs(
                "expression", np.stack(cast("list[np.ndarray]", exprs)), model.num_expression, problems
            ),
        }
        params = {k: np.ascontiguousarray(v, np.float32) for k, v in params.items()}
        verts = pose_model(model, params, "flame_params.json")
        canonical = model.rest_vertices({"betas": params["betas"]}).cpu().numpy()
        faces = model.faces.cpu().numpy()
        check_in_front(cameras, frames, verts, problems, _HINT)
    train, test = tail_split(len(frames), test_frames)
    manifest = {
        "cameras": cameras,
        "frames": frames,
        "vertices": "flame_params.json (posed FLAME x4)",
        "splits": {"train": train, "test_frames": test},
        "meta": {
            "source_format": NAME,
            "source": str(root),
            "flame_version": version,
            "mask": kind,
            "test_frames_rule": "last 350 frames (last 20% when <= 350 frames)"
            if test_frames is None
            else f"last {test_frames} frames",
        },
    }
    if model is not None:
        manifest["driver"] = flame_driver_record(model, "flame_params.json", _PER_FRAME)
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
        driver_params=params,
        format_name=NAME,
        allow_outside=allow_outside,
    )


def _mask_kind(root: Path, mode: str, images: list[str], problems: Problems) -> str:
    """``alpha`` (images are RGBA, every one: decided per file), ``folder`` (mask/ next to image/) or ``none``."""
    folder = (root / "mask").is_dir() or (root / "masks").is_dir()
    if mode == "alpha":
        alpha_frames(root, images, problems, required=True)
    if mode == "auto":
        return "alpha" if alpha_frames(root, images, problems) else ("folder" if folder else "none")
    if mode == "folder" and not folder:
        raise MeshsplatError(f"{root}: mask='folder' but there is no mask/ folder")
    return mode


# ---------------------------------------------------------------- writing
def write(dataset: AvatarDataset, out: Path | str, overwrite: bool = False) -> Path:
    """Write an IMavatar folder from a dataset with FLAME parameters.

    World units become DECA's x4 FLAME: ``x' = (4 / scale) (x - transl)`` per frame, the camera absorbs the
    translation (``t' = (4 / scale) (R transl + t)``), so every pixel projection is unchanged. Images are
    RGBA with the mask in alpha (RGB when the dataset has no masks). Splits are not stored (the reader
    takes the final frames as test frames)."""
    info, params, per_frame = flame_rows(dataset, NAME)
    if "static_offset" in params and np.any(params["static_offset"] != 0):
        raise MeshsplatError(
            "imavatar writer: the dataset's FLAME has a static_offset, which IMavatar's layout cannot "
            "store; write the vhap layout instead"
        )
    s = DECA_SCALE / float(info.get("scale", 1.0))

    def value(key: str, row: int, width: int) -> np.ndarray:
        if key not in params:
            return np.zeros(width)
        v = params[key]
        return v[row] if key in per_frame else v.reshape(-1)

    out = prepare_out(out, overwrite, ("image/*.png",))
    cams = dataset.manifest["cameras"]
    intr = None
    size = (0, 0)  # set together with intr
    frames = []
    for i in range(len(dataset)):
        rec = dataset.frame_info(i)
        row, cam = int(rec["mesh"]), cams[str(rec["camera"])]
        K, vm = np.asarray(cam["K"], np.float64), np.asarray(cam["viewmat"], np.float64)
        w, h = int(cam["width"]), int(cam["height"])
        K = K_to_integer_centers(K)  # IMavatar's pixel centres sit at integers
        this = [-K[0, 0] / w, K[1, 1] / h, K[0, 2] / w, K[1, 2] / h]
        if intr is None:
            intr, size = this, (w, h)
        elif size != (w, h) or not np.allclose(this, intr, rtol=1e-9, atol=1e-12):
            raise MeshsplatError(
                "imavatar writer: the layout stores one camera intrinsics and image size for all "
                "frames; "
                f"frame {i} differs ({w}x{h}, {this} vs {size[0]}x{size[1]}, {intr})"
            )
        R, t = vm[:3, :3], vm[:3, 3]
        new = np.eye(4)
        new[:3, :3] = R
        new[:3, 3] = s * (R @ value("transl", row, 3) + t)
        pose = join_flame_pose15({k: value(k, row, 3)[None] for k in _PER_FRAME[:5]})[0]
        k = i + 1
        rgb, m = frame_pixels(dataset, i)
        save_png(out / "image" / f"{k}.png", rgb if m is None else np.dstack([rgb, m]))
        frames.append(
            {
                "file_path": f"./image/{k}",
                "world_mat": world_mat_from_viewmat(new).tolist(),
                "expression": fit_out(
                    NAME, "expression", value("expression", row, NUM_EXPRESSION), NUM_EXPRESSION
                ).tolist(),
                "pose": pose.tolist(),
            }
        )
    write_json(
        out / "flame_params.json",
        {
            "intrinsics": intr,
            "shape_params": fit_out(NAME, "betas", value("betas", 0, NUM_SHAPE), NUM_SHAPE).tolist(),
            "frames": frames,
            "flame_version": str(info.get("flame_version", "2020")),
        },
    )
    return out
