"""Render an avatar through any mesh animation to PNG frames and an MP4.

    frames = gltf_animation(avatar, "walk.glb", clip="Walk", fps=25)        # list of [V,3]
    cams = orbit_cameras(frames, 512, 512, orbit_deg=360)                   # auto-framed
    render_animation(avatar, frames, cams, "out/", fps=25)                  # out/frames/*.png, out/animation.mp4

Drivers whose mesh is not the avatar's canonical mesh vertex for vertex (e.g. the raw glTF of a
synthetic dataset whose driving mesh had seams welded) are mapped by rest position (coincident
vertices told apart by their triangles): every canonical vertex must coincide (within ``1e-5`` of
the mesh size) with a driver vertex, or a clear error says so. A run synthesized from an asset keeps
``source_map.npz`` (:mod:`meshsplat.data.source_map`; a run's is found by
``meshsplat.run_folder.LoadedRun.source_map``): with it the asset's clips and vertex sequences in the asset's own order drive the avatar even when its driving
mesh was welded, smoothed or decimated.
Cameras follow the project convention (world->camera ``viewmat`` in OpenCV axes, world +y up).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat._typing import ArrayLike
from meshsplat.camera import Camera
from meshsplat.data.dataset import AvatarDataset
from meshsplat.data.source_map import SourceMap, rest_mismatch
from meshsplat.drivers import BlendshapeDriver, GltfDriver
from meshsplat.drivers.body_models import BodyModel, ParametricDriver
from meshsplat.drivers.mesh_sequence import read_mesh_sequence
from meshsplat.drivers.motion import load_motion, reenact
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.io.arrays import read_npy
from meshsplat.io.video import to_uint8, write_png_frames, write_video
from meshsplat.paths import resolve_input
from meshsplat.render.background import background_color

__all__ = [
    "AnimationResult",
    "render_animation",
    "motion_animation",
    "match_vertices",
    "avatar_gltf_driver",
    "gltf_animation",
    "blendshape_animation",
    "sequence_animation",
    "dataset_animation",
]


@dataclass
class AnimationResult:
    """``mp4`` path (None when it could not be written, see ``error``), ``pngs``, timing."""

    mp4: Path | None
    pngs: list[Path] = field(default_factory=list)
    num_frames: int = 0
    render_ms_mean: float = 0.0
    error: str | None = None


# ---------------------------------------------------------------- drivers -> vertex frames
def match_vertices(
    driver_rest: torch.Tensor,
    canonical: torch.Tensor,
    rel_tol: float = 1e-5,
    driver_faces: torch.Tensor | None = None,
    canonical_faces: torch.Tensor | None = None,
) -> torch.Tensor:
    """Index ``[V]`` of the driver vertex that is each canonical vertex, matched by rest position.

    ``driver_rest [Vd,3]``, ``canonical [V,3]``; a match lies within ``rel_tol`` times the canonical
    bounding-box diagonal. Where several driver vertices coincide (seams, parts touching at rest),
    the faces (``driver_faces [Fd,3]``, ``canonical_faces [F,3]``) pick the one whose triangles
    connect to the candidates of the canonical triangle's other corners. Raises when a canonical
    vertex has no candidate.
    """
    from scipy.spatial import cKDTree

    check_tensor("driver_rest", driver_rest, "Vd,3", dtype="float", finite=True)
    check_tensor("canonical", canonical, "V,3", dtype="float", finite=True)
    c = canonical.detach().double().cpu().numpy()
    d = driver_rest.detach().double().cpu().numpy()
    tol = max(rel_tol * float(np.linalg.norm(c.max(0) - c.min(0))), 1e-12)
    dist, nearest = cKDTree(d).query(c, k=1)
    bad = int((dist > tol).sum())
    if bad:
        raise MeshsplatError(
            f"driver mesh has {d.shape[0]} vertices, the avatar's canonical mesh {c.shape[0]}, "
            f"and {bad} canonical vertices match no driver vertex at rest (largest gap {float(dist.max()):.3g}, "
            f"tolerance {tol:.3g}): this animation does not drive the avatar's mesh"
        )
    idx = np.asarray(nearest, np.int64)
    cands = cKDTree(d).query_ball_point(c, r=tol)
    ambiguous = [i for i, cs in enumerate(cands) if len(cs) > 1]
    if ambiguous and driver_faces is not None and canonical_faces is not None:
        dfaces = driver_faces.detach().cpu().long().numpy()
        cfaces = canonical_faces.detach().cpu().long().numpy()
        d_of: list[list[np.ndarray]] = [[] for _ in range(d.shape[0])]  # driver vertex -> its faces
        for f in dfaces:
            for j in f:
                d_of[j].append(f)
        c_of: list[list[np.ndarray]] = [[] for _ in range(c.shape[0])]
        for f in cfaces:
            for i in f:
                c_of[i].append(f)
        sets = [set(cs) for cs in cands]
        for i in ambiguous:

            def score(j: int, i: int = i) -> int:
                hit = 0
                for f in c_of[i]:
                    p, q = [k for k in f if k != i][:2]
                    for g in d_of[j]:
                        o = [k for k in g if k != j]
                        if len(o) == 2 and (
                            (o[0] in sets[p] and o[1] in sets[q]) or (o[1] in sets[p] and o[0] in sets[q])
                        ):
                            hit += 1
                            break
                return hit

            idx[i] = max(sorted(cands[i]), key=score)
    return torch.from_numpy(idx)


MAX_ANIMATION_FRAMES = 100_000  # docs/limits.md


def _before_posing(n: int, what: str, advice: str, check: Callable[[int], None] | None) -> None:
    """Before any frame is posed: the documented frame limit, then the caller's own check of ``n`` frames
    (the command line's memory estimate), so a huge animation is refused before it is allocated."""
    if n > MAX_ANIMATION_FRAMES:
        raise MeshsplatError(f"{what}: {n:,} frames; at most {MAX_ANIMATION_FRAMES:,} (see docs/limits.md); {advice}")
    if check is not None:
        check(n)


def _check_frames(frames: list[torch.Tensor], num_vertices: int, what: str) -> list[torch.Tensor]:
    if not frames:
        raise MeshsplatError(f"{what}: no frames")
    for i, v in enumerate(frames):
        check_tensor(f"{what} frame {i}", v, "V,3", {"V": num_vertices}, dtype="float", finite=True)
        if v.shape[0] > 1 and float((v.amax(0) - v.amin(0)).max()) <= 0:
            raise MeshsplatError(f"{what} frame {i}: all {v.shape[0]} vertices lie at one point (a degenerate mesh)")
    return frames


def avatar_gltf_driver(
    avatar: Avatar, path: str | Path, clip: str | None = None, fps: float = 25.0, source_map: SourceMap | None = None
) -> tuple[GltfDriver, Callable[[torch.Tensor], torch.Tensor] | None]:
    """``(driver, to_world)``: a ``GltfDriver`` of ``path`` posing the avatar's canonical vertices.

    With ``source_map`` (the run's or dataset's :class:`~meshsplat.data.source_map.SourceMap`) the asset
    the avatar was synthesized from drives it whatever was done to its driving mesh (welded, smoothed,
    decimated, turned z-up -> y-up): the driving mesh is re-derived exactly as ``synth`` did, and
    ``to_world`` turns the driver's frames into the dataset's axes (None when no turn is needed).
    Otherwise the glTF mesh must be the avatar's canonical mesh (same vertex count) or contain its
    vertices at rest (see :func:`match_vertices`)."""
    path = resolve_input(path)
    if not path.is_file():
        raise MeshsplatError(f"glTF file not found: {path}")
    if fps <= 0:
        raise MeshsplatError(f"fps: expected > 0, got {fps}")
    drv = GltfDriver(path, clip=clip, fps=fps)
    if drv.clip is None:
        raise MeshsplatError(f"{path}: the file has no animation clip")
    v_avatar = avatar.mesh.num_vertices
    canonical = avatar.mesh.vertices.detach().cpu().float()
    to_world = None
    if source_map is not None and _is_source_asset(drv.rest_vertices(), source_map):
        R = torch.as_tensor(source_map.rotation, dtype=torch.float32)
        rest = None if source_map.exact else (canonical @ R).numpy()  # world -> asset axes
        drv = drv.derive(source_map.source_index, avatar.mesh.faces.cpu().numpy(), rest)
        if not np.allclose(source_map.rotation, np.eye(3)):
            to_world = source_map.to_world
    elif drv.num_vertices != v_avatar:
        hint = (
            ""
            if source_map is not None
            else " (this run and its dataset have no source_map.npz, which records "
            "how a smoothed/decimated driving mesh was derived: re-run `meshsplat synth` with this version)"
        )
        try:
            src = match_vertices(
                drv.rest_vertices(), canonical, driver_faces=drv.faces, canonical_faces=avatar.mesh.faces
            )
        except MeshsplatError as exc:
            what = "its mesh is not the asset this avatar was synthesized from" if source_map is not None else ""
            raise MeshsplatError(f"{path}: {exc}{'; ' + what if what else ''}{hint}") from None
        drv = drv.derive(src.numpy(), avatar.mesh.faces.cpu().numpy())
    return drv, to_world


def gltf_animation(
    avatar: Avatar,
    path: str | Path,
    clip: str | None = None,
    fps: float = 25.0,
    seconds: float | None = None,
    start: float = 0.0,
    source_map: SourceMap | None = None,
) -> list[torch.Tensor]:
    """Vertex frames ``[V,3]`` of glTF ``clip`` (default the first) sampled at ``fps`` for ``seconds``
    (default the clip's length) from ``start``; the driver as :func:`avatar_gltf_driver` derives it."""
    drv, to_world = avatar_gltf_driver(avatar, path, clip, fps, source_map)
    v_avatar = avatar.mesh.num_vertices
    t0, _ = drv.time_range()
    length = drv.duration() if seconds is None else float(seconds)
    if length < 0:
        raise MeshsplatError(f"seconds: expected >= 0, got {seconds}")
    n = max(1, math.floor(length * fps + 1e-6) + (1 if seconds is None else 0))
    if n > MAX_ANIMATION_FRAMES:
        raise MeshsplatError(
            f"{length:g} s at {fps:g} fps is {n:,} frames; at most {MAX_ANIMATION_FRAMES:,} (lower --fps or --seconds)"
        )
    frames = [drv.vertices_at(t0 + start + i / fps) for i in range(n)]
    if to_world is not None:
        frames = [to_world(v) for v in frames]
    return _check_frames(frames, v_avatar, "glTF animation")


def _is_source_asset(rest: torch.Tensor, source_map) -> bool:
    """True when ``rest [Vs,3]`` (asset axes) is the rest mesh recorded in ``source_map``."""
    if rest.shape[0] != source_map.num_source_vertices:
        return False
    ref = torch.from_numpy(source_map.source_rest).double()
    diag = float((ref.amax(0) - ref.amin(0)).norm())
    gap = float((source_map.to_world(rest.double()) - ref).norm(dim=1).max())
    return gap <= 1e-4 * max(diag, 1e-12)


def _read_sequence(vertices: Any) -> tuple[Any, str]:
    """``(array-like [T,V,3], description)`` from an array/tensor, a ``.npy``, a mesh-sequence ``.npz``
    or a folder of OBJ/PLY frames."""
    if not isinstance(vertices, (str, Path)):
        return vertices, "vertex sequence"
    p = resolve_input(vertices)
    if p.is_dir() or p.suffix.lower() == ".npz":
        return read_mesh_sequence(p, with_uvs=False).vertices, f"mesh sequence {p}"
    if not p.is_file():
        raise MeshsplatError(f"vertex sequence file not found: {p}")
    return read_npy(p, "vertex sequence [T,V,3]", mmap=True), f"vertex sequence {p}"


def sequence_animation(
    avatar: Avatar, vertices: ArrayLike | str | Path, source_map: SourceMap | None = None, max_mismatch: float = 0.05
) -> list[torch.Tensor]:
    """Frames of a vertex sequence ``[T,V,3]``: an array/tensor, a ``.npy``, a mesh-sequence ``.npz``
    (``vertices`` key) or a folder of OBJ/PLY frames.

    The sequence may follow the avatar's canonical vertex order, or, with ``source_map``, the order
    (and axes) of the asset the avatar was synthesized from. Either way it must be a deformation of
    the canonical mesh at rest: a sequence whose edges stretch beyond 3x on more than
    ``max_mismatch`` of the edges (a different mesh, another vertex order) or whose size differs
    (other units) is refused with the numbers.
    """
    seq, what = _read_sequence(vertices)
    shape = tuple(seq.shape)
    v = avatar.mesh.num_vertices
    vs = source_map.num_source_vertices if source_map is not None else None
    if len(shape) != 3 or shape[2] != 3 or shape[0] < 1 or shape[1] not in (v, vs):
        also = f" or [T,{vs},3] (the source asset's vertices, in its order)" if vs is not None and vs != v else ""
        raise MeshsplatError(
            f"{what}: expected shape [T,{v},3] (the avatar's {v} canonical vertices){also}, got {list(shape)}"
        )
    if isinstance(seq, np.ndarray) and seq.dtype.kind not in "fiu":
        raise MeshsplatError(f"{what}: expected numbers, got dtype {seq.dtype}")
    if shape[0] > MAX_ANIMATION_FRAMES:
        raise MeshsplatError(f"{what}: {shape[0]:,} frames; at most {MAX_ANIMATION_FRAMES:,} (see docs/limits.md)")

    def frame(i: int) -> torch.Tensor:
        f = seq[i]
        return f.detach().cpu().float() if isinstance(f, torch.Tensor) else torch.from_numpy(np.array(f, np.float32))

    probe = sorted({0, shape[0] // 2, shape[0] - 1})
    canonical = avatar.mesh.vertices.detach().cpu().float()
    faces = avatar.mesh.faces.detach().cpu().long()
    scores = {}
    if shape[1] == v:
        scores["canonical"] = [rest_mismatch(frame(i), canonical, faces) for i in probe]
    if source_map is not None and shape[1] == vs:
        srest = torch.from_numpy(source_map.source_rest)
        sfaces = torch.from_numpy(source_map.source_faces)
        scores["source"] = [rest_mismatch(source_map.to_world(frame(i)), srest, sfaces) for i in probe]
    worst = {k: (max(b for b, _ in r), max(abs(math.log(max(m, 1e-30))) for _, m in r)) for k, r in scores.items()}
    fits = [k for k, (bad, logscale) in worst.items() if bad <= max_mismatch and logscale <= math.log(1.5)]
    if not fits:
        why = "; ".join(
            f"in the {'canonical' if k == 'canonical' else 'source asset'} order "
            f"{100 * worst[k][0]:.0f}% of edges change length beyond 3x and edges are "
            f"{math.exp(worst[k][1]) if worst[k][1] else 1:.3g}x their rest length (median)"
            for k in scores
        )
        raise MeshsplatError(
            f"{what}: does not match the avatar's canonical mesh at rest ({why}): it is not "
            "an animation of this mesh, its vertices are in another order, or it is in other "
            "units (scale it to the dataset's)"
        )
    order = min(fits, key=lambda k: worst[k][0])
    if order == "canonical":
        frames = [frame(i) for i in range(shape[0])]
    else:
        assert source_map is not None  # "source" fits only with a source map
        frames = [source_map.to_canonical(source_map.to_world(frame(i)), canonical) for i in range(shape[0])]
    return _check_frames(frames, v, what)


_TOPOLOGY_KINDS = {6890: "smpl", 10475: "smplx", 5023: "flame"}  # vertex counts of the released models


def motion_animation(
    avatar: Avatar,
    dataset: AvatarDataset,
    motion: str | Path,
    model_dir: str | Path | None = None,
    max_frames: int | None = None,
    align: str = "pose",
    check: Callable[[int], None] | None = None,
) -> list[torch.Tensor]:
    """Frames of a body/head motion file driving an avatar trained on SMPL/SMPL-X/FLAME-tracked data.

    ``motion``: an SMPL ``.npz`` (``poses [S,72]``, ``trans [S,3]``), an SMPL-X/AMASS ``.npz``, an IMavatar
    ``flame_params.json`` or a VHAP ``flame_param/`` folder (``meshsplat.drivers.motion.load_motion``).
    Cross-identity reenactment: the avatar keeps its own shape (``betas``, ``static_offset`` from its
    capture) and takes the motion's pose and expression. ``align="pose"`` (default) starts the motion
    where and as the subject stood in its first frame, so the capture's cameras frame it; "translation"
    keeps the motion's orientation; "none" uses its poses as they are (``drivers.motion.reenact``).
    More than ``MAX_ANIMATION_FRAMES`` frames (after ``max_frames``) are refused before posing; ``check(n)``
    runs then too (the command line's memory estimate).
    A capture with per-frame meshes only (INSTA) on a standard topology (FLAME 5023, SMPL 6890, SMPL-X
    10475 vertices) is posed by that model with its canonical mesh as the per-vertex offset.
    """
    info, subject = dataset.driver_info, dataset.driver_params
    if info is None or subject is None:
        # per-frame meshes only (INSTA): a standard topology is posed with the capture's rest mesh as offsets
        kind = _TOPOLOGY_KINDS.get(avatar.mesh.num_vertices)
        if kind is None:
            raise MeshsplatError(
                f"--motion needs an avatar of a SMPL/SMPL-X/FLAME capture, but {dataset.root} "
                f"({dataset.format_name}) has no model parameters and its {avatar.mesh.num_vertices}-vertex "
                f"mesh is no standard topology; use --gltf or --vertices"
            )
        info = {"type": kind}
    model = BodyModel(
        info["type"],
        model_dir,
        gender=info.get("gender", "neutral"),
        flame_version=str(info.get("flame_version", "2020")),
        scale=float(info.get("scale", 1.0)),
    )
    if model.num_vertices != avatar.mesh.num_vertices:
        raise MeshsplatError(
            f"the {info['type']} model in {model.path} has {model.num_vertices} vertices but the "
            f"avatar's mesh {avatar.mesh.num_vertices}: not the model it was trained with"
        )
    if subject is None:
        with torch.no_grad():
            template = model.rest_vertices({}).cpu() / model.scale
        subject = {"static_offset": (dataset.canonical_vertices / model.scale - template).numpy()}
    betas = subject.get("betas")
    if betas is not None and np.ndim(betas) == 2:  # per frame (each split its own): the avatar's is the train one
        train = dataset.split("train") if "train" in dataset.split_names else [0]
        subject = {**subject, "betas": betas[int(dataset.frame_info(train[0])["mesh"])]}
    params = load_motion(motion, model)
    if max_frames is not None:
        params = {
            k: (v[:max_frames] if getattr(v, "ndim", 1) == 2 and k not in ("betas", "static_offset") else v)
            for k, v in params.items()
        }
    n = max(
        (len(v) for k, v in params.items() if getattr(v, "ndim", 1) == 2 and k not in ("betas", "static_offset")),
        default=1,
    )
    _before_posing(n, f"motion {motion}", "render the first N frames with --frames N", check)
    verts = ParametricDriver(model, reenact(params, subject, align=align)).all_vertices()
    return _check_frames(list(verts), avatar.mesh.num_vertices, f"motion {motion}")


def _read_weights(weights, names: list[str]) -> np.ndarray:
    """``[T,K]`` from an array, a ``.npy``, or a ``.json`` holding ``[[...], ...]`` or
    ``{"names": [...], "weights": [[...], ...]}`` (columns matched to the model's names)."""
    import json

    if isinstance(weights, (str, Path)):
        p = Path(weights)
        if not p.is_file():
            raise MeshsplatError(f"weights file not found: {p}")
        if p.suffix.lower() == ".json":
            try:
                doc = json.loads(p.read_text())
            except ValueError as exc:
                raise MeshsplatError(f"{p}: not valid JSON ({exc})") from None
            if isinstance(doc, dict):
                if "weights" not in doc:
                    raise MeshsplatError(f"{p}: expected a list [T][K] or an object with 'weights' (and 'names')")
                w = np.asarray(doc["weights"], np.float32)
                if "names" in doc:
                    cols = [str(s) for s in doc["names"]]
                    unknown = [c for c in cols if c not in names]
                    if unknown:
                        raise MeshsplatError(f"{p}: unknown blend-shape names {unknown[:5]}")
                    if w.ndim != 2 or w.shape[1] != len(cols):
                        raise MeshsplatError(f"{p}: 'weights' must be [T,{len(cols)}] to match 'names'")
                    full = np.zeros((w.shape[0], len(names)), np.float32)
                    full[:, [names.index(c) for c in cols]] = w
                    w = full
            else:
                w = np.asarray(doc, np.float32)
        else:
            a = read_npy(p, "blend-shape weights [T,K]")
            if a.dtype.kind not in "fiub":
                raise MeshsplatError(f"{p}: blend-shape weights must be numbers, got {a.dtype}")
            w = a.astype(np.float32)
    else:
        w = np.asarray(weights.detach().cpu() if isinstance(weights, torch.Tensor) else weights, np.float32)
    if w.ndim == 1:
        w = w[None]
    if w.ndim != 2 or w.shape[1] != len(names) or w.shape[0] < 1:
        raise MeshsplatError(
            f"weights: expected shape [T,{len(names)}] (one column per blend shape), got {list(w.shape)}"
        )
    if not np.isfinite(w).all():
        raise MeshsplatError("weights: contain NaN/Inf values")
    return w


def blendshape_animation(
    avatar: Avatar,
    model: BlendshapeDriver | str | Path | None,
    weights: ArrayLike | str | Path,
    rotations: ArrayLike | None = None,
    translations: ArrayLike | None = None,
    check: Callable[[int], None] | None = None,
) -> list[torch.Tensor]:
    """Frames of a blend-shape model (``.npz`` path or bundled name, None for the bundled ICT head, or a
    ``BlendshapeDriver``) driven by ``weights [T,K]`` (array, ``.npy`` or ``.json``). More than
    ``MAX_ANIMATION_FRAMES`` frames are refused before posing; ``check(n)`` runs then too."""
    drv = model if isinstance(model, BlendshapeDriver) else BlendshapeDriver.from_npz(model)
    w = _read_weights(weights, drv.names)
    _before_posing(len(w), "blend-shape weights", "give fewer rows", check)
    v_avatar = avatar.mesh.num_vertices
    if drv.neutral.shape[0] != v_avatar:
        src = match_vertices(
            drv.neutral,
            avatar.mesh.vertices.detach().cpu().float(),
            driver_faces=drv.faces,
            canonical_faces=avatar.mesh.faces,
        )
        drv = BlendshapeDriver(drv.neutral[src], avatar.mesh.faces.cpu(), drv.deltas[:, src], names=drv.names)
    drv.set_sequence(w, rotations, translations)
    return _check_frames([drv.vertices(i) for i in range(drv.num_frames)], v_avatar, "blend-shape animation")


def dataset_animation(avatar: Avatar, dataset: AvatarDataset, split: str) -> tuple[list[torch.Tensor], list[Camera]]:
    """Driving meshes of a dataset split, with each frame's own camera."""
    ids = dataset.split(split)
    if not ids:
        raise MeshsplatError(f"split {split!r} of {dataset.root} is empty")
    if dataset.num_vertices != avatar.mesh.num_vertices:
        raise MeshsplatError(
            f"dataset meshes have {dataset.num_vertices} vertices, the avatar's canonical mesh "
            f"{avatar.mesh.num_vertices}"
        )
    return [dataset.vertices(i) for i in ids], [dataset.frame_camera(i) for i in ids]


# ---------------------------------------------------------------- rendering
@torch.no_grad()
def render_animation(
    avatar: Avatar,
    vertices: Iterable[torch.Tensor] | torch.Tensor,
    cameras: Camera | Sequence[Camera] | Callable[[int], Camera],
    out_dir: str | Path,
    fps: float = 25.0,
    background: str | Sequence[float] | torch.Tensor = (1.0, 1.0, 1.0),
    name: str = "animation",
    write_pngs: bool = True,
    write_mp4: bool = True,
    backend: str = "auto",
    progress: bool = False,
) -> AnimationResult:
    """Render ``avatar`` at every frame of ``vertices`` (each ``[V,3]``) to ``out_dir``.

    ``cameras``: one :class:`Camera` for all frames, one per frame, or ``frame -> Camera``.
    Writes ``out_dir/frames/frame_00000.png ...`` and ``out_dir/<name>.mp4`` (PNG frames are kept as
    the fallback when no ffmpeg is available). ``background``: ``[3]`` in [0, 1] or white/black.
    """
    if fps <= 0:
        raise MeshsplatError(f"fps: expected > 0, got {fps}")
    if not (write_pngs or write_mp4):
        raise MeshsplatError("render_animation: nothing to write (write_pngs and write_mp4 are both False)")
    if isinstance(cameras, Camera):
        cam_at = lambda i: cameras  # noqa: E731
    elif callable(cameras):
        cam_at = cameras
    else:
        cam_list = list(cameras)

        def cam_at(i: int) -> Camera:
            if i >= len(cam_list):
                raise MeshsplatError(f"cameras: {len(cam_list)} given, but the animation has more frames")
            return cam_list[i]

    bg = background_color(background)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frames, times = [], []
    seq = list(vertices) if not isinstance(vertices, torch.Tensor) else list(vertices.unbind(0))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(seq), desc="render", dynamic_ncols=True)
    for i, v in enumerate(seq):
        cam = cam_at(i)
        t0 = time.perf_counter()
        r = avatar.render(v, cam, bg, backend=backend)
        frames.append(to_uint8(r.image.float().clamp(0, 1)))
        times.append(time.perf_counter() - t0)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    if not frames:
        raise MeshsplatError("vertices: the animation has no frames")
    result = AnimationResult(mp4=None, num_frames=len(frames), render_ms_mean=1000.0 * float(np.mean(times)))
    png_dir = out / "frames"
    if write_mp4:
        vr = write_video(frames, out / f"{name}.mp4", fps=fps, png_dir=png_dir if write_pngs else None)
        result.mp4, result.pngs, result.error = vr.mp4, vr.pngs, vr.error
    else:
        result.pngs = write_png_frames(frames, png_dir)
    return result
