"""A training run folder: the one place that knows its file names and how to read it back.

Layout (written by ``meshsplat.train``, read by eval, export, render, view and the demo)::

    RUN/config.json                       resolved TrainConfig (JSON)
    RUN/checkpoints/ckpt_<iter:08d>.pt    atomic checkpoints (``meshsplat.io.checkpoint``)
    RUN/log.csv                           training log, one row per ``log_every`` iterations
    RUN/previews/preview_<iter:06d>.png   render | ground truth of a fixed training frame
    RUN/refined_params.npz                refined tracker parameters (``pose_refine.enabled``)
    RUN/source_map.npz                    copied from a synthesized dataset (``meshsplat.data.source_map``)
    RUN/eval/                             ``meshsplat eval`` (metrics.json, report)
    RUN/export/                           ``meshsplat export``
    RUN/run.json                          the run's identity: the capture it trains (path, summary), recipe digest
    RUN/train.lock                        while training: the lock holding the trainer's PID (``io.folder_lock``)

A run folder is owned (:func:`check_training_target`): training refuses a capture folder, a non-empty
folder that is not a run, and a run that another process is training right now; a resumed run refuses
another capture than the one in its ``run.json`` (:func:`identity_differences`).

Layer: just below ``train`` (it imports io, gaussians and data, never train), so the trainer writes
through :class:`RunFolder` and everything above reads through :func:`load_run`. Wherever a run is
asked for, a checkpoint file inside it (``RUN/checkpoints/ckpt_*.pt``) may be given instead.
"""

from __future__ import annotations

import hashlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat._device import resolve_device
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.formats import FORMAT_NAMES, format_module, open_capture, reader_options
from meshsplat.data.source_map import FILE_NAME as SOURCE_MAP_NAME
from meshsplat.data.source_map import SourceMap, read_source_map
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.gaussians.avatar import Avatar
from meshsplat.io.checkpoint import checkpoint_path, list_checkpoints, load_checkpoint
from meshsplat.io.folder_lock import held_by_parent, holder_text, lock_holder
from meshsplat.io.json_file import read_json_object

__all__ = [
    "RunFolder",
    "LoadedRun",
    "load_run",
    "load_avatar",
    "ALLOW_OLDER_FLAG",
    "TRACKED_POSES_FLAG",
    "check_training_target",
    "capture_identity",
    "identity_differences",
]

ALLOW_OLDER_FLAG = "--allow-older-checkpoint"  # the command-line spelling of ``allow_older``
TRACKED_POSES_FLAG = "--tracked-poses"  # the command-line spelling of ``refined_poses=False``


def _reason(message: str, path: Path) -> str:
    """A checkpoint error without its file's name (the caller names the file): ``checkpoint 'X' is
    corrupt ...`` -> ``corrupt ...``."""
    for prefix in (f"checkpoint {str(path)!r} is ", f"checkpoint {str(path)!r} ", f"{path}: ", f"{path.name}: "):
        if message.startswith(prefix):
            return message[len(prefix) :]
    return message


class RunFolder:
    """Paths of the run folder ``root`` (nothing is read or created until asked)."""

    CONFIG = "config.json"
    CHECKPOINTS = "checkpoints"
    LOG = "log.csv"
    PREVIEWS = "previews"
    REFINED_PARAMS = "refined_params.npz"
    EVAL = "eval"
    EXPORT = "export"
    IDENTITY = "run.json"
    LOCK = "train.lock"

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    @classmethod
    def of(cls, path: str | Path) -> RunFolder:
        """The run folder ``path`` names: the folder itself, or the run holding the checkpoint file ``path``."""
        path = Path(path)
        if path.is_dir():
            return cls(path)
        return cls(path.parent.parent if path.parent.name == cls.CHECKPOINTS else path.parent)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.root)!r})"

    @property
    def config_path(self) -> Path:
        return self.root / self.CONFIG

    @property
    def checkpoint_dir(self) -> Path:
        return self.root / self.CHECKPOINTS

    @property
    def log_path(self) -> Path:
        return self.root / self.LOG

    @property
    def preview_dir(self) -> Path:
        return self.root / self.PREVIEWS

    @property
    def refined_params_path(self) -> Path:
        return self.root / self.REFINED_PARAMS

    @property
    def source_map_path(self) -> Path:
        return self.root / SOURCE_MAP_NAME

    @property
    def eval_dir(self) -> Path:
        return self.root / self.EVAL

    @property
    def export_dir(self) -> Path:
        return self.root / self.EXPORT

    @property
    def identity_path(self) -> Path:
        return self.root / self.IDENTITY

    @property
    def lock_path(self) -> Path:
        return self.root / self.LOCK

    def is_run(self) -> bool:
        """Whether ``root`` holds a training run: its ``run.json``, checkpoints, or a ``config.json`` that is a
        training config (a capture's or another tool's config.json is not)."""
        if self.identity_path.is_file() or self.checkpoints() or list_checkpoints(self.root):
            return True
        try:
            cfg = read_json_object(self.config_path) if self.config_path.is_file() else None
        except MeshsplatError:
            return False
        return isinstance(cfg, dict) and {"data", "out", "iterations", "model"} <= set(cfg)

    def identity(self) -> dict[str, Any] | None:
        """``RUN/run.json`` as a dict (None when absent: runs written before it existed)."""
        return read_json_object(self.identity_path) if self.identity_path.is_file() else None

    def checkpoint_path(self, iteration: int) -> Path:
        """``RUN/checkpoints/ckpt_<iteration:08d>.pt``."""
        return checkpoint_path(self.checkpoint_dir, iteration)

    def preview_path(self, iteration: int) -> Path:
        """``RUN/previews/preview_<iteration:06d>.png``."""
        return self.preview_dir / f"preview_{int(iteration):06d}.png"

    def checkpoints(self) -> list[tuple[int, Path]]:
        """``(iteration, path)`` of ``RUN/checkpoints/ckpt_*.pt``, oldest first (not validated)."""
        return list_checkpoints(self.checkpoint_dir)

    def latest_checkpoint(
        self, map_location: str | torch.device = "cpu", allow_older: bool = False
    ) -> tuple[Path, dict]:
        """``(path, state)`` of the newest checkpoint of ``RUN/checkpoints`` (else, for older runs,
        ``RUN/ckpt_*.pt``). An unreadable newest one is refused in one line naming it and the flag
        ``--allow-older-checkpoint``; with ``allow_older`` the newest readable one is used instead, with a
        one-line note naming the skipped files and the iteration used. One-line error when none loads."""
        if not self.root.exists():
            raise MeshsplatError(f"run not found: {self.root} (expected a training run folder or a checkpoint file)")
        for folder in (self.checkpoint_dir, self.root):
            ckpts = list_checkpoints(folder)
            if not ckpts:
                continue
            problems: list[tuple[Path, str]] = []
            for it, p in reversed(ckpts):
                try:
                    state = load_checkpoint(p, map_location)
                except MeshsplatError as exc:
                    problems.append((p, str(exc)))
                    if not allow_older:
                        break
                    continue
                if problems:
                    skipped = ", ".join(q.name for q, _ in problems)
                    warnings.warn(
                        f"{folder}: skipped the unreadable newest checkpoint(s) {skipped}; using {p.name} "
                        f"(iteration {it})",
                        MeshsplatWarning,
                        stacklevel=3,
                    )
                return p, state
            newest, why = problems[0]
            if not allow_older and len(ckpts) > 1:
                raise MeshsplatError(
                    f"the newest checkpoint {newest} is unreadable ({_reason(why, newest)}); pass "
                    f"{ALLOW_OLDER_FLAG} to use the newest readable one of the {len(ckpts) - 1} older checkpoint(s)"
                )
            raise MeshsplatError(f"all {len(ckpts)} checkpoint(s) in {folder} are unreadable; newest: {why}")
        raise MeshsplatError(
            f"no checkpoint in {self.root} (looked for {self.checkpoint_dir}/ckpt_*.pt); is this a training run folder?"
        )

    def load_config(self) -> dict[str, Any] | None:
        """``RUN/config.json`` as a dict, or None when the file is absent."""
        path = self.config_path
        if not path.is_file():
            return None
        return read_json_object(path)


def _checkpoint(
    path: str | Path, map_location: str | torch.device = "cpu", allow_older: bool = False
) -> tuple[RunFolder, Path, dict]:
    """``(run, checkpoint, state)`` for a run folder (its newest checkpoint; ``allow_older``: the newest
    readable one) or a checkpoint file."""
    path = Path(path)
    run = RunFolder.of(path)
    if path.is_file():
        return run, path, load_checkpoint(path, map_location)
    ckpt, state = RunFolder(path).latest_checkpoint(map_location, allow_older)
    return run, ckpt, state


def _avatar(ckpt: Path, state: dict, device) -> Avatar:
    if not isinstance(state, dict) or "avatar" not in state:
        raise MeshsplatError(f"{ckpt}: checkpoint holds no avatar")
    return Avatar.from_state_dict(state["avatar"], resolve_device(device))


def load_avatar(run: str | Path, device: str | torch.device | None = "cpu", allow_older: bool = False) -> Avatar:
    """The avatar of a run folder's newest checkpoint (``allow_older``: its newest readable one, with a
    note), or of one checkpoint file."""
    _, ckpt, state = _checkpoint(run, allow_older=allow_older)
    return _avatar(ckpt, state, device)


@dataclass
class LoadedRun:
    """``avatar`` of the checkpoint ``checkpoint`` of the run ``folder``; ``config`` is the run's config dict."""

    folder: RunFolder
    checkpoint: Path
    iteration: int | None
    avatar: Avatar
    config: dict[str, Any] = field(default_factory=dict)

    @property
    def run_dir(self) -> Path:
        return self.folder.root

    def dataset_path(self, dataset: str | Path | None = None) -> Path:
        """``dataset`` if given, else the ``data`` entry of the run's config. Runs store it absolute;
        a relative one (older runs) is tried from the current folder, then from the run folder."""
        if dataset is not None:
            return Path(dataset)
        data = self.config.get("data")
        if not data or not isinstance(data, str):
            raise MeshsplatError(f"{self.run_dir}: config.json names no dataset; pass --dataset PATH")
        p = Path(data)
        if not p.exists() and not p.is_absolute() and (self.run_dir / p).exists():
            p = self.run_dir / p
        if not p.exists():
            raise MeshsplatError(
                f"the run's dataset {data} (from {self.folder.config_path}) is not there: was it "
                "moved or deleted? Pass --dataset PATH"
            )
        return p

    def model_dir(self, model_dir: str | Path | None = None) -> Path | None:
        """``model_dir`` if given, else the run's ``model_dir`` (SMPL/FLAME files; None when the run has
        none: ``$MESHSPLAT_MODEL_DIR`` then applies). Runs store it absolute; a relative one (older runs,
        whose working folder is not recorded) is tried as given, then from the run folder's parent, then
        from the run folder; not found there is one line naming the config key."""
        if model_dir is not None:
            return Path(model_dir)
        value = self.config.get("model_dir")
        if not value:
            return None
        if not isinstance(value, str):
            raise MeshsplatError(f"{self.folder.config_path}: model_dir must be a folder path, got {value!r}")
        p = Path(value).expanduser()
        if p.is_absolute() or p.is_dir():
            return p.resolve() if p.is_dir() else p
        for base in (self.run_dir.resolve().parent, self.run_dir.resolve()):
            if (base / p).is_dir():
                return base / p
        raise MeshsplatError(
            f"the run's model_dir {value!r} (config key model_dir in {self.folder.config_path}) is a relative "
            f"path found neither from here nor from {self.run_dir.resolve().parent}; pass --model-dir DIR"
        )

    def open_dataset(
        self,
        dataset: str | Path | None = None,
        model_dir: str | Path | None = None,
        check_masks: bool = True,
        drop_bad_frames: bool | None = None,
        downscale: float | None = None,
        refined_poses: bool = True,
    ) -> AvatarDataset:
        """The run's capture (any layout, as recorded in its config), or ``dataset`` if given.

        ``model_dir`` (SMPL/FLAME files) defaults to the run's ``model_dir``, then ``$MESHSPLAT_MODEL_DIR``;
        ``drop_bad_frames`` to the run's (frames failing the camera check left out, as in training).
        ``downscale`` defaults to the run's ``data_downscale`` (also for another ``dataset``: the size the
        avatar was trained at); pass 1 to read a capture as recorded. ``refined_poses``: the run's own capture
        comes with the training poses it refined (:meth:`refined_meshes`) in place of the tracker's.
        """
        path = self.dataset_path(dataset)
        fmt = self.config.get("data_format") or None if dataset is None else None
        mdir = self.model_dir(model_dir)
        drop = bool(self.config.get("drop_bad_frames", False)) if drop_bad_frames is None else drop_bad_frames
        factor = self.training_downscale if downscale is None else downscale
        opts = reader_options(self.config.get("data_gender"), self.config.get("data_shape"))  # as trained
        ds = open_capture(
            path, format=fmt, model_dir=mdir, check_masks=check_masks, drop_bad_frames=drop, downscale=factor, **opts
        )
        if refined_poses and self._own_dataset(path):
            meshes = self.refined_meshes(ds, mdir)
            if meshes:
                ds = ds.with_meshes(meshes)
        return ds

    def head_model(self, dataset: str | Path | None = None) -> Path | None:
        """The blend-shape model the capture's tracker fitted (``meshsplat track``: the capture manifest's
        ``meta.head_model``, e.g. ``CAPTURE/head_model.npz``), the model the avatar was trained on; None for
        any other capture or when the run's capture is not there."""
        try:
            root = self.dataset_path(dataset)
        except MeshsplatError:
            return None
        manifest = root / "manifest.json"
        if not manifest.is_file():
            return None
        meta = read_json_object(manifest, "a capture manifest").get("meta")
        name = meta.get("head_model") if isinstance(meta, dict) else None
        if not isinstance(name, str) or not name or Path(name).name != name:
            return None  # a file name inside the capture, nothing else
        path = root / name
        if not path.is_file():
            raise MeshsplatError(
                f"{manifest} names the head model {name}, which is not there: pass the model the avatar was "
                "trained on (--animation blendshapes FILE.npz)"
            )
        return path

    def _own_dataset(self, path: Path) -> bool:
        data = self.config.get("data")
        if not isinstance(data, str) or not data:
            return False
        try:
            return self.dataset_path().resolve() == path.resolve()
        except MeshsplatError:
            return False

    def refined_meshes(self, dataset: AvatarDataset, model_dir: str | Path | None = None) -> dict[int, np.ndarray]:
        """Driving meshes ``row -> vertices [V,3]`` of the training frames whose poses the run refined
        (``RUN/refined_params.npz`` with ``dataset``'s shared parameters, through its body model); empty
        when the run refined none. A held-out view of a training frame is then rendered in the refined pose
        (fitted on the training images only); held-out frames keep the tracker's."""
        path = self.folder.refined_params_path
        if not path.is_file():
            return {}
        redo = f"retrain with pose refinement, or evaluate with the tracker's poses ({TRACKED_POSES_FLAG})"
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: np.asarray(z[k]) for k in z.files}
        except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same one line
            raise MeshsplatError(f"{path}: unreadable refined poses ({type(exc).__name__}); {redo}") from None
        rows = arrays.pop("mesh_rows", None)
        params = dataset.driver_params or {}
        per_frame = dataset.per_frame_param_names
        n = len(params[per_frame[0]]) if per_frame else 0
        if rows is None or rows.ndim != 1 or rows.dtype.kind not in "iu" or len(set(rows.tolist())) != len(rows):
            raise MeshsplatError(f"{path}: 'mesh_rows' must be distinct integers [R]; {redo}")
        if len(rows) and (rows.min() < 0 or rows.max() >= n):
            raise MeshsplatError(f"{path}: mesh rows outside the capture's {n} meshes (another capture?); {redo}")
        for k, v in arrays.items():
            if k not in per_frame:
                raise MeshsplatError(f"{path}: {k!r} is not a per-frame parameter of the capture {per_frame}; {redo}")
            if v.shape != (len(rows), *params[k].shape[1:]) or not np.isfinite(v).all():
                raise MeshsplatError(
                    f"{path}: {k!r} has shape {list(v.shape)} (finite numbers expected), expected "
                    f"{[len(rows), *params[k].shape[1:]]}; {redo}"
                )
        if not len(rows):
            return {}
        try:
            model = dataset.body_model(model_dir if model_dir is not None else self.model_dir(), "cpu")
        except MeshsplatError as exc:
            raise MeshsplatError(f"the run's refined poses need the body model: {exc}; {redo}") from None
        full = {k: (arrays[k] if k in arrays else params[k][rows]) if k in per_frame else v for k, v in params.items()}
        out: dict[int, np.ndarray] = {}
        with torch.no_grad():
            for a in range(0, len(rows), 64):  # bounded memory on long captures
                chunk = {k: (v[a : a + 64] if k in per_frame else v) for k, v in full.items()}
                verts = model.forward(chunk).vertices.float().cpu().numpy()
                out.update({int(r): verts[j] for j, r in enumerate(rows[a : a + 64])})
        return out

    @property
    def training_downscale(self) -> float:
        """The run's ``data_downscale`` (1 for runs written before the key existed)."""
        value = self.config.get("data_downscale", 1)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise MeshsplatError(f"{self.folder.config_path}: data_downscale must be a number, got {value!r}")
        return float(value)

    def source_map(self, dataset: str | Path | None = None) -> SourceMap | None:
        """The run's source map (``RUN/source_map.npz``), else its dataset folder's, else None."""
        found = read_source_map(self.run_dir)
        if found is not None:
            return found
        data = dataset if dataset is not None else self.config.get("data")
        if not data:
            return None
        p = Path(data)
        if not p.exists() and not p.is_absolute() and (self.run_dir / p).exists():
            p = self.run_dir / p
        return read_source_map(p) if p.is_dir() else None


def load_run(run: str | Path, device: str | torch.device | None = "cpu", allow_older: bool = False) -> LoadedRun:
    """Load the avatar of a run folder (newest ``checkpoints/ckpt_*.pt``; an unreadable one is refused unless
    ``allow_older``, which uses the newest readable one with a note) or of one checkpoint file, with the
    run's config (``config.json``, else the one stored in the checkpoint)."""
    folder, ckpt, state = _checkpoint(run, allow_older=allow_older)
    avatar = _avatar(ckpt, state, device)
    config = folder.load_config()
    if config is None:
        config = dict(state["config"]) if isinstance(state.get("config"), dict) else {}
    it = state.get("iteration")
    if it is not None and (isinstance(it, bool) or not isinstance(it, int) or it < 0):
        raise MeshsplatError(f"{ckpt}: 'iteration' must be a non-negative integer, got {it!r}")
    return LoadedRun(folder, Path(ckpt), int(it) if it is not None else None, avatar, config)


def check_training_target(out: str | Path, data: str | Path | None = None) -> None:
    """Refuse, in one line, a training ``--out`` that would overwrite what is not the run's own: the capture
    ``data`` itself or any capture folder, a non-empty folder that is not a run (:meth:`RunFolder.is_run`),
    or a run another process is training right now (its ``train.lock``; the ``--nproc`` launcher of this
    process does not count). A new or empty folder passes; nothing is created."""
    run = RunFolder(out)
    root = run.root
    if not root.exists():
        return
    if not root.is_dir():
        raise MeshsplatError(f"--out {root} is an existing file; give a run folder (new, empty, or a run to resume)")
    if data is not None and Path(data).exists() and root.resolve() == Path(data).resolve():
        raise MeshsplatError(
            f"--out {root} is the capture being trained: the run would overwrite its files; give a separate "
            "run folder, e.g. runs/NAME"
        )
    layout = next((name for name in FORMAT_NAMES if format_module(name).detect(root)), None)
    if layout is not None:
        raise MeshsplatError(
            f"--out {root} holds a capture ({layout} layout): the run would overwrite its files; give a "
            "separate run folder, e.g. runs/NAME"
        )
    entries = sorted(p.name for p in root.iterdir())
    early = {RunFolder.LOCK, SOURCE_MAP_NAME}  # what a run holds before its config.json (a launcher's lock)
    if set(entries) - early and not run.is_run():
        shown = ", ".join(entries[:4]) + (f" and {len(entries) - 4} more" if len(entries) > 4 else "")
        raise MeshsplatError(
            f"--out {root} is not empty and is not a training run (it holds {shown}); give a new or empty "
            "folder, or a run folder to resume"
        )
    holder = lock_holder(run.lock_path)
    if holder is not None and not held_by_parent(holder):
        raise MeshsplatError(
            f"--out {root} is being trained right now by {holder_text(holder)}; wait for it to finish or stop "
            "it (Ctrl-C or SIGTERM write a checkpoint), then --resume; or choose another --out"
        )


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def capture_identity(dataset: AvatarDataset) -> dict[str, Any]:
    """What tells one capture from another, for ``RUN/run.json``: the mesh topology (faces digest, vertex
    count), the rest mesh's bounding box and centroid, and the cameras (ids digest, count, image sizes, mean
    centre and focal length). Compared with a tolerance by :func:`identity_differences` (a capture that was
    moved, or read on another thread count, is the same capture)."""
    cano = dataset.canonical_vertices.double().numpy()
    faces = dataset.faces.numpy().astype(np.int64)
    ids = sorted(dataset.camera_ids)
    cams = [dataset.camera(c) for c in ids]
    centres = np.array([c.center.double().numpy() for c in cams]) if cams else np.zeros((0, 3))
    focal = np.array([[float(c.K[0, 0]), float(c.K[1, 1])] for c in cams]) if cams else np.zeros((0, 2))
    return {
        "faces": _digest(faces),
        "vertices": int(cano.shape[0]),
        "bbox": [cano.min(0).tolist(), cano.max(0).tolist()] if len(cano) else [],
        "centroid": cano.mean(0).tolist() if len(cano) else [],
        "cameras": len(ids),
        "camera_ids": hashlib.sha256("\n".join(ids).encode()).hexdigest()[:16],
        "image_sizes": sorted({f"{c.width}x{c.height}" for c in cams}),
        "camera_centre": centres.mean(0).tolist() if len(centres) else [],
        "focal": focal.mean(0).tolist() if len(focal) else [],
    }


def identity_differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """What differs between two :func:`capture_identity` dicts (empty: the same capture). Lengths compare to
    1e-3 of the rest mesh's size, focal lengths to 1e-3 relative; keys missing from either are skipped."""
    size = 1.0
    try:
        lo, hi = np.asarray(new["bbox"][0], float), np.asarray(new["bbox"][1], float)
        size = max(float(np.linalg.norm(hi - lo)), 1e-9)
    except (KeyError, IndexError, TypeError, ValueError):
        pass
    tolerance = {"bbox": 1e-3 * size, "centroid": 1e-3 * size, "camera_centre": 1e-3 * size}
    names = {
        "faces": "mesh topology",
        "vertices": "vertex count",
        "bbox": "rest mesh size",
        "centroid": "rest mesh position",
        "cameras": "camera count",
        "camera_ids": "camera names",
        "image_sizes": "image sizes",
        "camera_centre": "camera positions",
        "focal": "focal lengths",
    }
    out = []
    for key, label in names.items():
        if key not in old or key not in new:
            continue
        a, b = old[key], new[key]
        if key in tolerance or key == "focal":
            try:
                x, y = np.asarray(a, float), np.asarray(b, float)
                tol = tolerance.get(key, 1e-3 * float(np.abs(y).max(initial=1.0)))
                same = x.shape == y.shape and bool(np.all(np.abs(x - y) <= tol))
            except (TypeError, ValueError):
                same = False
        else:
            same = a == b
        if not same:
            out.append(label)
    return out
