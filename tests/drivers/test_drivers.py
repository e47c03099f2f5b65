"""Mesh drivers: glTF skinning/morphs against an independent plain evaluation, sequences, blendshapes."""

from __future__ import annotations

import math

import numpy as np
import pygltflib
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from meshsplat.drivers import BlendshapeDriver, GltfDriver, MeshDriver, SequenceDriver
from meshsplat.drivers.gltf_io import Channel, sample_channel, slerp_xyzw
from meshsplat.errors import MeshsplatError

_TYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_N = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _read(g, blob, i):
    a = g.accessors[i]
    bv = g.bufferViews[a.bufferView]
    dt = np.dtype(_TYPES[a.componentType])
    n = _N[a.type]
    stride = bv.byteStride or dt.itemsize * n
    out = np.empty((a.count, n), np.float64)
    for k in range(a.count):  # plain per-element read
        off = (bv.byteOffset or 0) + (a.byteOffset or 0) + k * stride
        out[k] = np.frombuffer(blob, dt, n, off)
    if a.normalized:
        out = out / np.iinfo(dt).max
    return out


def _sample(times, vals, interp, path, t):
    """Plain keyframe sampling with scipy's Slerp for rotations."""
    t = min(max(t, times[0]), times[-1])
    if interp == "STEP":
        return vals[np.searchsorted(times, t, side="right") - 1]
    if path == "rotation":
        return Slerp(times, Rotation.from_quat(vals))([t]).as_quat()[0]
    return np.array([np.interp(t, times, vals[:, c]) for c in range(vals.shape[1])])


def _reference(path, clip_index, frac):
    """Independent evaluation at ``frac`` of a clip's duration.

    Returns (time, vertex blocks in scene depth-first order of mesh nodes and primitives)."""
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()
    anim = g.animations[clip_index]
    t = frac * max(_read(g, blob, s.input)[-1, 0] for s in anim.samplers)
    trs = {
        i: [
            np.array(n.translation or [0, 0, 0.0]),
            np.array(n.rotation or [0, 0, 0, 1.0]),
            np.array(n.scale or [1, 1, 1.0]),
        ]
        for i, n in enumerate(g.nodes)
    }
    for ch in anim.channels:
        if ch.target.path not in ("translation", "rotation", "scale"):
            continue
        s = anim.samplers[ch.sampler]
        times = _read(g, blob, s.input)[:, 0]
        vals = _read(g, blob, s.output)
        trs[ch.target.node][("translation", "rotation", "scale").index(ch.target.path)] = _sample(
            times, vals, s.interpolation or "LINEAR", ch.target.path, t
        )
    parent = {c: i for i, n in enumerate(g.nodes) for c in (n.children or [])}

    def local(i):
        n = g.nodes[i]
        if n.matrix is not None:
            return np.array(n.matrix).reshape(4, 4).T
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(trs[i][1]).as_matrix() @ np.diag(trs[i][2])
        m[:3, 3] = trs[i][0]
        return m

    def world(i):
        return world(parent[i]) @ local(i) if i in parent else local(i)

    def dfs(i):
        yield i
        for c in g.nodes[i].children or []:
            yield from dfs(c)

    blocks = []
    for root in g.scenes[g.scene or 0].nodes:
        for ni in dfs(root):
            node = g.nodes[ni]
            if node.mesh is None:
                continue
            for prim in g.meshes[node.mesh].primitives:
                pos = _read(g, blob, prim.attributes.POSITION)
                if node.skin is not None:
                    skin = g.skins[node.skin]
                    ibm = _read(g, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
                    J = _read(g, blob, prim.attributes.JOINTS_0).astype(int)
                    W = _read(g, blob, prim.attributes.WEIGHTS_0)
                    out = np.zeros_like(pos)
                    for v in range(0, len(pos), 7):  # every 7th vertex, plain loop
                        m = sum(W[v, j] * world(skin.joints[J[v, j]]) @ ibm[J[v, j]] for j in range(4)) / W[v].sum()
                        out[v] = (m @ np.append(pos[v], 1))[:3]
                else:
                    m = world(ni)
                    out = pos @ m[:3, :3].T + m[:3, 3]
                blocks.append(out)
    return t, blocks


@pytest.mark.parametrize(
    "name,clip_index,frac",
    [("RiggedSimple", 0, 0.43), ("CesiumMan", 0, 0.61), ("RobotExpressive", 12, 0.37), ("RobotExpressive", 0, 0.8)],
)
def test_skinning_matches_independent_evaluation(assets, name, clip_index, frac):
    path = assets / "gltf" / f"{name}.glb"
    drv = GltfDriver(path)
    t, blocks = _reference(path, clip_index, frac)
    got = drv.vertices_at(t, drv.clips[clip_index]).double().numpy()
    ref = np.concatenate(blocks)
    assert got.shape == ref.shape
    offs = np.cumsum([0] + [len(b) for b in blocks])
    check = np.concatenate(
        [np.arange(o, o + len(b), 7) for b, o in zip(blocks, offs[:-1], strict=True)]
    )  # every 7th vertex
    size = float(np.linalg.norm(ref.max(0) - ref.min(0)))
    err = np.abs(got[check] - ref[check]).max()
    assert err < 1e-5 * size, f"{name}: max error {err} vs size {size}"
    # the pose actually moved something (not the rest pose)
    assert np.abs(got - drv.rest_vertices().double().numpy()).max() > 1e-3 * size


def test_morph_target_moves_exactly_its_vertices(assets):
    path = assets / "gltf" / "RobotExpressive.glb"
    drv = GltfDriver(path)
    nodes = drv.morph_nodes()
    assert len(nodes) == 3 and all(n == 3 for n in nodes.values())
    g = pygltflib.GLTF2().load(str(path))
    total = 0
    for node in sorted(nodes):
        base = drv.vertices_at(0.0, "Idle", morph_weights={node: [0, 0, 0]}).numpy()
        group = next(gr for gr in drv._rig.morphs if gr.node == node)
        prim = g.meshes[g.nodes[node].mesh].primitives[0]
        for target in range(3):
            w = [0.0, 0.0, 0.0]
            w[target] = 1.0
            moved = drv.vertices_at(0.0, "Idle", morph_weights={node: w}).numpy()
            changed = np.nonzero(np.abs(moved - base).max(1) > 1e-9)[0]
            delta = _read(g, g.binary_blob(), prim.targets[target]["POSITION"])
            expected = np.nonzero(np.abs(delta).max(1) > 0)[0]
            total += len(expected)
            np.testing.assert_array_equal(changed, group.index[expected])
    assert total > 0


def test_morph_weights_animated(assets):
    drv = GltfDriver(assets / "gltf" / "RobotExpressive.glb")
    w = drv._morph_weights("Wave", 0.5, None)
    assert set(w) == set(drv.morph_nodes())


def test_frame_view_and_errors(assets):
    drv = GltfDriver(assets / "gltf" / "CesiumMan.glb", fps=10)
    assert isinstance(drv, MeshDriver)
    assert drv.num_frames == 21 and math.isclose(drv.duration(), 2.0, rel_tol=1e-4)
    torch.testing.assert_close(drv.vertices(5), drv.vertices_at(0.5))
    rest = drv.rest_vertices()
    ext = rest.max(0).values - rest.min(0).values
    assert int(torch.argmax(ext)) != 2 and float(rest[:, 1].min()) > -0.05  # Z-up root handled: stands on y=0
    with pytest.raises(MeshsplatError, match="clip"):
        drv.vertices_at(0.1, "nope")
    with pytest.raises(MeshsplatError, match="frame"):
        drv.vertices(21)
    with pytest.raises(MeshsplatError, match="not found"):
        GltfDriver(assets / "gltf" / "missing.glb")


def test_derive_welded_follows_source(assets):
    drv = GltfDriver(assets / "gltf" / "CesiumMan.glb")
    src = np.arange(0, drv.num_vertices, 3)
    d2 = drv.derive(src, np.array([[0, 1, 2]]))
    torch.testing.assert_close(d2.vertices_at(0.7), drv.vertices_at(0.7)[src])
    moved = drv.rest_vertices()[src] + 0.01
    d3 = drv.derive(src, np.array([[0, 1, 2]]), rest_vertices=moved)
    torch.testing.assert_close(d3.rest_vertices(), moved, atol=1e-5, rtol=0)


def test_sampling_interpolations():
    q0 = np.array([0, 0, 0, 1.0])
    q1 = Rotation.from_euler("z", 90, degrees=True).as_quat()
    mid = slerp_xyzw(q0, q1, 0.5)
    np.testing.assert_allclose(Rotation.from_quat(mid).as_euler("xyz", degrees=True), [0, 0, 45], atol=1e-6)
    times = np.array([0.0, 1.0, 2.0])
    step = Channel(0, "translation", times, np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]), "STEP")
    np.testing.assert_allclose(sample_channel(step, 1.9), [1, 1, 1])
    lin = Channel(0, "translation", times, np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]), "LINEAR")
    np.testing.assert_allclose(sample_channel(lin, 1.25), [1.25] * 3)
    np.testing.assert_allclose(sample_channel(lin, 5.0), [2, 2, 2])  # clamped
    # cubic Hermite with tangents 1 reproduces the line t
    vals = np.stack([np.ones((3, 1)), times[:, None], np.ones((3, 1))], 1)
    cub = Channel(0, "scale", times, vals, "CUBICSPLINE")
    np.testing.assert_allclose(sample_channel(cub, 0.3), [0.3], atol=1e-12)


def test_sequence_driver():
    v = torch.randn(5, 4, 3)
    d = SequenceDriver(v, [[0, 1, 2], [1, 2, 3]])
    assert isinstance(d, MeshDriver) and d.num_frames == 5
    torch.testing.assert_close(d.vertices(3), v[3])
    torch.testing.assert_close(d.rest_vertices(), v[0])
    with pytest.raises(MeshsplatError, match="faces"):
        SequenceDriver(v, [[0, 1, 7]])
    with pytest.raises(MeshsplatError, match=r"\[T,V,3\]"):
        SequenceDriver(torch.randn(4, 3), [[0, 1, 2]])


def test_blendshape_driver(assets):
    d = BlendshapeDriver.from_npz(assets / "ict_facekit" / "ict_face_arkit53.npz")
    assert isinstance(d, MeshDriver)
    e = d.names.index("jawOpen")
    w = torch.zeros(len(d.names))
    torch.testing.assert_close(d.pose(w), d.neutral)
    w[e] = 0.5
    torch.testing.assert_close(d.pose(w), d.neutral + 0.5 * d.deltas[e])
    rot = d.pose(w, rotation=[0.0, 0.3, 0.0], translation=[1.0, 0, 0])
    a, b = d.pose(w)[:100], rot[:100]
    dist = lambda x: (x[:, None] - x[None]).norm(dim=-1)  # noqa: E731
    torch.testing.assert_close(dist(a), dist(b), atol=1e-3, rtol=1e-4)  # rigid
    d.talking_sequence(6)
    assert d.num_frames == 6 and torch.isfinite(d.vertices(5)).all()
    with pytest.raises(MeshsplatError, match="weights"):
        d.set_sequence(weights=torch.zeros(3, 2))
