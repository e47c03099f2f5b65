"""Motion files for re-enactment: another subject's poses and expressions driving an avatar's body model.

Layouts read (all numbers float, one row per frame ``S``):

* SMPL animation npz (SplattingAvatar / InstantAvatar ``eval_animate``, e.g. AIST++ ``aist_demo.npz``):
  ``poses [S,72]`` (global orient + 23 joints, axis-angle) and ``trans [S,3]``.
* AMASS-style npz: ``poses [S,165]`` (SMPL-X: global, body 63, jaw, left eye, right eye, hands 2x45) or
  ``[S,156]`` (SMPL-H: global, body 63, hands 2x45), ``trans [S,3]``, optional ``betas``; or the split keys
  ``root_orient, pose_body, pose_hand, pose_jaw, pose_eye``. Bodies are retargeted between SMPL and SMPL-X
  by joint (the first 22 joints are shared; SMPL's two hand joints and SMPL-X's face/finger joints are
  zero when the source lacks them).
* FLAME: IMavatar ``flame_params.json`` (``frames[].pose [15]`` = global, neck, jaw, eyes(6);
  ``frames[].expression``; ``shape_params``), a VHAP ``flame_param/`` folder of per-frame npz
  (``translation, rotation, neck_pose, jaw_pose, eyes_pose (1,6), shape, expr``; also one npz with those
  keys stacked over frames), or a folder/dataset holding ``flame_param/``.
* meshsplat's own ``driver_params.npz`` (:func:`meshsplat.drivers.body_models.save_driver_params`).
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from meshsplat.drivers.body_models import (
    POSE_KEYS,
    BodyModel,
    split_flame_pose15,
    split_smpl_thetas,
)
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.io.arrays import read_npz
from meshsplat.io.json_file import read_json_object
from meshsplat.paths import resolve_input
from meshsplat.plausible import sequence_gaps

__all__ = ["load_motion", "reenact", "motion_frame_rate", "ALIGN_MODES"]

ALIGN_MODES = ("none", "translation", "pose")
_BODY_LAYOUTS = (
    "SMPL poses [S,72] + trans [S,3] (AIST / InstantAvatar animation), SMPL-X poses [S,165] or "
    "SMPL-H poses [S,156] + trans (AMASS)"
)
_FLAME_LAYOUTS = (
    "IMavatar flame_params.json, a VHAP flame_param/ folder of npz (translation, rotation, "
    "neck_pose, jaw_pose, eyes_pose, expr)"
)
_VHAP_KEYS = ("rotation", "neck_pose", "jaw_pose", "eyes_pose", "expr")
_SHARED = ("betas", "static_offset")


def _f32(a, name: str, where: str, width: int | None = None) -> np.ndarray:
    try:
        x = np.asarray(a, np.float32)
    except (TypeError, ValueError):
        raise MeshsplatError(f"{where}: {name} must be numbers") from None
    if width is not None:
        x = x.reshape(len(x), -1) if x.ndim != 2 else x
        if x.shape[1] != width:
            raise MeshsplatError(f"{where}: {name} must be [S, {width}], got {list(x.shape)}")
    if not np.isfinite(x).all():
        raise MeshsplatError(f"{where}: {name} contains NaN or Inf")
    return x


# ---------------------------------------------------------------- bodies
def _body_parts(z: dict, where: str) -> dict:
    """Per-joint-group arrays from a body motion dict: global_orient, body21 [S,63], smpl_hands [S,6],
    jaw, leye, reye, left_hand, right_hand (missing groups absent), transl, betas."""
    out: dict = {}
    if "poses" in z:
        p = _f32(z["poses"], "poses", where)
        if p.ndim != 2 or p.shape[1] not in (72, 156, 165):
            raise MeshsplatError(
                f"{where}: poses must be [S,72], [S,156] or [S,165], got {list(p.shape)}; expected {_BODY_LAYOUTS}"
            )
        out["global_orient"], out["body21"] = p[:, :3], p[:, 3:66]
        if p.shape[1] == 72:
            out["smpl_hands"] = p[:, 66:72]
        elif p.shape[1] == 156:
            out["left_hand_pose"], out["right_hand_pose"] = p[:, 66:111], p[:, 111:156]
        else:
            out["jaw_pose"], out["leye_pose"], out["reye_pose"] = p[:, 66:69], p[:, 69:72], p[:, 72:75]
            out["left_hand_pose"], out["right_hand_pose"] = p[:, 75:120], p[:, 120:165]
    elif "root_orient" in z and "pose_body" in z:
        out["global_orient"] = _f32(z["root_orient"], "root_orient", where, 3)
        out["body21"] = _f32(z["pose_body"], "pose_body", where, 63)
        if "pose_hand" in z:
            h = _f32(z["pose_hand"], "pose_hand", where, 90)
            out["left_hand_pose"], out["right_hand_pose"] = h[:, :45], h[:, 45:]
        if "pose_jaw" in z:
            out["jaw_pose"] = _f32(z["pose_jaw"], "pose_jaw", where, 3)
        if "pose_eye" in z:
            e = _f32(z["pose_eye"], "pose_eye", where, 6)
            out["leye_pose"], out["reye_pose"] = e[:, :3], e[:, 3:]
    elif "thetas" in z:
        g, b = split_smpl_thetas(_f32(z["thetas"], "thetas", where))
        out["global_orient"], out["body21"], out["smpl_hands"] = g, b[:, :63], b[:, 63:]
    else:
        raise MeshsplatError(f"{where}: no body poses found (keys {sorted(z)}); expected {_BODY_LAYOUTS}")
    S = len(out["global_orient"])
    if S == 0:
        raise MeshsplatError(f"{where}: the motion has no frames (empty pose arrays); nothing to play")
    for key in ("trans", "transl"):
        if key in z:
            out["transl"] = _f32(z[key], key, where, 3)
            break
    if "expression" in z:
        out["expression"] = _f32(z["expression"], "expression", where)
    if "betas" in z:
        out["betas"] = _f32(z["betas"], "betas", where).reshape(-1, np.asarray(z["betas"]).shape[-1])[0]
    bad = {k: len(v) for k, v in out.items() if k != "betas" and len(v) != S}
    if bad:
        raise MeshsplatError(f"{where}: arrays disagree on the number of frames ({S} poses, {bad})")
    return out


def _body_params(parts: dict, kind: str) -> dict:
    S = len(parts["global_orient"])

    def zeros(w: int) -> np.ndarray:
        return np.zeros((S, w), np.float32)

    out = {"global_orient": parts["global_orient"]}
    if kind == "smpl":
        out["body_pose"] = np.concatenate([parts["body21"], parts.get("smpl_hands", zeros(6))], 1)
    else:
        out["body_pose"] = parts["body21"]
        for k, w in POSE_KEYS["smplx"][2:]:
            out[k] = parts.get(k, zeros(w))
        if "expression" in parts:
            out["expression"] = parts["expression"]
    out["transl"] = parts.get("transl", zeros(3))
    if "betas" in parts:
        out["betas"] = parts["betas"]
    return out


# ---------------------------------------------------------------- heads
def _flame_from_imavatar(path: Path) -> dict:
    what = "an IMavatar flame_params.json (frames[].pose [15], frames[].expression)"
    data = read_json_object(path, what)
    try:
        frames = data["frames"]
        pose = np.array([f["pose"] for f in frames], np.float32)
        expr = np.array([f["expression"] for f in frames], np.float32)
    except (ValueError, KeyError, TypeError) as e:
        raise MeshsplatError(f"{path}: not {what} ({type(e).__name__}: {e})") from None
    if pose.ndim != 2 or pose.shape[1] != 15 or expr.ndim != 2 or len(expr) != len(pose) or not len(pose):
        raise MeshsplatError(
            f"{path}: frames[].pose must be 15 numbers and frames[].expression one row per frame, "
            f"got pose {list(pose.shape)}, expression {list(expr.shape)}"
        )
    out = {k: _f32(v, k, str(path)) for k, v in split_flame_pose15(pose).items()}
    out["expression"] = _f32(expr, "expression", str(path))
    out["transl"] = np.zeros((len(pose), 3), np.float32)
    if "shape_params" in data:
        out["betas"] = _f32(data["shape_params"], "shape_params", str(path)).reshape(-1)
    return out


def _flame_from_vhap(z: dict, where: str) -> dict:
    missing = [k for k in _VHAP_KEYS if k not in z]
    if missing:
        raise MeshsplatError(f"{where}: missing {missing}; expected {_FLAME_LAYOUTS}")
    rot = _f32(z["rotation"], "rotation", where, 3)
    S = len(rot)
    if S == 0:
        raise MeshsplatError(f"{where}: the motion has no frames (rotation is empty); nothing to play")
    eyes = _f32(z["eyes_pose"], "eyes_pose", where, 6)
    out = {
        "global_orient": rot,
        "neck_pose": _f32(z["neck_pose"], "neck_pose", where, 3),
        "jaw_pose": _f32(z["jaw_pose"], "jaw_pose", where, 3),
        "leye_pose": eyes[:, :3],
        "reye_pose": eyes[:, 3:],
        "expression": _f32(z["expr"], "expr", where).reshape(S, -1),
        "transl": _f32(z["translation"], "translation", where, 3)
        if "translation" in z
        else np.zeros((S, 3), np.float32),
    }
    bad = {k: len(v) for k, v in out.items() if len(v) != S}
    if bad:
        raise MeshsplatError(f"{where}: arrays disagree on the number of frames ({S} rotations, {bad})")
    if "shape" in z:
        out["betas"] = _f32(z["shape"], "shape", where).reshape(-1, np.asarray(z["shape"]).shape[-1])[0]
    return out


def _frame_number(p: Path):
    nums = re.findall(r"\d+", p.stem)
    return (int(nums[-1]) if nums else -1, p.name)


def _read_npz(path: Path) -> dict:
    z = read_npz(path, "motion")
    if not z:
        raise MeshsplatError(f"{path}: the motion file holds no arrays (an empty npz)")
    return z


def _flame_folder(folder: Path) -> dict:
    files = sorted(folder.glob("*.npz"), key=_frame_number)
    if not files:
        raise MeshsplatError(f"{folder}: no .npz files; expected {_FLAME_LAYOUTS}")
    frames = [_flame_from_vhap(_read_npz(f), str(f)) for f in files]
    gaps = sequence_gaps([n for n, _ in map(_frame_number, files)], "frame files")
    if gaps is not None:
        warnings.warn(f"{folder}: {gaps}", MeshsplatWarning, stacklevel=3)
    for k in frames[0]:
        if k == "betas":
            continue
        widths: dict[tuple, list[int]] = {}
        for j, f in enumerate(frames):
            widths.setdefault(f[k].shape[1:] if k in f else (), []).append(j)
        if len(widths) > 1:
            common = max(widths, key=lambda w: len(widths[w]))
            odd = sorted(j for w, js in widths.items() if w != common for j in js)
            shown = ", ".join(files[j].name for j in odd[:3]) + (f" and {len(odd) - 3} more" if len(odd) > 3 else "")
            raise MeshsplatError(
                f"{folder}: {k} has another shape in {len(odd)} of {len(files)} files ({shown}: "
                f"{[list(frames[odd[0]][k].shape[1:]) if k in frames[odd[0]] else 'missing']} vs "
                f"{list(common)} in the others); every file of a sequence needs the same shapes"
            )
    out = {k: np.concatenate([f[k] for f in frames]) for k in frames[0] if k != "betas"}
    if "betas" in frames[0]:
        out["betas"] = frames[0]["betas"]
    return out


# ---------------------------------------------------------------- public
def _fit_width(params: dict, model: BodyModel, where: str) -> dict:
    """Zero-pad shorter betas/expression; longer betas are cut (the driver's own shape, which reenact
    replaces); longer expressions only when the extra columns are zero."""
    out = dict(params)
    for k in ("betas", "expression"):
        width = model.param_shapes.get(k, 0)
        if k not in out:
            continue
        x = out[k]
        if width == 0:
            del out[k]
        elif x.shape[-1] > width:
            if k == "expression" and np.any(x[..., width:] != 0):
                raise MeshsplatError(
                    f"{where}: expression has {x.shape[-1]} components, the {model.kind} model "
                    f"takes {width}; use a model file with more expression components"
                )
            out[k] = x[..., :width]
    return out


def load_motion(path: Path | str, model: BodyModel) -> dict:
    """Parameters ``[S, k]`` (numpy float32) for ``model`` from a motion file or folder (see module doc)."""
    p = resolve_input(path)
    where = str(p)
    if not p.exists():
        raise MeshsplatError(f"motion file not found: {p}")
    if model.kind == "flame":
        if p.is_dir():
            if not (p / "flame_param").is_dir() and (p / "flame_params.json").is_file():
                params = _flame_from_imavatar(p / "flame_params.json")
            else:
                params = _flame_folder(p / "flame_param" if (p / "flame_param").is_dir() else p)
        elif p.suffix == ".json":
            params = _flame_from_imavatar(p)
        elif p.suffix == ".npz":
            z = _read_npz(p)
            params = z if _is_driver_params(z, model) else _flame_from_vhap(z, where)
        else:
            raise MeshsplatError(f"{where}: a FLAME model takes {_FLAME_LAYOUTS}, or a driver_params.npz")
    else:
        if p.is_dir() or p.suffix != ".npz":
            raise MeshsplatError(f"{where}: a {model.kind.upper()} model takes an npz with {_BODY_LAYOUTS}")
        z = _read_npz(p)
        if _is_driver_params(z, model):
            params = z
        elif any(k in z for k in _VHAP_KEYS) and "poses" not in z:
            raise MeshsplatError(f"{where}: this is FLAME motion; a {model.kind.upper()} model takes {_BODY_LAYOUTS}")
        else:
            params = _body_params(_body_parts(z, where), model.kind)
    params = _fit_width({k: np.asarray(v, np.float32) for k, v in params.items()}, model, where)
    frames = {k: len(v) for k, v in params.items() if k not in _SHARED and np.ndim(v) >= 1}
    if not frames or min(frames.values()) == 0:
        raise MeshsplatError(f"{where}: the motion has no frames (empty arrays {sorted(frames)}); nothing to play")
    try:
        model.check_params(params)
    except MeshsplatError as e:
        raise MeshsplatError(f"{where}: {e}") from None
    return params


def _is_driver_params(z: dict, model: BodyModel) -> bool:
    return bool(z) and set(z) <= set(model.param_shapes) | set(_SHARED) and "global_orient" in z


def motion_frame_rate(path: Path | str) -> float | None:
    """Frame rate stored in a motion npz (AMASS ``mocap_framerate`` / ``mocap_frame_rate``, ``fps``), else None."""
    p = Path(path)
    if p.suffix != ".npz" or not p.is_file():
        return None
    z = read_npz(p, "motion")
    for k in ("mocap_framerate", "mocap_frame_rate", "fps"):
        if k in z and np.asarray(z[k]).size == 1:
            return float(np.asarray(z[k]).reshape(()))
    return None


def _first_row(x) -> np.ndarray:
    a = np.asarray(x, np.float64)
    return a.reshape(-1, a.shape[-1])[0]


def reenact(motion_params: dict, subject_params: dict, align: str = "translation") -> dict:
    """The avatar's own ``betas`` / ``static_offset`` with the driver's poses, expressions and translation.

    ``align``: ``"none"`` keeps the driver's global orientation and translation as they are;
    ``"translation"`` (default) starts the driver's path at the subject's first-frame translation;
    ``"pose"`` also rotates the whole motion so that its first frame has the subject's first-frame global
    orientation (the path rotates with it).
    """
    if align not in ALIGN_MODES:
        raise MeshsplatError(f"align: expected one of {list(ALIGN_MODES)}, got {align!r}")
    if "global_orient" not in motion_params:
        raise MeshsplatError("reenact: the motion has no global_orient; load it with load_motion")
    out = {k: np.asarray(v, np.float32) for k, v in motion_params.items() if k not in _SHARED}
    for k in _SHARED:
        if subject_params.get(k) is not None:
            v = subject_params[k]
            out[k] = np.asarray(v.detach().cpu() if hasattr(v, "detach") else v, np.float32)
    S = len(out["global_orient"])
    transl = out.get("transl", np.zeros((S, 3), np.float32)).astype(np.float64)
    if align != "none":
        subj_t0 = _first_row(subject_params["transl"]) if subject_params.get("transl") is not None else np.zeros(3)
        disp = transl - transl[0]
        if align == "pose" and subject_params.get("global_orient") is not None:
            r_sub = Rotation.from_rotvec(_first_row(subject_params["global_orient"]))
            rots = Rotation.from_rotvec(out["global_orient"].astype(np.float64))
            r_align = r_sub * rots[0].inv()
            out["global_orient"] = (r_align * rots).as_rotvec().astype(np.float32)
            disp = r_align.apply(disp)
        transl = subj_t0 + disp
    out["transl"] = transl.astype(np.float32)
    return out
