"""A glTF rig (skin, morph targets, node hierarchy, clips) as viewer-bundle sections, so that the
page evaluates the animation live (see docs/viewer.md, "Live glTF driver").

The arrays mirror :class:`meshsplat.drivers.GltfDriver`: vertex ``v`` is posed as
``sum_k w[v,k] * (world[pair_node[p]] @ pair_ibm[p]) @ (base[v] + sum_m weight[m] * delta[m, v])``
with ``p = pair_index[v,k]``; node world matrices come from the rest local matrices with animated
translation / rotation / scale channels (LINEAR with slerp for rotations, STEP, CUBICSPLINE).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from meshsplat.errors import MeshsplatError

__all__ = ["gltf_rig", "avatar_driver"]

_PATHS = ("translation", "rotation", "scale", "weights")


def avatar_driver(avatar, path, clip: str | None = None):
    """``GltfDriver`` of ``path`` whose vertices are the avatar's canonical mesh vertices (derived by
    matching rest positions when the avatar's mesh is not the glTF mesh itself, as
    :func:`meshsplat.animate.gltf_animation`)."""
    from meshsplat.animate import match_vertices
    from meshsplat.drivers import GltfDriver

    drv = GltfDriver(path, clip=clip)
    if drv.clip is None:
        raise MeshsplatError(f"{path}: the file has no animation clip")
    if drv.num_vertices != avatar.mesh.num_vertices:
        canonical = avatar.mesh.vertices.detach().cpu().float()
        src = match_vertices(drv.rest_vertices(), canonical, driver_faces=drv.faces,
                             canonical_faces=avatar.mesh.faces)
        drv = drv.derive(src.numpy(), avatar.mesh.faces.cpu().numpy())
    return drv


def gltf_rig(drv) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
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
        groups.append({"node": int(g.node), "count": int(m), "weight_base": wbase, "names": [str(s) for s in names],
                       "node_name": doc.nodes[g.node].name or f"node {g.node}"})
        texel += m * n
        wbase += m
    times, values, clips = [], [], []
    t_off = v_off = 0
    for name in drv.clips:
        chans = []
        for ch in drv._clips[name]:
            if ch.path not in _PATHS:
                continue
            t = np.asarray(ch.times, "<f4")
            v = np.asarray(ch.values, "<f4").reshape(-1)
            width = int(ch.values.shape[-1])
            chans.append({"node": int(ch.node), "path": ch.path, "interp": ch.interpolation, "t_off": t_off,
                          "count": len(t), "v_off": v_off, "width": width})
            times.append(t)
            values.append(v)
            t_off += len(t)
            v_off += len(v)
        t0, _ = drv.time_range(name)
        clips.append({"name": name, "start": float(t0), "duration": float(drv.duration(name)), "channels": chans})
    sections = {
        "rig_base": np.asarray(rig.base, "<f4"), "rig_pair_index": pair_index, "rig_pair_weight": pair_weight,
        "pair_node": np.asarray(drv._pair_node, "<u4"),
        "pair_ibm": np.asarray(drv._pair_ibm, "<f4").reshape(-1, 16),
        "node_parent": np.asarray(drv._parent, "<i4"), "node_order": np.asarray(drv._order, "<u4"),
        "node_rest": np.asarray(drv._rest_local, "<f4").reshape(-1, 16), "node_trs": trs,
        "morph_info": info,
        "morph_deltas": np.concatenate(deltas).astype("<f4") if deltas else np.zeros((0, 3), "<f4"),
        "morph_default_weights": np.concatenate(default_w).astype("<f4") if default_w else np.zeros(0, "<f4"),
        "anim_times": np.concatenate(times) if times else np.zeros(0, "<f4"),
        "anim_values": np.concatenate(values) if values else np.zeros(0, "<f4"),
    }
    clip = drv.clip if drv.clip is not None else (drv.clips[0] if drv.clips else None)
    header = {"kind": "gltf", "source": drv.path.name, "influences": kk, "num_pairs": int(len(drv._pair_node)),
              "num_nodes": n_nodes, "matrix_nodes": matrix_nodes, "morph_groups": groups,
              "num_morph_weights": wbase, "clips": clips, "clip": clip}
    if not all(math.isfinite(c["duration"]) for c in clips):
        raise MeshsplatError(f"{drv.path}: a clip has a non-finite duration")
    return sections, header
