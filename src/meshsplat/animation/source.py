"""One way to say an animation: ``AnimationSource`` (the CLI's ``--animation KIND [FILE]`` and its options)
and ``load_animation``, which turns it into vertex frames or a live driver on the avatar's mesh.

    src = AnimationSource("gltf", "walk.glb", clip="Walk", fps=25)     # --animation gltf walk.glb --clip Walk
    anim = load_animation(src, avatar, source_map=run.source_map())      # anim.frames: list of [V,3]
    live = load_animation(src, avatar, live=True)                        # anim.driver: the GltfDriver itself

Kinds (``ANIMATION_KINDS``): ``dataset`` (the capture's meshes, or one ``split``'s with each frame's own
camera), ``gltf FILE`` (a clip of a glTF/GLB rig), ``vertices FILE`` (a vertex sequence ``[T,V,3]``:
``.npy``, mesh-sequence ``.npz``, OBJ/PLY folder, or an array), ``blendshapes [FILE]`` (a blend-shape
model, default the bundled ICT head, driven by ``weights [T,K]`` or a procedural talking sequence) and
``motion FILE`` (SMPL/SMPL-X/FLAME parameters reenacting an avatar of a tracked capture).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat.animation.avatar_match import (
    MAX_ANIMATION_FRAMES,
    blendshapes_for_mesh,
    check_frames,
    gltf_for_mesh,
    sequence_for_mesh,
)
from meshsplat.animation.motion import load_motion, reenact
from meshsplat.camera import Camera
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.source_map import SourceMap
from meshsplat.drivers.blendshape import BlendshapeDriver, read_weights
from meshsplat.drivers.body_models import ParametricDriver, model_from_record, model_kind_for
from meshsplat.drivers.gltf import GltfDriver
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.mesh import TriMesh

__all__ = ["ANIMATION_KINDS", "AnimationSource", "Animation", "load_animation", "TALKING_FRAMES"]

ANIMATION_KINDS = ("dataset", "gltf", "vertices", "blendshapes", "motion")
_NEEDS_FILE = ("gltf", "vertices", "motion")
TALKING_FRAMES = 125  # length of the procedural talking sequence of a blend-shape model without weights


@dataclass(frozen=True)
class AnimationSource:
    """What drives the avatar, in the words of ``--animation KIND [FILE]`` and its options.

    ``file``: gltf/vertices/motion: the file (vertices: also an array ``[T,V,3]``); blendshapes: the model
    ``.npz`` or a bundled name (default the ICT head); dataset: none. ``clip``: the glTF clip (default the
    first). ``split``: dataset: that split's frames, each with its own camera (default every stored frame).
    ``weights``: blendshapes: ``[T,K]`` (``.npy``, ``.json`` or an array; default a talking sequence of
    ``frames`` frames at ``fps``). ``fps``: glTF sampling and playback rate. ``seconds``, ``start``: glTF:
    how long (default the clip) from when. ``frames``: keep at most N frames. ``model_dir``: motion: the
    SMPL/FLAME model files. ``align``: motion: "pose", "translation" or "none" (``animation.motion.reenact``).
    """

    kind: str
    file: str | Path | Any = None
    clip: str | None = None
    split: str | None = None
    weights: str | Path | Any = None
    fps: float = 25.0
    seconds: float | None = None
    start: float = 0.0
    frames: int | None = None
    model_dir: str | Path | None = None
    align: str = "pose"

    def __post_init__(self) -> None:
        k = self.kind
        if k not in ANIMATION_KINDS:
            raise MeshsplatError(f"animation kind: expected one of {', '.join(ANIMATION_KINDS)}, got {k!r}")
        if k in _NEEDS_FILE and self.file is None:
            raise MeshsplatError(f"--animation {k} needs a FILE")
        if k == "dataset" and self.file is not None:
            raise MeshsplatError("--animation dataset takes no FILE (the capture is the run's, or --dataset PATH)")
        if not (isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0):
            raise MeshsplatError(f"fps: expected > 0, got {self.fps}")
        if self.frames is not None and self.frames < 1:
            raise MeshsplatError(f"frames: expected >= 1, got {self.frames}")
        if self.seconds is not None and not self.seconds >= 0:
            raise MeshsplatError(f"seconds: expected >= 0, got {self.seconds}")
        for name, given, kinds in (
            ("clip", self.clip, ("gltf",)),
            ("split", self.split, ("dataset",)),
            ("weights", self.weights, ("blendshapes",)),
            ("seconds", self.seconds, ("gltf",)),
            ("model_dir", self.model_dir, ("motion",)),
        ):
            if given is not None and k not in kinds:
                raise MeshsplatError(f"{name} applies to --animation {' / '.join(kinds)}, not to {k}")

    def describe(self) -> str:
        """``"gltf walk.glb (clip Walk)"``: the source in the CLI's words."""
        what = f"{self.kind} {self.file}" if isinstance(self.file, (str, Path)) else self.kind
        extra = ", ".join(f"{k} {v}" for k, v in (("clip", self.clip), ("split", self.split)) if v)
        return f"{what} ({extra})" if extra else what


@dataclass
class Animation:
    """A loaded animation: ``frames`` (each ``[V,3]`` on the avatar's canonical mesh) or, loaded ``live``, the
    ``driver`` itself (glTF rig or blend-shape model on that mesh, for the player page to evaluate);
    ``cameras``: each frame's own camera (a dataset split), else None."""

    source: AnimationSource
    frames: list[torch.Tensor] | None = None
    driver: GltfDriver | BlendshapeDriver | None = None
    cameras: list[Camera] | None = None

    @property
    def fps(self) -> float:
        return float(self.source.fps)

    def vertex_frames(self) -> list[torch.Tensor]:
        """The frames; a live driver sampled at ``fps`` (glTF: its clip, blend shapes: its sequence)."""
        if self.frames is not None:
            return self.frames
        drv = self.driver
        if isinstance(drv, BlendshapeDriver):
            return [drv.vertices(i) for i in range(drv.num_frames)]
        assert drv is not None  # an Animation holds frames or a driver
        t0, _ = drv.time_range()
        n = max(1, math.floor(drv.duration() * self.fps + 1e-6) + 1)
        return [drv.vertices_at(t0 + i / self.fps) for i in range(min(n, MAX_ANIMATION_FRAMES))]


def load_animation(
    source: AnimationSource,
    avatar: Avatar | TriMesh,
    *,
    dataset: AvatarDataset | None = None,
    source_map: SourceMap | None = None,
    live: bool = False,
    check: Callable[[int], None] | None = None,
) -> Animation:
    """Frames (or, with ``live``, the driver of a gltf / blendshapes source) of ``source`` on the canonical
    mesh of ``avatar`` (an ``Avatar`` or its ``TriMesh``).

    ``dataset``: the avatar's capture (``run.open_dataset()``), needed by the dataset and motion kinds.
    ``source_map``: the run's or dataset's (``run.source_map()``), so that the asset the avatar was
    synthesized from drives it whatever was done to its driving mesh (:mod:`meshsplat.animation.avatar_match`).
    Before any frame is posed, more than ``MAX_ANIMATION_FRAMES`` frames are refused and ``check(n)`` runs
    (the command line's memory estimate), so a huge motion is refused before it is allocated.
    """
    if not isinstance(source, AnimationSource):
        raise MeshsplatError(f"source: expected an AnimationSource, got {type(source).__name__}")
    mesh = avatar.mesh if isinstance(avatar, Avatar) else avatar
    kind, n = source.kind, source.frames
    if kind == "gltf":
        drv, to_world = gltf_for_mesh(mesh, source.file, source.clip, source.fps, source_map)
        if live:
            if to_world is not None:
                raise MeshsplatError(
                    f"{source.file}: the avatar was synthesized from this asset turned to +y up; the live page "
                    "plays the asset in its own axes: use --bake (vertex frames) instead"
                )
            return Animation(source, driver=drv)
        frames = _sample_gltf(drv, source, check)
        if to_world is not None:
            frames = [to_world(v) for v in frames]
        frames = check_frames(frames[:n], mesh.num_vertices, "glTF animation")
    elif kind == "blendshapes":
        bs = blendshapes_for_mesh(mesh, None if _is_ict(source.file) else source.file, source_map)
        if source.weights is not None:
            weights = read_weights(source.weights, bs.names)[:n]
            _before_posing(len(weights), "blend-shape weights", "give fewer rows or --frames N", check)
            bs.set_sequence(weights)
        else:
            _before_posing(TALKING_FRAMES if n is None else n, "blend-shape animation", "lower --frames", check)
            bs.talking_sequence(TALKING_FRAMES if n is None else n, source.fps)
        if live:
            return Animation(source, driver=bs)
        frames = check_frames(
            [bs.vertices(i) for i in range(bs.num_frames)], mesh.num_vertices, "blend-shape animation"
        )
    elif kind == "vertices":
        frames = sequence_for_mesh(mesh, source.file, source_map=source_map)[:n]
        _before_posing(len(frames), f"vertex frames {source.file}", "keep fewer frames (--frames N)", check)
    elif kind == "motion":
        frames = _motion_frames(mesh, _need(dataset, kind), source, check)
    else:
        ds = _need(dataset, kind)
        if ds.num_vertices != mesh.num_vertices:
            raise MeshsplatError(
                f"dataset meshes have {ds.num_vertices} vertices, the avatar's canonical mesh {mesh.num_vertices}"
            )
        if source.split is not None:
            ids = ds.split(source.split)[:n]
            if not ids:
                raise MeshsplatError(f"split {source.split!r} of {ds.root} is empty")
            _before_posing(len(ids), f"split {source.split!r} of {ds.root}", "keep fewer frames (--frames N)", check)
            frames = [ds.vertices(i) for i in ids]
            return Animation(source, frames=frames, cameras=[ds.frame_camera(i) for i in ids])
        meshes = ds.driver()
        count = meshes.num_frames if n is None else min(meshes.num_frames, n)
        _before_posing(count, f"dataset {ds.root}", "keep fewer frames (--frames N)", check)
        frames = check_frames([meshes.vertices(i) for i in range(count)], mesh.num_vertices, f"dataset {ds.root}")
    return Animation(source, frames=frames)


def _before_posing(n: int, what: str, advice: str, check: Callable[[int], None] | None) -> None:
    """The documented frame limit, then the caller's own check of ``n`` frames, before any is posed."""
    if n > MAX_ANIMATION_FRAMES:
        raise MeshsplatError(f"{what}: {n:,} frames; at most {MAX_ANIMATION_FRAMES:,} (see docs/limits.md); {advice}")
    if check is not None:
        check(n)


def _is_ict(file: Any) -> bool:
    return file is None or (isinstance(file, str) and file.lower() == "ict")


def _need(dataset: AvatarDataset | None, kind: str) -> AvatarDataset:
    if dataset is None:
        raise MeshsplatError(f"a {kind} animation needs the avatar's capture (dataset=run.open_dataset())")
    return dataset


def _sample_gltf(
    drv: GltfDriver, source: AnimationSource, check: Callable[[int], None] | None = None
) -> list[torch.Tensor]:
    """Frames of the driver's clip at ``fps`` for ``seconds`` (default the clip, end included) from ``start``."""
    fps, seconds = source.fps, source.seconds
    t0, _ = drv.time_range()
    length = drv.duration() if seconds is None else float(seconds)
    count = max(1, math.floor(length * fps + 1e-6) + (1 if seconds is None else 0))
    if count > MAX_ANIMATION_FRAMES:
        raise MeshsplatError(
            f"{length:g} s at {fps:g} fps is {count:,} frames; at most {MAX_ANIMATION_FRAMES:,} (lower --fps or --seconds)"
        )
    if source.frames is not None:
        count = min(count, source.frames)
    _before_posing(count, f"glTF animation {source.file}", "lower --fps or --seconds", check)
    return [drv.vertices_at(t0 + source.start + i / fps) for i in range(count)]


def _motion_frames(
    mesh: TriMesh, dataset: AvatarDataset, source: AnimationSource, check: Callable[[int], None] | None = None
) -> list[torch.Tensor]:
    """A body/head motion file driving an avatar trained on SMPL/SMPL-X/FLAME-tracked data.

    ``source.file``: an SMPL ``.npz`` (``poses [S,72]``, ``trans [S,3]``), an SMPL-X/AMASS ``.npz``, an
    IMavatar ``flame_params.json`` or a VHAP ``flame_param/`` folder (``animation.motion.load_motion``).
    Cross-identity reenactment: the avatar keeps its own shape (``betas``, ``static_offset`` from its
    capture) and takes the motion's pose and expression. A capture with per-frame meshes only (INSTA) on a
    standard topology (FLAME 5023, SMPL 6890, SMPL-X 10475 vertices) is posed by that model with its
    canonical mesh as the per-vertex offset.
    """
    info, subject = dataset.driver_info, dataset.driver_params
    if info is None or subject is None:
        kind = model_kind_for(mesh.num_vertices)
        if kind is None:
            raise MeshsplatError(
                f"--animation motion needs an avatar of a SMPL/SMPL-X/FLAME capture, but {dataset.root} "
                f"({dataset.format_name}) has no model parameters and its {mesh.num_vertices}-vertex mesh is no "
                "standard topology; use --animation gltf FILE or --animation vertices FILE"
            )
        info = {"type": kind}
    model = model_from_record(info, source.model_dir)
    if model.num_vertices != mesh.num_vertices:
        raise MeshsplatError(
            f"the {info['type']} model in {model.path} has {model.num_vertices} vertices but the "
            f"avatar's mesh {mesh.num_vertices}: not the model it was trained with"
        )
    if subject is None:
        with torch.no_grad():
            template = model.rest_vertices({}).cpu() / model.scale
        subject = {"static_offset": (dataset.canonical_vertices / model.scale - template).numpy()}
    betas = subject.get("betas")
    if betas is not None and np.ndim(betas) == 2:  # per frame (each split its own): the avatar's is the train one
        train = dataset.split("train") if "train" in dataset.split_names else [0]
        subject = {**subject, "betas": betas[int(dataset.frame_info(train[0])["mesh"])]}
    params = load_motion(source.file, model)
    if source.frames is not None:
        params = {
            k: (v[: source.frames] if getattr(v, "ndim", 1) == 2 and k not in ("betas", "static_offset") else v)
            for k, v in params.items()
        }
    n_frames = max(
        (len(v) for k, v in params.items() if getattr(v, "ndim", 1) == 2 and k not in ("betas", "static_offset")),
        default=1,
    )
    _before_posing(n_frames, f"motion {source.file}", "take the first N frames with --frames N", check)
    verts = ParametricDriver(model, reenact(params, subject, align=source.align)).all_vertices()
    return check_frames(list(verts), mesh.num_vertices, f"motion {source.file}")
