"""meshsplat: animatable avatars of 3D Gaussians embedded on a driving mesh.

The front door, ``import meshsplat as ms``, covers the whole pipeline::

    ms.synthesize(asset, out_dir, ...)              render an animated asset into a capture (synth.generate)
    ms.open_capture(path)                           read a capture of any supported layout
    ms.TrainConfig, ms.train_avatar(dataset, out)   configure / train an avatar; returns the run folder
    ms.load_run(run), ms.load_avatar(run)           a trained run (avatar, config, dataset) / its avatar
    ms.Avatar, ms.Camera, ms.orbit_cameras          avatar.render(vertices, camera) -> image [H,W,3]
    ms.AnimationSource(kind, file, clip=...)        what drives the avatar (as --animation KIND FILE)
    ms.load_animation(source, avatar)               its frames (or live driver) on the avatar's mesh
    ms.render_animation(avatar, frames, cams, out)  PNG frames + MP4 (frames: also a loaded animation)
    ms.evaluate(run)                                metrics.json + report.html (eval.evaluate_run)
    ms.export_avatar(avatar, out)                   3DGS .ply + embedding JSON + canonical OBJ
    ms.write_viewer(avatar, frames, out)            one self-contained HTML page (viewer.write_viewer_bundle)
    ms.MeshsplatError, ms.__version__

Every name and every subpackage (``ms.camera``, ``ms.run_folder``, ``ms.train``, ...) is imported on
first use, so ``import meshsplat`` stays light (no torch, gsplat, smplx or video backends).
``train_avatar`` and ``export_avatar`` keep their ``_avatar``: ``meshsplat.train`` and
``meshsplat.export`` are modules, and importing a module rebinds its name on the package.
"""

from __future__ import annotations

import importlib
import os

from meshsplat.errors import MeshsplatError

# Intel MKL (torch's CPU BLAS) otherwise picks code paths by buffer alignment, so a matrix product can differ
# in the last bit from run to run and a resumed training would not be bit-exact (docs/architecture.md,
# "Determinism"). MKL reads it once, when it first computes; a user's own MKL_CBWR wins.
os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")

TYPE_CHECKING = False  # not typing.TYPE_CHECKING: importing typing would double the time of `import meshsplat`

__version__ = "0.1.0"

# front-door name -> (defining module, attribute)
_FRONT_DOOR: dict[str, tuple[str, str]] = {
    "synthesize": ("meshsplat.synth.generate", "synthesize"),
    "open_capture": ("meshsplat.data.formats", "open_capture"),
    "TrainConfig": ("meshsplat.train.config", "TrainConfig"),
    "train_avatar": ("meshsplat.pipeline", "train_avatar"),
    "load_run": ("meshsplat.run_folder", "load_run"),
    "load_avatar": ("meshsplat.run_folder", "load_avatar"),
    "Avatar": ("meshsplat.gaussians.avatar", "Avatar"),
    "Camera": ("meshsplat.camera", "Camera"),
    "orbit_cameras": ("meshsplat.camera", "orbit_cameras"),
    "AnimationSource": ("meshsplat.animation.source", "AnimationSource"),
    "load_animation": ("meshsplat.animation.source", "load_animation"),
    "render_animation": ("meshsplat.animate", "render_animation"),
    "evaluate": ("meshsplat.eval.evaluate", "evaluate_run"),
    "export_avatar": ("meshsplat.export", "export_avatar"),
    "write_viewer": ("meshsplat.viewer.bundle", "write_viewer_bundle"),
}

# every public module and subpackage, reachable as ``meshsplat.<name>``
_SUBMODULES = (
    "errors",
    "paths",
    "plausible",
    "io",
    "metrics",
    "camera",
    "drivers",
    "mesh",
    "embedding",
    "render",
    "gaussians",
    "data",
    "animation",
    "run_folder",
    "train",
    "synth",
    "eval",
    "export",
    "animate",
    "demo",
    "viewer",
    "track",
    "pipeline",
    "fleet",
    "cli",
)

__all__ = [
    "synthesize",
    "open_capture",
    "TrainConfig",
    "train_avatar",
    "load_run",
    "load_avatar",
    "Avatar",
    "Camera",
    "orbit_cameras",
    "AnimationSource",
    "load_animation",
    "render_animation",
    "evaluate",
    "export_avatar",
    "write_viewer",
    "MeshsplatError",
    "__version__",
]

if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from typing import Any

    from meshsplat.animate import render_animation
    from meshsplat.animation.source import AnimationSource, load_animation
    from meshsplat.camera import Camera, orbit_cameras
    from meshsplat.data.formats import open_capture
    from meshsplat.eval.evaluate import evaluate_run as evaluate
    from meshsplat.export import export_avatar
    from meshsplat.gaussians.avatar import Avatar
    from meshsplat.pipeline import train_avatar
    from meshsplat.run_folder import load_avatar, load_run
    from meshsplat.synth.generate import synthesize
    from meshsplat.train.config import TrainConfig
    from meshsplat.viewer.bundle import write_viewer_bundle as write_viewer


def __getattr__(name: str) -> Any:
    if name in _FRONT_DOOR:
        module, attr = _FRONT_DOOR[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value  # later look-ups skip this function
        return value
    if name in _SUBMODULES:
        return importlib.import_module(f"meshsplat.{name}")
    raise AttributeError(f"module 'meshsplat' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(__all__) | set(_SUBMODULES) | {n for n in globals() if n.startswith("__")})
