"""Matching a driver to an avatar's canonical mesh: the one place a driver's vertices become the avatar's.

A driver whose mesh is not the canonical mesh vertex for vertex (the raw glTF of a synthetic dataset
whose driving mesh had seams welded) is matched by rest position (coincident vertices told apart by
their triangles): every canonical vertex must coincide (within ``1e-5`` of the mesh size) with a driver
vertex, or a clear error says so. With the run's or dataset's source map (``source_map.npz``,
:class:`meshsplat.data.source_map.SourceMap`) the asset the avatar was synthesized from drives it even
when its driving mesh was welded, smoothed, decimated or turned z-up -> y-up.

``mesh`` is the avatar's canonical mesh (``avatar.mesh``: ``vertices [V,3]``, ``faces [F,3]``).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat._checks import check_tensor
from meshsplat._typing import ArrayLike
from meshsplat.data.source_map import SourceMap
from meshsplat.drivers.blendshape import BlendshapeDriver
from meshsplat.drivers.gltf import GltfDriver
from meshsplat.drivers.mesh_sequence import read_mesh_sequence
from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npy
from meshsplat.mesh import TriMesh
from meshsplat.paths import resolve_input

__all__ = [
    "MAX_ANIMATION_FRAMES",
    "match_vertices",
    "rest_mismatch",
    "check_frames",
    "is_source_asset",
    "gltf_for_mesh",
    "blendshapes_for_mesh",
    "sequence_for_mesh",
]

MAX_ANIMATION_FRAMES = 100_000  # docs/limits.md


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
    from scipy.spatial import cKDTree  # scipy: optional, only matching needs it

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


def check_frames(frames: list[torch.Tensor], num_vertices: int, what: str) -> list[torch.Tensor]:
    """``frames`` (each ``[V,3]``, V = ``num_vertices``), checked finite and not collapsed to a point."""
    if not frames:
        raise MeshsplatError(f"{what}: no frames")
    for i, v in enumerate(frames):
        check_tensor(f"{what} frame {i}", v, "V,3", {"V": num_vertices}, dtype="float", finite=True)
        if v.shape[0] > 1 and float((v.amax(0) - v.amin(0)).max()) <= 0:
            raise MeshsplatError(f"{what} frame {i}: all {v.shape[0]} vertices lie at one point (a degenerate mesh)")
    return frames


def gltf_for_mesh(
    mesh: TriMesh, path: str | Path, clip: str | None = None, fps: float = 25.0, source_map: SourceMap | None = None
) -> tuple[GltfDriver, Callable[[torch.Tensor], torch.Tensor] | None]:
    """``(driver, to_world)``: a ``GltfDriver`` of ``path`` posing the canonical ``mesh``'s vertices.

    With ``source_map`` (the run's or dataset's) the asset
    the avatar was synthesized from drives it whatever was done to its driving mesh (welded, smoothed,
    decimated, turned z-up -> y-up): the driving mesh is re-derived exactly as ``synth`` did, and
    ``to_world`` turns the driver's frames into the dataset's axes (None when no turn is needed).
    Otherwise the glTF mesh must be the canonical mesh (same vertex count) or contain its
    vertices at rest (see :func:`match_vertices`)."""
    path = resolve_input(path)
    if not path.is_file():
        raise MeshsplatError(f"glTF file not found: {path}")
    if fps <= 0:
        raise MeshsplatError(f"fps: expected > 0, got {fps}")
    drv = GltfDriver(path, clip=clip, fps=fps)
    if drv.clip is None:
        raise MeshsplatError(f"{path}: the file has no animation clip")
    v_avatar = mesh.num_vertices
    canonical = mesh.vertices.detach().cpu().float()
    to_world = None
    if source_map is not None and is_source_asset(drv.rest_vertices(), source_map):
        R = torch.as_tensor(source_map.rotation, dtype=torch.float32)
        rest = None if source_map.exact else (canonical @ R).numpy()  # world -> asset axes
        drv = drv.derive(source_map.source_index, mesh.faces.cpu().numpy(), rest)
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
            src = match_vertices(drv.rest_vertices(), canonical, driver_faces=drv.faces, canonical_faces=mesh.faces)
        except MeshsplatError as exc:
            what = "its mesh is not the asset this avatar was synthesized from" if source_map is not None else ""
            raise MeshsplatError(f"{path}: {exc}{'; ' + what if what else ''}{hint}") from None
        drv = drv.derive(src.numpy(), mesh.faces.cpu().numpy())
    return drv, to_world


def is_source_asset(rest: torch.Tensor, source_map: SourceMap) -> bool:
    """True when ``rest [Vs,3]`` (asset axes) is the rest mesh recorded in ``source_map``."""
    if rest.shape[0] != source_map.num_source_vertices:
        return False
    ref = torch.from_numpy(source_map.source_rest).double()
    diag = float((ref.amax(0) - ref.amin(0)).norm())
    gap = float((source_map.to_world(rest.double()) - ref).norm(dim=1).max())
    return gap <= 1e-4 * max(diag, 1e-12)


def blendshapes_for_mesh(
    mesh: TriMesh, model: BlendshapeDriver | str | Path | None, source_map: SourceMap | None = None
) -> BlendshapeDriver:
    """A blend-shape model (a ``BlendshapeDriver``, an ``.npz`` path, a bundled name, None or "ict" for the
    bundled ICT head) on the canonical ``mesh``: as it is when the vertex counts agree; through the
    source map when the avatar was synthesized from this model (``meshsplat synth ict``: hidden shells
    dropped, seams welded); else matched by rest position (:func:`match_vertices`)."""
    drv = copy.copy(model) if isinstance(model, BlendshapeDriver) else BlendshapeDriver.from_npz(model)
    v = mesh.num_vertices
    if drv.neutral.shape[0] == v:
        return drv  # a copy: setting its sequence leaves the caller's model alone
    faces = mesh.faces.detach().cpu()
    canonical = mesh.vertices.detach().cpu().float()
    if source_map is not None and is_source_asset(drv.neutral, source_map):
        if not np.allclose(source_map.rotation, np.eye(3)):
            raise MeshsplatError(
                "blend-shape model: the avatar was synthesized from it turned to +y up; "
                "a blend-shape animation plays the model in its own axes"
            )
        return drv.derive(source_map.source_index, faces, None if source_map.exact else canonical)
    try:
        src = match_vertices(drv.neutral, canonical, driver_faces=drv.faces, canonical_faces=faces)
    except MeshsplatError as exc:
        raise MeshsplatError(f"blend-shape model: {exc}; use the blend-shape model the avatar was trained on") from None
    return drv.derive(src, faces)


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


def sequence_for_mesh(
    mesh: TriMesh, vertices: ArrayLike | str | Path, source_map: SourceMap | None = None, max_mismatch: float = 0.05
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
    v = mesh.num_vertices
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
    for i in probe:  # NaN edges compare as no stretch: named as such, not as another mesh (all frames: below)
        check_tensor(f"{what} frame {i}", frame(i), "V,3", {"V": shape[1]}, dtype="float", finite=True)
    canonical = mesh.vertices.detach().cpu().float()
    faces = mesh.faces.detach().cpu().long()
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
    return check_frames(frames, v, what)


def rest_mismatch(frame: torch.Tensor, rest: torch.Tensor, faces: torch.Tensor) -> tuple[float, float]:
    """How badly ``frame [V,3]`` fails to be a deformation of ``rest [V,3]`` on ``faces [F,3]``:
    ``(fraction of edges stretched or shrunk beyond 3x, median edge-length ratio frame/rest)``.
    A posed mesh in the same vertex order keeps most edge lengths; a reordered one does not."""
    f = faces.long()
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    lr = (rest[e[:, 0]] - rest[e[:, 1]]).double().norm(dim=1)
    lf = (frame[e[:, 0]] - frame[e[:, 1]]).double().norm(dim=1)
    ok = lr > 1e-12 * float(lr.max().clamp_min(1e-30))
    ratio = lf[ok] / lr[ok]
    if ratio.numel() == 0:
        return 0.0, 1.0
    med = float(ratio.median())
    rel = ratio / max(med, 1e-30)  # a uniform scale (units) is reported by the median, not counted here
    bad = float(((rel > 3.0) | (rel < 1.0 / 3.0)).double().mean())
    return bad, med
