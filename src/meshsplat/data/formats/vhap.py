"""GaussianAvatars / VHAP head captures (multi-view or monocular, NeRF-style transforms).

``transforms_{train,val,test}.json`` (per frame ``timestep_index``, ``camera_index``, OpenGL camera->world
``transform_matrix``, ``fl_x fl_y cx cy w h`` per frame or top level, ``file_path``, ``fg_mask_path``,
``flame_param_path``) and ``flame_param/{t:05d}.npz`` (FLAME 2023 by default: ``translation``, ``rotation``,
``neck_pose``, ``jaw_pose``, ``eyes_pose``, ``shape``, ``expr``, optional ``static_offset``). One mesh row per
timestep, shared by that timestep's cameras. Page: docs/formats/vhap.md.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, cast

import numpy as np

from meshsplat.camera import K_from_focal, opengl_c2w_from_viewmat, viewmat_from_opengl_c2w
from meshsplat.data.camera_check import group_ids
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.formats._files import (
    alpha_frames,
    find_file,
    fit_out,
    frame_pixels,
    mask_choice,
    merge_transform_frames,
    not_a_path,
    npz_or_problem,
    prepare_out,
    save_png,
    transforms_files,
    whole_number,
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
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.plausible import parameter_problems, sequence_gaps

__all__ = ["NAME", "DESCRIPTION", "SIGNATURE", "detect", "read", "write", "SPLIT_FILES", "TEETH_VERTICES"]

NAME = "vhap"
DESCRIPTION = "GaussianAvatars/VHAP head capture: transforms_*.json + flame_param/*.npz (FLAME 2023)"
SIGNATURE = "transforms_train.json + flame_param/"
WRITE_MODEL = "flame"  # write() stores FLAME parameters: only FLAME-posed datasets can be written
SPLIT_FILES = {"train": "train", "val": "test_views", "test": "test_frames"}  # VHAP file -> meshsplat split
TEETH_VERTICES = 120  # VHAP appends 120 teeth vertices after FLAME's; meshsplat's FLAME has none
NUM_SHAPE, NUM_EXPRESSION = 300, 100
_KEYS = {"translation": 3, "rotation": 3, "neck_pose": 3, "jaw_pose": 3, "eyes_pose": 6, "expr": None}
_PER_FRAME = ["global_orient", "neck_pose", "jaw_pose", "leye_pose", "reye_pose", "expression", "transl"]
_HINT = "VHAP's transform_matrix is camera->world in OpenGL axes (camera looks down -z); check the capture"


def _split_files(root: Path) -> dict[str, Path]:
    """meshsplat split name -> file: VHAP's train/val/test, then any other ``transforms_<name>.json``."""
    out: dict[str, Path] = {}
    found = transforms_files(root)
    for name in [*SPLIT_FILES, *sorted(found)]:
        if name in found and name not in ("backup", "backup_flame"):
            out.setdefault(SPLIT_FILES.get(name, name), found[name])
    return out


def detect(root: Path | str) -> bool:
    root = Path(root)
    has_json = (root / "transforms_train.json").is_file() or (root / "transforms.json").is_file()
    return has_json and (root / "flame_param").is_dir()


def _intrinsics(fr: dict, top: dict):

    def get(k: str) -> Any:
        return fr[k] if k in fr else top[k]

    fx = float(get("fl_x") if ("fl_x" in fr or "fl_x" in top) else get("fl_y"))
    fy = float(get("fl_y") if ("fl_y" in fr or "fl_y" in top) else fx)
    w, h = whole_number(get("w"), "w"), whole_number(get("h"), "h")
    cx = float(get("cx")) if ("cx" in fr or "cx" in top) else w / 2
    cy = float(get("cy")) if ("cy" in fr or "cy" in top) else h / 2
    return K_from_focal(fx, fy, cx, cy), w, h


def _load_frames(root: Path, problems: Problems):
    """All frames (deduplicated by image path, in file order) and the split each file gives them."""
    split_files = _split_files(root)
    files: list[tuple[str | None, Path]] = []
    if (root / "transforms.json").is_file():  # every frame, in capture order; no split of its own
        files.append((None if split_files else "train", root / "transforms.json"))
    files += list(split_files.items())
    return merge_transform_frames(files, problems)


def _npz(path: Path, where: str, problems: Problems, num_vertices: int | None):
    raw = npz_or_problem(path, where, problems, "FLAME parameters")
    if raw is None:
        return None
    bad_kind = [k for k, a in raw.items() if a.dtype.kind not in "fiub"]
    if bad_kind:
        problems.add(where, f"{path.name}: {bad_kind} are not numbers")
        return None
    d = {k: a.astype(np.float64) for k, a in raw.items()}
    missing = [k for k in (*_KEYS, "shape") if k not in d]
    if missing:
        problems.add(where, f"{path.name} lacks {missing}")
        return None
    out = {}
    for k, n in _KEYS.items():
        a = d[k].reshape(-1)
        if n is not None and a.size != n:
            problems.add(where, f"{path.name}: {k} has {a.size} numbers, expected {n}")
            return None
        out[k] = a
    out["shape"] = d["shape"].reshape(-1)
    for k in ("static_offset", "dynamic_offset"):
        if k in d:
            a = d[k].reshape(-1, 3) if d[k].size % 3 == 0 else d[k]
            if num_vertices is not None and (a.ndim != 2 or a.shape[0] < num_vertices):
                problems.add(
                    where, f"{path.name}: {k} has shape {list(d[k].shape)}, expected [1, >= {num_vertices}, 3]"
                )
                return None
            out[k] = a[:num_vertices] if num_vertices is not None else a
    bad = [k for k, a in out.items() if not np.isfinite(a).all()]
    if bad:
        problems.add(where, f"{path.name}: {bad} contain NaN/Inf")
        return None
    implausible = parameter_problems(out)
    for line in implausible:
        problems.add(where, f"{path.name}: {line}")
    return None if implausible else out


def read(
    root: Path | str,
    model_dir: Path | str | None = None,
    flame_version: str | None = None,
    mask: str = "auto",
    ignore_dynamic_offset: bool = False,
    check_masks: bool = True,
    cache_size: int = 8,
    drop_bad_frames: bool = False,
    allow_outside: bool | None = None,
) -> AvatarDataset:
    """Open a GaussianAvatars/VHAP folder. ``flame_version``: default the transforms' ``flame_version`` key,
    else "2023" (VHAP's default); ``mask``: auto (``fg_mask_path``, else RGBA alpha, else ``fg_masks/``) |
    alpha | folder | none; ``ignore_dynamic_offset``: pose without VHAP's per-frame offsets; ``allow_outside``:
    let the JSON name files outside the folder (default: ``MESHSPLAT_ALLOW_OUTSIDE_FILES=1``)."""
    root = Path(root)
    mask = mask_choice(mask)
    problems = Problems(root)
    items, splits, tops = _load_frames(root, problems)
    if not items:
        problems.add("transforms", "no frames")
        problems.raise_if_any()
    version = str(flame_version or next((t["flame_version"] for t in tops if "flame_version" in t), "2023"))
    model = flame_model(model_dir, version, 1.0, problems)
    V = model.num_vertices if model is not None else None

    cameras: dict[str, dict] = {}
    cam_key: dict[tuple, str] = {}
    frames: list[dict] = []
    steps: dict[int, str] = {}
    for i, (fr, top, fname) in enumerate(items):
        where = f"frame {i} ({fname})"
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            problems.add(where, "needs 'file_path'")
            continue
        where = f"frame {i} ({fr['file_path']!r})"
        bad = not_a_path(fr, ("fg_mask_path", "flame_param_path"))
        if bad:
            problems.add(where, bad)
            continue
        try:
            t = whole_number(fr["timestep_index"], "timestep_index")
            c = whole_number(fr.get("camera_index", 0), "camera_index")
            K, w, h = _intrinsics(fr, top)
            vm = viewmat_from_opengl_c2w(fr["transform_matrix"])
        except (KeyError, TypeError, ValueError, MeshsplatError, np.linalg.LinAlgError) as exc:
            problems.add(where, f"needs timestep_index, transform_matrix and fl_x/fl_y/cx/cy/w/h ({exc})")
            continue
        key = (c, w, h, tuple(np.round(K, 9).ravel()), tuple(np.round(vm, 12).ravel()))
        if key not in cam_key:
            same = sum(1 for k in cam_key if k[0] == c)
            cid = str(c) if same == 0 else f"{c}_{same}"
            cam_key[key] = cid
            cameras[cid] = {"K": K.tolist(), "viewmat": vm.tolist(), "width": w, "height": h}
        fp = fr.get("flame_param_path") or f"flame_param/{t:05d}.npz"
        if steps.setdefault(t, fp) != fp:
            problems.add(where, f"timestep {t} has two FLAME files ({steps[t]} and {fp})")
        image = find_file(root, fr["file_path"]) or fr["file_path"]
        rec = {"name": Path(image).stem, "image": image, "camera": cam_key[key], "mesh": t}
        if fr.get("fg_mask_path"):
            rec["mask"] = find_file(root, fr["fg_mask_path"]) or fr["fg_mask_path"]
        frames.append(rec)

    kind = _mask_kind(root, mask, frames, problems)
    for rec in frames:
        if kind == "alpha":
            rec.pop("mask", None)
            rec["mask_kind"] = "alpha"
        elif kind == "folder" and "mask" not in rec:
            rec["mask"] = find_file(root, f"fg_masks/{rec['name']}") or f"fg_masks/{rec['name']}.png"
        elif kind == "none":
            rec.pop("mask", None)

    timesteps = sorted(steps)
    gaps = sequence_gaps(timesteps)
    if gaps is not None:  # training is unaffected (frames are independent); a test clip or motion would jump
        warnings.warn(f"{root}: {gaps} (check that no flame_param file is missing)", MeshsplatWarning, stacklevel=2)
    row_of = {t: r for r, t in enumerate(timesteps)}
    for rec in frames:
        rec["mesh"] = row_of[rec["mesh"]]
    loaded: list[dict | None] = []
    for t in timesteps:
        if inside_capture(root, steps[t], "FLAME parameter file", f"timestep {t}", problems, allow_outside) is None:
            loaded.append(None)
            continue
        path = root / steps[t]
        if not path.is_file():
            problems.add(f"timestep {t}", f"FLAME parameter file {steps[t]} is missing")
            loaded.append(None)
            continue
        loaded.append(_npz(path, f"timestep {t}", problems, V))
    verts = canonical = faces = params = None
    if model is not None and loaded and all(p is not None for p in loaded):
        params = _params(cast("list[dict]", loaded), timesteps, model, problems, ignore_dynamic_offset)
        if params is not None:
            verts = pose_model(model, params, "flame_param/ (rows in timestep order)")
            shared = {k: params[k] for k in ("betas", "static_offset") if k in params}
            canonical = model.rest_vertices(shared).cpu().numpy()
            faces = model.faces.cpu().numpy()
            check_in_front(cameras, frames, verts, problems, _HINT)
    manifest = {
        "cameras": cameras,
        "frames": frames,
        "vertices": "flame_param/ (posed FLAME)",
        "splits": splits,
        "meta": {
            "source_format": NAME,
            "source": str(root),
            "flame_version": version,
            "mask": kind,
            "num_timesteps": len(timesteps),
        },
    }
    if model is not None:
        manifest["driver"] = flame_driver_record(model, "flame_param/", _PER_FRAME)
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


def _mask_kind(root: Path, mode: str, frames: list[dict], problems: Problems) -> str:
    images = [r["image"] for r in frames]
    if mode == "alpha":
        alpha_frames(root, images, problems, required=True)
    if mode == "auto":
        if frames and all("mask" in r for r in frames):
            return "file"
        if alpha_frames(root, images, problems):
            return "alpha"
        return "folder" if (root / "fg_masks").is_dir() else "none"
    if mode == "folder":
        return "file" if frames and all("mask" in r for r in frames) else "folder"
    return mode


def _params(
    loaded: list[dict], timesteps: list[int], model, problems: Problems, ignore_dynamic_offset: bool
) -> dict | None:
    shape0 = loaded[0]["shape"]
    if any(p["shape"].shape != shape0.shape or not np.allclose(p["shape"], shape0) for p in loaded):
        problems.add("flame_param/", "'shape' differs between timesteps; meshsplat needs one subject shape")
        return None
    stat: list[Any] = [p.get("static_offset") for p in loaded]
    if any((s is None) != (stat[0] is None) or (s is not None and not np.allclose(s, stat[0])) for s in stat):
        problems.add("flame_param/", "'static_offset' differs between timesteps; meshsplat needs one per subject")
        return None
    dyn = max((float(np.abs(p["dynamic_offset"]).max()) for p in loaded if "dynamic_offset" in p), default=0.0)
    if dyn > 0 and not ignore_dynamic_offset:
        problems.add(
            "flame_param/",
            f"per-timestep dynamic_offset (up to {dyn:.3g}) is not supported; "
            "pass ignore_dynamic_offset=True to pose without it",
        )
        return None
    for k in _KEYS:  # one file with another shape among many: name the timesteps, never a numpy traceback
        by_shape: dict[tuple, list[int]] = {}
        for t, p in zip(timesteps, loaded, strict=True):
            by_shape.setdefault(p[k].shape, []).append(t)
        if len(by_shape) > 1:
            common = max(by_shape, key=lambda sh: len(by_shape[sh]))
            odd = [t for sh, ts in by_shape.items() if sh != common for t in ts]
            other = next(sh for sh in by_shape if sh != common)
            problems.add(
                "flame_param/",
                f"{k} has shape {list(other)} in timestep{'s' if len(odd) > 1 else ''} {group_ids(odd)} "
                f"but {list(common)} in the other "
                f"{len(by_shape[common])}; every timestep needs the same shape",
            )
            return None

    def stack(k: str) -> np.ndarray:
        return np.stack([p[k] for p in loaded])

    eyes = stack("eyes_pose")
    params = {
        "betas": fit_coeffs("shape", shape0, model.num_betas, problems),
        "global_orient": stack("rotation"),
        "neck_pose": stack("neck_pose"),
        "jaw_pose": stack("jaw_pose"),
        "leye_pose": eyes[:, :3],
        "reye_pose": eyes[:, 3:],
        "expression": fit_coeffs("expr", stack("expr"), model.num_expression, problems),
        "transl": stack("translation"),
    }
    if stat[0] is not None:
        params["static_offset"] = stat[0]
    return {k: np.ascontiguousarray(v, np.float32) for k, v in params.items()}


# ---------------------------------------------------------------- writing
def write(dataset: AvatarDataset, out: Path | str, overwrite: bool = False) -> Path:
    """Write a GaussianAvatars/VHAP folder from a dataset with FLAME parameters.

    One timestep per mesh row the frames use, one camera index per camera; world units become FLAME's
    (``x' = x / scale``, cameras scaled alike, so pixels are unchanged). ``train`` -> transforms_train,
    ``test_views`` -> transforms_val, ``test_frames`` -> transforms_test, other splits ->
    ``transforms_<name>.json``; ``transforms.json`` lists every frame. ``static_offset`` gets 120 zero
    rows for VHAP's teeth."""
    info, params, per_frame = flame_rows(dataset, NAME)
    s = float(info.get("scale", 1.0))
    out = prepare_out(out, overwrite, ("transforms*.json", "flame_param/*.npz"))
    cams = dataset.manifest["cameras"]
    rows = sorted({int(dataset.frame_info(i)["mesh"]) for i in range(len(dataset))})
    step = {r: t for t, r in enumerate(rows)}
    cam_ids = list(dict.fromkeys(str(dataset.frame_info(i)["camera"]) for i in range(len(dataset))))
    cam_index = {c: j for j, c in enumerate(cam_ids)}

    def value(key: str, row: int, width: int) -> np.ndarray:
        if key not in params:
            return np.zeros(width)
        v = params[key]
        return v[row] if key in per_frame else v.reshape(-1)

    shape = fit_out(NAME, "betas", value("betas", 0, NUM_SHAPE), NUM_SHAPE)
    static = None
    if "static_offset" in params:
        so = params["static_offset"].reshape(-1, 3)  # model units: BodyModel scales after posing
        static = np.concatenate([so, np.zeros((TEETH_VERTICES, 3))])[None]
    (out / "flame_param").mkdir(exist_ok=True)
    for r, t in step.items():
        npz = {
            "translation": value("transl", r, 3)[None] / s,
            "rotation": value("global_orient", r, 3)[None],
            "neck_pose": value("neck_pose", r, 3)[None],
            "jaw_pose": value("jaw_pose", r, 3)[None],
            "eyes_pose": np.concatenate([value("leye_pose", r, 3), value("reye_pose", r, 3)])[None],
            "shape": shape,
            "expr": fit_out(NAME, "expression", value("expression", r, NUM_EXPRESSION), NUM_EXPRESSION)[None],
        }
        if static is not None:
            npz["static_offset"] = static
        np.savez(
            out / "flame_param" / f"{t:05d}.npz",
            **cast("dict[str, Any]", {k: np.asarray(v, np.float32) for k, v in npz.items()}),
        )

    records, used = [], set()
    for i in range(len(dataset)):
        info_i = dataset.frame_info(i)
        cid, row = str(info_i["camera"]), int(info_i["mesh"])
        cam = cams[cid]
        K, vm = np.asarray(cam["K"], np.float64), np.array(cam["viewmat"], np.float64)
        vm[:3, 3] /= s
        t, c = step[row], cam_index[cid]
        stem = f"{t:05d}_{c:02d}"
        if stem in used:
            stem = f"{stem}_{i}"
        used.add(stem)
        rgb, m = frame_pixels(dataset, i)
        save_png(out / "images" / f"{stem}.png", rgb)
        w, h = int(cam["width"]), int(cam["height"])
        rec = {
            "timestep_index": t,
            "timestep_index_original": t,
            "timestep_id": f"frame_{t:05d}",
            "camera_index": c,
            "camera_id": cid,
            "cx": K[0, 2],
            "cy": K[1, 2],
            "fl_x": K[0, 0],
            "fl_y": K[1, 1],
            "h": h,
            "w": w,
            "camera_angle_x": 2 * np.arctan(w / (2 * K[0, 0])),
            "camera_angle_y": 2 * np.arctan(h / (2 * K[1, 1])),
            "transform_matrix": opengl_c2w_from_viewmat(vm).tolist(),
            "file_path": f"images/{stem}.png",
            "flame_param_path": f"flame_param/{t:05d}.npz",
        }
        if m is not None:
            save_png(out / "fg_masks" / f"{stem}.png", m)
            rec["fg_mask_path"] = f"fg_masks/{stem}.png"
        records.append(rec)

    first = records[0]
    top = {k: first[k] for k in ("cx", "cy", "fl_x", "fl_y", "h", "w", "camera_angle_x", "camera_angle_y")}
    top.update(
        {
            "timestep_indices": sorted(step.values()),
            "camera_indices": sorted(cam_index.values()),
            "flame_version": str(info.get("flame_version", "2020")),
        }
    )
    write_json(out / "transforms.json", {**top, "frames": records})
    inverse = {v: k for k, v in SPLIT_FILES.items()}
    for name in dataset.split_names:
        idx = dataset.split(name)
        write_json(out / f"transforms_{inverse.get(name, name)}.json", {**top, "frames": [records[i] for i in idx]})
    for fname in SPLIT_FILES:
        if not (out / f"transforms_{fname}.json").exists():
            write_json(out / f"transforms_{fname}.json", {**top, "frames": []})
    canon = {
        "translation": np.zeros((1, 3)),
        "rotation": np.zeros((1, 3)),
        "neck_pose": np.zeros((1, 3)),
        "jaw_pose": np.array([[0.3, 0.0, 0.0]]),
        "eyes_pose": np.zeros((1, 6)),
        "shape": shape,
        "expr": np.zeros((1, NUM_EXPRESSION)),
    }
    if static is not None:
        canon["static_offset"] = static
    np.savez(
        out / "canonical_flame_param.npz",
        **cast("dict[str, Any]", {k: np.asarray(v, np.float32) for k, v in canon.items()}),
    )
    return out
