"""The player's webcam mode: what the page needs to drive a blend-shape head from a face in a webcam.

The page finds MediaPipe's 478 face landmarks in each webcam frame (the ``@mediapipe/face_mesh`` npm
package, model inside, copied next to the page by :func:`copy_landmarker`) and solves, per frame and in
JavaScript (``solveFace`` in ``static/viewer.js``), the expression weights and the head pose of the ICT
head the tracker fits (``meshsplat.track.head_fit``): the same landmark correspondence, the same camera
(60° diagonal field of view, principal point at the centre), the same robust reprojection loss and L1
prior on the weights, with the identity fixed at the ICT neutral and the gaze at rest (the iris
landmarks are left out). :func:`webcam_model` restricts the head's blend-shape basis to the landmarks:
``point_l(w) = neutral_l + sum_e w_e delta_e,l`` (47 free shapes x 478 landmarks), so the solve is a
small bounded least squares (Gauss-Newton with an active set) instead of a pose of the whole mesh.

The weights drive the avatar's morph targets of the same ARKit name, the rotation and the translation
(the move since the first solved frame, scaled by the avatar's size over the ICT head's) its head node.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from meshsplat.errors import MeshsplatError
from meshsplat.paths import asset

__all__ = [
    "webcam_model",
    "find_landmarker",
    "copy_landmarker",
    "LANDMARKER_PACKAGE",
    "LANDMARKER_VERSION",
    "LANDMARKER_FILES",
    "LANDMARKER_FOLDER",
]

LANDMARKER_PACKAGE = "@mediapipe/face_mesh"
LANDMARKER_VERSION = "0.4.1633559619"  # 0.4.1657299874 fails to start its face detector (RET_CHECK num_classes)
LANDMARKER_FOLDER = "face_mesh"  # beside index.html
# what the page loads (the SIMD build; browsers without wasm SIMD get the plain one)
LANDMARKER_FILES = (
    "face_mesh.js",
    "face_mesh.binarypb",
    "face_mesh_solution_packed_assets.data",  # the detector and landmark models
    "face_mesh_solution_packed_assets_loader.js",
    "face_mesh_solution_simd_wasm_bin.js",
    "face_mesh_solution_simd_wasm_bin.wasm",
    "face_mesh_solution_wasm_bin.js",
    "face_mesh_solution_wasm_bin.wasm",
    "package.json",
)
INSTALL_HINT = f"npm install --prefix .node-tools {LANDMARKER_PACKAGE}@{LANDMARKER_VERSION} (or make node-tools)"
_DIAGONAL_FOV_DEG = 60.0  # meshsplat.track.tracker_camera.DEFAULT_DIAGONAL_FOV_DEG (the page gets it in the header)


def webcam_model(head: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """For ``head``, a ``meshsplat.track.ict_head.IctHead`` (``load_ict_head()``; track and viewer are one
    layer, so the caller loads it): ``(sections, header)`` of the landmark model the page solves: ``webcam_neutral [L,3]`` (the
    neutral's landmark points, cm), ``webcam_deltas [E,L,3]`` (the free shapes' landmark deltas) and,
    in the header, the shape names, the landmarks the solve uses, the head-pose pivot and the camera's
    diagonal field of view."""
    tri = head.faces[head.landmark_face].numpy()  # [L,3]
    bary = head.landmark_bary.numpy().astype(np.float64)
    if tri.shape[0] == 0:
        raise MeshsplatError("webcam: the head has no landmark correspondence")

    def blend(x: np.ndarray) -> np.ndarray:  # [..., V, 3] -> [..., L, 3]
        return (bary[..., None] * x[..., tri, :]).sum(-2)

    neutral = head.neutral.double().numpy()
    free = head.free_shapes.numpy()
    deltas = blend(head.deltas.double().numpy()[free])
    # the gaze stays at rest in the page: landmarks on the eyeballs (the iris points) are not fitted
    on_eye = np.zeros(len(tri), bool)
    for e in head.eye_vertices:
        on_eye |= np.isin(tri, e.numpy()).all(1)
    pivot = (neutral.min(0) + neutral.max(0)) / 2
    sections = {
        "webcam_neutral": blend(neutral).astype("<f4"),
        "webcam_deltas": deltas.astype("<f4"),
    }
    header = {
        "names": [head.names[i] for i in free],
        "landmarks": len(tri),
        "used": [int(i) for i in np.nonzero(~on_eye)[0]],
        "pivot": [float(x) for x in pivot],
        # the page scales the head's move (cm) by the avatar's size over this (the ICT neutral's bounding-box diagonal)
        "head_size_cm": float(np.linalg.norm(neutral.max(0) - neutral.min(0))),
        "diagonal_fov_deg": _DIAGONAL_FOV_DEG,
        "landmarker": {"package": LANDMARKER_PACKAGE, "version": LANDMARKER_VERSION, "folder": LANDMARKER_FOLDER},
    }
    return sections, header


def find_landmarker(where: str | Path | None = None) -> Path:
    """The installed ``@mediapipe/face_mesh`` package folder: ``where`` (the package folder, or an npm
    prefix holding ``node_modules/@mediapipe/face_mesh``), else ``$MESHSPLAT_NODE_TOOLS``, ``.node-tools``
    and ``node_modules`` of the current folder."""
    candidates: list[Path] = []
    if where is not None:
        candidates.append(Path(where))
    else:
        env = os.environ.get("MESHSPLAT_NODE_TOOLS")
        candidates += [Path(env)] if env else []
        candidates += [Path(".node-tools"), Path(".")]
    for c in candidates:
        for p in (c, c / "node_modules" / LANDMARKER_PACKAGE):
            if all((p / f).is_file() for f in LANDMARKER_FILES):
                return p
    looked = ", ".join(str(c) for c in candidates)
    raise MeshsplatError(
        f"webcam: the face landmarker ({LANDMARKER_PACKAGE}) is not installed (looked in {looked}); "
        f"install it with: {INSTALL_HINT}"
    )


def copy_landmarker(package_dir: Path, out_dir: Path) -> int:
    """Copy the landmarker's files (scripts, wasm, model) into ``out_dir/face_mesh``; returns their bytes."""
    dest = out_dir / LANDMARKER_FOLDER
    dest.mkdir(parents=True, exist_ok=True)
    total = 0
    for f in LANDMARKER_FILES:
        shutil.copyfile(package_dir / f, dest / f)
        total += (dest / f).stat().st_size
    # the package states its licence in package.json only; its text goes along
    shutil.copyfile(asset("licenses/Apache-2.0.txt"), dest / "LICENSE")
    (dest / "NOTICE").write_text(
        f"{LANDMARKER_PACKAGE} {LANDMARKER_VERSION} (MediaPipe Face Mesh: scripts, WebAssembly and the face detection\n"
        "and face landmark models), Copyright Google LLC, licensed under the Apache License 2.0 (LICENSE).\n"
        "Copied unmodified from the npm package by meshsplat view --webcam.\n",
        encoding="utf-8",
    )
    return total
