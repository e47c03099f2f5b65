"""PeopleSnapshot in the InstantAvatar / Anim-NeRF layout (docs/formats/peoplesnapshot.md).

    cameras.npz                 intrinsic [3,3], extrinsic [4,4] world->camera (OpenCV), height, width
    poses.npz                   betas [10] or [1,10], thetas [N,72], transl [N,3]   (row = absolute frame index)
    poses/anim_nerf_<split>.npz optional refined betas, global_orient [n,3], body_pose [n,69], transl [n,3]
                                (row = position inside the split; wins over poses.npz for that split)
    images/image_%04d.png       one fixed camera
    masks/mask_%04d.png|.npy    0-255 PNG or 0/1 array (optional folder)
    config.json                 gender, train/val/test: {start, end (inclusive), skip}

Meshes are SMPL (``BodyModel("smpl", model_dir, gender)``) posed with those parameters; the canonical
mesh is the rest pose with the train file's betas. Each split is posed with its own file, betas
included (``shape="per_split"``, as InstantAvatar and SplattingAvatar do); ``shape="train"`` poses every
frame with the train betas. Splits: train -> "train", val -> "val", test -> "test_frames".
``cameras.npz``'s ``intrinsic`` puts pixel centres at integers (InstantAvatar casts its rays through
``np.arange(W)``): cx, cy move by +0.5 when read and -0.5 when written (``meshsplat.camera``).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import cast

import numpy as np
import torch

from meshsplat.camera import K_from_integer_centers, K_to_integer_centers
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.formats._files import npz_or_problem, whole_number
from meshsplat.data.manifest import Problems, build_dataset
from meshsplat.drivers.body_models import GENDERS, BodyModel, driver_record, join_smpl_thetas, split_smpl_thetas
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.io.images import float_to_uint8, write_png
from meshsplat.io.out_folder import empty_or_new_folder

__all__ = [
    "NAME",
    "DESCRIPTION",
    "SIGNATURE",
    "detect",
    "read",
    "write",
    "SPLIT_NAMES",
    "DEFAULT_TEST_FRACTION",
    "SHAPE_MODES",
    "KNOWN_SUBJECTS",
]

NAME = "peoplesnapshot"
DESCRIPTION = "PeopleSnapshot, InstantAvatar / Anim-NeRF layout (SMPL, one fixed camera)"
SIGNATURE = "cameras.npz + poses.npz (or poses/anim_nerf_*.npz) + images/image_0000.png"
WRITE_MODEL = "smpl"  # write() stores SMPL parameters: only SMPL-posed datasets can be written
WRITE_RIGS = ("monocular-turn",)  # one fixed training camera: the synth rigs whose captures it can hold

# PeopleSnapshot split -> meshsplat split; the order is also the precedence when splits share a frame
SPLIT_NAMES = {"train": "train", "test": "test_frames", "val": "val"}
DEFAULT_TEST_FRACTION = 0.2  # without config.json: the last 20% of the frames are test frames
PER_FRAME = ("global_orient", "body_pose", "transl")
_CHUNK = 64
# "per_split": each split posed with its own parameter file, betas included (InstantAvatar's
# PeopleSnapshotDataset and SplattingAvatar's instant_avatar reader: the published protocol);
# "train": every frame posed with the train file's betas (one shape for the whole capture)
SHAPE_MODES = ("per_split", "train")
_BETAS_ATOL = 1e-6
# The published PeopleSnapshot subjects as InstantAvatar trains and tests them: gender and inclusive
# frame ranges (start, end, skip) per split. Source: InstantAvatar, github.com/tijiang13/InstantAvatar,
# confs/dataset/peoplesnapshot/<subject>.yaml (commit 82a6c09); its preprocessing writes no config.json.
KNOWN_SUBJECTS: dict[str, dict] = {
    "male-3-casual": {"gender": "male", "train": (0, 455, 4), "val": (456, 456, 4), "test": (456, 675, 4)},
    "male-4-casual": {"gender": "male", "train": (0, 659, 6), "val": (660, 660, 6), "test": (660, 872, 6)},
    "female-3-casual": {"gender": "female", "train": (0, 445, 4), "val": (446, 446, 4), "test": (446, 647, 4)},
    "female-4-casual": {"gender": "female", "train": (0, 335, 4), "val": (335, 335, 4), "test": (335, 523, 4)},
}


def detect(root: Path | str) -> bool:
    root = Path(root)
    has_poses = (root / "poses.npz").is_file() or any((root / "poses").glob("anim_nerf_*.npz"))
    return (root / "cameras.npz").is_file() and has_poses and (root / "images").is_dir()


# ---------------------------------------------------------------- reading
def read(
    root: Path | str,
    model_dir: Path | str | None = None,
    gender: str | None = None,
    shape: str = "per_split",
    check_masks: bool = True,
    cache_size: int = 8,
    drop_bad_frames: bool = False,
    device: str | torch.device = "cpu",
) -> AvatarDataset:
    """Open a PeopleSnapshot folder lazily (images decode on access); every problem in one error.

    ``gender`` overrides config.json's; ``model_dir`` holds ``smpl/SMPL_<GENDER>.pkl``. ``shape``:
    ``"per_split"`` (default, the published protocol) poses each split with its own file's betas,
    ``"train"`` every frame with the train betas. Without config.json the ranges and gender of a
    published subject come from ``KNOWN_SUBJECTS`` (by folder name); any other folder needs ``gender``.
    ``ds.meta["split_rule"]`` says which rule chose the splits.
    """
    root = Path(root)
    if not root.is_dir():
        raise MeshsplatError(f"capture folder not found: {root}")
    if shape not in SHAPE_MODES:
        raise MeshsplatError(f"shape: expected one of {list(SHAPE_MODES)}, got {shape!r}")
    problems = Problems(root)
    cfg_gender, ranges = _read_config(root, problems)
    split_rule = "config.json"
    if ranges is None and not (root / "config.json").is_file():
        cfg_gender, ranges, split_rule = _ranges_without_config(root, gender)
    gender = (gender or cfg_gender or "neutral").lower()
    if gender not in GENDERS:
        problems.add("gender", f"unknown gender {gender!r} (expected one of {list(GENDERS)})")
    camera = _read_camera(root, problems)
    placeable = ranges is not None and split_rule != _DEFAULT_RULE
    if ranges is None:
        ranges = _default_ranges(root)
    splits_in_use = [s for s in SPLIT_NAMES if s in ranges]
    refined = {
        s: _read_refined(root / "poses" / f"anim_nerf_{s}.npz", len(ranges[s]), problems, split_rule)
        for s in splits_in_use
        if placeable and (root / "poses" / f"anim_nerf_{s}.npz").is_file()
    }
    if not placeable and any((root / "poses").glob("anim_nerf_*.npz")):
        warnings.warn(
            f"{root}: no config.json and no known subject name, so the split-relative poses/anim_nerf_*.npz "
            "cannot be placed; using poses.npz",
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

    params, frame_betas = _assemble_params(order, rows, refined, poses, problems)
    model = None
    if gender in GENDERS:
        try:
            model = BodyModel("smpl", model_dir, gender=gender, device=device)
        except MeshsplatError as exc:
            problems.add("SMPL model", str(exc))
    canonical = faces = verts = None
    betas_note: dict = {"mode": shape}
    if model is not None and params is not None and frame_betas is not None:
        train_betas = params["betas"]
        differs = bool((np.abs(frame_betas - train_betas) > _BETAS_ATOL).any())
        if shape == "per_split" and differs:
            params = {**params, "betas": frame_betas}  # per-frame rows: each frame its own file's shape
        try:
            model.check_params(params, num_frames=len(order))
        except MeshsplatError as exc:
            problems.add("SMPL parameters", str(exc))
        else:
            canonical, verts = _pose(model, params, train_betas)
            faces = model.faces.cpu().numpy()
            if differs:
                split_of = [SPLIT_NAMES[rows[i][0]] for i in order]
                betas_note.update(_betas_difference(model, params, train_betas, frame_betas, split_of))

    if camera is None or not frames:  # nothing to check images against: report what we have
        if not frames:
            problems.add("config.json", "no frames selected (empty train/val/test ranges and no images)")
        _check_files_exist(root, frames, problems)
        problems.raise_if_any()
    if verts is None and not problems.items:
        problems.add("SMPL", "could not pose the model")
    per_frame = list(PER_FRAME) + (["betas"] if params is not None and np.ndim(params["betas"]) == 2 else [])
    record = {**driver_record(model, "poses.npz"), "per_frame": per_frame} if model is not None else None
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
            "split_rule": split_rule,
            "betas": betas_note,
        },
        "driver": record,
    }
    if shape == "train" and "max_abs_diff" in betas_note:
        warnings.warn(_betas_warning(betas_note), MeshsplatWarning, stacklevel=2)
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
    return npz_or_problem(path, path.name, problems)


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
            start, end = whole_number(spec["start"], "start"), whole_number(spec["end"], "end")
            skip = whole_number(spec.get("skip", 1), "skip")
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


_DEFAULT_RULE = f"no config.json: the last {round(DEFAULT_TEST_FRACTION * 100)}% of the images are test frames"


def _ranges_without_config(root: Path, gender: str | None) -> tuple[str | None, dict[str, range] | None, str]:
    """InstantAvatar's own output has no config.json: a published subject (folder name) gets its ranges
    and gender from ``KNOWN_SUBJECTS``; any other folder the default split, and only with a gender."""
    name = root.resolve().name
    known = KNOWN_SUBJECTS.get(name)
    if known is not None:
        ranges = {s: range(a, b + 1, k) for s, (a, b, k) in ((s, known[s]) for s in SPLIT_NAMES)}
        return known["gender"], ranges, f"InstantAvatar's {name} ranges (confs/dataset/peoplesnapshot/{name}.yaml)"
    if gender is None:
        raise MeshsplatError(
            f"{root}: no config.json and {name!r} is not a published PeopleSnapshot subject "
            f"({', '.join(KNOWN_SUBJECTS)}), so the subject's gender is unknown: pass --gender male|female|neutral "
            f"(the splits then follow the default rule: the last {round(DEFAULT_TEST_FRACTION * 100)}% of the "
            "images are test frames), or add a config.json with gender and train/val/test ranges"
        )
    return None, None, _DEFAULT_RULE


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
        "K": K_from_integer_centers(K).tolist() if np.isfinite(K).all() else np.asarray(K, np.float64).tolist(),
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


def _read_refined(path: Path, n: int, problems: Problems, rule: str = "config.json") -> dict | None:
    """A split's ``anim_nerf_<split>.npz`` with ``n`` rows, the split's frame count under ``rule`` (config.json
    or a known subject's ranges)."""
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
        why = (
            "config.json"
            if rule == "config.json"
            else f"{rule}, chosen by the folder name: is the folder another subject? rename it, or add a "
            "config.json with its gender and train/val/test ranges"
        )
        problems.add(
            where,
            f"rows {counts} do not match the {n} frames of its split in {why} (rows are split-relative positions)",
        )
        return None
    return out


def _assemble_params(order, rows, refined, poses, problems: Problems) -> tuple[dict | None, np.ndarray | None]:
    """Per-frame SMPL parameters in frame order with the train file's ``betas [B]``, and each frame's own
    betas ``[T,B]`` (those of the file that poses it: its split's anim_nerf file, else poses.npz).
    ``(None, None)`` when some are unusable; the reasons go to ``problems``, except missing pose rows,
    which the caller reports."""
    if not order:
        return None, None
    train_src = refined.get("train") if "train" in refined else poses
    if train_src is None:
        return None, None
    betas = train_src["betas"]
    usable = True
    out: dict[str, list] = {k: [] for k in PER_FRAME}
    own_betas: list[np.ndarray] = []
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
        if src["betas"].shape != betas.shape:
            problems.add(name, f"betas have {src['betas'].size} values but the train file's have {betas.size}")
            usable = False
        own_betas.append(src["betas"])
        if not all(np.isfinite(src[k][r]).all() for k in PER_FRAME):
            nonfinite.setdefault(name, []).append(r)
        if not np.isfinite(src["betas"]).all():
            nonfinite.setdefault(name, [])
    for name, bad in nonfinite.items():
        problems.add(name, f"NaN/Inf parameters in rows {_ids(bad)}" if bad else "betas contain NaN/Inf")
    if nonfinite or not usable:
        return None, None
    params = {"betas": betas, **{k: np.stack(v).astype(np.float32) for k, v in out.items()}}
    return params, np.stack(own_betas).astype(np.float32)


def _betas_difference(
    model: BodyModel, params: dict, train_betas: np.ndarray, frame_betas: np.ndarray, splits: list[str]
) -> dict:
    """How far the frames whose own betas are not the train file's lie from it: max |delta betas|, and the
    mean vertex displacement (mm; SMPL is in metres) between posing them with either shape."""
    idx = np.flatnonzero(np.abs(frame_betas - train_betas).max(1) > _BETAS_ATOL)
    total, count = 0.0, 0
    with torch.no_grad():
        for s in range(0, len(idx), _CHUNK):
            sel = idx[s : s + _CHUNK]
            pose = {k: params[k][sel] for k in PER_FRAME}
            own = model.forward({**pose, "betas": frame_betas[sel]}).vertices
            shared = model.forward({**pose, "betas": train_betas}).vertices
            total += float((own - shared).norm(dim=-1).sum())
            count += own.shape[0] * own.shape[1]
    return {
        "max_abs_diff": round(float(np.abs(frame_betas[idx] - train_betas).max()), 6),
        "mean_vertex_shift_mm": round(1000.0 * total / max(count, 1), 3),
        "splits": sorted({splits[i] for i in idx}),
        "frames": len(idx),
    }


def _betas_warning(note: dict) -> str:
    splits = " and ".join(note["splits"])
    return (
        f"PeopleSnapshot: the {splits} parameter files carry their own betas (max |delta betas| "
        f"{note['max_abs_diff']:.3g} from the train file; posed with the train betas their meshes move "
        f"{note['mean_vertex_shift_mm']:.2f} mm on average); shape='train' poses them with the train betas, so "
        "their metrics are not on the published protocol (InstantAvatar and SplattingAvatar pose each split "
        "with its own file: shape='per_split', the default) and do not compare with the papers' tables"
    )


def _pose(model: BodyModel, params: dict, train_betas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Canonical ``[V,3]`` (rest pose, train betas) and posed vertices ``[T,V,3]`` (batched; ``betas`` may
    be per frame ``[T,B]``)."""
    T = len(params["transl"])
    out = np.empty((T, model.num_vertices, 3), np.float32)
    per_frame = (*PER_FRAME, "betas") if np.ndim(params["betas"]) == 2 else PER_FRAME
    with torch.no_grad():
        canonical = model.rest_vertices({"betas": train_betas}).cpu().numpy()
        for s in range(0, T, _CHUNK):
            chunk = {k: (v[s : s + _CHUNK] if k in per_frame else v) for k, v in params.items()}
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
    out = empty_or_new_folder(out, overwrite)
    plan = plan_frames(dataset)

    (out / "images").mkdir(parents=True, exist_ok=True)
    rows: dict[str, list[np.ndarray]] = {k: [] for k in PER_FRAME}
    split_rows: dict[str, list[int]] = {}  # PeopleSnapshot split -> written rows
    frame_betas: list[np.ndarray] = []
    config: dict = {"gender": info.get("gender", "neutral")}
    k = 0
    has_mask = None
    for ps_split, idx in plan.items():
        config[ps_split] = {"start": k, "end": k + len(idx) - 1, "skip": 1}
        split_rows[ps_split] = list(range(k, k + len(idx)))
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
            frame_betas.append(np.asarray(fp.get("betas", np.zeros(10)), np.float32).reshape(-1))
            k += 1
    go, bp, tr = (np.stack(rows[key]) for key in PER_FRAME)
    betas = frame_betas[split_rows["train"][0]] if "train" in split_rows else frame_betas[0]
    np.savez(out / "poses.npz", betas=betas, thetas=join_smpl_thetas(go, bp).astype(np.float32), transl=tr)
    # per-frame betas (each split posed with its own shape): a split whose shape is not the train one
    # gets its own poses/anim_nerf_<split>.npz, as InstantAvatar's refined files carry their own betas
    for ps_split, rws in split_rows.items():
        own = np.stack([frame_betas[r] for r in rws])
        if np.abs(own - betas).max() <= _BETAS_ATOL:
            continue
        if np.abs(own - own[0]).max() > _BETAS_ATOL:
            raise MeshsplatError(
                f"{dataset.root}: the {ps_split} frames have differing betas; PeopleSnapshot stores one shape per split"
            )
        (out / "poses").mkdir(exist_ok=True)
        np.savez(
            out / "poses" / f"anim_nerf_{ps_split}.npz",
            betas=own[:1],
            global_orient=go[rws],
            body_pose=bp[rws],
            transl=tr[rws],
        )
    cam_id = dataset.frame_info(next(iter(plan.values()))[0])["camera"]
    cam = dataset.camera(cam_id)
    np.savez(
        out / "cameras.npz",
        intrinsic=K_to_integer_centers(cam.K.double().numpy()),
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
    return float_to_uint8(x)
