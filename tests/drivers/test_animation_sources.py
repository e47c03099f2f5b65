"""One way to say an animation and a camera: ``render``, ``view`` and the Python API share ``--animation KIND
[FILE]`` (``AnimationSource`` / ``load_animation``) and the player page's orbit description."""

from __future__ import annotations

import json
import math
import shutil
import subprocess

import numpy as np
import pytest
import torch

from _eval_kit import deform, make_avatar, make_dataset, make_run
from meshsplat.animation import AnimationSource, load_animation
from meshsplat.camera import orbit_camera, orbit_viewmat
from meshsplat.cli import render_cmd
from meshsplat.cli._options import animation_source, orbit_request
from meshsplat.cli.main import build_parser, main
from meshsplat.drivers import BlendshapeDriver
from meshsplat.errors import MeshsplatError
from meshsplat.run_folder import load_run
from meshsplat.viewer import page_camera, read_viewer_bundle

NODE = shutil.which("node")


@pytest.fixture(scope="module")
def kit(tmp_path_factory):
    root = tmp_path_factory.mktemp("anim")
    av = make_avatar(n=60)
    ds = make_dataset(av, root / "ds")
    run = make_run(av, root / "run", ds)
    seq = torch.stack([deform(av.mesh.vertices, t) for t in (0.0, 0.5, 1.0)])
    np.save(root / "seq.npy", seq.numpy())
    return av, run, root


def _args(command: str, words: list[str]):
    return build_parser().parse_args([command, "RUN", "--out", "OUT", *words])


@pytest.mark.parametrize(
    "words",
    [
        ["--animation", "gltf", "walk.glb", "--clip", "Walk", "--fps", "10", "--seconds", "2", "--start", "0.5"],
        ["--animation", "vertices", "seq.npy", "--frames", "4"],
        ["--animation", "blendshapes", "ict", "--weights", "w.json"],
        ["--animation", "dataset", "--split", "test_frames"],
        [],
    ],
)
def test_render_and_view_read_an_animation_alike(kit, words):
    _, run, _ = kit
    r = load_run(run)
    got = {c: animation_source(_args(c, words), r, c) for c in ("render", "view")}
    assert got["render"] == got["view"]
    if not words:
        assert got["render"] == AnimationSource("dataset")


def test_animation_source_errors_name_the_fix():
    with pytest.raises(MeshsplatError, match="expected one of dataset, gltf"):
        AnimationSource("bvh", "x.bvh")
    with pytest.raises(MeshsplatError, match="--animation gltf needs a FILE"):
        AnimationSource("gltf")
    with pytest.raises(MeshsplatError, match="clip applies to --animation gltf, not to vertices"):
        AnimationSource("vertices", "seq.npy", clip="Walk")
    with pytest.raises(MeshsplatError, match="takes no FILE"):
        AnimationSource("dataset", "x")
    with pytest.raises(MeshsplatError, match="needs the avatar's capture"):
        load_animation(AnimationSource("dataset"), make_avatar(n=10))


def test_load_animation_feeds_render_and_the_viewer(kit, tmp_path):
    """One loaded animation is what render_animation renders and write_viewer ships."""
    import meshsplat as ms
    from meshsplat.data import open_dataset

    av, run, root = kit
    anim = ms.load_animation(ms.AnimationSource("vertices", root / "seq.npy", fps=10), av)
    assert len(anim.frames) == 3 and anim.fps == 10
    res = ms.render_animation(av, anim, None, tmp_path / "r", write_mp4=False)
    assert res.num_frames == 3
    ms.write_viewer(av, anim, tmp_path / "v")
    h, a = read_viewer_bundle(tmp_path / "v")
    assert h["num_frames"] == 3 and h["fps"] == 10
    np.testing.assert_allclose(a["vertices"][2], anim.frames[2].double().numpy(), atol=1e-3)
    # a dataset split brings each frame's own camera
    ds = open_dataset(load_run(run).dataset_path())
    split = load_animation(AnimationSource("dataset", split="test_frames"), av, dataset=ds)
    assert [c.viewmat.tolist() for c in split.cameras] == [ds.frame_camera(i).viewmat.tolist() for i in (2, 3)]


def test_view_motion_error_names_flags_view_has(kit, tmp_path, capsys):
    """A motion for an avatar of no SMPL/FLAME capture: the error suggests spellings view (and render) have."""
    _, run, root = kit
    np.savez(root / "motion.npz", poses=np.zeros((2, 72), np.float32), trans=np.zeros((2, 3), np.float32))
    for cmd in ("view", "render"):
        out = tmp_path / cmd
        assert main([cmd, str(run), "--out", str(out), "--animation", "motion", str(root / "motion.npz")]) == 2
        err = capsys.readouterr().err
        assert "use --animation gltf FILE or --animation vertices FILE" in err and "--gltf" not in err
        assert err.count("\n") == 1


# ---------------------------------------------------------------- one camera language
def test_orbit_camera_golden():
    """Centre (0,1,0), distance 2, azimuth 90 (from +x), elevation 0, +y up: the eye at (2,1,0) looks along -x."""
    vm = orbit_viewmat((0.0, 1.0, 0.0), 2.0, 90.0, 0.0)
    want = np.array([[0, 0, -1, 0], [0, -1, 0, 1], [-1, 0, 0, 2], [0, 0, 0, 1]], np.float64)
    np.testing.assert_allclose(vm, want, atol=1e-12)
    cam = orbit_camera((0.0, 1.0, 0.0), 2.0, 90.0, 0.0, fov_deg=90.0, width=40, height=20)
    np.testing.assert_allclose(cam.K.numpy(), [[10, 0, 20], [0, 10, 10], [0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(cam.center.numpy(), [2, 1, 0], atol=1e-6)


def _page_js_camera(cam: dict, tmp_path) -> dict:
    """The page's own camera maths (viewer.js orbitViewmat + intrinsics) on a bundle's camera, under Node."""
    script = f"""
import {{ orbitViewmat, intrinsics }} from {json.dumps((tmp_path / "viewer.js").as_uri())};
const c = {json.dumps(cam)};
console.log(JSON.stringify({{ viewmat: Array.from(orbitViewmat(c.center, c.distance, c.azimuth_deg,
  c.elevation_deg, c.up, c.front)), K: intrinsics(c.width, c.height, c.fov_deg) }}));
"""
    (tmp_path / "t.mjs").write_text(script)
    out = subprocess.run([NODE, str(tmp_path / "t.mjs")], capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout)


def test_render_reproduces_the_page_camera(kit, tmp_path):
    """`view` writes a page with a camera given by the shared flags; `render --camera page:FOLDER` renders
    with the camera the page's own maths gives (viewmat and K compared), and the same flags given to
    `render` directly describe the same camera."""
    av, run, _ = kit
    flags = ["--center", "0.1,0.2,-0.1", "--azimuth", "35", "--elevation", "20", "--distance", "3.5", "--fov", "40"]
    flags += ["--up", "0,0,1", "--front", "0,-1,0"]  # a z-up capture's axes
    assert main(["view", str(run), "--out", str(tmp_path / "page"), *flags]) == 0
    cam = read_viewer_bundle(tmp_path / "page")[0]["camera"]
    assert cam["center"] == [0.1, 0.2, -0.1] and cam["distance"] == 3.5 and cam["up"] == [0.0, 0.0, 1.0]
    frames = [deform(av.mesh.vertices, t) for t in (0.0, 1.0)]
    no_dataset = lambda: None  # noqa: E731
    up_front = lambda: ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0))  # noqa: E731
    args = _args("render", ["--camera", f"page:{tmp_path / 'page'}"])
    got = render_cmd.render_cameras(args, frames, None, None, up_front, no_dataset)
    assert len(got) == 2 and (got[0].width, got[0].height) == (cam["width"], cam["height"])
    np.testing.assert_allclose(got[0].viewmat.double().numpy(), np.asarray(cam["viewmat"]), atol=1e-6)
    np.testing.assert_allclose(got[0].K.double().numpy(), np.asarray(cam["K"]), atol=1e-4)
    if NODE is not None:
        shutil.copy(tmp_path / "page" / "viewer.js", tmp_path / "viewer.js")
        js = _page_js_camera(cam, tmp_path)
        np.testing.assert_allclose(got[1].viewmat.double().numpy(), np.reshape(js["viewmat"], (4, 4)), atol=1e-6)
        K = got[0].K.double().numpy()
        np.testing.assert_allclose([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], js["K"], rtol=1e-6)
    same = render_cmd.render_cameras(
        _args("render", [*flags, "--size", "800x800"]), frames, None, None, up_front, no_dataset
    )
    np.testing.assert_allclose(same[0].viewmat.numpy(), got[0].viewmat.numpy(), atol=1e-6)
    rc = main(
        [
            "render",
            str(run),
            "--animation",
            "vertices",
            str(kit[2] / "seq.npy"),
            "--camera",
            f"page:{tmp_path / 'page'}",
        ]
        + ["--size", "20x16", "--no-mp4", "--no-progress", "--out", str(tmp_path / "r")]
    )
    assert rc == 0 and len(list((tmp_path / "r" / "frames").glob("*.png"))) == 3
    # a flag refines the page's camera; a bad one is named
    turned = orbit_request(_args("render", ["--camera", f"page:{tmp_path / 'page'}", "--azimuth", "50"]), None, None)
    assert turned["azimuth_deg"] == 50 and turned["distance"] == 3.5
    with pytest.raises(MeshsplatError, match="--center: expected X,Y,Z"):
        orbit_request(_args("view", ["--center", "1,2"]), None, None)
    with pytest.raises(MeshsplatError, match="not found"):
        page_camera(tmp_path / "nope")
    with pytest.raises(MeshsplatError, match="exclude each other"):
        orbit_request(_args("render", ["--camera", "dataset:front", "--azimuth", "10"]), None, None)


def test_view_accepts_a_dataset_camera(kit, tmp_path):
    """`--camera dataset:<id>`, which render takes, is the page's initial view too (an orbit through it)."""
    _, run, _ = kit
    assert main(["view", str(run), "--out", str(tmp_path / "v"), "--camera", "dataset:side"]) == 0
    cam = read_viewer_bundle(tmp_path / "v")[0]["camera"]
    ds_cam = load_run(run).open_dataset().camera("side")
    np.testing.assert_allclose(
        np.asarray(cam["viewmat"])[:3, :3], ds_cam.viewmat[:3, :3].double().numpy(), atol=1e-5
    )  # the same view direction (the orbit keeps the camera's axes; the dataset camera has no roll)


# ---------------------------------------------------------------- the ICT head trained from `meshsplat synth ict`
@pytest.mark.slow
def test_ict_head_from_synth_drives_render_and_view(tmp_path, capsys):
    """`synth ict` drops hidden shells and welds seams (25739 of 26719 vertices): the bundled ICT model
    drives an avatar on that mesh in `view` (live) as in `render`, through the run's source map, and the
    derived model poses each vertex as the full model poses its source vertex (same head-pose pivot)."""
    from meshsplat.data import open_dataset
    from meshsplat.data.source_map import copy_source_map, read_source_map
    from meshsplat.gaussians import Avatar, init_params
    from meshsplat.mesh import TriMesh

    assert main(["synth", "ict", "--out", str(tmp_path / "ds"), "--frames", "2", "--resolution", "32"]) == 0
    ds = open_dataset(tmp_path / "ds")
    mesh = TriMesh(ds.canonical_vertices, ds.faces)
    av = Avatar(mesh, init_params(mesh, 300, generator=torch.Generator().manual_seed(0)))
    run = make_run(av, tmp_path / "run", tmp_path / "ds")
    copy_source_map(tmp_path / "ds", run)
    smap = read_source_map(run)
    full = BlendshapeDriver.from_npz("ict")
    assert mesh.num_vertices < full.neutral.shape[0]

    live = load_animation(AnimationSource("blendshapes", frames=6), av, source_map=smap, live=True).driver
    assert isinstance(live, BlendshapeDriver) and live.neutral.shape[0] == mesh.num_vertices
    full.talking_sequence(6, 25.0)
    idx = torch.from_numpy(smap.source_index)
    for i in (0, 3, 5):
        torch.testing.assert_close(live.vertices(i), full.vertices(i)[idx], atol=1e-5, rtol=0)
    baked = load_animation(AnimationSource("blendshapes", "ict", frames=6), av, source_map=smap).frames
    torch.testing.assert_close(baked[5], live.vertices(5))

    capsys.readouterr()
    assert main(["view", str(run), "--out", str(tmp_path / "v"), "--animation", "blendshapes", "--frames", "6"]) == 0
    h, a = read_viewer_bundle(tmp_path / "v")
    assert h["driver"]["kind"] == "gltf" and h["driver"]["morph_groups"][0]["names"] == full.names
    assert a["rig_base"].shape == (mesh.num_vertices, 3) and "live blendshapes" in capsys.readouterr().out
    (tmp_path / "w.json").write_text(json.dumps({"names": ["jawOpen"], "weights": [[0.0], [0.8]]}))
    rc = main(
        ["render", str(run), "--animation", "blendshapes", "ict", "--weights", str(tmp_path / "w.json")]
        + ["--size", "24x24", "--no-mp4", "--no-progress", "--out", str(tmp_path / "r")]
    )
    assert rc == 0 and len(list((tmp_path / "r" / "frames").glob("*.png"))) == 2
    assert math.isfinite(float(h["camera"]["distance"]))
