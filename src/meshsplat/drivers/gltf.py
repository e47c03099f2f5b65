"""glTF 2.0 / GLB mesh driver: node hierarchy, skins (linear blend skinning), morph targets, clips.

All meshes and primitives of the scene are merged into one fixed-topology triangle mesh (glTF
vertices are kept, seams included). Skinned meshes ignore their node transform (glTF spec);
other meshes follow their node's world transform, so a mesh attached to a bone moves rigidly.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike

from meshsplat.drivers.gltf_io import Channel, GltfFile, sample_channel, trs_matrix
from meshsplat.errors import MeshsplatError
from meshsplat.plausible import skinning_problem

__all__ = ["GltfDriver", "Material", "MorphGroup"]


@dataclass
class Material:
    """Base colour of a glTF material: factor ``[4]`` times an optional texture (uint8 ``[H,W,3|4]``)."""

    name: str
    base_color: np.ndarray
    texture: np.ndarray | None = None
    texcoord: int = 0


@dataclass
class MorphGroup:
    """Morph targets of one primitive: ``deltas [M, n, 3]`` on vertices ``index [n]``, weights from ``node``."""

    node: int
    index: np.ndarray
    deltas: np.ndarray
    default_weights: np.ndarray


@dataclass
class _Rig:
    base: np.ndarray  # [V, 3] mesh-local positions (float64)
    pair_index: np.ndarray  # [V, K] into the (node, inverse bind) pair table
    pair_weight: np.ndarray  # [V, K]
    morphs: list[MorphGroup] = field(default_factory=list)


def _triangles(mode: int, idx: np.ndarray) -> np.ndarray:
    if mode == 4:
        return idx[: len(idx) // 3 * 3].reshape(-1, 3)
    if mode == 5:  # strip: alternate winding
        tris = [
            (idx[i], idx[i + 1], idx[i + 2]) if i % 2 == 0 else (idx[i + 1], idx[i], idx[i + 2])
            for i in range(len(idx) - 2)
        ]
        return np.array(tris, np.int64).reshape(-1, 3)
    if mode == 6:  # fan
        return np.stack([np.full(len(idx) - 2, idx[0]), idx[1:-1], idx[2:]], 1)
    return np.zeros((0, 3), np.int64)


class GltfDriver:
    """Poses the meshes of a glTF/GLB file at any time of any clip.

    Args:
        path: ``.glb`` or ``.gltf`` file.
        clip: clip (animation name) for the frame-based view; default the first clip.
        fps: frame rate of the frame-based view (``vertices(frame)`` = time ``frame / fps``).

    Attributes: ``faces [F,3] long``, ``uvs [V,2] float32`` (TEXCOORD_0, zeros where absent),
    ``vertex_colors [V,4] float32`` (COLOR_0, ones where absent), ``face_material [F] long`` into
    ``materials``, ``clips`` (names), ``num_vertices``.
    """

    def __init__(self, path: Path | str, clip: str | None = None, fps: float = 30.0) -> None:
        self.file = GltfFile(path)
        self.path = self.file.path
        doc = self.file.doc
        if fps <= 0:
            raise MeshsplatError(f"fps: expected > 0, got {fps}")
        self.fps = float(fps)
        self._parent = np.full(len(doc.nodes), -1, np.int64)
        for i, n in enumerate(doc.nodes):
            for c in n.children or []:
                self._parent[c] = i
        self._order = self._topological_order()
        self._rest_local = np.stack([self._node_local(n) for n in doc.nodes]) if doc.nodes else np.zeros((0, 4, 4))
        self._trs = [self._node_trs(n) for n in doc.nodes]
        self._load_materials()
        self._load_meshes()
        self._load_animations()
        if clip is not None and clip not in self._clips:
            raise MeshsplatError(f"clip: {clip!r} not in {self.clips}")
        self.clip = clip if clip is not None else (self.clips[0] if self.clips else None)

    # ---------------------------------------------------------------- parsing
    def _topological_order(self) -> list[int]:
        order: list[int] = []
        seen: set[int] = set()
        for i in range(len(self._parent)):
            chain = []
            j = i
            while j >= 0 and j not in seen:
                chain.append(j)
                seen.add(j)
                j = int(self._parent[j])
            order.extend(reversed(chain))
        return order

    @staticmethod
    def _node_trs(n):
        if n.matrix is not None:
            return None
        return (
            np.array(n.translation or [0, 0, 0], np.float64),
            np.array(n.rotation or [0, 0, 0, 1], np.float64),
            np.array(n.scale or [1, 1, 1], np.float64),
        )

    @staticmethod
    def _node_local(n) -> np.ndarray:
        if n.matrix is not None:
            return np.asarray(n.matrix, np.float64).reshape(4, 4).T  # column-major
        t = n.translation or [0, 0, 0]
        r = n.rotation or [0, 0, 0, 1]
        s = n.scale or [1, 1, 1]
        return trs_matrix(t, r, s)

    def _scene_nodes(self) -> list[int]:
        doc = self.file.doc
        if doc.scenes:
            roots = doc.scenes[doc.scene or 0].nodes or []
        else:
            roots = [i for i in range(len(doc.nodes)) if self._parent[i] < 0]
        out, stack = [], list(reversed(roots))
        while stack:
            i = stack.pop()
            out.append(i)
            stack.extend(reversed(doc.nodes[i].children or []))
        return out

    def _load_materials(self) -> None:
        doc = self.file.doc
        self.materials: list[Material] = []
        for i, m in enumerate(doc.materials or []):
            pbr = m.pbrMetallicRoughness
            factor = np.array((pbr.baseColorFactor if pbr and pbr.baseColorFactor else [1, 1, 1, 1]), np.float32)
            tex, tc = None, 0
            if pbr is not None and pbr.baseColorTexture is not None:
                t = doc.textures[pbr.baseColorTexture.index]
                if t.source is not None:
                    tex = self.file.image(t.source)
                tc = pbr.baseColorTexture.texCoord or 0
            self.materials.append(Material(m.name or f"material{i}", factor, tex, tc))

    def _load_meshes(self) -> None:
        doc = self.file.doc
        pairs_node: list[int] = []
        pairs_ibm: list[np.ndarray] = []
        skin_offset: dict[int, int] = {}
        rigid_pair: dict[int, int] = {}
        base, faces, uvs, colors, fmat, pidx, pw, morphs = [], [], [], [], [], [], [], []
        default_mat = None
        nv = 0
        for ni in self._scene_nodes():
            node = doc.nodes[ni]
            if node.mesh is None:
                continue
            mesh = doc.meshes[node.mesh]
            for prim in mesh.primitives:
                a = prim.attributes
                mode = 4 if prim.mode is None else prim.mode
                if a.POSITION is None or mode not in (4, 5, 6):
                    continue
                pos = self.file.accessor(a.POSITION)
                n = len(pos)
                idx = (
                    self.file.accessor(prim.indices, as_float=False)[:, 0].astype(np.int64)
                    if prim.indices is not None
                    else np.arange(n)
                )
                tri = _triangles(mode, idx)
                if len(tri) == 0:
                    continue
                if node.skin is not None and a.JOINTS_0 is not None and a.WEIGHTS_0 is not None:
                    if node.skin not in skin_offset:
                        skin = doc.skins[node.skin]
                        skin_offset[node.skin] = len(pairs_node)
                        ibm = (
                            self.file.accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
                            if skin.inverseBindMatrices is not None
                            else np.tile(np.eye(4), (len(skin.joints), 1, 1))
                        )
                        pairs_node.extend(skin.joints)
                        pairs_ibm.extend(ibm)
                    j_parts = [self.file.accessor(a.JOINTS_0, as_float=False).astype(np.int64)]
                    w_parts = [self.file.accessor(a.WEIGHTS_0)]
                    if getattr(a, "JOINTS_1", None) is not None and getattr(a, "WEIGHTS_1", None) is not None:
                        j_parts.append(self.file.accessor(a.JOINTS_1, as_float=False).astype(np.int64))
                        w_parts.append(self.file.accessor(a.WEIGHTS_1))
                    j = np.concatenate(j_parts, 1) + skin_offset[node.skin]
                    w = np.concatenate(w_parts, 1)
                    why = skinning_problem(w, f"mesh node {ni} ({node.name or 'unnamed'}): WEIGHTS_0")
                    if why is not None:
                        raise MeshsplatError(f"{self.path}: {why}")
                    s = w.sum(1, keepdims=True)
                    w = np.where(s > 0, w / np.where(s > 0, s, 1), 0)
                else:
                    if ni not in rigid_pair:
                        rigid_pair[ni] = len(pairs_node)
                        pairs_node.append(ni)
                        pairs_ibm.append(np.eye(4))
                    j = np.full((n, 1), rigid_pair[ni], np.int64)
                    w = np.ones((n, 1))
                base.append(pos)
                faces.append(tri + nv)
                uvs.append(self.file.accessor(a.TEXCOORD_0)[:, :2] if a.TEXCOORD_0 is not None else np.zeros((n, 2)))
                if a.COLOR_0 is not None:
                    c = self.file.accessor(a.COLOR_0)
                    c = np.concatenate([c, np.ones((n, 1))], 1) if c.shape[1] == 3 else c
                else:
                    c = np.ones((n, 4))
                colors.append(c)
                if prim.material is None:
                    if default_mat is None:
                        default_mat = len(self.materials)
                        self.materials.append(Material("default", np.array([0.8, 0.8, 0.8, 1], np.float32)))
                    m = default_mat
                else:
                    m = prim.material
                fmat.append(np.full(len(tri), m, np.int64))
                pidx.append(j)
                pw.append(w)
                if prim.targets:
                    d = np.stack(
                        [
                            self.file.accessor(t["POSITION"])
                            if isinstance(t, dict) and t.get("POSITION") is not None
                            else np.zeros((n, 3))
                            for t in prim.targets
                        ]
                    )
                    dw = getattr(node, "weights", None) or mesh.weights or [0.0] * len(prim.targets)
                    morphs.append(MorphGroup(ni, np.arange(nv, nv + n), d, np.asarray(dw, np.float64)))
                nv += n
        if nv == 0:
            raise MeshsplatError(f"{self.path}: no triangle meshes in the scene")
        k = max(x.shape[1] for x in pidx)

        def pad(x: np.ndarray, v: float) -> np.ndarray:
            return np.concatenate([x, np.full((len(x), k - x.shape[1]), v, x.dtype)], 1)

        self._pair_node = np.asarray(pairs_node, np.int64)
        self._pair_ibm = np.stack(pairs_ibm)
        self._rig = _Rig(
            np.concatenate(base),
            np.concatenate([pad(x, 0) for x in pidx]),
            np.concatenate([pad(x, 0.0) for x in pw]),
            morphs,
        )
        self.faces = torch.from_numpy(np.concatenate(faces)).long()
        self.uvs = torch.from_numpy(np.concatenate(uvs)).float()
        self.vertex_colors = torch.from_numpy(np.concatenate(colors)).float()
        self.face_material = torch.from_numpy(np.concatenate(fmat)).long()

    def _load_animations(self) -> None:
        doc = self.file.doc
        self._clips: dict[str, list[Channel]] = {}
        for ai, anim in enumerate(doc.animations or []):
            name = anim.name or f"clip{ai}"
            if name in self._clips:
                name = f"{name}_{ai}"
            chans = []
            for ch in anim.channels:
                if ch.target.node is None or ch.target.path not in ("translation", "rotation", "scale", "weights"):
                    continue
                smp = anim.samplers[ch.sampler]
                times = self.file.accessor(smp.input)[:, 0]
                vals = self.file.accessor(smp.output)
                interp = smp.interpolation or "LINEAR"
                k = len(times)
                vals = vals.reshape(k, 3, -1) if interp == "CUBICSPLINE" else vals.reshape(k, -1)
                chans.append(Channel(ch.target.node, ch.target.path, times, vals, interp))
            self._clips[name] = chans

    # ---------------------------------------------------------------- queries
    @property
    def clips(self) -> list[str]:
        return list(self._clips)

    @property
    def num_vertices(self) -> int:
        return int(self._rig.base.shape[0])

    def time_range(self, clip: str | None = None) -> tuple[float, float]:
        chans = self._clips.get(self._clip_name(clip), []) if self._clips else []
        if not chans:
            return 0.0, 0.0
        return float(min(c.times[0] for c in chans)), float(max(c.times[-1] for c in chans))

    def duration(self, clip: str | None = None) -> float:
        """Length in seconds of ``clip`` (default the driver's clip); 0 without animation."""
        t0, t1 = self.time_range(clip)
        return t1 - min(t0, 0.0) if t1 > 0 else 0.0

    def _clip_name(self, clip):
        name = clip if clip is not None else self.clip
        if name is not None and name not in self._clips:
            raise MeshsplatError(f"clip: {name!r} not in {self.clips}")
        return name

    @property
    def num_frames(self) -> int:
        return int(np.floor(self.duration() * self.fps + 1e-6)) + 1

    def rest_vertices(self) -> torch.Tensor:
        """Vertices in the file's default node pose and default morph weights ``[V, 3]``."""
        return self._to_torch(self._pose(None, None))

    def vertices(self, frame: int) -> torch.Tensor:
        if not 0 <= frame < self.num_frames:
            raise MeshsplatError(f"frame: expected 0 <= frame < {self.num_frames}, got {frame}")
        return self.vertices_at(frame / self.fps)

    def vertices_at(
        self, time: float, clip: str | None = None, morph_weights: dict[int, np.ndarray] | None = None
    ) -> torch.Tensor:
        """Posed vertices ``[V, 3]`` at ``time`` seconds of ``clip`` (clamped to the clip's range).

        ``morph_weights`` maps a mesh node index to weights overriding default and animation.
        """
        name = self._clip_name(clip)
        if not np.isfinite(time):
            raise MeshsplatError(f"time: expected a finite number, got {time}")
        return self._to_torch(self._pose(name, float(time), morph_weights))

    def morph_nodes(self) -> dict[int, int]:
        """Mesh node index -> number of morph targets."""
        return {g.node: g.deltas.shape[0] for g in self._rig.morphs}

    # ---------------------------------------------------------------- posing
    def node_world_matrices(self, clip: str | None, time: float | None) -> np.ndarray:
        """World matrices ``[nodes, 4, 4]`` of all nodes at ``time`` of ``clip`` (None: default pose)."""
        local = self._rest_local.copy()
        if clip is not None and time is not None:
            trs: dict[int, list[np.ndarray]] = {}
            for ch in self._clips[clip]:
                if ch.path == "weights":
                    continue
                base = self._trs[ch.node]
                if base is None:
                    continue  # matrix nodes cannot be animated
                cur = trs.setdefault(ch.node, [b.copy() for b in base])
                cur[("translation", "rotation", "scale").index(ch.path)] = sample_channel(ch, time)
            for i, (t, r, s) in trs.items():
                local[i] = trs_matrix(t, r, s)
        world = np.empty_like(local)
        for i in self._order:
            p = self._parent[i]
            world[i] = local[i] if p < 0 else world[p] @ local[i]
        return world

    def _morph_weights(self, clip, time, override) -> dict[int, np.ndarray]:
        weights = {g.node: g.default_weights.copy() for g in self._rig.morphs}
        if clip is not None and time is not None:
            for ch in self._clips[clip]:
                if ch.path == "weights" and ch.node in weights:
                    weights[ch.node] = np.asarray(sample_channel(ch, time), np.float64)
        for k, v in (override or {}).items():
            weights[k] = np.asarray(v, np.float64)
        return weights

    def _blend_matrices(self, world: np.ndarray) -> np.ndarray:
        pair = world[self._pair_node] @ self._pair_ibm  # [P, 4, 4]
        return np.einsum("vk,vkij->vij", self._rig.pair_weight, pair[self._rig.pair_index])

    def _morphed_base(self, weights) -> np.ndarray:
        pos = self._rig.base.copy()
        for g in self._rig.morphs:
            w = weights[g.node]
            if np.any(w != 0):
                pos[g.index] += np.einsum("m,mnc->nc", w, g.deltas)
        return pos

    def _pose(self, clip, time, override=None) -> np.ndarray:
        world = self.node_world_matrices(clip, time)
        m = self._blend_matrices(world)
        pos = self._morphed_base(self._morph_weights(clip, time, override))
        return np.einsum("vij,vj->vi", m[:, :3, :3], pos) + m[:, :3, 3]

    @staticmethod
    def _to_torch(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(x.astype(np.float32))

    # ---------------------------------------------------------------- derived rigs
    def derive(
        self,
        source_index: ArrayLike,
        faces: torch.Tensor | ArrayLike,
        rest_vertices: torch.Tensor | ArrayLike | None = None,
    ) -> GltfDriver:
        """A driver on another mesh carried through the same skinning and morphs.

        Vertex ``i`` of the new mesh copies skin weights and morph deltas of glTF vertex
        ``source_index[i]``; its rest position is ``rest_vertices[i]`` (world space, default pose)
        or the source vertex's rest position. Used for welded, smoothed or decimated driving meshes.
        """
        src = np.asarray(source_index, np.int64).reshape(-1)
        if src.size == 0 or src.min() < 0 or src.max() >= self.num_vertices:
            raise MeshsplatError(f"source_index: expected indices in [0, {self.num_vertices})")
        out = copy.copy(self)
        r = self._rig
        pi, pw = r.pair_index[src], r.pair_weight[src]
        morphs = []
        for g in r.morphs:
            lookup = np.full(self.num_vertices, -1, np.int64)
            lookup[g.index] = np.arange(len(g.index))
            sel = lookup[src]
            keep = np.nonzero(sel >= 0)[0]
            if keep.size:
                morphs.append(MorphGroup(g.node, keep, g.deltas[:, sel[keep]], g.default_weights))
        base = r.base[src].copy()
        out._rig = _Rig(base, pi, pw, morphs)
        if rest_vertices is not None:
            rv = np.asarray(
                rest_vertices.detach().cpu() if isinstance(rest_vertices, torch.Tensor) else rest_vertices, np.float64
            )
            if rv.shape != (src.size, 3) or not np.isfinite(rv).all():
                raise MeshsplatError(f"rest_vertices: expected finite shape [{src.size}, 3], got {list(rv.shape)}")
            m = out._blend_matrices(out.node_world_matrices(None, None))
            delta = out._morphed_base(out._morph_weights(None, None, None)) - base
            local = np.linalg.solve(m[:, :3, :3], (rv - m[:, :3, 3])[..., None])[..., 0]
            out._rig.base = local - delta
        out.faces = torch.as_tensor(np.asarray(faces), dtype=torch.long)
        if out.faces.ndim != 2 or out.faces.shape[1] != 3 or int(out.faces.max()) >= src.size:
            raise MeshsplatError("faces: expected [F, 3] indices into the derived vertices")
        out.uvs = self.uvs[torch.from_numpy(src)]
        out.vertex_colors = self.vertex_colors[torch.from_numpy(src)]
        return out
