"""A live rig as viewer-bundle sections, so that the page evaluates the animation itself (see
docs/viewer.md): a glTF rig (skin, morph targets, node hierarchy, clips) or a blendshape model
(e.g. the ARKit face, as a morph rig: one rigid head node, one morph target per expression, and
its weight / head-pose sequence as a clip).

The arrays mirror :class:`meshsplat.drivers.GltfDriver`: vertex ``v`` is posed as
``sum_k w[v,k] * (world[pair_node[p]] @ pair_ibm[p]) @ (base[v] + sum_m weight[m] * delta[m, v])``
with ``p = pair_index[v,k]``; node world matrices come from the rest local matrices with animated
translation / rotation / scale channels (LINEAR with slerp for rotations, STEP, CUBICSPLINE).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from meshsplat.animation import AnimationSource, load_animation
from meshsplat.data.source_map import SourceMap
from meshsplat.drivers import GltfDriver
from meshsplat.drivers.blendshape import BlendshapeDriver
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar

__all__ = ["gltf_rig", "blendshape_rig", "bundle_rig", "avatar_driver", "rig_preview_frames"]

_PATHS = ("translation", "rotation", "scale", "weights")


def avatar_driver(
    avatar: Avatar, path: str | Path, clip: str | None = None, source_map: SourceMap | None = None
) -> GltfDriver:
    """``GltfDriver`` of ``path`` whose vertices are the avatar's canonical mesh vertices: the live driver of
    ``load_animation(AnimationSource("gltf", path, clip=clip), avatar, source_map=..., live=True)``."""
    drv = load_animation(AnimationSource("gltf", path, clip=clip), avatar, source_map=source_map, live=True).driver
    assert isinstance(drv, GltfDriver)  # a live gltf source loads its driver
    return drv


def gltf_rig(drv: GltfDriver) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``(sections, header)`` describing the rig and clips of a ``GltfDriver`` for the bundle."""
    # The driver keeps its rig in private fields (drivers/gltf.py); read them here, in one place.
    rig, doc = drv._rig, drv.file.doc
    V = int(rig.base.shape[0])
    k = rig.pair_index.shape[1]
    if k > 8:
        raise MeshsplatError(f"{drv.path}: {k} joint influences per vertex; the viewer handles at most 8")
    kk = 4 if k <= 4 else 8
    pair_index = np.zeros((V, kk), "<u4")
    pair_weight = np.zeros((V, kk), "<f4")
    pair_index[:, :k] = rig.pair_index
    pair_weight[:, :k] = rig.pair_weight
    n_nodes = len(drv._parent)
    trs = np.zeros((n_nodes, 10), "<f4")
    matrix_nodes = []
    for i, t in enumerate(drv._trs):
        if t is None:
            matrix_nodes.append(i)
        else:
            trs[i] = np.concatenate(t)
    # morph targets: per vertex (first delta texel, target count, group size, first weight)
    info = np.zeros((V, 4), "<u4")
    deltas, default_w, groups = [], [], []
    texel, wbase = 0, 0
    mesh_names = {}
    for ni, node in enumerate(doc.nodes):
        if node.mesh is not None:
            extras = doc.meshes[node.mesh].extras or {}
            mesh_names[ni] = list(extras.get("targetNames", [])) if isinstance(extras, dict) else []
    for g in rig.morphs:
        m, n = g.deltas.shape[0], len(g.index)
        info[g.index, 0] = texel + np.arange(n)
        info[g.index, 1] = m
        info[g.index, 2] = n
        info[g.index, 3] = wbase
        deltas.append(g.deltas.reshape(m * n, 3))
        default_w.append(g.default_weights)
        names = mesh_names.get(g.node, [])
        names = names if len(names) == m else [f"target {i}" for i in range(m)]
        groups.append(
            {
                "node": int(g.node),
                "count": int(m),
                "weight_base": wbase,
                "names": [str(s) for s in names],
                "node_name": doc.nodes[g.node].name or f"node {g.node}",
            }
        )
        texel += m * n
        wbase += m
    times: list[np.ndarray] = []
    values: list[np.ndarray] = []
    clips: list[dict[str, Any]] = []
    t_off = v_off = 0
    for name in drv.clips:
        chans = []
        for ch in drv._clips[name]:
            if ch.path not in _PATHS:
                continue
            t = np.asarray(ch.times, "<f4")
            v = np.asarray(ch.values, "<f4").reshape(-1)
            width = int(ch.values.shape[-1])
            chans.append(
                {
                    "node": int(ch.node),
                    "path": ch.path,
                    "interp": ch.interpolation,
                    "t_off": t_off,
                    "count": len(t),
                    "v_off": v_off,
                    "width": width,
                }
            )
            times.append(t)
            values.append(v)
            t_off += len(t)
            v_off += len(v)
        t0, _ = drv.time_range(name)
        clips.append({"name": name, "start": float(t0), "duration": float(drv.duration(name)), "channels": chans})
    sections = {
        "rig_base": np.asarray(rig.base, "<f4"),
        "rig_pair_index": pair_index,
        "rig_pair_weight": pair_weight,
        "pair_node": np.asarray(drv._pair_node, "<u4"),
        "pair_ibm": np.asarray(drv._pair_ibm, "<f4").reshape(-1, 16),
        "node_parent": np.asarray(drv._parent, "<i4"),
        "node_order": np.asarray(drv._order, "<u4"),
        "node_rest": np.asarray(drv._rest_local, "<f4").reshape(-1, 16),
        "node_trs": trs,
        "morph_info": info,
        "morph_deltas": np.concatenate(deltas).astype("<f4") if deltas else np.zeros((0, 3), "<f4"),
        "morph_default_weights": np.concatenate(default_w).astype("<f4") if default_w else np.zeros(0, "<f4"),
        "anim_times": np.concatenate(times) if times else np.zeros(0, "<f4"),
        "anim_values": np.concatenate(values) if values else np.zeros(0, "<f4"),
    }
    clip = drv.clip if drv.clip is not None else (drv.clips[0] if drv.clips else None)
    header = {
        "kind": "gltf",
        "source": drv.path.name,
        "influences": kk,
        "morph_encoding": "float32",
        "num_pairs": len(drv._pair_node),
        "num_nodes": n_nodes,
        "matrix_nodes": matrix_nodes,
        "morph_groups": groups,
        "num_morph_weights": wbase,
        "clips": clips,
        "clip": clip,
    }
    if not all(math.isfinite(c["duration"]) for c in clips):
        raise MeshsplatError(f"{drv.path}: a clip has a non-finite duration")
    return sections, header


def _axis_angle_to_xyzw(aa: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(aa, axis=-1, keepdims=True)
    axis = aa / np.maximum(theta, 1e-12)
    return np.concatenate([axis * np.sin(theta / 2), np.cos(theta / 2)], -1)


def blendshape_rig(
    drv: BlendshapeDriver, fps: float = 25.0, clip_name: str = "sequence"
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``(sections, header)`` of a :class:`meshsplat.drivers.BlendshapeDriver` as a morph rig.

    ``posed = R (neutral + sum w_e delta_e - pivot) + pivot + t`` is one node (rotation R,
    translation pivot + t) with inverse bind ``translate(-pivot)``; the expressions are its morph
    targets (named by the model, e.g. ARKit), stored as half floats (the ICT FaceKit file is float16:
    exact there; otherwise relative error <= 2^-11), only those that move their vertex (an expression
    moves a part of the face: the ICT head's vertices have 25 of its 57 on average), vertex by vertex,
    each with its target's number (``morph_encoding`` "float16-sparse"); the driver's sequence is a clip
    with keys at ``frame / fps`` (LINEAR, rotations slerped), so the page reproduces ``vertices(frame)``
    at the keys.
    """
    neutral = drv.neutral.detach().cpu().double().numpy()
    deltas = drv.deltas.detach().cpu().double().numpy()  # [E, V, 3]
    e, v = deltas.shape[:2]
    if e > 0xFFFF:
        raise MeshsplatError(f"blendshapes: {e} expressions; the player holds at most 65535")
    pivot = drv.pivot.detach().cpu().double().numpy()
    half = deltas.transpose(1, 0, 2).astype(np.float16)  # [V, E, 3], vertex-major
    if not np.isfinite(half).all():
        raise MeshsplatError("blendshapes: expression deltas beyond the half-float range (|x| > 65504)")
    bits = half.view(np.uint16).astype(np.uint32)
    moves = (bits & 0x7FFF).any(-1)  # [V, E]: a delta other than +-0
    vert, expr = np.nonzero(moves)  # vertex-major, expressions ascending
    b = bits[vert, expr]
    packed = np.stack([b[:, 0] | (b[:, 1] << 16), b[:, 2] | (expr.astype(np.uint32) << 16)], 1).astype("<u4")
    count = moves.sum(1)
    info = np.zeros((v, 4), "<u4")
    info[:, 0] = np.concatenate([[0], np.cumsum(count)[:-1]])
    info[:, 1] = count
    info[:, 2] = 1
    ibm = np.eye(4)
    ibm[:3, 3] = -pivot
    rest = np.eye(4)
    rest[:3, 3] = pivot
    t = drv.num_frames
    times = (np.arange(t) / float(fps)).astype("<f4")
    w = drv.weights.detach().cpu().numpy().astype("<f4")
    rot = _axis_angle_to_xyzw(drv.rotations.detach().cpu().double().numpy()).astype("<f4")
    tra = (pivot[None] + drv.translations.detach().cpu().double().numpy()).astype("<f4")
    chans: list[dict[str, Any]] = []
    vals: list[np.ndarray] = []
    off = 0
    for path, arr in (("weights", w), ("rotation", rot), ("translation", tra)):
        chans.append(
            {
                "node": 0,
                "path": path,
                "interp": "LINEAR",
                "t_off": len(chans) * t,
                "count": t,
                "v_off": off,
                "width": int(arr.shape[1]),
            }
        )
        vals.append(arr.reshape(-1))
        off += arr.size
    sections = {
        "rig_base": neutral.astype("<f4"),
        "rig_pair_index": np.zeros((v, 4), "<u4"),
        "rig_pair_weight": np.tile(np.array([1, 0, 0, 0], "<f4"), (v, 1)),
        "pair_node": np.zeros(1, "<u4"),
        "pair_ibm": ibm.reshape(1, 16).astype("<f4"),
        "node_parent": np.full(1, -1, "<i4"),
        "node_order": np.zeros(1, "<u4"),
        "node_rest": rest.reshape(1, 16).astype("<f4"),
        "node_trs": np.concatenate([pivot, [0, 0, 0, 1], [1, 1, 1]])[None].astype("<f4"),
        "morph_info": info,
        "morph_deltas": packed,
        "morph_default_weights": np.zeros(e, "<f4"),
        "anim_times": np.tile(times, 3),
        "anim_values": np.concatenate(vals).astype("<f4"),
    }
    header = {
        "kind": "gltf",
        "source": "blendshapes",
        "influences": 4,
        "num_pairs": 1,
        "num_nodes": 1,
        "matrix_nodes": [],
        "morph_encoding": "float16-sparse",
        "morph_groups": [
            {"node": 0, "count": e, "weight_base": 0, "names": [str(n) for n in drv.names], "node_name": "face"}
        ],
        "num_morph_weights": e,
        "clips": [{"name": clip_name, "start": 0.0, "duration": float((t - 1) / fps), "channels": chans}],
        "clip": clip_name,
    }
    return sections, header


def bundle_rig(
    drv: GltfDriver | BlendshapeDriver, fps: float = 25.0
) -> tuple[dict[str, np.ndarray], dict[str, Any], int]:
    """``(sections, header, num_vertices)`` of a GltfDriver or a BlendshapeDriver."""
    if isinstance(drv, BlendshapeDriver):
        return (*blendshape_rig(drv, fps), int(drv.neutral.shape[0]))
    return (*gltf_rig(drv), drv.num_vertices)


def rig_preview_frames(drv: GltfDriver | BlendshapeDriver, count: int = 16) -> list:
    """A few posed vertex frames across the default clip / sequence (to frame the camera)."""
    if isinstance(drv, BlendshapeDriver):
        idx = np.unique(np.linspace(0, drv.num_frames - 1, count).round().astype(int))
        return [drv.vertices(int(i)) for i in idx]
    t0, t1 = drv.time_range()
    return [drv.vertices_at(t0 + (t1 - t0) * i / (count - 1)) for i in range(count)]
