"""Ground-truth generator: renders an animated textured mesh into a dataset in the native format.

Rigs: ``monocular-turn`` (one fixed camera, subject turning about the vertical axis while it
animates, like PeopleSnapshot), ``orbit`` (camera circles a non-turning subject) and ``multiview``
(fixed ring of cameras). Splits: ``train``; ``test_frames`` (the last ``1 - train_fraction`` of the
clip); ``test_views`` (cameras never used for training); ``test_clip`` (other clips, novel poses).
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat.camera import intrinsics, look_at, orbit_position, yaw_matrix
from meshsplat.data.writer import DatasetWriter
from meshsplat.errors import MeshsplatError
from meshsplat.mesh.geometry import bbox_diagonal
from meshsplat.synth.body_source import perturb_pose
from meshsplat.synth.driving import cluster_decimate, taubin_smooth, weld
from meshsplat.synth.pbr import RENDERERS, PbrRenderer, PbrSettings
from meshsplat.synth.raster import lambert, rasterize_triangles, sample_texture, vertex_normals
from meshsplat.synth.sequence_source import up_rotation, with_up
from meshsplat.synth.sources import load_source

__all__ = ["synthesize", "SynthSpec", "synth_spec", "render_view", "clip_motion", "RIGS", "RENDERERS", "Shot"]

RIGS = ("monocular-turn", "orbit", "multiview")
_LIGHT = np.array([0.35, 0.75, 0.55]) / np.linalg.norm([0.35, 0.75, 0.55])
_POSE_CACHE_BYTES = 256 * 2**20  # posed meshes kept between planning and rendering; more are posed again


@dataclass
class Shot:
    """One frame to render: pose (clip, time, subject yaw) seen by a camera, in a split."""

    clip: str | None
    time: float
    yaw: float
    camera: str
    split: str


@dataclass(frozen=True)
class SynthSpec:
    """What a synthetic capture holds: its cameras, which frames of which clips, the image size, how the
    stored driving mesh differs from the rendered surface, and the renderer. Every field has a default, so
    ``SynthSpec(frames=8, resolution=64)`` names only what changes; ``synthesize(asset, out, spec)`` renders it.
    """

    rig: str = "monocular-turn"
    """Cameras (one of ``RIGS``): ``monocular-turn`` (one fixed camera, the subject turning about the vertical
    while it animates, like PeopleSnapshot), ``orbit`` (a camera circling a subject that does not turn) or
    ``multiview`` (a fixed ring of ``views`` cameras)."""
    frames: int = 60
    """Training time steps (per camera for ``multiview``), spread over the first ``train_fraction`` of the clip."""
    resolution: int = 256
    """Square image size in pixels (at least 8)."""
    clip: str | None = None
    """Training clip; None: the asset's preset, else the clip with the most motion (then the longest)."""
    test_clips: Sequence[str] | None = None
    """Clips of the novel-pose split ``test_clip``; None: the asset's preset, else up to two other moving clips."""
    train_fraction: float = 0.7
    """Leading part of the training clip used for training, in (0, 1]; the rest is the ``test_frames`` split."""
    test_frames: int | None = None
    """Frames per test clip and for the held-out end of the clip; None: ``max(2, frames // 4)``."""
    test_views: int = 2
    """Cameras never used for training (the ``test_views`` split)."""
    test_view_frames: int | None = None
    """Training poses each held-out camera sees; None: ``max(2, frames // 8)``."""
    views: int = 8
    """Cameras of the ``multiview`` ring (more than ``test_views``)."""
    turns: float = 1.0
    """``monocular-turn``: full turns of the subject over the training frames."""
    driver_smooth: int = 0
    """Taubin smoothing iterations applied to the stored driving mesh (not to the rendered surface)."""
    driver_decimate: float | None = None
    """Keep about this ratio of the driving mesh's vertices (vertex clustering); None or 1: all."""
    supersample: int | None = None
    """Anti-aliasing factor of images and masks (rasterizer only); None: 2 up to 384 px, else 1."""
    background: Sequence[float] = (0.0, 0.0, 0.0)
    """RGB in [0, 1] behind the subject."""
    fov_deg: float = 30.0
    """Field of view of every camera, in degrees."""
    model_dir: Path | str | None = None
    """Body/head models (``smpl``, ``smplx``, ``flame``): the folder of the model files; None:
    ``$MESHSPLAT_MODEL_DIR``. Their parameters are stored as the dataset's driver."""
    gender: str = "neutral"
    """Body models: ``neutral``, ``male`` or ``female``."""
    up: str | None = None
    """The asset's up axis, ``"y"`` or ``"z"``; None: the asset's own, else y. A z-up asset is turned into
    the y-up world."""
    renderer: str = "lambert"
    """``"lambert"`` (the fast rasterizer) or ``"pbr"`` (path traced with shadows and gloss,
    :mod:`meshsplat.synth.pbr`, needs the ``[pbr]`` extra; its samples per pixel antialias)."""
    pbr: PbrSettings | None = None
    """Settings of the ``pbr`` renderer; None: ``PbrSettings()``."""
    pose_noise: float = 0.0
    """Body/head models: the stored (tracked) parameters and driving meshes get every joint rotation turned
    by a random rotation of this many radians standard deviation per axis-angle component (0..1), while
    the images show the exact pose, so pose refinement has an error to fix."""
    seed: int = 0
    """Seed of the pose noise."""
    light_dir: Sequence[float] | None = None
    """World direction towards the light (the rasterizer's directional light, the path tracer's key light),
    normalised; None: the default ``(0.35, 0.75, 0.55)`` (front, above, to the right). Written in the
    dataset's meta as ``light_dir``."""
    splits: Sequence[str] | None = None
    """Render only the frames of these splits (same names, cameras, poses and per-frame sampler seeds as
    the full capture; e.g. held-out frames again with more samples per pixel, as low-noise references);
    None: all."""

    def __post_init__(self) -> None:
        if self.renderer not in RENDERERS:
            raise MeshsplatError(f"renderer: expected one of {', '.join(RENDERERS)}, got {self.renderer!r}")
        if self.frames < 1 or self.resolution < 8:
            raise MeshsplatError(f"frames >= 1 and resolution >= 8 required, got {self.frames}, {self.resolution}")
        if not 0.0 <= self.pose_noise <= 1.0:
            raise MeshsplatError(f"pose_noise: expected 0..1 radians, got {self.pose_noise}")
        resolved = {
            "pose_noise": float(self.pose_noise),
            "seed": int(self.seed),
            "splits": None if self.splits is None else [str(x) for x in self.splits],
            "light_dir": None if self.light_dir is None else _unit_light(self.light_dir),
        }
        for name, value in resolved.items():
            object.__setattr__(self, name, value)

    @property
    def light(self) -> np.ndarray:
        """The unit light direction ``[3]`` (``light_dir`` or the default)."""
        return _LIGHT if self.light_dir is None else np.asarray(self.light_dir, np.float64)

    @property
    def supersample_factor(self) -> int:
        """``supersample``, or its default for ``resolution``: 2 up to 384 px, else 1."""
        return int(self.supersample) if self.supersample else (2 if self.resolution <= 384 else 1)


def render_view(
    source: Any,
    verts: torch.Tensor,
    viewmat: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    weld_group: torch.Tensor | None = None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    supersample: int = 2,
    light_dir: ArrayLike = _LIGHT,
    ambient: float = 0.4,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render ``verts [V,3]`` (world) of ``source``: returns ``(rgb [H,W,3], alpha [H,W,1])`` in [0,1]."""
    s = int(supersample)
    R = torch.from_numpy(viewmat[:3, :3]).float()
    t = torch.from_numpy(viewmat[:3, 3]).float()
    Ks = torch.from_numpy(K).float().clone()
    Ks[:2] *= s
    vc = verts @ R.T + t
    faces = source.faces
    frags = rasterize_triangles(vc, faces, Ks, width * s, height * s)
    m = frags.mask
    fid = frags.face[m]
    bary = frags.bary[m]
    fv = faces[fid]

    def interp(attr):
        return (bary[..., None] * attr[fv]).sum(1)

    albedo = interp(source.vertex_colors)
    mat = source.face_material[fid]
    uv = None
    for mi, (base, tex) in enumerate(source.materials):
        sel = mat == mi
        if not bool(sel.any()):
            continue
        col = base.expand(int(sel.sum()), 3)
        if tex is not None:
            if uv is None:
                uv = interp(source.uvs)
            col = col * sample_texture(tex, uv[sel])
        albedo[sel] = albedo[sel] * col
    normals = vertex_normals(verts, faces, weld_group) @ R.T
    n = interp(normals)
    pos = interp(vc)
    light = torch.from_numpy(viewmat[:3, :3] @ np.asarray(light_dir, np.float64)).float()
    rgb_fg = lambert(albedo, n, pos, light, ambient=ambient, diffuse=1.0 - ambient)
    hs, ws = height * s, width * s
    rgb = torch.tensor(background, dtype=torch.float32).expand(hs, ws, 3).clone()
    rgb[m] = rgb_fg
    alpha = m.float()[..., None]
    if s > 1:
        rgb = rgb.view(height, s, width, s, 3).mean((1, 3))
        alpha = alpha.view(height, s, width, s, 1).mean((1, 3))
    return rgb, alpha


def _plan(
    rig: str,
    clips: dict,
    frames: int,
    test_frames: int,
    test_view_frames: int,
    views: int,
    n_test_views: int,
    turns: float,
) -> tuple[list[Shot], dict]:
    """Shots and camera placements (azimuth, elevation) per camera id."""
    train_clip, (t0, t1), t_split = clips["train"]
    tests = clips["tests"]
    shots: list[Shot] = []
    cams: dict[str, tuple[float, float]] = {}
    train_times = [t0 + (t_split - t0) * i / frames for i in range(frames)]
    test_times = (
        [t_split + (t1 - t_split) * (j + 0.5) / test_frames for j in range(test_frames)] if t1 > t_split else []
    )
    view_elev = [math.radians(35), math.radians(-12), math.radians(60), math.radians(20)]
    pick: np.ndarray | list[int] = (
        np.linspace(0, frames - 1, test_view_frames).round().astype(int) if test_view_frames else []
    )
    if rig == "monocular-turn":
        cams["0"] = (0.0, math.radians(5))

        def yaw(k: float, n: int) -> float:
            return 2 * math.pi * turns * k / n

        shots += [Shot(train_clip, tt, yaw(i, frames), "0", "train") for i, tt in enumerate(train_times)]
        shots += [
            Shot(train_clip, tt, yaw(j + 0.5, len(test_times)), "0", "test_frames") for j, tt in enumerate(test_times)
        ]
        for v in range(n_test_views):
            cid = f"view{v + 1}"
            cams[cid] = (math.radians(25) * (v + 1), view_elev[v % len(view_elev)])
            shots += [Shot(train_clip, train_times[i], yaw(i, frames), cid, "test_views") for i in pick]
        for c, (a, b) in tests:
            shots += [
                Shot(c, a + (b - a) * (j + 0.5) / test_frames, yaw(j + 0.25, test_frames), "0", "test_clip")
                for j in range(test_frames)
            ]
    elif rig == "orbit":
        for i, tt in enumerate(train_times):
            cams[f"orbit{i:03d}"] = (2 * math.pi * i / frames, math.radians(8))
            shots.append(Shot(train_clip, tt, 0.0, f"orbit{i:03d}", "train"))
        for j, tt in enumerate(test_times):
            cams[f"testf{j:03d}"] = (2 * math.pi * (j + 0.5) / len(test_times), math.radians(8))
            shots.append(Shot(train_clip, tt, 0.0, f"testf{j:03d}", "test_frames"))
        for v in range(n_test_views):
            for k, i in enumerate(pick):
                cid = f"view{v + 1}_{k:03d}"
                cams[cid] = (2 * math.pi * (i + 0.5) / frames, view_elev[v % len(view_elev)])
                shots.append(Shot(train_clip, train_times[i], 0.0, cid, "test_views"))
        for c, (a, b) in tests:
            for j in range(test_frames):
                cid = f"clip_{c}_{j:03d}"
                cams[cid] = (2 * math.pi * (j + 0.25) / test_frames, math.radians(8))
                shots.append(Shot(c, a + (b - a) * (j + 0.5) / test_frames, 0.0, cid, "test_clip"))
    elif rig == "multiview":
        if views < 2 or n_test_views >= views:
            raise MeshsplatError(f"views: multiview needs views >= 2 and more views than test views, got {views}")
        held = (
            set(np.linspace(0, views - 1, n_test_views + 2).round().astype(int)[1:-1].tolist())
            if n_test_views
            else set()
        )
        for c in range(views):
            cams[f"cam{c:02d}"] = (2 * math.pi * c / views, math.radians(5 if c % 2 == 0 else 25))
        for c in range(views):
            cid = f"cam{c:02d}"
            if c in held:
                shots += [Shot(train_clip, train_times[i], 0.0, cid, "test_views") for i in pick]
                continue
            shots += [Shot(train_clip, tt, 0.0, cid, "train") for tt in train_times]
            shots += [Shot(train_clip, tt, 0.0, cid, "test_frames") for tt in test_times]
            shots += [
                Shot(c_, a + (b - a) * (j + 0.5) / test_frames, 0.0, cid, "test_clip")
                for c_, (a, b) in tests
                for j in range(test_frames)
            ]
    else:
        raise MeshsplatError(f"rig: expected one of {RIGS}, got {rig!r}")
    return shots, cams


def _driving_mesh(source, smooth: int, decimate: float | None):
    """Weld seams, then optionally Taubin-smooth and/or decimate; returns (driving source, render weld
    group, source map: ``source_index [Vd]`` (asset vertex lending each driving vertex its motion) and
    ``exact`` (driving rest == asset rest at those vertices))."""
    rest = source.rest().numpy().astype(np.float64)
    faces = source.faces.numpy()
    clip = source.clips[0]
    a, b = source.time_range(clip)
    probes = [rest] + [source.pose(clip, a + (b - a) * f).numpy().astype(np.float64) for f in (0.3, 0.7)]
    tol = 1e-6 * bbox_diagonal(rest)
    group, rep, wfaces = weld(probes, faces, tol)
    wrest = rest[rep]
    if decimate is not None and decimate < 1.0:
        wrest, wfaces, near = cluster_decimate(wrest, wfaces, decimate)
        rep = rep[near]
    if smooth > 0:
        wrest = taubin_smooth(wrest, wfaces, smooth)
    changed = smooth > 0 or (decimate is not None and decimate < 1.0)
    drive = source.derive(rep, wfaces, wrest if changed else None)
    smap = {"source_index": np.asarray(rep, np.int64), "exact": not changed}
    return drive, torch.from_numpy(np.where(group >= 0, group, np.arange(len(group)) + group.max() + 1)), smap


def _model_mesh(source, driver_smooth: int, driver_decimate: float | None):
    """A body/head model source drives itself (its parameters must reproduce the stored meshes);
    coincident vertices are welded only for the rendered normals."""
    if driver_smooth or (driver_decimate is not None and driver_decimate < 1.0):
        source.derive(None, None)  # raises: not available for model sources
    rest = source.rest().numpy().astype(np.float64)
    tol = 1e-6 * bbox_diagonal(rest)
    group, _, _ = weld([rest], source.faces.numpy(), tol)
    weld_group = torch.from_numpy(np.where(group >= 0, group, np.arange(len(group)) + group.max() + 1))
    smap = {"source_index": np.arange(rest.shape[0], dtype=np.int64), "exact": True}
    return source, weld_group, smap


def clip_motion(source: Any, clip: str | None, samples: int = 6) -> float:
    """Mean per-vertex standard deviation of position over ``samples`` times of ``clip`` (asset units)."""
    a, b = source.time_range(clip)
    if b <= a:
        return 0.0
    poses = torch.stack([source.pose(clip, a + (b - a) * k / (samples - 1)) for k in range(samples)]).double()
    return float(poses.std(0).norm(dim=-1).mean())


def _default_clips(source, clip, test_clips, train_fraction, say=None):
    """Training clip and novel-pose clips: the asset's own presets, else the clip with the most motion
    (then the longest) for training and up to two other moving clips for the test."""
    names = [c for c in source.clips if c is not None]
    if clip is not None and clip not in names:
        raise MeshsplatError(f"clip: {clip!r} not in {names}")
    for c in test_clips or []:
        if c not in names:
            raise MeshsplatError(f"test clip {c!r} not in {names}")
    preset_train = getattr(source, "default_train_clip", None)
    preset_tests = getattr(source, "default_test_clips", None)
    if preset_train is None and preset_tests:  # a source naming its test clips trains on its first other clip
        preset_train = next((c for c in names if c not in preset_tests), None)
    scores = None
    if (clip is None and preset_train is None and len(names) > 1) or (test_clips is None and preset_tests is None):
        scores = {c: (clip_motion(source, c), float(np.subtract(*source.time_range(c)[::-1]))) for c in names}
    if clip is None:
        if preset_train in names:
            clip, why = preset_train, "the asset's preset"
        elif len(names) <= 1:
            clip, why = (names[0] if names else None), "its only clip"
        else:
            clip = max(names, key=lambda c: scores[c])
            why = f"most motion of {len(names)} clips ({scores[clip][0]:.3g} mean vertex spread)"
        if say:
            say(f"training clip: {clip} ({why}; --clip to choose)")
    if test_clips is None:
        if preset_tests is not None:
            test_clips = [c for c in preset_tests if c in names and c != clip]
        else:
            best = max((scores[c][0] for c in names), default=0.0)
            moving = sorted(
                (c for c in names if c != clip and scores[c][0] > 1e-6 * max(best, 1e-30)),
                key=lambda c: scores[c],
                reverse=True,
            )
            test_clips = moving[:2]
        if say:
            chosen = ", ".join(test_clips) if test_clips else "none (the asset has no other moving clip)"
            say(f"novel-pose clips: {chosen} (--test-clips to choose)")
    t0, t1 = source.time_range(clip)
    if not 0 < train_fraction <= 1:
        raise MeshsplatError(f"train_fraction: expected in (0, 1], got {train_fraction}")
    return {
        "train": (clip, (t0, t1), t0 + (t1 - t0) * train_fraction),
        "tests": [(c, source.time_range(c)) for c in test_clips],
    }


def synthesize(
    asset: Path | str,
    out_dir: Path | str,
    spec: SynthSpec | None = None,
    *,
    overwrite: bool = False,
    progress: bool = False,
    threads: int | None = 1,
    say: Callable[[str], object] | None = None,
    **fields: Any,
) -> Path:
    """Render ``asset`` (see :func:`meshsplat.synth.sources.load_source`) into a dataset at ``out_dir``, as
    ``spec`` (a :class:`SynthSpec`; default ``SynthSpec()``) says; keyword ``fields`` of ``SynthSpec``
    override it (``synthesize(a, out, frames=8)`` is ``synthesize(a, out, SynthSpec(frames=8))``).

    ``overwrite``: replace a dataset at ``out_dir``. ``progress``: print every 20 frames. ``threads``: torch
    CPU threads while rendering (1 is fastest for these small kernels on a busy machine; None = keep).
    ``say``: callable told the choices made (default ``print`` when ``progress``). The dataset keeps
    ``source_map.npz`` (asset vertex of each driving vertex, the asset's rest mesh, the up rotation) so the
    asset's own animations drive the avatar later. Returns the dataset folder.
    """
    spec = synth_spec(spec, **fields)
    old_threads = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        return _generate(
            asset,
            Path(out_dir),
            spec,
            overwrite,
            progress,
            threads,
            say if say is not None else (print if progress else None),
        )
    finally:
        torch.set_num_threads(old_threads)


def _unit_light(d: Sequence[float]) -> list[float]:
    v = np.asarray(d, np.float64)
    n = float(np.linalg.norm(v)) if v.shape == (3,) and np.isfinite(v).all() else 0.0
    if n < 1e-9:
        raise MeshsplatError(f"light_dir: expected a non-zero direction [3], got {list(np.ravel(v))}")
    return (v / n).tolist()


def synth_spec(spec: SynthSpec | None = None, **fields: Any) -> SynthSpec:
    """``spec`` (default ``SynthSpec()``) with ``fields`` replaced; an unknown field is a ``TypeError``."""
    unknown = sorted(set(fields) - {f.name for f in dataclasses.fields(SynthSpec)})
    if unknown:
        raise TypeError(f"unexpected synthesis option(s) {', '.join(unknown)}: see meshsplat.synth.SynthSpec")
    return dataclasses.replace(spec or SynthSpec(), **fields)


def _generate(
    asset: Path | str,
    out: Path,
    spec: SynthSpec,
    overwrite: bool,
    progress: bool,
    threads: int | None,
    say: Callable[[str], object] | None,
) -> Path:
    """The capture in six steps: open the asset, plan the shots, derive the driving mesh, frame the
    cameras, write the header (cameras, source map, meta), then render and write every shot."""
    t_start = _time.perf_counter()
    src = _open_asset(asset, spec, say)
    clips, shots, cams = _plan_capture(src, spec, say)
    drive, weld_group, smap = _driving_for(src, spec)
    poses = _Poses(src.source, drive, shots)
    framing = _frame(poses, cams, spec)
    tracer, render_record = _renderer(src, weld_group, framing, spec, threads)
    meta = _meta(asset, src, drive, clips, spec, render_record)
    writer = _open_writer(out, overwrite, drive, smap, src, cams, framing, spec, meta)
    written, mesh_params = _render_shots(writer, shots, src, poses, framing, weld_group, tracer, spec, progress)
    return _close(writer, written, mesh_params, src, spec, t_start)


@dataclass
class _Asset:
    """The asset as rendered: ``source`` (in the +y-up world), ``is_model`` (a body/head model, whose
    parameters become the dataset's driver), its up axis ``up`` and ``R_up [3,3]`` (asset -> world),
    ``rest [V,3]`` float64 and ``size`` (the rest mesh's bounding-box diagonal)."""

    source: Any
    is_model: bool
    up: str
    R_up: np.ndarray
    rest: np.ndarray
    size: float


def _open_asset(asset: Path | str, spec: SynthSpec, say: Callable[[str], object] | None) -> _Asset:
    """Load the asset, check the options that depend on its kind, turn a z-up asset y-up."""
    source = load_source(asset, model_dir=spec.model_dir, gender=spec.gender)
    is_model = hasattr(source, "placed_params")
    if spec.pose_noise and not is_model:
        raise MeshsplatError(
            "pose noise applies to body/head models (smpl, smplx, flame); for other assets use "
            "--driver-smooth / --driver-decimate"
        )
    if is_model and spec.up not in (None, "y"):
        raise MeshsplatError(f"up: body/head models are y-up; --up {spec.up} applies to glTF and mesh-sequence assets")
    source, up_used, up_how = with_up(source, spec.up)
    rest = source.rest().numpy().astype(np.float64)
    size = bbox_diagonal(rest)
    if say:
        say(f"up axis: {up_used} ({up_how}); mesh size {size:.4g} asset units (bounding-box diagonal)")
    return _Asset(source, is_model, up_used, up_rotation(up_used), rest, size)


def _plan_capture(src: _Asset, spec: SynthSpec, say: Callable[[str], object] | None) -> tuple[dict, list[Shot], dict]:
    """``(clips, shots, cameras)``: the training and novel-pose clips, every frame to render, and each
    camera's ``(azimuth, elevation)``; ``spec.splits`` must name some of the planned splits."""
    clips = _default_clips(src.source, spec.clip, spec.test_clips, spec.train_fraction, say)
    n_test = spec.test_frames if spec.test_frames is not None else max(2, spec.frames // 4)
    n_tv = spec.test_view_frames if spec.test_view_frames is not None else max(2, spec.frames // 8)
    shots, cams = _plan(
        spec.rig, clips, spec.frames, n_test, min(n_tv, spec.frames), spec.views, spec.test_views, spec.turns
    )
    planned = sorted({s.split for s in shots})
    splits = spec.splits
    if splits is not None and (not splits or set(splits) - set(planned)):
        raise MeshsplatError(f"splits: expected some of {planned} (this capture's splits), got {list(splits)}")
    return clips, shots, cams


def _driving_for(src: _Asset, spec: SynthSpec) -> tuple[Any, torch.Tensor, dict]:
    """``(driving source, render weld group, source map)``: a model drives itself, an asset through its
    welded (and optionally smoothed or decimated) mesh."""
    make = _model_mesh if src.is_model else _driving_mesh
    return make(src.source, int(spec.driver_smooth), spec.driver_decimate)


class _Poses:
    """The rendered and driving vertices of each ``(clip, rounded time)`` the shots need (``times``, in shot
    order), each posed once while all of them fit in ``_POSE_CACHE_BYTES``; a longer capture keeps the latest
    only (the cameras of one time step share it), so memory stays bounded in the frame count."""

    def __init__(self, source: Any, drive: Any, shots: list[Shot]) -> None:
        self.source, self.drive = source, drive
        self.times: dict[tuple, float] = {}
        for s in shots:
            self.times.setdefault((s.clip, round(s.time, 9)), s.time)
        per_pose = 12 * (int(source.rest().shape[0]) + int(drive.rest().shape[0]))
        self._keep = len(self.times) * per_pose <= _POSE_CACHE_BYTES
        self._cache: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def __call__(self, key: tuple) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rendered [V,3], driving [Vd,3])`` vertices at ``key = (clip, round(time, 9))``."""
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        both = (self.source.pose(key[0], self.times[key]), self.drive.pose(key[0], self.times[key]))
        if not self._keep:
            self._cache.clear()
        self._cache[key] = both
        return both


@dataclass
class _Framing:
    """Where the cameras stand: the subject turns about the vertical through ``pivot [3]`` (the box centre's
    x, z at y = 0); the cameras look at ``center [3]`` from far enough to see every pose (``extent``: the
    box diagonal over all poses), with intrinsics ``K [3,3]`` and a world->camera ``viewmats`` entry per id."""

    pivot: np.ndarray
    center: np.ndarray
    extent: float
    K: np.ndarray
    viewmats: dict[str, np.ndarray]


def _frame(poses: _Poses, cams: dict[str, tuple[float, float]], spec: SynthSpec) -> _Framing:
    """Frame every pose of the capture: the box over all rendered poses, the radius about the turning
    axis, and a distance at which the ``fov_deg`` view holds both."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for key in poses.times:
        v = poses(key)[0].numpy().astype(np.float64)
        lo, hi = np.minimum(lo, v.min(0)), np.maximum(hi, v.max(0))
    pivot = np.array([(lo[0] + hi[0]) / 2, 0.0, (lo[2] + hi[2]) / 2])
    center = np.array([pivot[0], (lo[1] + hi[1]) / 2, pivot[2]])
    half_h = (hi[1] - lo[1]) / 2
    radius = max(
        float(np.linalg.norm((poses(key)[0].numpy().astype(np.float64) - pivot)[:, [0, 2]], axis=1).max())
        for key in poses.times
    )
    half_fov = math.radians(spec.fov_deg) / 2
    distance = 1.1 * max(half_h, radius) / math.tan(half_fov) + 0.5 * radius
    K = intrinsics(spec.resolution, spec.resolution, spec.fov_deg)
    viewmats = {cid: look_at(orbit_position(center, distance, az, el), center) for cid, (az, el) in cams.items()}
    return _Framing(pivot, center, float(np.linalg.norm(hi - lo)), K, viewmats)


def _renderer(
    src: _Asset, weld_group: torch.Tensor, framing: _Framing, spec: SynthSpec, threads: int | None
) -> tuple[PbrRenderer | None, dict]:
    """``(path tracer or None for the rasterizer, the renderer's record for the dataset's meta)``."""
    if spec.renderer == "pbr":
        settings = spec.pbr or PbrSettings()
        tracer = PbrRenderer(src.source, weld_group, framing.center, framing.extent, spec.light, settings, threads)
        return tracer, settings.record()
    return None, {"name": "lambert", "ambient": 0.4, "supersample": spec.supersample_factor}


def _meta(asset: Path | str, src: _Asset, drive: Any, clips: dict, spec: SynthSpec, render_record: dict) -> dict:
    """The generator's record in the dataset's ``meta`` (what was rendered, and how)."""
    return {
        "generator": "meshsplat.synth",
        "asset": str(asset),
        "rig": spec.rig,
        "resolution": spec.resolution,
        "train_clip": clips["train"][0],
        "train_time_range": [clips["train"][1][0], clips["train"][2]],
        "test_clips": [c for c, _ in clips["tests"]],
        "driver_smooth": int(spec.driver_smooth),
        "driver_decimate": spec.driver_decimate,
        "render_vertices": int(src.source.rest().shape[0]),
        "driver_vertices": int(drive.rest().shape[0]),
        "pose_noise": spec.pose_noise,
        "seed": spec.seed,
        "light_dir": spec.light.tolist(),
        "renderer": render_record,
        "fov_deg": spec.fov_deg,
        "background": list(spec.background),
        "up": [0, 1, 0],
        "asset_up": src.up,
        "mesh_size": src.size,
        "attribution": getattr(src.source, "attribution", ""),
    }


def _open_writer(
    out: Path,
    overwrite: bool,
    drive: Any,
    smap: dict,
    src: _Asset,
    cams: dict[str, tuple[float, float]],
    framing: _Framing,
    spec: SynthSpec,
    meta: dict,
) -> DatasetWriter:
    """The dataset's header: the driving mesh at rest, the meta, the source map and every camera."""
    writer = DatasetWriter(
        out, drive.rest(), drive.faces, overwrite=overwrite, meta=meta, backdrop=list(spec.background)
    )
    writer.set_source_map(
        smap["source_index"],
        src.rest,
        src.source.faces,
        src.R_up,
        exact=smap["exact"],
        smooth=int(spec.driver_smooth),
        decimate=spec.driver_decimate,
    )
    for cid in cams:
        writer.add_camera(cid, framing.K, framing.viewmats[cid], spec.resolution, spec.resolution)
    return writer


def _place(v: torch.Tensor, yaw: float, pivot: np.ndarray) -> torch.Tensor:
    """Vertices ``v [V,3]`` turned by ``yaw`` about the vertical through ``pivot``."""
    if yaw == 0.0:
        return v
    Ry = torch.from_numpy(yaw_matrix(yaw)).float()
    p = torch.from_numpy(pivot).float()
    return (v - p) @ Ry.T + p


def _render_shots(
    writer: DatasetWriter,
    shots: list[Shot],
    src: _Asset,
    poses: _Poses,
    framing: _Framing,
    weld_group: torch.Tensor,
    tracer: PbrRenderer | None,
    spec: SynthSpec,
    progress: bool,
) -> tuple[dict[str, list[int]], list[dict]]:
    """Write each shot's driving mesh (once per pose; a model's tracked parameters, with ``pose_noise`` the
    perturbed ones) and, in ``spec.splits``, its image and mask. Returns ``(frame indices per split, the
    model parameters of each stored mesh)``."""
    rng = np.random.default_rng(spec.seed)
    source, pivot, res = src.source, framing.pivot, spec.resolution
    written: dict[str, list[int]] = {}
    mesh_ids: dict[tuple, int] = {}
    mesh_params: list[dict] = []
    for k, s in enumerate(shots):
        rv, dv = poses((s.clip, round(s.time, 9)))
        mkey = (s.clip, round(s.time, 9), round(s.yaw, 9))
        if mkey not in mesh_ids:
            if src.is_model and spec.pose_noise > 0:
                tracked = perturb_pose(source.placed_params(s.clip, s.time, s.yaw, pivot), spec.pose_noise, rng)
                mesh_ids[mkey] = writer.add_mesh(source.vertices_of(tracked))
                mesh_params.append(tracked)
            else:
                mesh_ids[mkey] = writer.add_mesh(_place(dv, s.yaw, pivot))
                if src.is_model:
                    mesh_params.append(source.placed_params(s.clip, s.time, s.yaw, pivot))
        if spec.splits is not None and s.split not in spec.splits:
            continue  # not rendered; poses and seeds above stay those of the full capture
        viewmat = framing.viewmats[s.camera]
        if tracer is not None:
            rgb, alpha = tracer.render(_place(rv, s.yaw, pivot), viewmat, framing.K, res, res, frame=k)
            rgb = (rgb + (1 - alpha) * torch.tensor(spec.background, dtype=torch.float32)).clamp(0, 1)
        else:
            rgb, alpha = render_view(
                source,
                _place(rv, s.yaw, pivot),
                viewmat,
                framing.K,
                res,
                res,
                weld_group,
                spec.background,
                spec.supersample_factor,
                light_dir=spec.light,
            )
        if float(alpha.max()) == 0.0:
            raise MeshsplatError(f"shot {k} ({s.split}, camera {s.camera}): subject not visible")
        idx = writer.add_frame(
            rgb,
            s.camera,
            mesh=mesh_ids[mkey],
            mask=alpha,
            name=f"{k:06d}",
            clip=s.clip,
            time=s.time,
            extra={"yaw": s.yaw, "split": s.split},
        )
        written.setdefault(s.split, []).append(idx)
        if progress and (k + 1) % 20 == 0:
            print(f"  rendered {k + 1}/{len(shots)} frames", flush=True)
    return written, mesh_params


def _close(
    writer: DatasetWriter,
    written: dict[str, list[int]],
    mesh_params: list[dict],
    src: _Asset,
    spec: SynthSpec,
    t_start: float,
) -> Path:
    """Splits, a model's driver parameters and the timing into the dataset; close it and return its folder."""
    if spec.splits is not None:
        written.setdefault("train", [])  # not rendered: an empty split, not "every frame" (the writer's default)
    for name, indices in written.items():
        writer.set_split(name, indices)
    if src.is_model:
        source = src.source
        per_frame = {k: np.stack([p[k] for p in mesh_params]) for k in mesh_params[0]}
        writer.set_driver({**source.driver_record(), "per_frame": sorted(per_frame)}, {**source.shared, **per_frame})
        writer.meta["model"] = {"type": source.kind, "gender": source.model.gender, "fps": source.fps}
    writer.meta["seconds"] = round(_time.perf_counter() - t_start, 2)
    rendered = sum(len(v) for v in written.values())  # with ``splits``, only those frames were rendered
    writer.meta["frames_rendered"] = rendered
    writer.meta["seconds_per_frame"] = round(writer.meta["seconds"] / max(rendered, 1), 3)
    return writer.close()
