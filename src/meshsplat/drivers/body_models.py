"""Parametric body and head models (SMPL, SMPL-X, FLAME) from the user's own model files.

The model files are licensed and never shipped or downloaded: the user passes ``--model-dir DIR``
(or sets ``MESHSPLAT_MODEL_DIR``). Files are read into numpy without chumpy
(:mod:`meshsplat.drivers.model_files`) and posed with smplx's linear blend skinning
(``smplx.lbs.lbs``, imported lazily), batched over frames and differentiable in every parameter.

Conventions (as smplx): axis-angle poses; SMPL-X hand poses are full axis-angle without PCA and
without the file's mean hand (smplx ``flat_hand_mean=True``); shape columns ``[:num_betas]``,
expression columns ``[300:]`` when ``shapedirs`` has >= 400 columns, else ``[10:20]``. Shorter
``betas`` / ``expression`` vectors are zero-padded (the first k components). ``scale`` multiplies the
posed vertices and joints (same as scaling template, shapedirs, posedirs and static offsets, as
IMavatar/DECA's FLAME x4 does); ``transl`` is added after scaling.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import torch

from meshsplat.drivers.anny_body import MODEL_TYPE as ANNY_TYPE
from meshsplat.drivers.anny_body import load_anny_body
from meshsplat.drivers.base import as_faces
from meshsplat.drivers.model_files import read_model_file
from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npz
from meshsplat.plausible import parameter_problems, skinning_problem

__all__ = [
    "MODEL_KINDS",
    "REGISTER_SITES",
    "GENDERS",
    "TOPOLOGY_KINDS",
    "model_kind_for",
    "BodyModel",
    "BodyOutput",
    "model_from_record",
    "ParametricDriver",
    "resolve_model_dir",
    "find_model_file",
    "split_smpl_thetas",
    "join_smpl_thetas",
    "split_flame_pose15",
    "join_flame_pose15",
    "save_driver_params",
    "load_driver_params",
    "driver_record",
    "POSE_KEYS",
]

MODEL_KINDS = ("smpl", "smplx", "flame")
GENDERS = ("neutral", "male", "female")
FLAME_VERSIONS = ("2020", "2023")
REGISTER_SITES = {
    "smpl": "https://smpl.is.tue.mpg.de",
    "smplx": "https://smpl-x.is.tue.mpg.de",
    "flame": "https://flame.is.tue.mpg.de",
}
_TITLE = {"smpl": "SMPL", "smplx": "SMPL-X", "flame": "FLAME"}
TOPOLOGY_KINDS = {6890: "smpl", 10475: "smplx", 5023: "flame"}  # vertex counts of the released models


def model_kind_for(num_vertices: int) -> str | None:
    """The body/head model ("smpl", "smplx", "flame") whose released mesh has ``num_vertices``, else None."""
    return TOPOLOGY_KINDS.get(int(num_vertices))


_NUM_JOINTS = {"smpl": 24, "smplx": 55, "flame": 5}
# pose parameters in the order of the full pose vector (joint order of the kinematic tree)
POSE_KEYS = {
    "smpl": (("global_orient", 3), ("body_pose", 69)),
    "smplx": (
        ("global_orient", 3),
        ("body_pose", 63),
        ("jaw_pose", 3),
        ("leye_pose", 3),
        ("reye_pose", 3),
        ("left_hand_pose", 45),
        ("right_hand_pose", 45),
    ),
    "flame": (("global_orient", 3), ("neck_pose", 3), ("jaw_pose", 3), ("leye_pose", 3), ("reye_pose", 3)),
}
_SHARED_KEYS = ("betas", "static_offset")
_CHUNK = 64  # frames per batched forward in ParametricDriver.all_vertices
ENV_MODEL_DIR = "MESHSPLAT_MODEL_DIR"


# ---------------------------------------------------------------- locating files
def resolve_model_dir(model_dir: str | Path | None) -> Path:
    """The model directory: the argument, else ``$MESHSPLAT_MODEL_DIR``; it must exist."""
    if model_dir is None or str(model_dir) == "":
        env = os.environ.get(ENV_MODEL_DIR, "")
        if not env:
            raise MeshsplatError(
                f"no body/head model directory: pass --model-dir DIR or set {ENV_MODEL_DIR} to the "
                "folder holding your smpl/, smplx/ or flame/ model files"
            )
        model_dir = env
    p = Path(model_dir).expanduser()
    if p.is_file():
        raise MeshsplatError(
            f"model directory {p} is a file; pass the folder that holds smpl/, smplx/ or flame/ "
            "(or the model files) as --model-dir"
        )
    if not p.is_dir():
        raise MeshsplatError(
            f"model directory {p} does not exist; pass --model-dir DIR or set {ENV_MODEL_DIR} to the "
            "folder holding your smpl/, smplx/ or flame/ model files"
        )
    return p


def _candidate_names(kind: str, gender: str, flame_version: str) -> list[str]:
    g, G = gender.lower(), gender.upper()
    if kind == "smpl":
        return [
            f"SMPL_{G}.pkl",
            f"SMPL_{G}.npz",
            f"basicmodel_{g}_lbs_10_207_0_v1.1.0.pkl",
            f"basicModel_{g}_lbs_10_207_0_v1.0.0.pkl",
        ]
    if kind == "smplx":
        return [f"SMPLX_{G}.npz", f"SMPLX_{G}.pkl"]
    if flame_version == "2023":
        return ["flame2023.pkl"]  # FLAME 2023 ships one generic model
    return [f"FLAME_{G}.pkl", f"FLAME_{G}.npz", "generic_model.pkl" if g == "neutral" else f"{g}_model.pkl"]


def _candidate_dirs(kind: str, root: Path, flame_version: str) -> list[Path]:
    dirs = [root / kind, root / kind.upper()]
    if kind == "flame":
        dirs += [root / f"FLAME{flame_version}", root / "flame" / f"FLAME{flame_version}"]
    dirs.append(root)
    out: list[Path] = []
    for d in dirs:
        if d not in out:
            out.append(d)
    return out


def _check_choice(name: str, value: str, allowed) -> str:
    v = str(value).lower()
    if v not in allowed:
        raise MeshsplatError(f"{name}: expected one of {list(allowed)}, got {value!r}")
    return v


def find_model_file(
    kind: str, model_dir: Path | str | None, gender: str = "neutral", flame_version: str = "2020"
) -> Path:
    """Path of the model file for ``kind`` / ``gender`` under the model directory.

    Looks in ``DIR/<kind>/``, ``DIR/<KIND>/`` (FLAME also ``DIR/FLAME2020/`` or ``DIR/FLAME2023/``) and
    ``DIR/`` for the names smplx and the official downloads use.
    """
    kind = _check_choice("model kind", kind, MODEL_KINDS)
    gender = _check_choice("gender", gender, GENDERS)
    flame_version = _check_choice("flame_version", str(flame_version), FLAME_VERSIONS)
    root = resolve_model_dir(model_dir)
    names = _candidate_names(kind, gender, flame_version)
    dirs = _candidate_dirs(kind, root, flame_version)
    for d in dirs:
        for n in names:
            if (d / n).is_file():
                return d / n
    raise MeshsplatError(
        f"{_TITLE[kind]} model file not found: expected {' or '.join(names)} in {', '.join(str(d) for d in dirs)}; "
        f"these files are licensed and not shipped: register at {REGISTER_SITES[kind]}, download the model and "
        f"put it there (or pass --model-dir)"
    )


# ---------------------------------------------------------------- pose layouts
def _as_2d(name: str, x, width: int):
    arr = x if isinstance(x, torch.Tensor) else np.asarray(x)
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != width:
        raise MeshsplatError(f"{name}: expected shape [T, {width}], got {list(arr.shape)}")
    return arr


_ArrayT = TypeVar("_ArrayT", np.ndarray, torch.Tensor)  # numpy in, numpy out; torch in, torch out


def split_smpl_thetas(thetas: _ArrayT) -> tuple[_ArrayT, _ArrayT]:
    """``thetas [T,72]`` -> ``(global_orient [T,3], body_pose [T,69])`` (numpy or torch in, same out)."""
    t = _as_2d("thetas", thetas, 72)
    return t[:, :3], t[:, 3:]


def join_smpl_thetas(global_orient: _ArrayT, body_pose: _ArrayT) -> _ArrayT:
    """Inverse of :func:`split_smpl_thetas`: ``[T,3]``, ``[T,69]`` -> ``[T,72]``."""
    g, b = _as_2d("global_orient", global_orient, 3), _as_2d("body_pose", body_pose, 69)
    return cast(_ArrayT, torch.cat([g, b], 1) if isinstance(g, torch.Tensor) else np.concatenate([g, b], 1))


_FLAME15 = (
    ("global_orient", 0, 3),
    ("neck_pose", 3, 6),
    ("jaw_pose", 6, 9),
    ("leye_pose", 9, 12),
    ("reye_pose", 12, 15),
)


def split_flame_pose15(pose: np.ndarray | torch.Tensor) -> dict:
    """IMavatar/DECA ``pose [T,15]`` = global, neck, jaw, left eye, right eye -> dict of ``[T,3]``."""
    p = _as_2d("pose", pose, 15)
    return {k: p[:, a:b] for k, a, b in _FLAME15}


def join_flame_pose15(parts: dict) -> Any:
    """Inverse of :func:`split_flame_pose15`."""
    missing = [k for k, _, _ in _FLAME15 if k not in parts]
    if missing:
        raise MeshsplatError(f"join_flame_pose15: missing {missing}")
    xs = [_as_2d(k, parts[k], 3) for k, _, _ in _FLAME15]
    return torch.cat(xs, 1) if isinstance(xs[0], torch.Tensor) else np.concatenate(xs, 1)


# ---------------------------------------------------------------- the model
@dataclass
class BodyOutput:
    vertices: torch.Tensor  # [T, V, 3]
    joints: torch.Tensor  # [T, J, 3]


def _import_smplx_lbs():
    try:
        from smplx.lbs import lbs
    except ImportError:
        raise MeshsplatError(
            "SMPL/SMPL-X/FLAME models need the smplx package: pip install 'meshsplat[smplx]'"
        ) from None
    return lbs


class BodyModel:
    """SMPL, SMPL-X or FLAME from the user's model file, posed with smplx's LBS.

    Args: ``kind`` in ``MODEL_KINDS``; ``model_dir`` (default ``$MESHSPLAT_MODEL_DIR``); ``gender``;
    ``flame_version`` ("2020" or "2023", FLAME only); ``scale`` (uniform, e.g. 4 for IMavatar/DECA FLAME);
    ``device``. ``path`` loads one file directly instead of searching ``model_dir``.
    """

    def __init__(
        self,
        kind: str,
        model_dir: Path | str | None = None,
        gender: str = "neutral",
        flame_version: str = "2020",
        scale: float = 1.0,
        device: str | torch.device = "cpu",
        path: Path | str | None = None,
    ) -> None:
        self.kind = _check_choice("model kind", kind, MODEL_KINDS)
        self.gender = _check_choice("gender", gender, GENDERS)
        self.flame_version = _check_choice("flame_version", str(flame_version), FLAME_VERSIONS)
        if not (isinstance(scale, (int, float)) and np.isfinite(scale) and scale > 0):
            raise MeshsplatError(f"scale: expected a positive number, got {scale!r}")
        self.scale = float(scale)
        self.path = (
            Path(path) if path is not None else find_model_file(self.kind, model_dir, self.gender, self.flame_version)
        )
        if not self.path.is_file():
            raise MeshsplatError(
                f"{_TITLE[self.kind]} model file {self.path} does not exist; register at "
                f"{REGISTER_SITES[self.kind]} and download it"
            )
        self._lbs = _import_smplx_lbs()
        self.device = torch.device(device)
        try:
            data = read_model_file(self.path)
        except MeshsplatError as e:
            msg = " ".join(str(e).split())
            raise MeshsplatError(
                f"{msg}; expected the {_TITLE[self.kind]} model file from {REGISTER_SITES[self.kind]}"
            ) from None
        self._load(data)

    # ------------------------------------------------------------ loading
    def _load(self, d: dict) -> None:
        where = f"{self.path}"
        missing = [
            k
            for k in ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
            if k not in d
        ]
        if missing:
            raise MeshsplatError(f"{where}: not a {_TITLE[self.kind]} model file, missing keys {missing}")
        arr = {
            k: np.asarray(d[k])
            for k in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
        }
        v = arr["v_template"]
        J = _NUM_JOINTS[self.kind]
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshsplatError(f"{where}: v_template must be [V,3], got {list(v.shape)}")
        V = v.shape[0]
        sd = arr["shapedirs"]
        sd = sd[:, :, None] if sd.ndim == 2 else sd
        checks = [
            ("shapedirs", sd.shape[:2] == (V, 3) and sd.ndim == 3, "[V,3,S]", sd.shape),
            ("posedirs", arr["posedirs"].shape == (V, 3, (J - 1) * 9), f"[{V},3,{(J - 1) * 9}]", arr["posedirs"].shape),
            ("J_regressor", arr["J_regressor"].shape == (J, V), f"[{J},{V}]", arr["J_regressor"].shape),
            ("weights", arr["weights"].shape == (V, J), f"[{V},{J}]", arr["weights"].shape),
            ("kintree_table", arr["kintree_table"].shape == (2, J), f"[2,{J}]", arr["kintree_table"].shape),
            ("f", arr["f"].ndim == 2 and arr["f"].shape[1] == 3, "[F,3]", arr["f"].shape),
        ]
        bad = [f"{k} {list(s)} (expected {want})" for k, ok, want, s in checks if not ok]
        if bad:
            raise MeshsplatError(f"{where}: not a {_TITLE[self.kind]} model file: " + "; ".join(bad))
        why = skinning_problem(arr["weights"], "weights (skinning)")
        if why is not None:
            raise MeshsplatError(f"{where}: {why}")
        S = sd.shape[2]
        if self.kind == "smpl":
            nb, ex = S, (0, 0)
        elif S >= 400:
            nb, ex = 300, (300, S)
        else:
            if S < 11:
                raise MeshsplatError(
                    f"{where}: shapedirs has {S} columns; {_TITLE[self.kind]} needs >= 11 (shape then expression)"
                )
            nb, ex = 10, (10, min(S, 20))
        dev, f32 = self.device, torch.float32

        def t(x: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(x, np.float32), device=dev)

        self.num_vertices, self.num_joints = V, J
        self.num_betas, self.num_expression = nb, ex[1] - ex[0]
        self.v_template = t(v)
        self.shapedirs = t(sd[:, :, :nb])
        self.exprdirs = t(sd[:, :, ex[0] : ex[1]])
        self.posedirs = t(arr["posedirs"].reshape(-1, (J - 1) * 9).T)  # [P, 3V] as smplx
        self.J_regressor = t(arr["J_regressor"])
        self.lbs_weights = t(arr["weights"])
        parents = arr["kintree_table"][0].astype(np.int64)
        parents[0] = -1
        if np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, J)):
            raise MeshsplatError(f"{where}: kintree_table parents must precede their children")
        self.parents = torch.as_tensor(parents, device=dev)
        self.faces = as_faces(f"{where}: f", arr["f"].astype(np.int64), V).to(dev)
        self.param_shapes = {"betas": nb, **dict(POSE_KEYS[self.kind]), "transl": 3}
        if self.num_expression:
            self.param_shapes["expression"] = self.num_expression
        self._dtype = f32

    def __repr__(self) -> str:
        return (
            f"BodyModel({self.kind}, {self.gender}, V={self.num_vertices}, J={self.num_joints}, "
            f"betas={self.num_betas}, expression={self.num_expression}, scale={self.scale}, file={self.path})"
        )

    # ------------------------------------------------------------ parameters
    def check_params(self, params: dict, num_frames: int | None = None) -> int:
        """Validate a parameter dict; returns the number of frames T. One error lists every problem."""
        if not isinstance(params, dict):
            raise MeshsplatError(f"{self.kind} params: expected a dict of arrays, got {type(params).__name__}")
        problems, frames = [], {}
        plain = {}  # finite values read from files (not tensors being optimised): their ranges are checked
        V = self.num_vertices
        for k, x in params.items():
            if not hasattr(x, "shape"):
                try:
                    x = np.asarray(x, np.float32)
                except (TypeError, ValueError):
                    problems.append(f"{k}: expected numbers, got {type(x).__name__}")
                    continue
            if k == "static_offset":
                shape = tuple(x.shape) if hasattr(x, "shape") else None
                if shape not in ((V, 3), (1, V, 3)):
                    problems.append(
                        f"static_offset: expected [{V},3], got {list(shape) if shape else type(x).__name__}"
                    )
                elif not _finite(x):
                    problems.append("static_offset: contains NaN or Inf")
                continue
            if k not in self.param_shapes:
                problems.append(f"unknown key {k!r} (expected {sorted(self.param_shapes) + ['static_offset']})")
                continue
            shape = tuple(x.shape) if hasattr(x, "shape") else None
            width = self.param_shapes[k]
            padded = k in ("betas", "expression")
            if (
                shape is None
                or len(shape) not in (1, 2)
                or shape[-1] == 0
                or (shape[-1] > width if padded else shape[-1] != width)
            ):
                want = f"<= {width}" if padded else f"{width}"
                problems.append(
                    f"{k}: expected [T, {want}] or [{want}], got {list(shape) if shape else type(x).__name__}"
                )
                continue
            if not _finite(x):
                problems.append(f"{k}: contains NaN or Inf")
            elif not (isinstance(x, torch.Tensor) and x.requires_grad):
                plain[k] = x
            if len(shape) == 2 and shape[0] != 1:
                frames[k] = shape[0]
        problems += parameter_problems(plain)
        counts = set(frames.values())
        if len(counts) > 1:
            problems.append(
                "per-frame parameters disagree on the number of frames: "
                + ", ".join(f"{k}={n}" for k, n in frames.items())
            )
        T = counts.pop() if len(counts) == 1 else (num_frames or 1)
        if num_frames is not None and num_frames != T and frames:
            problems.append(f"expected {num_frames} frames, parameters have {T}")
        if problems:
            raise MeshsplatError(f"{_TITLE[self.kind]} parameters: " + "; ".join(problems))
        return T

    def _tensor(self, x) -> torch.Tensor:
        if isinstance(x, torch.Tensor):
            return x.to(device=self.device, dtype=self._dtype)
        return torch.as_tensor(np.asarray(x, np.float32), device=self.device)

    def _frames(self, params: dict, key: str, T: int, width: int) -> torch.Tensor:
        x = params.get(key)
        if x is None:
            return torch.zeros(T, width, device=self.device, dtype=self._dtype)
        x = self._tensor(x)
        x = x[None] if x.ndim == 1 else x
        if x.shape[1] < width:
            x = torch.cat([x, x.new_zeros(x.shape[0], width - x.shape[1])], 1)
        return x.expand(T, width) if x.shape[0] == 1 else x

    def forward(self, params: dict) -> BodyOutput:
        """Posed ``vertices [T,V,3]`` and ``joints [T,J,3]``; differentiable w.r.t. every parameter."""
        params = {k: (v if hasattr(v, "shape") else np.asarray(v, np.float32)) for k, v in params.items()}
        T = self.check_params(params)
        pose = torch.cat([self._frames(params, k, T, w) for k, w in POSE_KEYS[self.kind]], 1)
        coeffs = [self._frames(params, "betas", T, self.num_betas)]
        dirs = [self.shapedirs]
        if self.num_expression:
            coeffs.append(self._frames(params, "expression", T, self.num_expression))
            dirs.append(self.exprdirs)
        template = self.v_template
        if params.get("static_offset") is not None:
            template = template + self._tensor(params["static_offset"]).reshape(self.num_vertices, 3)
        verts, joints = self._lbs(
            torch.cat(coeffs, 1),
            pose,
            template,
            torch.cat(dirs, 2),
            self.posedirs,
            self.J_regressor,
            self.parents,
            self.lbs_weights,
            pose2rot=True,
        )
        transl = self._frames(params, "transl", T, 3)[:, None]
        return BodyOutput(verts * self.scale + transl, joints * self.scale + transl)

    __call__ = forward

    def rest_vertices(self, params: dict | None = None) -> torch.Tensor:
        """Canonical mesh ``[V,3]``: zero pose, expression and translation with the subject's betas and
        static_offset (first frame's betas if they are per frame)."""
        params = params or {}
        keep = {}
        for k in _SHARED_KEYS:
            if params.get(k) is not None:
                x = params[k]
                keep[k] = x[:1] if k == "betas" and getattr(x, "ndim", 1) == 2 else x
        return self.forward(keep).vertices[0]


def _finite(x) -> bool:
    if isinstance(x, torch.Tensor):
        return bool(torch.isfinite(x).all())
    a = np.asarray(x)
    return a.dtype.kind in "fiub" and bool(np.isfinite(a).all())


# ---------------------------------------------------------------- driver
class ParametricDriver:
    """MeshDriver posing a :class:`BodyModel` with per-frame parameters ``params`` (dict of ``[T,k]``)."""

    def __init__(self, model: BodyModel, params: dict) -> None:
        self.model = model
        self.params = dict(params)
        self._T = model.check_params(self.params)
        self.faces = model.faces.cpu()

    @property
    def num_frames(self) -> int:
        return self._T

    @property
    def num_vertices(self) -> int:
        return self.model.num_vertices

    def frame_params(self, start: int, stop: int | None = None) -> dict:
        """Parameters of frames ``[start, stop)`` (shared ones as they are)."""
        stop = start + 1 if stop is None else stop
        out = {}
        for k, x in self.params.items():
            per_frame = k != "static_offset" and getattr(x, "ndim", 1) == 2 and x.shape[0] == self._T and self._T > 1
            out[k] = x[start:stop] if per_frame else x
        return out

    def rest_vertices(self) -> torch.Tensor:
        with torch.no_grad():
            return self.model.rest_vertices(self.params).float().cpu()

    def vertices(self, frame: int) -> torch.Tensor:
        if not 0 <= frame < self._T:
            raise MeshsplatError(f"frame: expected 0 <= frame < {self._T}, got {frame}")
        with torch.no_grad():
            return self.model.forward(self.frame_params(frame)).vertices[0].float().cpu()

    def all_vertices(self) -> torch.Tensor:
        """All frames ``[T,V,3]`` (batched in chunks)."""
        out = []
        with torch.no_grad():
            for s in range(0, self._T, _CHUNK):
                p = self.frame_params(s, min(s + _CHUNK, self._T))
                v = self.model.forward(p).vertices
                out.append(v.expand(min(_CHUNK, self._T - s), -1, -1).float().cpu())
        return torch.cat(out, 0)


# ---------------------------------------------------------------- params files
_KNOWN_PARAM_KEYS = {"betas", "static_offset", "transl", "expression"} | {k for v in POSE_KEYS.values() for k, _ in v}


def save_driver_params(path: Path | str, params: dict) -> Path:
    """Write parameters as an npz of float32 arrays (one row per mesh frame for per-frame keys)."""
    path = Path(path)
    out = {}
    for k, x in params.items():
        if k not in _KNOWN_PARAM_KEYS:
            raise MeshsplatError(f"driver params: unknown key {k!r} (expected {sorted(_KNOWN_PARAM_KEYS)})")
        a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
        if a.dtype.kind not in "fiu" or not np.isfinite(a).all():
            raise MeshsplatError(f"driver params: {k} must be finite numbers, got dtype {a.dtype}")
        out[k] = a.astype(np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **cast("dict[str, Any]", out))  # savez stub: kwargs vs allow_pickle
    return path


def load_driver_params(path: Path | str) -> dict:
    """Read a parameter npz written by :func:`save_driver_params` (``allow_pickle=False``)."""
    path = Path(path)
    if not path.is_file():
        raise MeshsplatError(f"driver params file not found: {path}")
    out = read_npz(path, "driver params")
    bad = [k for k in out if k not in _KNOWN_PARAM_KEYS or out[k].dtype.kind not in "fiu"]
    if bad:
        raise MeshsplatError(f"{path}: unexpected or non-numeric keys {bad} (expected {sorted(_KNOWN_PARAM_KEYS)})")
    return {k: v.astype(np.float32) for k, v in out.items()}


def driver_record(model: BodyModel, params_file: str = "driver_params.npz") -> dict:
    """Manifest entry naming the model (not its file: that stays with the user) and the params file."""
    return {
        "type": model.kind,
        "gender": model.gender,
        "flame_version": model.flame_version,
        "scale": model.scale,
        "params": params_file,
    }


def model_from_record(
    record: dict, model_dir: Path | str | None = None, device: torch.device | str = "cpu"
) -> BodyModel:
    """The model a manifest's ``driver`` entry (``driver_record``) names, from the user's files in
    ``model_dir`` (default ``$MESHSPLAT_MODEL_DIR``); ``{"type": "anny"}`` (a body tracked by ``meshsplat
    track --subject body``) needs no files: the compact Anny body (``drivers.anny_body``)."""
    if record.get("type") == ANNY_TYPE:
        return cast(BodyModel, load_anny_body(device))
    return BodyModel(
        record["type"],
        model_dir,
        gender=record.get("gender", "neutral"),
        flame_version=str(record.get("flame_version", "2020")),
        scale=float(record.get("scale", 1.0)),
        device=device,
    )
