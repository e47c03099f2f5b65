"""PeopleSnapshot in the InstantAvatar / Anim-NeRF layout (docs/formats/peoplesnapshot.md).

    cameras.npz                 intrinsic [3,3], extrinsic [4,4] world->camera (OpenCV), height, width
    poses.npz                   betas [10] or [1,10], thetas [N,72], transl [N,3]   (row = absolute frame index)
    poses/anim_nerf_<split>.npz optional refined betas, global_orient [n,3], body_pose [n,69], transl [n,3]
                                (row = position inside the split; wins over poses.npz for that split)
    images/image_%04d.png       one fixed camera
    masks/mask_%04d.png|.npy    0-255 PNG or 0/1 array (optional folder)
    config.json                 gender, train/val/test: {start, end (inclusive), skip}

Meshes are SMPL (``BodyModel("smpl", model_dir, gender)``) posed with those parameters; the canonical
mesh is the rest pose with the subject's betas. Splits: train -> "train", val -> "val",
test -> "test_frames".
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import cast

import numpy as np
import torch

from meshsplat.data.dataset import AvatarDataset, Problems, build_dataset
from meshsplat.data.png import write_png
from meshsplat.drivers.body_models import GENDERS, BodyModel, driver_record, join_smpl_thetas, split_smpl_thetas
from meshsplat.errors import MeshsplatError, MeshsplatWarning

__all__ = ["NAME", "DESCRIPTION", "SIGNATURE", "detect", "read", "write", "SPLIT_NAMES", "DEFAULT_TEST_FRACTION"]

NAME = "peoplesnapshot"
DESCRIPTION = "PeopleSnapshot, InstantAvatar / Anim-NeRF layout (SMPL, one fixed camera)"
SIGNATURE = "cameras.npz + poses.npz (or poses/anim_nerf_*.npz) + images/image_0000.png"

# PeopleSnapshot split -> meshsplat split; the order is also the precedence when splits share a frame
SPLIT_NAMES = {"train": "train", "test": "test_frames", "val": "val"}
DEFAULT_TEST_FRACTION = 0.2  # without config.json: the last 20% of the frames are test frames
PER_FRAME = ("global_orient", "body_pose", "transl")
_CHUNK = 64


def detect(root: Path | str) -> bool:
    root = Path(root)
    has_poses = (root / "poses.npz").is_file() or any((root / "poses").glob("anim_nerf_*.npz"))
    return (root / "cameras.npz").is_file() and has_poses and (root / "images").is_dir()


# ---------------------------------------------------------------- reading
def read(
    root: Path | str,
    model_dir: Path | str | None = None,
    gender: str | None = None,
    check_masks: bool = True,
    cache_size: int = 8,
    drop_bad_frames: bool = False,
    device: str | torch.device = "cpu",
) -> AvatarDataset:
    """Open a PeopleSnapshot folder lazily (images decode on access); every problem in one error.

    ``gender`` overrides config.json's; ``model_dir`` holds ``smpl/SMPL_<GENDER>.pkl``.
    """
    root = Path(root)
    if not root.is_dir():
        raise MeshsplatError(f"capture folder not found: {root}")
    problems = Problems(root)
    cfg_gender, ranges = _read_config(root, problems)
    gender = (gender or cfg_gender or "neutral").lower()
    if gender not in GENDERS:
        problems.add("gender", f"unknown gender {gender!r} (expected one of {list(GENDERS)})")
    camera = _read_camera(root, problems)
    has_config = ranges is not None
    if ranges is None:
        ranges = _default_ranges(root)
    splits_in_use = [s for s in SPLIT_NAMES if s in ranges]
    refined = {
        s: _read_refined(root / "poses" / f"anim_nerf_{s}.npz", len(ranges[s]), problems)
        for s in splits_in_use
        if has_config and (root / "poses" / f"anim_nerf_{s}.npz").is_file()
    }
    if not has_config and any((root / "poses").glob("anim_nerf_*.npz")):
        warnings.warn(
            f"{root}: no config.json, so the split-relative poses/anim_nerf_*.npz cannot be placed; using poses.npz",
            MeshsplatWarning,
            stacklevel=2,
        )
    needs_poses = any(s not in refined for s in splits_in_use) or not refined
    poses = _read_poses(root, problems) if needs_poses or (root / "poses.npz").is_file() else None

    # one frame record per absolute index; a frame in several splits takes the first split's params
    rows: dict[int, tuple[str, int]] = {}  # absolute index -> (params source split, position)
    for s in splits_in_use:
        for pos, idx in enumerate(ranges[s]):
            rows.setdefault(idx, (s, pos))
    order = sorted(rows)
    if poses is not None:
        n = len(poses["transl"])
        beyond = [i for i in order if rows[i][0] not in refined and i >= n]
        if beyond:
            problems.add("poses.npz", f"has {n} pose rows but frames {_ids(beyond)} are used (no pose for them)")

    masks_dir = (root / "masks").is_dir()
    frames, missing_masks = [], []
    for k, idx in enumerate(order):
        rec = {
            "name": f"image_{idx:04d}",
            "image": f"images/image_{idx:04d}.png",
            "camera": "0",
            "mesh": k,
            "frame_index": idx,
            "split": SPLIT_NAMES[rows[idx][0]],
        }
        if masks_dir:
            png, npy = root / "masks" / f"mask_{idx:04d}.png", root / "masks" / f"mask_{idx:04d}.npy"
            if png.is_file():
                rec.update(mask=f"masks/{png.name}", mask_kind="png")
            elif npy.is_file():
                rec.update(mask=f"masks/{npy.name}", mask_kind="npy")
            else:
                missing_masks.append(idx)
        frames.append(rec)
    if missing_masks:
        problems.add("masks/", f"no mask_%04d.png or .npy for frames {_ids(missing_masks)}")
    pos_of = {idx: k for k, idx in enumerate(order)}
    splits = {SPLIT_NAMES[s]: [pos_of[i] for i in ranges[s]] for s in splits_in_use}

    params = _assemble_params(order, rows, refined, poses, problems)
    model = None
    if gender in GENDERS:
        try:
            model = BodyModel("smpl", model_dir, gender=gender, device=device)
        except MeshsplatError as exc:
            problems.add("SMPL model", str(exc))
    canonical = faces = verts = None
    if model is not None and params is not None:
        try:
            model.check_params(params, num_frames=len(order))
        except MeshsplatError as exc:
            problems.add("SMPL parameters", str(exc))
        else:
            canonical, verts = _pose(model, params)
            faces = model.faces.cpu().numpy()

    if camera is None or not frames:  # nothing to check images against: report what we have
        if not frames:
            problems.add("config.json", "no frames selected (empty train/val/test ranges and no images)")
        _check_files_exist(root, frames, problems)
        problems.raise_if_any()
    if verts is None and not problems.items:
        problems.add("SMPL", "could not pose the model")
    record = {**driver_record(model, "poses.npz"), "per_frame": list(PER_FRAME)} if model is not None else None
    manifest = {
        "cameras": {"0": camera},
        "frames": frames,
        "splits": splits,
        "vertices": "SMPL vertices (posed)",
        "meta": {
            "source_format": NAME,
            "gender": gender,
            "frame_ranges": {s: _range_dict(ranges[s]) for s in splits_in_use},
            "params_source": {
                SPLIT_NAMES[s]: (f"poses/anim_nerf_{s}.npz" if s in refined else "poses.npz") for s in splits_in_use
            },
        },
        "driver": record,
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
        driver_params=params,
        format_name=NAME,
    )


def _ids(xs: list[int], k: int = 8) -> str:
    return ", ".join(map(str, xs[:k])) + (f", ... ({len(xs)} in all)" if len(xs) > k else "")


def _range_dict(r: range) -> dict:
    return {"start": r.start, "end": r[-1] if len(r) else r.start, "skip": r.step}


def _npz(path: Path, problems: Problems) -> dict | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError) as exc:
        problems.add(path.name, f"cannot read ({exc})")
        return None


def _read_config(root: Path, problems: Problems) -> tuple[str | None, dict[str, range] | None]:
    p = root / "config.json"
    if not p.is_file():
        return None, None
    try:
        cfg = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        problems.add("config.json", f"invalid JSON ({exc})")
        return None, None
    if not isinstance(cfg, dict):
        problems.add("config.json", "must be an object with gender and train/val/test ranges")
        return None, None
    gender = cfg.get("gender")
    if gender is not None and not isinstance(gender, str):
        problems.add("config.json", f"gender must be a string, got {gender!r}")
        gender = None
    ranges = {}
    for s in SPLIT_NAMES:
        spec = cfg.get(s)
        if spec is None:
            continue
        try:
            start, end, skip = int(spec["start"]), int(spec["end"]), int(spec.get("skip", 1))
        except (KeyError, TypeError, ValueError):
            problems.add("config.json", f"{s!r} needs integer start, end (inclusive) and skip, got {spec!r}")
            continue
        if start < 0 or end < start or skip < 1:
            problems.add("config.json", f"{s!r}: need 0 <= start <= end and skip >= 1, got {start}, {end}, {skip}")
            continue
        ranges[s] = range(start, end + 1, skip)
    if cfg.get("train") is None:
        problems.add("config.json", "has no 'train' range ({start, end, skip})")
    return gender, ranges


def _default_ranges(root: Path) -> dict[str, range]:
    """Without config.json: images 0..N-1, the last ``DEFAULT_TEST_FRACTION`` of them test frames."""
    n = 0
    while (root / "images" / f"image_{n:04d}.png").is_file():
        n += 1
    if n < 2:
        return {"train": range(0, n)}
    n_test = max(1, round(DEFAULT_TEST_FRACTION * n))
    return {"train": range(0, n - n_test), "test": range(n - n_test, n)}


def _read_camera(root: Path, problems: Problems) -> dict | None:
    p = root / "cameras.npz"
    if not p.is_file():
        problems.add("cameras.npz", "is missing (needs intrinsic [3,3], extrinsic [4,4], height, width)")
        return None
    z = _npz(p, problems)
    if z is None:
        return None
    missing = [k for k in ("intrinsic", "extrinsic", "height", "width") if k not in z]
    if missing:
        problems.add("cameras.npz", f"missing keys {missing} (has {sorted(z)})")
        return None
    K, E = z["intrinsic"], z["extrinsic"]
    ok = True
    if K.shape != (3, 3):
        problems.add("cameras.npz", f"intrinsic must be [3,3], got {list(K.shape)}")
        ok = False
    if E.shape not in ((4, 4), (3, 4)):
        problems.add("cameras.npz", f"extrinsic must be [4,4] world->camera, got {list(E.shape)}")
        ok = False
    try:
        h, w = int(np.asarray(z["height"]).reshape(-1)[0]), int(np.asarray(z["width"]).reshape(-1)[0])
    except (IndexError, TypeError, ValueError):
        problems.add("cameras.npz", "height and width must be numbers")
        ok = False
    if not ok:
        return None
    if E.shape == (3, 4):
        E = np.vstack([E, [0.0, 0.0, 0.0, 1.0]])
    return {
        "K": np.asarray(K, np.float64).tolist(),
        "viewmat": np.asarray(E, np.float64).tolist(),
        "width": w,
        "height": h,
    }


def _betas(a: np.ndarray, where: str, problems: Problems) -> np.ndarray | None:
    a = np.asarray(a)
    if a.ndim == 2 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != 1 or a.size == 0:
        problems.add(where, f"betas must be [B] or [1,B], got {list(np.shape(a))}")
        return None
    return a.astype(np.float32)


def _rows(z: dict, key: str, width: int, where: str, problems: Problems) -> np.ndarray | None:
    a = z[key]
    if a.ndim != 2 or a.shape[1] != width:
        problems.add(where, f"{key} must be [N,{width}], got {list(a.shape)}")
        return None
    if a.dtype.kind not in "fiu":
        problems.add(where, f"{key} must be numbers, got {a.dtype}")
        return None
    return a.astype(np.float32)  # NaN/Inf are reported for the rows in use (_assemble_params)


def _read_poses(root: Path, problems: Problems) -> dict | None:
    p = root / "poses.npz"
    if not p.is_file():
        problems.add("poses.npz", "is missing (needs betas, thetas [N,72], transl [N,3])")
        return None
    z = _npz(p, problems)
    if z is None:
        return None
    if "thetas" not in z and {"global_orient", "body_pose"} <= set(z):
        z["thetas"] = np.concatenate([z["global_orient"], z["body_pose"]], -1)
    missing = [k for k in ("betas", "thetas", "transl") if k not in z]
    if missing:
        problems.add("poses.npz", f"missing keys {missing} (has {sorted(z)})")
        return None
    betas = _betas(z["betas"], "poses.npz", problems)
    thetas = _rows(z, "thetas", 72, "poses.npz", problems)
    transl = _rows(z, "transl", 3, "poses.npz", problems)
    if thetas is None or transl is None or betas is None:
        return None
    if len(thetas) != len(transl):
        problems.add("poses.npz", f"thetas has {len(thetas)} rows but transl has {len(transl)}")
        return None
    go, bp = split_smpl_thetas(thetas)
    return {"betas": betas, "global_orient": go, "body_pose": bp, "transl": transl}


def _read_refined(path: Path, n: int, problems: Problems) -> dict | None:
    where = f"poses/{path.name}"
    z = _npz(path, problems)
    if z is None:
        return None
    missing = [k for k in ("betas", *PER_FRAME) if k not in z]
    if missing:
        problems.add(where, f"missing keys {missing} (has {sorted(z)})")
        return None
    out: dict[str, np.ndarray | None] = {"betas": _betas(z["betas"], where, problems)}
    for k, w in zip(PER_FRAME, (3, 69, 3), strict=True):
        out[k] = _rows(z, k, w, where, problems)
    if any(v is None for v in out.values()):
        return None
    counts = {k: len(cast(np.ndarray, out[k])) for k in PER_FRAME}
    if len(set(counts.values())) > 1 or counts["transl"] != n:
        problems.add(
            where,
            f"rows {counts} do not match the {n} frames of its split in config.json "
            "(rows are split-relative positions)",
        )
        return None
    return out


def _assemble_params(order, rows, refined, poses, problems: Problems) -> dict | None:
    """Per-frame SMPL parameters in frame order (None when some are unusable; the reasons go to
    ``problems``, except missing pose rows, which the caller reports). Betas: the first refined file
    (train, test, val), else poses.npz."""
    betas_from = [refined[s] for s in SPLIT_NAMES if refined.get(s) is not None] + ([poses] if poses else [])
    if not order or not betas_from:
        return None
    betas = betas_from[0]["betas"]
    for other in betas_from[1:]:
        b = other["betas"]
        if b.shape != betas.shape or not np.allclose(b, betas, atol=1e-4):
            warnings.warn(
                "PeopleSnapshot: betas differ between pose files; using the first one "
                "(train refinement, else poses.npz)",
                MeshsplatWarning,
                stacklevel=3,
            )
            break
    usable = bool(np.isfinite(betas).all())
    if not usable:
        problems.add("betas", "contain NaN/Inf")
    out: dict[str, list] = {k: [] for k in PER_FRAME}
    n_poses = len(poses["transl"]) if poses is not None else 0
    nonfinite: dict[str, list[int]] = {}
    for idx in order:
        s, pos = rows[idx]
        src, r, name = (refined[s], pos, f"poses/anim_nerf_{s}.npz") if s in refined else (poses, idx, "poses.npz")
        if src is None or (src is poses and r >= n_poses):
            usable = False  # unreadable file or no row: reported elsewhere
            continue
        for k in PER_FRAME:
            out[k].append(src[k][r])
        if not all(np.isfinite(src[k][r]).all() for k in PER_FRAME):
            nonfinite.setdefault(name, []).append(r)
    for name, bad in nonfinite.items():
        problems.add(name, f"NaN/Inf parameters in rows {_ids(bad)}")
    if nonfinite or not usable:
        return None
    return {"betas": betas, **{k: np.stack(v).astype(np.float32) for k, v in out.items()}}


def _pose(model: BodyModel, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """Canonical ``[V,3]`` and posed vertices ``[T,V,3]`` (batched)."""
    T = len(params["transl"])
    out = np.empty((T, model.num_vertices, 3), np.float32)
    with torch.no_grad():
        canonical = model.rest_vertices({"betas": params["betas"]}).cpu().numpy()
        for s in range(0, T, _CHUNK):
            chunk = {k: (v[s : s + _CHUNK] if k in PER_FRAME else v) for k, v in params.items()}
            out[s : s + _CHUNK] = model.forward(chunk).vertices.cpu().numpy()
    return canonical, out


def _check_files_exist(root: Path, frames: list[dict], problems: Problems) -> None:
    missing = [r["frame_index"] for r in frames if not (root / r["image"]).is_file()]
    if missing:
        problems.add("images/", f"missing image_%04d.png for frames {_ids(missing)}")


# ---------------------------------------------------------------- writing
def write(dataset: AvatarDataset, out: Path | str, masks: str = "png", overwrite: bool = False) -> Path:
    """Write ``dataset`` (SMPL driver parameters, one training camera) as a PeopleSnapshot folder.

    Frames of the training camera in the splits train, val and test_frames are written in that order
    as ``images/image_%04d.png`` (a frame in two splits is written twice); other cameras and splits
    are left out. ``masks``: ``"png"`` (0-255) or ``"npy"`` (0/1 uint8, thresholded at 0.5).
    """
    if masks not in ("png", "npy"):
        raise MeshsplatError(f"masks: expected 'png' or 'npy', got {masks!r}")
    info, params = dataset.driver_info, dataset.driver_params
    if info is None or params is None or info.get("type") != "smpl":
        kind = info.get("type") if info else "no model"
        raise MeshsplatError(
            f"{dataset.root}: PeopleSnapshot needs SMPL driver parameters, this dataset has {kind} "
            "(synthesize it with `meshsplat synth smpl`)"
        )
    offset = params.get("static_offset")
    if offset is not None and np.abs(offset).max() > 0:
        raise MeshsplatError(f"{dataset.root}: SMPL static_offset cannot be stored in PeopleSnapshot poses.npz")
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise MeshsplatError(f"{out}: exists and is not empty (pass --overwrite)")
    plan = plan_frames(dataset)

    (out / "images").mkdir(parents=True, exist_ok=True)
    rows: dict[str, list[np.ndarray]] = {k: [] for k in PER_FRAME}
    config: dict = {"gender": info.get("gender", "neutral")}
    k = 0
    has_mask = None
    for ps_split, idx in plan.items():
        config[ps_split] = {"start": k, "end": k + len(idx) - 1, "skip": 1}
        for i in idx:
            fr = dataset[i]
            write_png(out / "images" / f"image_{k:04d}.png", _u8(fr.image))
            if has_mask is None:
                has_mask = fr.mask is not None
            if (fr.mask is not None) != has_mask:
                raise MeshsplatError(
                    f"{dataset.root}: frame {fr.name!r} {'lacks' if has_mask else 'has'} a mask "
                    "unlike the others; PeopleSnapshot needs masks for all frames or none"
                )
            if fr.mask is not None:
                (out / "masks").mkdir(exist_ok=True)
                if masks == "png":
                    write_png(out / "masks" / f"mask_{k:04d}.png", _u8(fr.mask))
                else:
                    np.save(out / "masks" / f"mask_{k:04d}.npy", (fr.mask[..., 0].numpy() >= 0.5).astype(np.uint8))
            fp = dataset.frame_params(i)
            assert fp is not None  # the dataset has driver parameters (checked above)
            for key in PER_FRAME:
                rows[key].append(
                    np.asarray(fp.get(key, np.zeros((1, 69 if key == "body_pose" else 3))), np.float32).reshape(-1)
                )
            k += 1
    go, bp, tr = (np.stack(rows[key]) for key in PER_FRAME)
    betas = np.asarray(params.get("betas", np.zeros(10)), np.float32).reshape(-1)
    np.savez(out / "poses.npz", betas=betas, thetas=join_smpl_thetas(go, bp).astype(np.float32), transl=tr)
    cam_id = dataset.frame_info(next(iter(plan.values()))[0])["camera"]
    cam = dataset.camera(cam_id)
    np.savez(
        out / "cameras.npz",
        intrinsic=cam.K.double().numpy(),
        extrinsic=cam.viewmat.double().numpy(),
        height=np.array(cam.height),
        width=np.array(cam.width),
    )
    (out / "config.json").write_text(json.dumps(config, indent=1))
    return out


def plan_frames(dataset: AvatarDataset) -> dict[str, list[int]]:
    """Frames :func:`write` stores: PeopleSnapshot split -> dataset frame indices (training camera only)."""
    if "train" not in dataset.split_names or not dataset.split("train"):
        raise MeshsplatError(f"{dataset.root}: has no train frames to write")
    train = dataset.split("train")
    cam = dataset.frame_info(train[0])["camera"]
    others = sorted({dataset.frame_info(i)["camera"] for i in train} - {cam})
    if others:
        raise MeshsplatError(
            f"{dataset.root}: training frames use {len(others) + 1} cameras; PeopleSnapshot holds one "
            "fixed camera (synthesize with --rig monocular-turn)"
        )
    plan = {}
    for ps_split, name in (("train", "train"), ("val", "val"), ("test", "test_frames")):
        if name in dataset.split_names:
            idx = [i for i in dataset.split(name) if dataset.frame_info(i)["camera"] == cam]
            if idx:
                plan[ps_split] = idx
    return plan


def _u8(x: torch.Tensor) -> np.ndarray:
    return np.clip(np.rint(x.numpy() * 255.0), 0, 255).astype(np.uint8)
