"""FLAME posing for the head-capture layouts (IMavatar, INSTA, GaussianAvatars/VHAP).

The user's FLAME model, coefficients fitted to it, posing a parameter dict (out-of-range values refused
naming their file), the manifest's driver entry, the "mesh in front of its camera" check, and the FLAME
parameters of a native dataset per mesh row (for the writers). Generic file helpers live in ``_files``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.manifest import Problems
from meshsplat.drivers.body_models import BodyModel, driver_record
from meshsplat.errors import MeshsplatError

__all__ = ["flame_model", "fit_coeffs", "pose_model", "flame_driver_record", "check_in_front", "flame_rows"]


def flame_model(model_dir: Path | str | None, flame_version: str, scale: float, problems: Problems) -> BodyModel | None:
    """The user's FLAME model (its error, e.g. the file is missing, becomes one of ``problems``)."""
    try:
        return BodyModel("flame", model_dir, flame_version=str(flame_version), scale=scale)
    except MeshsplatError as exc:
        problems.add("FLAME model", str(exc))
        return None


def fit_coeffs(name: str, a: np.ndarray, width: int, problems: Problems) -> np.ndarray:
    """Coefficients ``[..., k]`` for a model with ``width`` of them: zero-padded, or trimmed when the
    extra trailing coefficients are all zero (they add nothing); a problem otherwise."""
    k = a.shape[-1]
    if k > width:
        if np.any(a[..., width:] != 0):
            problems.add(
                name,
                f"{k} coefficients, but the FLAME model file has {width}; "
                f"non-zero coefficients beyond {width} cannot be used (use a full FLAME model file)",
            )
        return a[..., :width]
    if k < width:
        pad = np.zeros(a.shape[:-1] + (width - k,), a.dtype)
        return np.concatenate([a, pad], -1)
    return a


def pose_model(model: BodyModel, params: dict, source: str, chunk: int = 128) -> np.ndarray:
    """Posed vertices ``[T,V,3]`` float32 of per-frame ``params`` (shared ones broadcast); parameters out of
    their plausible range (``meshsplat.plausible``) are refused in one line naming ``source``."""
    try:
        T = model.check_params(params)
    except MeshsplatError as exc:
        raise MeshsplatError(f"{source}: {exc}") from None
    out = np.empty((T, model.num_vertices, 3), np.float32)
    with torch.no_grad():
        for s in range(0, T, chunk):
            e = min(T, s + chunk)
            p = {
                k: (v[s:e] if k != "static_offset" and np.ndim(v) == 2 and len(v) == T else v)
                for k, v in params.items()
            }
            out[s:e] = model.forward(p).vertices.cpu().numpy()
    return out


def flame_driver_record(model: BodyModel, source: str, per_frame: list[str]) -> dict:
    """Manifest ``driver`` entry for meshes posed from a capture's FLAME parameters."""
    rec = driver_record(model, source)
    rec["per_frame"] = list(per_frame)
    return rec


def check_in_front(cameras: dict, frames: list[dict], verts: np.ndarray | None, problems: Problems, hint: str) -> None:
    """Every frame's mesh centre must lie in front of its camera (catches a flipped camera convention)."""
    if verts is None:
        return
    centres = np.asarray(verts, np.float64).mean(axis=1)
    for i, rec in enumerate(frames):
        cam = cameras.get(str(rec.get("camera")))
        row = rec.get("mesh")
        if cam is None or not isinstance(row, int) or not 0 <= row < len(centres):
            continue
        vm = np.asarray(cam["viewmat"], np.float64)
        if vm.shape != (4, 4):
            continue
        z = float(vm[2, :3] @ centres[row] + vm[2, 3])
        if not z > 0:
            problems.add(f"frame {i} ({rec.get('name')!r})", f"the mesh lies behind its camera (depth {z:.3g}); {hint}")


def flame_rows(dataset: AvatarDataset, fmt: str) -> tuple[dict, dict[str, np.ndarray], set[str]]:
    """``(driver_info, params, per_frame names)`` of a dataset whose meshes are FLAME-posed."""
    info, params = dataset.driver_info, dataset.driver_params
    if info is None or params is None or info.get("type") != "flame":
        kind = info.get("type") if info else "no body/head model"
        raise MeshsplatError(
            f"{fmt} writer: {dataset.root} must carry FLAME parameters (driver type 'flame'), "
            f"it has {kind}; generate it from a FLAME source"
        )
    return info, {k: np.asarray(v, np.float64) for k, v in params.items()}, set(info.get("per_frame", []))
