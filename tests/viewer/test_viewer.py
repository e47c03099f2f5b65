"""Viewer bundle: binary layout round trip, the JS posing/sorting math under Node vs compose, CLI,
and (slow, when chromium is installed) a headless-browser screenshot vs the Python rasterizer."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from _browser import find_chromium, screenshot
from _eval_kit import deform, make_avatar, make_run
from meshsplat.camera import Camera
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.gaussians.compose import effective_uv
from meshsplat.gaussians.params import SH_C0
from meshsplat.gaussians.shading import Shading
from meshsplat.viewer import read_viewer_bundle, write_viewer_bundle

NODE = shutil.which("node")
REFERENCE_JS = json.dumps((Path(__file__).resolve().parent / "viewer_reference.mjs").as_uri())  # CPU reference
needs_node = pytest.mark.skipif(NODE is None, reason="node is not installed")


def _frames(avatar, ts=(0.0, 0.4, 1.0)):
    return [deform(avatar.mesh.vertices, t) for t in ts]


def _with_scale_mode(avatar, mode):
    return Avatar(avatar.mesh, avatar.params, mode, avatar.clamp_to_face)


def _node(script: str, cwd: Path) -> dict:
    path = cwd / "check.mjs"
    path.write_text(script)
    r = subprocess.run([NODE, str(path)], check=False, capture_output=True, text=True, cwd=cwd, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _js_pose(bundle: Path) -> list[dict]:
    script = f"""
import {{ decodeBundle }} from {json.dumps((bundle / "viewer.js").as_uri())};
import {{ poseGaussians }} from {REFERENCE_JS};
import fs from "fs";
const h = JSON.parse(fs.readFileSync({json.dumps(str(bundle / "avatar.json"))}, "utf8"));
const b = decodeBundle(h, fs.readFileSync({json.dumps(str(bundle / "avatar.bin"))}));
const out = [];
for (let t = 0; t < b.T; t++) {{
  const p = poseGaussians(b, t);
  out.push({{ means: Array.from(p.means), quats: Array.from(p.quats), scales: Array.from(p.scales),
              cov: Array.from(p.cov) }});
}}
console.log(JSON.stringify(out));
"""
    return _node(script, bundle)


# ---------------------------------------------------------------- Python: layout round trip
@pytest.mark.parametrize("clamp", [False, True])
def test_bundle_round_trip(tmp_path, clamp):
    av = make_avatar(n=200, clamp_to_face=clamp)
    frames = _frames(av)
    index = write_viewer_bundle(av, frames, tmp_path, fps=12.5, title="tiny <test>", vertex_encoding="float32")
    assert index == tmp_path / "index.html"
    h, a = read_viewer_bundle(tmp_path)
    p = av.params
    assert (h["num_vertices"], h["num_faces"], h["num_gaussians"], h["num_frames"]) == (42, 80, 200, 3)
    assert h["fps"] == 12.5 and h["scale_mode"] == "sqrt_area" and h["version"] == 3
    assert all(s["offset"] % 4 == 0 for s in h["sections"].values())
    assert np.array_equal(a["faces"], av.mesh.faces.numpy())
    assert np.array_equal(a["canonical_vertices"], av.mesh.vertices.numpy())
    assert np.array_equal(a["vertices"], torch.stack(frames).numpy().astype(np.float64))
    assert np.array_equal(a["gaussian_face"], p["face"].numpy())
    with torch.no_grad():
        uv = effective_uv(p, clamp).numpy()
        rot = torch.nn.functional.normalize(p["rotation"], dim=-1).numpy()
        rgb = (0.5 + SH_C0 * p["sh0"][:, 0]).clamp_min(0).numpy()
        # half floats: relative error <= 2^-11 (absolute for values below 1)
        half = 2.0**-11
        np.testing.assert_allclose(a["gaussian_uv"], uv, atol=half, rtol=half)
        np.testing.assert_allclose(a["gaussian_d"], p["d"].numpy(), atol=1e-7, rtol=half)
        np.testing.assert_allclose(a["gaussian_rotation"], rot, atol=half)
        np.testing.assert_allclose(a["gaussian_scale"], p["log_scale"].exp().numpy(), rtol=half)
        np.testing.assert_allclose(a["gaussian_opacity"], torch.sigmoid(p["opacity_logit"]).numpy(), atol=half)
        np.testing.assert_allclose(a["gaussian_rgb"], rgb, atol=half, rtol=half)
        # exactly the float16 rounding of each value
        assert np.array_equal(a["gaussian_scale"], p["log_scale"].exp().numpy().astype(np.float16).astype(np.float32))
    assert a["gaussians"].shape == (200, 8) and a["gaussians"].dtype == np.uint32
    if clamp:  # projected onto the triangle
        assert (a["gaussian_uv"] >= -1e-3).all() and (a["gaussian_uv"].sum(1) <= 1 + 1e-3).all()
    # index.html embeds the same header and bytes, and escapes the title
    page = index.read_text()
    data = re.search(r'id="avatar-data">([^<]*)<', page).group(1)
    assert base64.b64decode(data) == (tmp_path / "avatar.bin").read_bytes()
    header = json.loads(re.search(r'id="avatar-header">([^<]*)<', page).group(1))
    assert header == h
    assert "<title>tiny &lt;test&gt;</title>" in page and "__VIEWER_JS__" not in page


@pytest.mark.parametrize(
    "title", ["__VIEWER_JS__", "__AVATAR_DATA__ </script><script>alert(1)</script>", "a & b <!-- \u2028 __TITLE__"]
)
def test_title_cannot_break_the_page(tmp_path, title):
    """User text is inserted once, escaped, after the template is filled (no placeholder re-expansion)."""
    av = make_avatar(n=20)
    index = write_viewer_bundle(av, _frames(av), tmp_path, title=title)
    page = index.read_text()
    template = (Path(__file__).parents[2] / "src/meshsplat/viewer/static/index.html").read_text()
    js = (tmp_path / "viewer.js").read_text()
    assert page.count(js) == 1 and page.count("<script") == template.count("<script")
    assert page.count("</script>") == template.count("</script>")
    header = json.loads(re.search(r'id="avatar-header">([^<]*)<', page).group(1))
    assert header["title"] == title
    data = re.search(r'id="avatar-data">([^<]*)<', page).group(1)
    assert base64.b64decode(data) == (tmp_path / "avatar.bin").read_bytes()
    import html as html_mod

    assert f"<title>{html_mod.escape(title)}</title>" in page


def test_old_bundle_version_is_named(tmp_path):
    av = make_avatar(n=10)
    write_viewer_bundle(av, _frames(av), tmp_path)
    h = json.loads((tmp_path / "avatar.json").read_text())
    h["version"] = 1
    (tmp_path / "avatar.json").write_text(json.dumps(h))
    with pytest.raises(MeshsplatError, match="version 1"):
        read_viewer_bundle(tmp_path)


def test_int16_vertices_within_half_a_step(tmp_path):
    av = make_avatar(n=50)
    frames = torch.stack(_frames(av, ts=np.linspace(0, 1, 7)))
    write_viewer_bundle(av, frames, tmp_path)  # a [T,V,3] tensor, int16 by default
    h, a = read_viewer_bundle(tmp_path)
    assert h["vertex_encoding"] == "int16" and a["frames"].dtype == np.int16
    err = np.abs(a["vertices"] - frames.double().numpy()).max(axis=(0, 1))
    assert (err <= 0.5 * np.asarray(h["vertex_step"]) + 1e-7).all()
    assert (tmp_path / "avatar.bin").stat().st_size < 50 * 60 + 7 * 42 * 6 + 80 * 12 + 42 * 12 + 64


def test_default_camera_frames_the_animation(tmp_path):
    from meshsplat.camera import orbit_cameras

    av = make_avatar(n=30)
    frames = _frames(av)
    write_viewer_bundle(av, frames, tmp_path)
    cam = read_viewer_bundle(tmp_path)[0]["camera"]
    ref = orbit_cameras(frames, 800, 800)[0]
    np.testing.assert_allclose(np.asarray(cam["viewmat"]), ref.viewmat.numpy(), atol=1e-5)
    np.testing.assert_allclose(np.asarray(cam["K"]), ref.K.numpy(), rtol=1e-6)
    # an explicit Camera is kept (no roll) through its orbit description
    other = orbit_cameras(frames, 320, 240, azimuth_deg=70, elevation_deg=-20, fov_deg=45, distance=9.0)[0]
    write_viewer_bundle(av, frames, tmp_path / "b", camera=other)
    cam = read_viewer_bundle(tmp_path / "b")[0]["camera"]
    np.testing.assert_allclose(np.asarray(cam["viewmat"]), other.viewmat.numpy(), atol=1e-5)
    np.testing.assert_allclose(np.asarray(cam["K"]), other.K.numpy(), rtol=1e-5)
    assert (cam["width"], cam["height"]) == (320, 240)


def test_bad_inputs_raise_clear_errors(tmp_path):
    av = make_avatar(n=10)
    v = av.mesh.vertices
    with pytest.raises(MeshsplatError, match=r"frames\[1\].*\[V,3\]|frames\[1\].*42"):
        write_viewer_bundle(av, [v, v[:-1]], tmp_path)
    with pytest.raises(MeshsplatError, match="no frames"):
        write_viewer_bundle(av, [], tmp_path)
    with pytest.raises(MeshsplatError, match="frames"):
        write_viewer_bundle(av, [v * float("nan")], tmp_path)
    with pytest.raises(MeshsplatError, match="fps"):
        write_viewer_bundle(av, [v], tmp_path, fps=0)
    with pytest.raises(MeshsplatError, match="vertex_encoding"):
        write_viewer_bundle(av, [v], tmp_path, vertex_encoding="float16")
    with pytest.raises(MeshsplatError, match="camera"):
        write_viewer_bundle(av, [v], tmp_path, camera={"zoom": 2})
    with pytest.raises(MeshsplatError, match="not a viewer bundle"):
        read_viewer_bundle(tmp_path / "missing")


# ---------------------------------------------------------------- JS math under Node
def _bundle_avatar(av, a, mode):
    """float64 Avatar holding exactly the (half-float) Gaussian values of a bundle."""
    from meshsplat.gaussians.params import make_params
    from meshsplat.mesh import TriMesh

    t = {
        k: torch.from_numpy(np.asarray(a[k], np.float64))
        for k in (
            "gaussian_uv",
            "gaussian_d",
            "gaussian_rotation",
            "gaussian_scale",
            "gaussian_opacity",
            "gaussian_rgb",
        )
    }
    params = make_params(
        torch.from_numpy(a["gaussian_face"].astype(np.int64)),
        t["gaussian_uv"],
        d=t["gaussian_d"],
        log_scale=t["gaussian_scale"].log(),
        rotation=t["gaussian_rotation"],
        opacity_logit=torch.logit(t["gaussian_opacity"]),
        sh0=((t["gaussian_rgb"] - 0.5) / SH_C0)[:, None, :],
    )
    return Avatar(TriMesh(av.mesh.vertices.double(), av.mesh.faces), params, mode)


@needs_node
@pytest.mark.parametrize("mode,encoding", [("sqrt_area", "int16"), ("area", "float32"), ("none", "float32")])
def test_js_pose_matches_compose(tmp_path, mode, encoding):
    av = _with_scale_mode(make_avatar(n=300), mode)
    write_viewer_bundle(av, _frames(av), tmp_path, vertex_encoding=encoding)
    _, a = read_viewer_bundle(tmp_path)
    js = _js_pose(tmp_path)
    av64 = _bundle_avatar(av, a, mode)
    for t, out in enumerate(js):
        with torch.no_grad():
            ref = av64.compose(torch.from_numpy(a["vertices"][t]))  # the vertices the bundle stores
        means = np.asarray(out["means"]).reshape(-1, 3)
        quats = np.asarray(out["quats"]).reshape(-1, 4)
        scales = np.asarray(out["scales"]).reshape(-1, 3)
        extent = float(np.abs(a["vertices"][t]).max())
        np.testing.assert_allclose(means, ref.means.numpy(), atol=1e-4 * extent, rtol=1e-4)
        rq = ref.quats.numpy()
        sign = np.where((quats * rq).sum(1, keepdims=True) < 0, -1.0, 1.0)  # q and -q: the same rotation
        np.testing.assert_allclose(quats * sign, rq, atol=1e-5)
        np.testing.assert_allclose(scales, ref.scales.numpy(), rtol=1e-4)
        from meshsplat.render.projection import covariance_3d

        cov = covariance_3d(ref.quats, ref.scales).numpy()[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
        scale2 = ref.scales.numpy().max(1, keepdims=True) ** 2
        np.testing.assert_allclose(np.asarray(out["cov"]).reshape(-1, 6), cov, atol=1e-4 * scale2.max())
    assert not np.allclose(js[0]["means"], js[-1]["means"])  # the pose moves the Gaussians


@needs_node
def test_js_sort_and_camera(tmp_path):
    av = make_avatar(n=50)
    write_viewer_bundle(
        av,
        _frames(av),
        tmp_path,
        camera={"azimuth_deg": 30, "elevation_deg": 25, "width": 640, "height": 480, "fov_deg": 40},
    )
    h = read_viewer_bundle(tmp_path)[0]
    cam = h["camera"]
    rng = np.random.default_rng(0)
    means = rng.normal(size=(3000, 3)) * [1, 1, 3] + [0, 0, 2.0]  # some behind the near plane
    means[:40] = means[40]  # exact ties
    script = f"""
import {{ orbitViewmat, intrinsics }} from {json.dumps((tmp_path / "viewer.js").as_uri())};
import {{ sortByDepth }} from {REFERENCE_JS};
const c = {json.dumps(cam)};
const means = Float32Array.from({json.dumps(means.ravel().tolist())});
const vm = [0.6, 0, 0.8, 0, 0, 1, 0, 0, -0.8, 0, 0.6, 0.1, 0, 0, 0, 1];  // rotated: float32 depth rounding
const order = new Uint32Array(means.length / 3);
const n = sortByDepth(means, order.length, vm, order);
console.log(JSON.stringify({{ n, order: Array.from(order.subarray(0, n)),
  viewmat: Array.from(orbitViewmat(c.center, c.distance, c.azimuth_deg, c.elevation_deg)),
  K: intrinsics(c.width, c.height, c.fov_deg) }}));
"""
    out = _node(script, tmp_path)
    m32 = means.astype(np.float32).astype(np.float64)
    z = (-0.8 * m32[:, 0] + 0.6 * m32[:, 2] + 0.1).astype(np.float32)
    visible = np.nonzero(z >= 0.01)[0]
    order = np.asarray(out["order"])
    assert out["n"] == len(visible) and sorted(order.tolist()) == visible.tolist()  # a permutation of the visible
    bin_width = (z[visible].max() - z[visible].min()) / 65535
    assert (np.diff(z[order]) <= bin_width * 1.01).all()  # back to front up to one 16-bit depth bin
    np.testing.assert_allclose(np.asarray(out["viewmat"]).reshape(4, 4), np.asarray(cam["viewmat"]), atol=1e-9)
    K = np.asarray(cam["K"])
    np.testing.assert_allclose(out["K"], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], rtol=1e-12)


def _rig_bundle(tmp_path, name, n=300, seed=0):
    from meshsplat.drivers import GltfDriver
    from meshsplat.gaussians import init_params
    from meshsplat.mesh import TriMesh
    from meshsplat.paths import assets_dir
    from meshsplat.viewer.rig import avatar_driver

    glb = assets_dir() / "gltf" / f"{name}.glb"
    drv0 = GltfDriver(glb)
    mesh = TriMesh(drv0.rest_vertices(), drv0.faces)
    av = Avatar(mesh, init_params(mesh, n, generator=torch.Generator().manual_seed(seed)))
    drv = avatar_driver(av, glb)
    write_viewer_bundle(av, None, tmp_path, rig=drv, camera={"width": 256, "height": 256})
    return av, drv


@needs_node
@pytest.mark.parametrize("name", ["CesiumMan", "RobotExpressive"])
def test_js_rig_matches_gltf_driver(tmp_path, name):
    """evalRig + skinVertices (the page's clip evaluation and, on the CPU, its GPU skinning) equal
    GltfDriver.vertices_at, morph weight overrides included."""
    _av, drv = _rig_bundle(tmp_path, name, n=20)
    h = read_viewer_bundle(tmp_path)[0]
    clips = h["driver"]["clips"]
    cases = [(0, 0.0, None), (0, 0.37, None), (len(clips) - 1, 0.9, None), (0, 123.0, None)]
    groups = h["driver"]["morph_groups"]
    if groups:
        cases.append((2, 0.5, {groups[0]["weight_base"]: 1.0, groups[-1]["weight_base"] + 1: 0.6}))
    script = f"""
import {{ decodeBundle, evalRig, skinVertices }} from {json.dumps((tmp_path / "viewer.js").as_uri())};
import fs from "fs";
const h = JSON.parse(fs.readFileSync({json.dumps(str(tmp_path / "avatar.json"))}, "utf8"));
const b = decodeBundle(h, fs.readFileSync({json.dumps(str(tmp_path / "avatar.bin"))}));
const out = [];
for (const [clip, t, ov] of {json.dumps([[c, t, o] for c, t, o in cases])}) {{
  const w = new Float64Array(b.rig.defaultWeights.length).fill(NaN);
  for (const [i, v] of Object.entries(ov || {{}})) w[Number(i)] = v;
  const s = evalRig(b.rig, clip, b.rig.clips[clip].start + t, w);
  out.push(Array.from(skinVertices(b.rig, s, b.V)));
}}
console.log(JSON.stringify(out));
"""
    js = _node(script, tmp_path)
    extent = float(np.abs(drv.rest_vertices().numpy()).max())
    for (clip, t, ov), got in zip(cases, js, strict=True):
        name_ = clips[clip]["name"]
        morph = None
        if ov:
            morph = {}
            for g in groups:
                w = drv._morph_weights(name_, clips[clip]["start"] + t, None)[g["node"]].copy()
                for i, v in ov.items():
                    if g["weight_base"] <= int(i) < g["weight_base"] + g["count"]:
                        w[int(i) - g["weight_base"]] = v
                morph[g["node"]] = w
        ref = drv.vertices_at(clips[clip]["start"] + t, clip=name_, morph_weights=morph).numpy()
        np.testing.assert_allclose(np.asarray(got).reshape(-1, 3), ref, atol=2e-6 * extent)
    if groups:  # the override moved something
        assert not np.allclose(
            js[-1], drv.vertices_at(clips[2]["start"] + 0.5, clip=clips[2]["name"]).numpy().ravel(), atol=1e-6
        )


@needs_node
def test_worker_sort_keys_are_the_drawn_centre_depths(tmp_path):
    """The worker's keys (from vertices and normals only) equal the camera depth of the centres the
    shader draws (poseGaussians), and sortJob returns a back-to-front permutation of the visible."""
    av = make_avatar(n=400)
    write_viewer_bundle(av, _frames(av), tmp_path, vertex_encoding="float32")
    script = f"""
import {{ decodeBundle, frameVertices, vertexNormals, sortJob, sortSetup, sortScratch,
         orbitViewmat }} from {json.dumps((tmp_path / "viewer.js").as_uri())};
import {{ poseGaussians, gaussianDepths }} from {REFERENCE_JS};
import fs from "fs";
const h = JSON.parse(fs.readFileSync({json.dumps(str(tmp_path / "avatar.json"))}, "utf8"));
const b = decodeBundle(h, fs.readFileSync({json.dumps(str(tmp_path / "avatar.bin"))}));
const c = h.camera, vm = orbitViewmat(c.center, c.distance, 35, 20);
const p = Float32Array.from(frameVertices(b, 2));
const keys = gaussianDepths({{ ...sortSetup(b) }}, p, vertexNormals(b.faces, b.V, p), vm).depth;
const m = poseGaussians(b, 2).means;
const z = Array.from({{ length: b.N }}, (_, g) => vm[8] * m[3 * g] + vm[9] * m[3 * g + 1] + vm[10] * m[3 * g + 2] + vm[11]);
const S = sortScratch(sortSetup(b));
const r1 = sortJob(S, {{ id: 1, verts: p, viewmat: vm }});
const vm2 = orbitViewmat(c.center, c.distance, 36, 20);
const r2 = sortJob(S, {{ id: 2, verts: p, viewmat: vm2 }});
const keys2 = gaussianDepths({{ ...sortSetup(b) }}, p, vertexNormals(b.faces, b.V, p), vm2).depth;
console.log(JSON.stringify({{ keys: Array.from(keys), keys2: Array.from(keys2), z, order: Array.from(r1.order.subarray(0, r1.n)),
                              bin: (r1.hi - r1.lo) / 65535, moved1: r1.moved === Infinity ? -1 : r1.moved, moved2: r2.moved }}));
"""
    out = _node(script, tmp_path)
    keys, z = np.asarray(out["keys"]), np.asarray(out["z"])
    np.testing.assert_allclose(keys, z, atol=1e-5 * np.abs(z).max())
    order = np.asarray(out["order"])
    assert sorted(order.tolist()) == np.nonzero(keys >= 0.01)[0].tolist()
    assert (np.diff(keys[order]) <= out["bin"] * 1.01).all()  # back to front up to one 16-bit bin
    assert out["bin"] < 1.5 * (keys.max() - keys.min()) / 65535  # the range bound from the vertices is tight
    actual = np.abs(np.asarray(out["keys2"]) - keys).max()  # the reported motion bounds the real one
    assert out["moved1"] == -1 and actual <= out["moved2"] < 0.2 * (keys.max() - keys.min())


def _small_blendshapes(av, frames=6, seed=1):
    """A BlendshapeDriver on the test avatar's mesh: 4 random expressions (float16 values), each moving
    only half the vertices (as a face's expressions move a part of it), a sequence."""
    from meshsplat.drivers import BlendshapeDriver

    g = torch.Generator().manual_seed(seed)
    v = av.mesh.vertices
    deltas = (0.2 * torch.randn(4, *v.shape, generator=g)).half().float()
    for e in range(4):
        deltas[e, (v[:, e % 3] > 0) ^ (e == 3)] = 0.0
    return BlendshapeDriver(
        v,
        av.mesh.faces,
        deltas,
        names=["jawOpen", "mouthSmile_L", "browInnerUp_L", "eyeBlink_R"],
        weights=torch.rand(frames, 4, generator=g),
        rotations=0.3 * torch.randn(frames, 3, generator=g),
        translations=0.1 * torch.randn(frames, 3, generator=g),
    )


@needs_node
def test_js_blendshape_rig_matches_driver(tmp_path):
    """A blendshape model ships as a morph rig: at the sequence's keys the page's posing equals
    BlendshapeDriver.vertices (expressions, head rotation about the pivot, translation)."""
    av = make_avatar(n=30)
    drv = _small_blendshapes(av)
    write_viewer_bundle(av, None, tmp_path, fps=10.0, rig=drv)
    h = read_viewer_bundle(tmp_path)[0]
    g = h["driver"]["morph_groups"][0]
    assert g["names"] == drv.names and h["driver"]["morph_encoding"] == "float16-sparse"
    # only the deltas that move their vertex are stored, vertex by vertex
    a = read_viewer_bundle(tmp_path)[1]
    moves = (drv.deltas != 0).any(-1)  # [E, V]
    assert a["morph_deltas"].shape == (int(moves.sum()), 2) and 0 < moves.float().mean() < 0.75
    np.testing.assert_array_equal(a["morph_info"][:, 1], moves.sum(0).numpy())
    script = f"""
import {{ decodeBundle, evalRig, skinVertices }} from {json.dumps((tmp_path / "viewer.js").as_uri())};
import fs from "fs";
const h = JSON.parse(fs.readFileSync({json.dumps(str(tmp_path / "avatar.json"))}, "utf8"));
const b = decodeBundle(h, fs.readFileSync({json.dumps(str(tmp_path / "avatar.bin"))}));
const out = [];
for (let i = 0; i < 6; i++) out.push(Array.from(skinVertices(b.rig, evalRig(b.rig, 0, i / 10, null), b.V)));
const w = new Float64Array(4).fill(NaN); w[1] = 0.9;
out.push(Array.from(skinVertices(b.rig, evalRig(b.rig, 0, 0.2, w), b.V)));
console.log(JSON.stringify(out));
"""
    js = _node(script, tmp_path)
    for i in range(6):
        np.testing.assert_allclose(np.asarray(js[i]).reshape(-1, 3), drv.vertices(i).numpy(), atol=2e-6)
    wts = drv.weights[2].clone()
    wts[1] = 0.9
    np.testing.assert_allclose(
        np.asarray(js[6]).reshape(-1, 3), drv.pose(wts, drv.rotations[2], drv.translations[2]).numpy(), atol=2e-6
    )


def _one_side(av, n_min=20):
    """The avatar with only its Gaussians on faces whose centroid has x > 0.35 (a part of the mesh)."""
    v, f = av.mesh.vertices, av.mesh.faces
    keep = v[f].mean(1)[:, 0][av.params["face"]] > 0.35
    assert int(keep.sum()) >= n_min
    return Avatar(av.mesh, {k: t[keep] for k, t in av.params.items()}, av.scale_mode, av.clamp_to_face)


@needs_node
def test_draw_mesh_holds_every_face_around_the_gaussians(tmp_path):
    """drawMesh (the GPU posing passes' mesh): the faces that carry Gaussians, with each of their corners'
    faces in the bundle's order (a corner's normal and frame sum the same faces in the same order), and
    the Gaussians' faces renumbered; the whole mesh when every face carries one."""
    av = make_avatar(n=400)
    part = _one_side(av)
    for name, a in (("part", part), ("whole", av)):
        write_viewer_bundle(a, _frames(a), tmp_path / name)
    script = f"""
import {{ decodeBundle, drawMesh, vertexFaces }} from {json.dumps((tmp_path / "part" / "viewer.js").as_uri())};
import fs from "fs";
const load = (d) => decodeBundle(JSON.parse(fs.readFileSync(d + "/avatar.json", "utf8")), fs.readFileSync(d + "/avatar.bin"));
const out = {{}};
for (const name of ["part", "whole"]) {{
  const b = load({json.dumps(str(tmp_path))} + "/" + name), m = drawMesh(b);
  const full = vertexFaces(b.faces, b.V), mine = vertexFaces(m.faces, m.V);
  const vert = (i) => m.vertex ? m.vertex[i] : i, face = (k) => m.face ? m.face[k] : k;
  const faceOf = Array.from(m.gaussianFace, (k, g) => [face(k) === b.face[g],
    [0, 1, 2].every((j) => vert(m.faces[3 * k + j]) === b.faces[3 * b.face[g] + j])]);
  const rings = []; // each Gaussian corner's faces: the draw mesh's (as bundle faces) and the bundle's
  for (let g = 0; g < b.N; g++) for (let j = 0; j < 3; j++) {{
    const i = m.faces[3 * m.gaussianFace[g] + j], v = vert(i);
    rings.push([Array.from(mine.adj.subarray(mine.va[4 * i], mine.va[4 * i] + mine.va[4 * i + 1]), face),
                Array.from(full.adj.subarray(full.va[4 * v], full.va[4 * v] + full.va[4 * v + 1]))]);
  }}
  out[name] = {{ V: m.V, F: m.F, bV: b.V, bF: b.F, whole: m.vertex === null && m.face === null, faceOf, rings }};
}}
console.log(JSON.stringify(out));
"""
    js = _node(script, tmp_path)
    part_js, whole_js = js["part"], js["whole"]
    assert not part_js["whole"] and part_js["F"] < part_js["bF"] and part_js["V"] < part_js["bV"]
    assert all(a and b for a, b in part_js["faceOf"])
    assert all(mine == full for mine, full in part_js["rings"]) and len(part_js["rings"]) == 3 * part.num_gaussians
    assert whole_js["whole"] and (whole_js["V"], whole_js["F"]) == (whole_js["bV"], whole_js["bF"])


@pytest.mark.slow
def test_browser_draw_mesh_poses_as_the_whole_mesh(tmp_path):
    """Gaussians on part of the mesh: the page posing only the faces around them (the default) draws the
    image that posing the whole mesh (?mesh=all) draws, bit for bit, for vertex frames and a live
    blend-shape rig, and both match avatar.render."""
    av = _one_side(make_avatar(n=400))
    write_viewer_bundle(av, _frames(av), tmp_path / "f", camera={"width": 256, "height": 256})
    h, a = read_viewer_bundle(tmp_path / "f")
    drawn = _shoot(tmp_path / "f", 1, 256, tmp_path / "f.png")
    whole = _page_image((tmp_path / "f" / "index.html").as_uri() + "?frame=1&ui=0&mesh=all", 256, tmp_path / "fa.png")
    assert np.array_equal(drawn, whole)
    assert _psnr(drawn, _render_ref(av, a["vertices"][1], h["camera"])) > 40.0
    assert (drawn < 250).any(axis=-1).mean() > 0.01  # the avatar is drawn
    drv = _small_blendshapes(av)
    write_viewer_bundle(av, None, tmp_path / "r", fps=10.0, rig=drv, camera={"width": 256, "height": 256})
    cam = read_viewer_bundle(tmp_path / "r")[0]["camera"]
    url = (tmp_path / "r" / "index.html").as_uri() + "?time=0.3&morph=0:1&ui=0"
    drawn = _page_image(url, 256, tmp_path / "r.png")
    assert np.array_equal(drawn, _page_image(url + "&mesh=all", 256, tmp_path / "ra.png"))
    wts = drv.weights[3].clone()
    wts[0] = 1.0
    assert _psnr(drawn, _render_ref(av, drv.pose(wts, drv.rotations[3], drv.translations[3]), cam)) > 40.0


# ---------------------------------------------------------------- CLI
def test_view_cli_vertices_and_dataset(tmp_path, capsys):
    from _eval_kit import make_dataset
    from meshsplat.cli.main import main

    av = make_avatar(n=80)
    ds = make_dataset(av, tmp_path / "ds")
    run = make_run(av, tmp_path / "run", ds)
    seq = torch.stack(_frames(av, ts=(0.0, 0.2, 0.5, 0.9)))
    np.save(tmp_path / "seq.npy", seq.numpy())
    assert (
        main(
            [
                "view",
                str(run),
                "--out",
                str(tmp_path / "v1"),
                "--animation",
                "vertices",
                str(tmp_path / "seq.npy"),
                "--frames",
                "3",
                "--fps",
                "10",
                "--vertex-encoding",
                "float32",
            ]
        )
        == 0
    )
    h, a = read_viewer_bundle(tmp_path / "v1")
    assert h["num_frames"] == 3 and h["fps"] == 10.0 and h["title"] == "run"
    np.testing.assert_array_equal(a["vertices"], seq[:3].double().numpy())
    assert "open file://" in capsys.readouterr().out
    # default: the dataset's stored meshes, in order; --split picks one split's frames
    assert main(["view", str(run), "--out", str(tmp_path / "v2")]) == 0
    assert read_viewer_bundle(tmp_path / "v2")[0]["num_frames"] == 5
    assert main(["view", str(run), "--out", str(tmp_path / "v3"), "--split", "test_frames"]) == 0
    _, a3 = read_viewer_bundle(tmp_path / "v3")
    np.testing.assert_allclose(a3["vertices"][0], deform(av.mesh.vertices, 0.6).numpy(), atol=1e-4)
    # a title that names a template placeholder stays plain text (it used to break the page)
    assert main(["view", str(run), "--out", str(tmp_path / "v5"), "--title", "__VIEWER_JS__"]) == 0
    page = (tmp_path / "v5" / "index.html").read_text()
    assert "<title>__VIEWER_JS__</title>" in page and page.count("export function decodeBundle") == 1
    assert read_viewer_bundle(tmp_path / "v5")[0]["title"] == "__VIEWER_JS__"
    # user errors: one line, exit 2
    assert main(["view", str(run), "--out", str(tmp_path / "v4"), "--animation", "gltf"]) == 2
    assert main(["view", str(run), "--out", str(tmp_path / "v4"), "--animation", "bvh", "x"]) == 2
    assert main(["view", str(tmp_path / "nope"), "--out", str(tmp_path / "v4")]) == 2
    err = capsys.readouterr().err
    assert "--animation gltf needs a FILE" in err and "expected one of" in err and "run not found" in err


def test_view_cli_gltf(tmp_path, assets):
    """A CesiumMan avatar driven by its glTF clip; the bundle stays small."""
    from meshsplat.cli.main import main
    from meshsplat.drivers import GltfDriver
    from meshsplat.gaussians import init_params
    from meshsplat.mesh import TriMesh

    glb = assets / "gltf" / "CesiumMan.glb"
    drv = GltfDriver(glb, fps=25)
    mesh = TriMesh(drv.rest_vertices(), drv.faces)
    av = Avatar(mesh, init_params(mesh, 2000, generator=torch.Generator().manual_seed(0)))
    run = make_run(av, tmp_path / "run", None)
    assert (
        main(
            [
                "view",
                str(run),
                "--out",
                str(tmp_path / "v"),
                "--animation",
                "gltf",
                str(glb),
                "--bake",
                "--frames",
                "20",
            ]
        )
        == 0
    )
    h, a = read_viewer_bundle(tmp_path / "v")
    assert h["num_frames"] == 20 and h["num_vertices"] == mesh.num_vertices and h["driver"] == {"kind": "frames"}
    assert np.abs(a["vertices"][10] - a["vertices"][0]).max() > 1e-2  # it moves
    assert (tmp_path / "v" / "index.html").stat().st_size < 2_000_000
    # live (default): the rig and clip ship instead of frames, and the page is smaller
    assert main(["view", str(run), "--out", str(tmp_path / "live"), "--animation", "gltf", str(glb)]) == 0
    h, a = read_viewer_bundle(tmp_path / "live")
    assert h["driver"]["kind"] == "gltf" and h["num_frames"] == 0 and "frames" not in a
    assert [c["name"] for c in h["driver"]["clips"]] == drv.clips and a["rig_base"].shape == (mesh.num_vertices, 3)
    assert (tmp_path / "live" / "index.html").stat().st_size < (tmp_path / "v" / "index.html").stat().st_size
    assert (
        main(["view", str(run), "--out", str(tmp_path / "x"), "--animation", "gltf", str(glb), "--clip", "nope"]) == 2
    )


# ---------------------------------------------------------------- headless browser (slow)
# CI (.ci/run) installs Debian's chromium when it is missing and sets MESHSPLAT_REQUIRE_BROWSER=1,
# so there the browser tests fail instead of skipping.
REQUIRE_BROWSER = os.environ.get("MESHSPLAT_REQUIRE_BROWSER") == "1"


def _chromium() -> str:
    path = find_chromium()
    if path is None:
        if REQUIRE_BROWSER:
            pytest.fail("chromium is not installed (MESHSPLAT_REQUIRE_BROWSER=1)")
        pytest.skip("chromium is not installed")
    return path


def _psnr(img: np.ndarray, ref: np.ndarray) -> float:
    return float(10 * np.log10(255.0**2 / max(((img - ref) ** 2).mean(), 1e-10)))


def _page_image(url: str, size: int, out: Path) -> np.ndarray:
    """A ``size``-square screenshot of the page at ``url`` (saved to ``out``) as float RGB ``[H,W,3]``."""
    from PIL import Image

    screenshot(url, size, size, out, chromium=_chromium())
    return np.asarray(Image.open(out).convert("RGB"), dtype=np.float64)


def _shoot(bundle: Path, frame: int, size: int, out: Path) -> np.ndarray:
    return _page_image((bundle / "index.html").as_uri() + f"?frame={frame}&ui=0", size, out)


@pytest.mark.slow
def test_browser_screenshot_matches_rasterizer(tmp_path):
    """GPU posing (vertex shader), worker sort, one draw call: the page equals avatar.render."""
    av = make_avatar(n=400)
    frames = _frames(av)
    write_viewer_bundle(av, frames, tmp_path / "b", camera={"width": 256, "height": 256})
    h, a = read_viewer_bundle(tmp_path / "b")
    cam = h["camera"]
    for frame in (0, 1):
        ref = av.render(
            torch.from_numpy(a["vertices"][frame]).float(), _bundle_camera(cam, 256), background=torch.ones(3)
        ).image
        ref = ref.detach().clamp(0, 1).numpy() * 255
        img = _shoot(tmp_path / "b", frame, 256, tmp_path / f"shot{frame}.png")
        assert img.shape == ref.shape
        psnr = _psnr(img, ref)
        print(f"browser vs rasterizer, frame {frame}: PSNR {psnr:.1f} dB")
        assert psnr > 40.0, psnr
        assert (img < 250).any(axis=-1).mean() > 0.02  # the avatar is drawn, not an empty page
    # sorting on the main thread (?worker=0, the fallback without Web Workers) draws the same image
    same = _page_image((tmp_path / "b" / "index.html").as_uri() + "?frame=1&ui=0&worker=0", 256, tmp_path / "main.png")
    assert np.array_equal(same, img)
    # colours <= 1: the 8-bit path (?float=0) composites the same image, up to its rounding after every blend
    eight = _page_image((tmp_path / "b" / "index.html").as_uri() + "?frame=1&ui=0&float=0", 256, tmp_path / "8bit.png")
    print(
        f"float vs 8-bit blending, frame 1: PSNR {_psnr(img, eight):.1f} dB; 8-bit vs rasterizer {_psnr(eight, ref):.1f} dB"
    )
    assert _psnr(img, eight) > 45.0


def _bundle_camera(cam, size):
    """The Camera of a viewer bundle's camera record, rendered at ``size`` x ``size``."""
    return Camera(torch.tensor(cam["viewmat"]).float(), torch.tensor(cam["K"]).float(), size, size)


def _render_ref(av, verts, cam, size=256):
    ref = av.render(torch.as_tensor(verts).float(), _bundle_camera(cam, size), background=torch.ones(3)).image
    return ref.detach().clamp(0, 1).numpy() * 255


@pytest.mark.slow
def test_browser_live_blendshapes_match_rasterizer(tmp_path):
    """An ARKit-style blendshape rig (morph targets + rigid head pose) live in the page, a weight
    set by URL, against avatar.render of BlendshapeDriver.pose."""
    from PIL import Image

    av = make_avatar(n=400)
    drv = _small_blendshapes(av)
    write_viewer_bundle(av, None, tmp_path / "b", fps=10.0, rig=drv, camera={"width": 256, "height": 256})
    cam = read_viewer_bundle(tmp_path / "b")[0]["camera"]
    wts = drv.weights[3].clone()
    wts[0] = 1.0
    ref = _render_ref(av, drv.pose(wts, drv.rotations[3], drv.translations[3]), cam)
    screenshot(
        (tmp_path / "b" / "index.html").as_uri() + "?time=0.3&morph=0:1&ui=0",
        256,
        256,
        tmp_path / "s.png",
        chromium=_chromium(),
    )
    img = np.asarray(Image.open(tmp_path / "s.png").convert("RGB"), dtype=np.float64)
    psnr = _psnr(img, ref)
    print(f"browser live blendshapes vs rasterizer: PSNR {psnr:.1f} dB")
    assert psnr > 40.0, psnr


@pytest.mark.slow
def test_browser_live_gltf_skin_and_morphs_match_rasterizer(tmp_path):
    """Live drivers in the page (skinning + morph targets on the GPU) against avatar.render of
    GltfDriver's vertices at the same clip time and weights."""
    from PIL import Image

    for name, query, morph in (
        ("CesiumMan", "time=0.8", None),
        ("RobotExpressive", "clip=Wave&time=0.5&morph=0:1,4:0.7", True),
    ):
        folder = tmp_path / name
        av, drv = _rig_bundle(folder, name, n=3000)
        h = read_viewer_bundle(folder)[0]
        cam, d = h["camera"], h["driver"]
        clip = next(
            c
            for c in d["clips"]
            if c["name"] == (query.split("clip=")[1].split("&")[0] if "clip=" in query else d["clip"])
        )
        t = clip["start"] + float(query.split("time=")[1].split("&")[0])
        weights = None
        if morph:
            weights = {}
            for g in d["morph_groups"]:
                w = drv._morph_weights(clip["name"], t, None)[g["node"]].copy()
                for i, v in ((0, 1.0), (4, 0.7)):
                    if g["weight_base"] <= i < g["weight_base"] + g["count"]:
                        w[i - g["weight_base"]] = v
                weights[g["node"]] = w
        ref = _render_ref(av, drv.vertices_at(t, clip=clip["name"], morph_weights=weights), cam)
        url = (folder / "index.html").as_uri() + f"?{query}&ui=0"
        screenshot(url, 256, 256, tmp_path / f"{name}.png", chromium=_chromium())
        img = np.asarray(Image.open(tmp_path / f"{name}.png").convert("RGB"), dtype=np.float64)
        psnr = _psnr(img, ref)
        print(f"browser live glTF ({name}, {query}) vs rasterizer: PSNR {psnr:.1f} dB")
        assert psnr > 40.0, psnr
        assert (img < 250).any(axis=-1).mean() > 0.01


@pytest.mark.slow
def test_view_cli_blendshapes_ict_head(tmp_path, assets, capsys):
    """`--animation blendshapes` ships the ICT FaceKit ARKit model live (one slider per expression,
    the talking sequence as a clip); a mismatched avatar is a one-line error."""
    from meshsplat.cli.main import main
    from meshsplat.drivers import BlendshapeDriver
    from meshsplat.gaussians import init_params
    from meshsplat.mesh import TriMesh

    drv = BlendshapeDriver.from_npz(assets / "ict_facekit" / "ict_face_arkit53.npz")
    mesh = TriMesh(drv.neutral, drv.faces)
    av = Avatar(mesh, init_params(mesh, 500, generator=torch.Generator().manual_seed(0)))
    run = make_run(av, tmp_path / "run", None)
    assert main(["view", str(run), "--out", str(tmp_path / "v"), "--animation", "blendshapes", "--frames", "10"]) == 0
    h, a = read_viewer_bundle(tmp_path / "v")
    d = h["driver"]
    assert d["kind"] == "gltf" and d["morph_groups"][0]["names"] == drv.names and "jawOpen" in drv.names
    assert d["clips"][0]["duration"] == pytest.approx(9 / 25) and d["morph_encoding"] == "float16-sparse"
    moves = int((drv.deltas.half() != 0).any(-1).sum())  # an expression moves part of the face: 43% of (shape, vertex)
    assert a["morph_deltas"].shape == (moves, 2) and moves < 0.5 * len(drv.names) * 26719
    assert "live blendshapes" in capsys.readouterr().out
    small = make_run(make_avatar(n=20), tmp_path / "small", None)
    assert main(["view", str(small), "--out", str(tmp_path / "x"), "--animation", "blendshapes"]) == 2
    assert "driver mesh has 26719 vertices" in capsys.readouterr().err


def shaded_avatar(
    n: int = 400, sh_degree: int = 2, sh_frame: str = "triangle", normal: str = "phong", specular: bool = False
) -> Avatar:
    """The test avatar with pose-dependent shading: a strongly directional learned irradiance (key light
    from +x+y, coloured) and view-dependent SH bands in the triangle frame; ``specular``: plus an added
    highlight from -x+z (shading.specular=sh2), negative in places."""
    av = make_avatar(n=n, sh_degree=sh_degree)
    coeffs = torch.zeros(9, 3)
    coeffs[0] = torch.tensor([2.2, 2.0, 1.8])
    coeffs[1] = torch.tensor([0.9, 0.6, 0.3])  # y
    coeffs[3] = torch.tensor([1.1, 0.8, 1.2])  # x
    coeffs[4] = torch.tensor([0.4, -0.3, 0.2])
    coeffs[6] = torch.tensor([-0.3, 0.2, 0.1])
    coeffs[8] = torch.tensor([0.2, 0.3, -0.4])
    spec = None
    if specular:
        spec = torch.zeros(9, 3)
        spec[0] = torch.tensor([0.2, 0.25, 0.3])
        spec[3] = torch.tensor([-0.3, -0.25, -0.2])  # x
        spec[2] = torch.tensor([0.25, 0.2, 0.3])  # z
        spec[5] = torch.tensor([0.1, -0.1, 0.05])  # yz
        spec[8] = torch.tensor([-0.1, 0.05, 0.1])
    shading = Shading(coeffs, normal, specular="sh2" if specular else "none", specular_coeffs=spec)
    return Avatar(av.mesh, av.params, av.scale_mode, shading=shading, sh_frame=sh_frame)


def test_bundle_carries_the_shading(tmp_path):
    av = shaded_avatar(n=50, sh_degree=3, normal="axis")
    write_viewer_bundle(av, _frames(av), tmp_path)
    h, a = read_viewer_bundle(tmp_path)
    assert h["sh_degree"] == 3 and h["sh_frame"] == "triangle" and h["antialiased"] is False
    assert h["shading"]["normal"] == "axis"
    np.testing.assert_allclose(h["shading"]["coeffs"], av.shading.coeffs.numpy(), rtol=1e-7)
    shn = av.params["shN"].detach().numpy()
    assert a["gaussian_sh_rest"].shape == shn.shape == (50, 15, 3)
    np.testing.assert_allclose(a["gaussian_sh_rest"], shn, rtol=2**-11, atol=1e-7)  # half floats
    # the DC colour is the albedo (0.5 + C0 sh0, not clamped: the page adds the bands, clamps, shades)
    np.testing.assert_allclose(
        a["gaussian_rgb"], 0.5 + SH_C0 * av.params["sh0"].detach().numpy()[:, 0], rtol=2**-11, atol=1e-7
    )
    assert a["sh_rest"].shape == (50, 24)  # 45 halves -> 23 words -> whole texels
    plain = make_avatar(n=50)
    write_viewer_bundle(plain, _frames(plain), tmp_path / "p")
    h, a = read_viewer_bundle(tmp_path / "p")
    assert h["shading"] is None and h["sh_degree"] == 0 and "sh_rest" not in a


@pytest.mark.slow
@pytest.mark.parametrize(
    "sh_degree,sh_frame,normal,antialiased,specular",
    [(2, "triangle", "phong", False, False), (1, "world", "axis", True, False), (2, "triangle", "phong", False, True)],
)
def test_browser_shading_matches_rasterizer(tmp_path, sh_degree, sh_frame, normal, antialiased, specular):
    """Pose-dependent shading on the GPU: the shaded page equals avatar.render in two poses, on the
    subject and on the full frame; the canonical pose's shading baked in would not. With ``specular``
    the page adds the specular term (and leaving it out would not match)."""
    av = shaded_avatar(sh_degree=sh_degree, sh_frame=sh_frame, normal=normal, specular=specular)
    av.antialiased = antialiased
    frames = _frames(av, ts=(0.0, 1.0))
    write_viewer_bundle(av, frames, tmp_path / "b", camera={"width": 256, "height": 256})
    h, a = read_viewer_bundle(tmp_path / "b")
    refs = []
    for frame in (0, 1):
        ref = _render_ref(av, a["vertices"][frame], h["camera"])
        img = _shoot(tmp_path / "b", frame, 256, tmp_path / f"shot{frame}.png")
        subject = (np.abs(ref - 255).max(-1) > 2) | (np.abs(img - 255).max(-1) > 2)
        full, on = _psnr(img, ref), _psnr(img[subject], ref[subject])
        print(f"shaded page vs avatar.render, frame {frame}: full {full:.1f} dB, subject {on:.1f} dB")
        assert subject.mean() > 0.05
        assert on >= 40.0 and full >= 40.0, (on, full)
        refs.append(ref)
    # the colours do follow the pose: the two frames' shading differs by far more than the page's error
    assert _psnr(refs[0], refs[1]) < 30.0
    if specular:  # the term is visible: the same avatar without it renders far from the page's error
        assert av.shading is not None and av.shading.specular is not None
        without = Avatar(
            av.mesh, av.params, av.scale_mode, shading=Shading(av.shading.coeffs, normal), sh_frame=sh_frame
        )
        without.antialiased = antialiased
        assert _psnr(_render_ref(without, a["vertices"][0], h["camera"]), refs[0]) < 30.0


@pytest.mark.slow
def test_browser_bright_splats_blend_unclamped(tmp_path):
    """Colours above 1 (the shaded test avatar with its irradiance 1.5 times as bright) where splats
    overlap with partial alpha: the page blends into a float target and clamps the blended image once,
    as avatar.render does, on a white and a black background and after the canvas is resized (a new
    size, then the same pixels at twice the pixel ratio). Blending straight into the 8-bit canvas
    (?float=0, the page before, and its fallback without a float target) clamps every splat's
    premultiplied colour and is far off; the page says so in its status line."""
    from PIL import Image

    from _browser import open_page
    from meshsplat.camera import intrinsics

    shaded = shaded_avatar()
    assert shaded.shading is not None
    shading = Shading(1.5 * shaded.shading.coeffs, "phong")
    av = Avatar(shaded.mesh, shaded.params, shaded.scale_mode, shading=shading, sh_frame="triangle")
    write_viewer_bundle(av, _frames(av, ts=(0.0,)), tmp_path / "b", camera={"width": 256, "height": 256})
    h, a = read_viewer_bundle(tmp_path / "b")
    verts = torch.from_numpy(a["vertices"][0]).float()
    bright = (av.base_rgb(verts).max(-1).values > 1.0).float().mean().item()
    assert bright > 0.1, bright  # Gaussians brighter than 1 (the lit side)
    url = (tmp_path / "b" / "index.html").as_uri() + "?frame=0&ui=0"
    shot = lambda out: np.asarray(Image.open(out).convert("RGB"), dtype=np.float64)  # noqa: E731

    def compare(img, ref, what):
        subject = (np.abs(ref - ref[0, 0]).max(-1) > 2) | (np.abs(img - ref[0, 0]).max(-1) > 2)
        full, on = _psnr(img, ref), _psnr(img[subject], ref[subject])
        print(f"bright splats, {what}: full {full:.1f} dB, subject {on:.1f} dB")
        assert subject.mean() > 0.05
        return full, on

    for bg in ("white", "black"):
        ref = av.render(verts, _bundle_camera(h["camera"], 256), background=torch.full((3,), float(bg == "white")))
        ref = ref.image.detach().clamp(0, 1).numpy() * 255
        for blend in ("float", "8-bit") if bg == "white" else ("float",):
            with open_page(url + f"&bg={bg}" + ("&float=0" if blend == "8-bit" else ""), 256, 256, _chromium()) as page:
                page.wait_ready()
                assert page.evaluate("window.meshsplatViewer.floatTarget") is (blend == "float")
                stats = page.evaluate("document.getElementById('stats').textContent")
                assert ("8-bit blending" in stats) is (blend == "8-bit"), stats
                img = shot(page.screenshot(tmp_path / f"{bg}-{blend}.png"))
            full, on = compare(img, ref, f"{blend} blending, {bg} background")
            if blend == "float":
                assert on >= 40.0 and full >= 40.0, (on, full)
            else:  # the 8-bit canvas clamps splat by splat: darker where bright splats overlap
                assert on < 35.0, on
    # resized canvas: a float target of the new size, at a device pixel ratio of 1, then 2
    cam = h["camera"]
    K = torch.from_numpy(intrinsics(320, 200, cam["fov_deg"])).float()
    ref = av.render(verts, Camera(torch.tensor(cam["viewmat"]).float(), K, 320, 200), background=torch.ones(3))
    ref = ref.image.detach().clamp(0, 1).numpy() * 255
    with open_page(url, 256, 256, chromium=_chromium()) as page:
        page.wait_ready()
        assert page.evaluate("window.meshsplatViewer.floatTarget") is True
        for width, height, scale in ((320, 200, 1), (160, 100, 2)):
            metrics = {"width": width, "height": height, "deviceScaleFactor": scale, "mobile": False}
            page.call("Emulation.setDeviceMetricsOverride", metrics)
            for _ in range(100):  # until the canvas has the new size and a frame after it was drawn
                size = page.evaluate(
                    "new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(() => "
                    "r([document.getElementById('canvas').width, document.getElementById('canvas').height, "
                    "window.meshsplatViewer.state.drawnKey]))))"
                )
                if size[:2] == [320, 200] and size[2].endswith("320x200"):
                    break
            img = shot(page.screenshot(tmp_path / f"resized{scale}.png"))
            assert img.shape == ref.shape, img.shape
            full, on = compare(img, ref, f"float blending, resized to 320x200 at pixel ratio {scale}")
            assert on >= 40.0 and full >= 40.0, (on, full)


@pytest.mark.slow
def test_browser_phone_gestures_and_space_bar(tmp_path):
    """On an emulated phone (touch screen, mobile viewport, 2x pixels): one finger orbits, a pinch
    zooms without orbiting, a double tap and the reset button give the default view back; the space
    bar plays/pauses whichever button has the focus, and only once."""
    from _browser import open_page

    av = make_avatar(n=200)
    write_viewer_bundle(av, _frames(av), tmp_path / "b")
    view = "JSON.stringify(window.meshsplatViewer.view)"
    url = (tmp_path / "b" / "index.html").as_uri() + "?play=0"  # paused: a still page does not redraw
    with open_page(url, 390, 844, chromium=_chromium(), mobile=True, scale=2) as page:
        page.wait_ready()
        assert page.evaluate("window.devicePixelRatio") == 2 and page.evaluate("navigator.maxTouchPoints") > 0
        v0 = json.loads(page.evaluate(view))
        # one finger: orbit (0.3 degree per CSS pixel)
        page.touch("touchStart", [(200, 500)])
        page.touch("touchMove", [(260, 500)])
        page.touch("touchMove", [(300, 530)])
        page.touch("touchEnd", [])
        v1 = json.loads(page.evaluate(view))
        assert v1["az"] == pytest.approx(v0["az"] - 30) and v1["el"] == pytest.approx(v0["el"] + 9)
        assert v1["dist"] == pytest.approx(v0["dist"])
        # two fingers spread from 100 to 200 px: twice as close, no orbit
        page.touch("touchStart", [(150, 400), (250, 400)])
        page.touch("touchMove", [(100, 400), (300, 400)])
        page.touch("touchEnd", [])
        v2 = json.loads(page.evaluate(view))
        assert v2["dist"] == pytest.approx(v0["dist"] / 2) and (v2["az"], v2["el"]) == (v1["az"], v1["el"])
        # a double tap resets the view
        for xy in ((200, 300), (203, 302)):
            page.touch("touchStart", [xy])
            page.touch("touchEnd", [])
        assert json.loads(page.evaluate(view)) == v0
        # ... and so does the visible reset button
        page.touch("touchStart", [(200, 500)])
        page.touch("touchMove", [(240, 500)])
        page.touch("touchEnd", [])
        assert json.loads(page.evaluate(view)) != v0
        assert page.evaluate("document.getElementById('reset').getBoundingClientRect().width") > 0
        page.evaluate("document.getElementById('reset').click()")
        assert json.loads(page.evaluate(view)) == v0
        # space bar: play/pause whatever has the focus, never the focused button's own action
        playing = "window.meshsplatViewer.state.playing"
        assert page.evaluate(playing) is False
        page.evaluate("document.getElementById('play').focus()")
        page.key(" ", "Space", " ")
        assert page.evaluate(playing) is True
        assert page.evaluate("document.getElementById('play').textContent") == "pause"
        page.evaluate("document.getElementById('bg').focus()")
        page.key(" ", "Space", " ")
        assert page.evaluate(playing) is False
        assert page.evaluate("window.meshsplatViewer.state.white") is True  # the background did not toggle


# ---------------------------------------------------------------- the key light's shadow (shading.occlusion=key)
KEY_DIR = (1.0, 0.25, 0.1)  # the light: from +x, where the smaller sphere shades the larger one


def key_avatar(
    n: int = 3000, grid: int = 64, normal: str = "phong", specular: bool = False, soft: float = 0.0
) -> Avatar:
    """Two spheres side by side (the right one, smaller, higher and nearer, shadows the left one's lit
    side), Gaussians on the surface (rotated, scales perturbed), shaded by ``key_shading(KEY_DIR)``."""
    import trimesh

    from meshsplat.gaussians import init_params
    from meshsplat.mesh import TriMesh

    ico = trimesh.creation.icosphere(subdivisions=2)
    v = torch.tensor(ico.vertices, dtype=torch.float32) * 0.5
    f = torch.tensor(ico.faces, dtype=torch.long)
    verts = torch.cat([v + torch.tensor([-0.55, 0.0, 0.0]), v * 0.8 + torch.tensor([0.45, 0.25, 0.15])])
    mesh = TriMesh(verts, torch.cat([f, f + len(v)]))
    g = torch.Generator().manual_seed(0)
    p = init_params(
        mesh,
        n,
        init_opacity=0.8,
        generator=g,
        colors_fn=lambda f, uv: 0.3 + 0.5 * torch.rand(f.shape[0], 3, generator=g),
    )
    with torch.no_grad():  # no ties among the scales (the axis normal is the shortest one)
        p["log_scale"].add_(0.3 * torch.randn(n, 3, generator=g))
        p["rotation"].copy_(torch.randn(n, 4, generator=g))
    return Avatar(mesh, p, "sqrt_area", shading=key_shading(KEY_DIR, grid, normal, specular, soft))


def key_shading(direction, grid: int = 64, normal: str = "phong", specular: bool = False, soft: float = 0.0) -> Shading:
    """A low ambient ``sh2`` irradiance (a little more from above) plus an aligned, bright key light from
    ``direction`` (shading.occlusion=key after its last stage; ``soft``: its angular radius, degrees);
    ``specular``: plus an added SH2 term. With
    albedos up to 0.8 and opacities 0.8 the colours stay below 1 / opacity, so that even the page's 8-bit
    fallback (which clamps each splat's premultiplied colour at 1) would not clamp them."""
    from meshsplat.gaussians.shading import KEY_STAGES

    coeffs = torch.zeros(9, 3)
    coeffs[0] = torch.tensor([0.35, 0.35, 0.4]) / 0.28209479177387814  # E = 0.35 everywhere
    coeffs[1] = torch.tensor([0.1, 0.1, 0.15])  # a little more from above
    key = torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float32), dim=0)[None]
    spec = torch.zeros(9, 3)
    spec[0] = torch.tensor([0.1, 0.12, 0.15])
    spec[2] = torch.tensor([0.1, 0.05, 0.1])
    return Shading(
        coeffs,
        normal,
        occlusion="key",
        directions=16,
        grid=grid,
        key=key,
        key_stage=KEY_STAGES,
        light=torch.tensor([[1.1, 1.0, 0.9]]),
        specular="sh2" if specular else "none",
        specular_coeffs=spec if specular else None,
        key_soft=soft,
    )


def _key_frames(av: Avatar, ts=(0.0, 0.5, 1.0)) -> list[torch.Tensor]:
    return [deform(av.mesh.vertices, t) for t in ts]


def test_bundle_carries_the_key_light_and_refuses_other_occlusion(tmp_path):
    from meshsplat.gaussians.shading import KEY_SOFT_SAMPLES, KEY_STAGES

    av = key_avatar(n=100, grid=48)
    write_viewer_bundle(av, _key_frames(av), tmp_path / "k")
    h, _ = read_viewer_bundle(tmp_path / "k")
    key = h["shading"]["key"]
    assert av.shading is not None and av.shading.directions is not None and av.shading.light is not None
    np.testing.assert_allclose(key["direction"], av.shading.directions[0].numpy(), rtol=1e-7)
    np.testing.assert_allclose(key["light"], av.shading.light[0].numpy(), rtol=1e-7)
    assert key["grid"] == 48
    np.testing.assert_allclose(key["shadows"], av.shading.directions.numpy(), rtol=1e-7)  # a hard key: its own map
    soft = key_avatar(n=100, grid=48, soft=8.0)
    write_viewer_bundle(soft, _key_frames(soft), tmp_path / "s")
    shadows = read_viewer_bundle(tmp_path / "s")[0]["shading"]["key"]["shadows"]
    assert soft.shading is not None
    assert np.array_equal(shadows, soft.shading.shadow_directions().numpy())  # type: ignore[union-attr]
    assert len(shadows) == KEY_SOFT_SAMPLES
    # without occlusion: no key in the header
    plain = shaded_avatar(n=50)
    write_viewer_bundle(plain, _frames(plain), tmp_path / "p")
    assert "key" not in read_viewer_bundle(tmp_path / "p")[0]["shading"]
    # refused: lights from fixed directions, and a key light not aligned yet (one line each, naming the option)
    sh = av.shading
    for shading, match in (
        (Shading(sh.coeffs, occlusion="directions", directions=8), r"shading\.occlusion=directions"),
        (Shading(sh.coeffs, occlusion="key", directions=8), r"shading\.occlusion=key .*not aligned"),
        (
            Shading(sh.coeffs, occlusion="key", directions=8, key=sh.directions.expand(7, 3), key_stage=KEY_STAGES - 1),
            r"shading\.occlusion=key .*not aligned",
        ),
    ):
        bad = Avatar(av.mesh, av.params, av.scale_mode, shading=shading)
        with pytest.raises(MeshsplatError, match=match) as err:
            write_viewer_bundle(bad, _key_frames(av), tmp_path / "bad")
        assert "\n" not in str(err.value)
    assert not (tmp_path / "bad").exists()


@needs_node
@pytest.mark.parametrize("soft", [0.0, 8.0])
def test_js_key_visibility_matches_shading_visibility(tmp_path, soft):
    """The page's height maps (keyShadowMap, CPU) and the shader's lookup (keyVisibility mirrors
    keyVisible) against Shading.visibility on the same posed vertices, surface points and Phong
    normals: the same lit/shadowed verdict (a soft key: the same mean over its 12 maps) for every
    Gaussian, in three poses, with real self-shadowing."""
    from meshsplat.embedding import embed, surface_points
    from meshsplat.mesh import MeshPose, TriMesh

    av = key_avatar(n=3000, soft=soft)
    frames = _key_frames(av)
    write_viewer_bundle(av, frames, tmp_path)
    _, a = read_viewer_bundle(tmp_path)
    script = f"""
import {{ decodeBundle }} from {json.dumps((tmp_path / "viewer.js").as_uri())};
import {{ keyVisibilities }} from {REFERENCE_JS};
import fs from "fs";
const h = JSON.parse(fs.readFileSync({json.dumps(str(tmp_path / "avatar.json"))}, "utf8"));
const b = decodeBundle(h, fs.readFileSync({json.dumps(str(tmp_path / "avatar.bin"))}));
const out = [];
for (let t = 0; t < b.T; t++) out.push(keyVisibilities(b, t));
console.log(JSON.stringify(out));
"""
    js = _node(script, tmp_path)
    sh = av.shading
    assert sh is not None and sh.directions is not None
    faces = av.mesh.faces
    face = torch.from_numpy(a["gaussian_face"].astype(np.int64))
    for t, out in enumerate(js):
        for dtype in (torch.float32, torch.float64):
            verts = torch.from_numpy(a["vertices"][t]).float().to(dtype)  # the float32 vertices the page uploads
            uv = torch.from_numpy(a["gaussian_uv"]).to(dtype)  # the half-float uv the page reads
            pose = MeshPose.from_vertices(TriMesh(av.mesh.vertices.to(dtype), faces), verts)
            _, normals = embed(pose, face, uv, torch.zeros(len(uv), dtype=dtype))
            vis = sh.visibility(pose, surface_points(verts, faces, face, uv), normals)
            assert vis is not None
            want, got = vis[:, 0].double().numpy(), np.asarray(out["visible"], np.float64)
            differ = np.abs(want - got) > 1e-6  # float32: k / 12 rounded
            print(f"pose {t} ({dtype}): {int(differ.sum())} of {len(want)} Gaussians differ")
            assert differ.sum() <= 0.001 * len(want)
            if dtype == torch.float64:
                assert np.array_equal(want, got)
        # real self-shadowing: many Gaussians facing the light are in the other sphere's shadow
        facing = (normals @ sh.directions[0].double()).numpy() > 0.2
        dark = (want[facing] < 0.5).mean()
        assert facing.mean() > 0.2 and dark > 0.2, (dark, facing.mean())
        if soft:  # and a penumbra: partly lit Gaussians
            assert ((want > 0) & (want < 1)).mean() > 0.02


@needs_node
def test_shadow_worker_job_is_the_pages_height_maps(tmp_path):
    """The shadow worker's job (shadowJob, vertex frames and a soft key) gives keyShadowMap's heights as
    the float32 texture data (KEY_EMPTY where no sample fell), in each pose, reusing its buffers; its
    inline source (SHADOW_WORKER_SOURCE) runs on its own and answers a request with the same maps."""
    av = key_avatar(n=500, soft=8.0)
    write_viewer_bundle(av, _key_frames(av), tmp_path)
    script = f"""
import {{ decodeBundle, frameVertices, keyShadowMap, shadowJob, shadowSetup, SHADOW_WORKER_SOURCE, KEY_EMPTY }}
  from {json.dumps((tmp_path / "viewer.js").as_uri())};
import fs from "fs";
const h = JSON.parse(fs.readFileSync({json.dumps(str(tmp_path / "avatar.json"))}, "utf8"));
const b = decodeBundle(h, fs.readFileSync({json.dumps(str(tmp_path / "avatar.bin"))}));
const S = shadowSetup(b), out = [];
for (let t = 0; t < b.T; t++) {{
  const p = Float32Array.from(frameVertices(b, t));
  const want = keyShadowMap(b.faces, b.V, p, h.shading.key);
  const r = shadowJob(S, {{ id: t, verts: p }});
  const f32 = Float32Array.from(want.depth, (x) => (x === -Infinity ? KEY_EMPTY : x));
  out.push({{ same: r.depth.every((x, i) => x === f32[i]), maps: want.frames.length, empty: f32.filter((x) => x === KEY_EMPTY).length,
             cells: f32.length, place: [r.centre, r.radius, r.cell].flat().every((x, i) => x === [want.centre, want.radius, want.cell].flat()[i]) }});
  S.spare.push(r.depth);
}}
// the worker source alone: its onmessage answers as shadowJob does
const posted = [];
const onmessage = new Function("postMessage", "performance", SHADOW_WORKER_SOURCE.replace('"use strict";', "") + "; return onmessage;")(
  (r) => posted.push(r), performance);
onmessage({{ data: {{ type: "init", setup: shadowSetup(b) }} }});
const p = Float32Array.from(frameVertices(b, 1));
onmessage({{ data: {{ type: "map", id: 7, verts: p }} }});
const again = shadowJob(shadowSetup(b), {{ id: 7, verts: p }});
console.log(JSON.stringify({{ out, worker: posted.length === 1 && posted[0].id === 7 && posted[0].ms >= 0 &&
  posted[0].depth.every((x, i) => x === again.depth[i]) }}));
"""
    res = _node(script, tmp_path)
    assert len(res["out"]) == 3
    for r in res["out"]:
        assert r["same"] and r["place"] and r["maps"] == 12
        assert r["empty"] < r["cells"]
    assert res["worker"]


@pytest.mark.slow
@pytest.mark.parametrize("normal,specular,soft", [("phong", False, 0.0), ("axis", True, 0.0), ("phong", False, 8.0)])
def test_browser_key_shadow_matches_rasterizer(tmp_path, normal, specular, soft):
    """The page shades the key light's shadow (hard, or soft: 12 maps) from the posed mesh as
    avatar.render does, in two poses; the same avatar with the key light unshadowed (V = 1) renders far
    from the page's error."""
    av = key_avatar(normal=normal, specular=specular, soft=soft)
    frames = _key_frames(av, ts=(0.0, 1.0))
    write_viewer_bundle(av, frames, tmp_path / "b", camera={"width": 256, "height": 256, "azimuth_deg": 60.0})
    h, a = read_viewer_bundle(tmp_path / "b")
    for frame in (0, 1):
        ref = _render_ref(av, a["vertices"][frame], h["camera"])
        img = _shoot(tmp_path / "b", frame, 256, tmp_path / f"shot{frame}.png")
        subject = (np.abs(ref - 255).max(-1) > 2) | (np.abs(img - 255).max(-1) > 2)
        full, on = _psnr(img, ref), _psnr(img[subject], ref[subject])
        # the shadow is visible: the key light without it (lit everywhere, as a convex mesh would be)
        sh = av.shading
        assert sh is not None and sh.light is not None and sh.directions is not None
        unshadowed = _render_unshadowed(av, a["vertices"][frame], h["camera"])
        off = _psnr(unshadowed[subject], ref[subject])
        print(
            f"key shadow page vs avatar.render, frame {frame}: full {full:.1f} dB, subject {on:.1f} dB; "
            f"unshadowed vs avatar.render: subject {off:.1f} dB"
        )
        assert subject.mean() > 0.05
        assert on >= 40.0 and full >= 40.0, (on, full)
        assert off < 30.0, off


def _render_unshadowed(av: Avatar, verts, cam) -> np.ndarray:
    """avatar.render with the key light's visibility forced to 1 (the key light, no shadow)."""
    from unittest import mock

    sh = av.shading
    assert sh is not None
    with mock.patch.object(sh, "visibility", lambda pose, p, n: torch.ones(len(p), 1, dtype=p.dtype)):
        return _render_ref(av, verts, cam)


@pytest.mark.slow
def test_browser_live_gltf_key_shadow_matches_rasterizer(tmp_path):
    """Live glTF skinning (CesiumMan): the page skins the mesh on the GPU and, for the height map, on
    the CPU; its key-light shadows equal avatar.render of GltfDriver's vertices."""
    from PIL import Image

    from meshsplat.drivers import GltfDriver
    from meshsplat.gaussians import init_params
    from meshsplat.mesh import TriMesh
    from meshsplat.paths import assets_dir
    from meshsplat.viewer.rig import avatar_driver

    glb = assets_dir() / "gltf" / "CesiumMan.glb"
    drv0 = GltfDriver(glb)
    mesh = TriMesh(drv0.rest_vertices(), drv0.faces)
    g = torch.Generator().manual_seed(0)
    p = init_params(
        mesh,
        6000,
        init_opacity=0.8,
        generator=g,
        colors_fn=lambda f, uv: 0.3 + 0.5 * torch.rand(f.shape[0], 3, generator=g),
    )
    av = Avatar(mesh, p, shading=key_shading((0.6, 0.3, 0.75)))
    drv = avatar_driver(av, glb)
    write_viewer_bundle(av, None, tmp_path / "b", rig=drv, camera={"width": 256, "height": 256})
    h = read_viewer_bundle(tmp_path / "b")[0]
    clip = next(c for c in h["driver"]["clips"] if c["name"] == h["driver"]["clip"])
    verts = drv.vertices_at(clip["start"] + 0.8, clip=clip["name"])
    ref = _render_ref(av, verts, h["camera"])
    screenshot(
        (tmp_path / "b" / "index.html").as_uri() + "?time=0.8&ui=0", 256, 256, tmp_path / "s.png", chromium=_chromium()
    )
    img = np.asarray(Image.open(tmp_path / "s.png").convert("RGB"), dtype=np.float64)
    subject = (np.abs(ref - 255).max(-1) > 2) | (np.abs(img - 255).max(-1) > 2)
    full, on = _psnr(img, ref), _psnr(img[subject], ref[subject])
    off = _psnr(_render_unshadowed(av, verts, h["camera"])[subject], ref[subject])
    print(f"live glTF key shadow vs avatar.render: full {full:.1f} dB, subject {on:.1f} dB; unshadowed {off:.1f} dB")
    assert subject.mean() > 0.02
    assert on >= 40.0 and full >= 40.0, (on, full)
    assert off < 35.0, off
    # without Web Workers the page skins and builds the height maps on the main thread: the same image
    main = _page_image((tmp_path / "b" / "index.html").as_uri() + "?time=0.8&ui=0&worker=0", 256, tmp_path / "s0.png")
    assert np.array_equal(main, img)


def test_view_cli_key_light_run(tmp_path, capsys):
    """`meshsplat view` of a run trained with shading.occlusion=key: the checkpoint's aligned key light
    reaches the page's header; a run saved before the key was aligned is a one-line error."""
    from meshsplat.cli.main import main

    av = key_avatar(n=200, grid=32)
    seq = torch.stack(_key_frames(av))
    np.save(tmp_path / "seq.npy", seq.numpy())
    run = make_run(av, tmp_path / "run", None)
    argv = ["view", str(run), "--animation", "vertices", str(tmp_path / "seq.npy")]
    assert main([*argv[:2], "--out", str(tmp_path / "v"), *argv[2:]]) == 0
    h, _ = read_viewer_bundle(tmp_path / "v")
    sh = av.shading
    assert sh is not None and sh.directions is not None
    assert h["shading"]["key"]["grid"] == 32
    np.testing.assert_allclose(h["shading"]["key"]["direction"], sh.directions[0].numpy(), rtol=1e-6)
    early = Avatar(av.mesh, av.params, av.scale_mode, shading=Shading(sh.coeffs, occlusion="key", directions=8))
    run2 = make_run(early, tmp_path / "run2", None)
    capsys.readouterr()
    assert main(["view", str(run2), "--out", str(tmp_path / "v2"), *argv[2:]]) == 2
    err = capsys.readouterr().err
    assert "shading.occlusion=key" in err and "not aligned" in err
