"""Your own mesh, your own animation (docs/bring-your-own-mesh.md): mesh sequences as inputs, vertex order, re-derived
driving meshes, axes and units, clip defaults, credits, threads, the demo's continuous animation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from _creature import creature_frames, write_creature_frames, write_creature_npz
from _eval_kit import make_dataset, make_run
from meshsplat.animation import AnimationSource, load_animation
from meshsplat.animation.avatar_match import sequence_for_mesh
from meshsplat.data import open_dataset
from meshsplat.data.source_map import read_source_map
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.gaussians.params import init_params
from meshsplat.mesh import TriMesh
from meshsplat.synth import synthesize
from meshsplat.synth.sources import load_source
from meshsplat.train.recipes import recipe_config

TINY = dict(frames=4, resolution=32, test_views=1, test_frames=2, test_view_frames=1, supersample=1)


def _avatar(ds, n: int = 60) -> Avatar:
    mesh = TriMesh(ds.canonical_vertices, ds.faces)
    g = torch.Generator().manual_seed(0)
    return Avatar(mesh, init_params(mesh, n, generator=g), "sqrt_area")


@pytest.fixture(scope="module")
def creature(tmp_path_factory):
    root = tmp_path_factory.mktemp("creature")
    npz = write_creature_npz(root / "creature.npz", frames_per_clip=12)
    ds = open_dataset(synthesize(npz, root / "ds", rig="orbit", **TINY))
    return npz, ds


# ---------------------------------------------------------------- mesh sequences are inputs
def test_npz_sequence_synthesizes_with_defaults_from_its_clips(creature):
    _npz, ds = creature
    m = ds.meta
    assert m["asset_up"] == "z" and m["train_clip"] == "crawl" and m["test_clips"] == ["idle"]
    assert "procedural caterpillar" in m["attribution"]
    assert m["driver_vertices"] < m["render_vertices"]  # the UV seam was welded
    assert {"train", "test_frames", "test_views", "test_clip"} <= set(ds.split_names)
    lo, hi = ds.canonical_vertices.min(0).values, ds.canonical_vertices.max(0).values
    ext = hi - lo
    assert ext[0] > 3 * ext[1]  # 60 cm long along x, and z-up turned y-up: the body stands on its belly
    assert abs(float(lo[1]) - 1.0) < 0.5  # the creature's lowest point (z = 1 cm in the asset) is now y


def test_obj_and_ply_frame_folders_are_sources(tmp_path):
    folder = write_creature_frames(tmp_path / "objs", frames=3)
    src = load_source(folder)
    assert src.clips == ["sequence"] and src.materials[0][1] is not None  # texture.png with OBJ uvs
    assert src.rest().shape[0] > creature_frames(frames_per_clip=1)["vertices"].shape[1] - 1
    d = creature_frames(frames_per_clip=2)
    plys = tmp_path / "plys"
    plys.mkdir()
    for k, v in enumerate(d["vertices"][:2]):
        lines = (
            [
                "ply",
                "format ascii 1.0",
                f"element vertex {len(v)}",
                "property float x",
                "property float y",
                "property float z",
                f"element face {len(d['faces'])}",
                "property list uchar int vertex_indices",
                "end_header",
            ]
            + [f"{a} {b} {c}" for a, b, c in v]
            + [f"3 {a} {b} {c}" for a, b, c in d["faces"]]
        )
        (plys / f"f{k}.ply").write_text("\n".join(lines) + "\n")
    ply_src = load_source(plys)
    assert torch.allclose(ply_src.pose("sequence", 1 / 30), torch.from_numpy(d["vertices"][1]))


def test_layout_errors_name_the_layout(tmp_path):
    np.save(tmp_path / "seq.npy", np.zeros((2, 3, 3), np.float32))
    with pytest.raises(MeshsplatError, match="npz mesh sequence"):
        load_source(tmp_path / "seq.npy")
    np.savez(tmp_path / "other.npz", verts=np.zeros((2, 3, 3)))
    with pytest.raises(MeshsplatError, match=r"npz mesh sequence.*blend-shape head npz"):
        load_source(tmp_path / "other.npz")
    np.savez(tmp_path / "bad.npz", faces=np.array([[0, 1, 5]]), vertices=np.zeros((2, 3, 3), np.float32))
    with pytest.raises(MeshsplatError, match=r"face indices.*npz mesh sequence"):
        load_source(tmp_path / "bad.npz")
    (tmp_path / "frames").mkdir()
    write_creature_frames(tmp_path / "frames", frames=2, with_texture=False)
    (tmp_path / "frames" / "frame_001.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshsplatError, match=r"same mesh.*OBJ/PLY frames"):
        load_source(tmp_path / "frames")


def test_meshseq_capture_imports_and_trains_input(creature, tmp_path):
    from meshsplat.data.convert import write_native
    from meshsplat.data.formats import detect_format, format_module, open_capture

    _, ds = creature
    cap = format_module("meshseq").write(ds, tmp_path / "cap")
    assert detect_format(cap) == "meshseq"
    opened = open_capture(cap)
    assert len(opened) == len(ds) and opened.split("test_clip") == ds.split("test_clip")
    assert torch.equal(opened[2].vertices, ds[2].vertices) and torch.equal(opened[2].image, ds[2].image)
    # the minimal folder: one camera (OpenGL camera->world), images in name order, no frames list
    cam0 = ds.frame_camera(0)
    K, vm, w, h = cam0.K, cam0.viewmat, cam0.width, cam0.height
    from meshsplat.camera import opengl_c2w_from_viewmat

    mini = tmp_path / "mini"
    (mini / "images").mkdir(parents=True)
    for k in range(2):
        (mini / "images" / f"{k:03d}.png").write_bytes((ds.root / ds.frame_info(k)["image"]).read_bytes())
    seq = np.stack([ds.vertices(0).numpy(), ds.vertices(0).numpy()])
    np.savez(mini / "mesh.npz", faces=ds.faces.numpy(), vertices=seq)
    (mini / "cameras.json").write_text(
        json.dumps(
            {
                "cameras": {
                    "c": {
                        "K": np.asarray(K).tolist(),
                        "c2w_opengl": opengl_c2w_from_viewmat(np.asarray(vm)).tolist(),
                        "width": w,
                        "height": h,
                    }
                }
            }
        )
    )
    mds = open_capture(mini)
    assert len(mds) == 2 and np.allclose(mds.camera("c").viewmat, np.asarray(vm), atol=1e-6)
    assert (write_native(mds, tmp_path / "native") / "manifest.json").is_file()
    from meshsplat.synth.capture import synth_capture

    written = synth_capture(creature[0], tmp_path / "synth_meshseq", format="meshseq", rig="orbit", **TINY)
    assert detect_format(written) == "meshseq" and len(open_capture(written)) == len(ds)
    (mini / "mesh.npz").unlink()
    np.savez(mini / "mesh.npz", faces=ds.faces.numpy(), vertices=seq[:1, :5])
    with pytest.raises(MeshsplatError, match="meshseq layout"):
        open_capture(mini)


def test_meshseq_capture_with_a_gltf_mesh(creature, assets, tmp_path):
    """A glTF as the mesh sequence: frames say time (and clip) instead of mesh."""
    import shutil

    from meshsplat.data.formats import open_capture
    from meshsplat.drivers import GltfDriver

    _, ds = creature
    gl = tmp_path / "gl"
    (gl / "images").mkdir(parents=True)
    for k in range(2):
        (gl / "images" / f"{k:03d}.png").write_bytes((ds.root / ds.frame_info(k)["image"]).read_bytes())
    shutil.copyfile(assets / "gltf" / "RiggedSimple.glb", gl / "mesh.glb")
    cam0 = ds.frame_camera(0)
    K, vm, w, h = cam0.K, cam0.viewmat, cam0.width, cam0.height
    doc = {
        "cameras": {"c": {"K": np.asarray(K).tolist(), "viewmat": np.asarray(vm).tolist(), "width": w, "height": h}},
        "frames": [
            {"image": "images/000.png", "camera": "c", "time": 0.0},
            {"image": "images/001.png", "camera": "c", "time": 0.5},
        ],
    }
    (gl / "cameras.json").write_text(json.dumps(doc))
    gds = open_capture(gl)
    assert torch.allclose(gds[1].vertices, GltfDriver(gl / "mesh.glb").vertices_at(0.5))
    doc["frames"][1].pop("time")
    (gl / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(MeshsplatError, match="needs 'time'"):
        open_capture(gl)


# ---------------------------------------------------------------- vertex order survives
def test_source_order_sequence_drives_the_avatar(creature, tmp_path):
    npz, ds = creature
    smap = read_source_map(ds.root)
    assert smap is not None and smap.exact and len(smap.source_index) == ds.num_vertices
    av = _avatar(ds)
    raw = np.load(npz)["vertices"]  # the asset's own order, z-up, centimetres
    frames = sequence_for_mesh(av.mesh, raw[:12], source_map=smap)
    i0 = next(i for i in ds.split("train") if ds.frame_info(i)["time"] == 0.0)
    assert torch.allclose(frames[0], ds.vertices(i0), atol=1e-4)
    canon = torch.stack([ds.vertices(i) for i in ds.split("train")])  # canonical order is accepted too
    assert len(sequence_for_mesh(av.mesh, canon, source_map=smap)) == len(canon)
    # same count, wrong order: refused (this rendered noise before)
    perm = np.random.default_rng(0).permutation(ds.num_vertices)
    with pytest.raises(MeshsplatError, match="does not match the avatar's canonical mesh at rest"):
        sequence_for_mesh(av.mesh, canon.numpy()[:, perm], source_map=smap)
    with pytest.raises(MeshsplatError, match="does not match"):
        sequence_for_mesh(av.mesh, raw[:2, np.random.default_rng(1).permutation(raw.shape[1])], source_map=smap)
    with pytest.raises(MeshsplatError, match="other units"):
        sequence_for_mesh(av.mesh, canon.numpy() * 0.01, source_map=smap)
    with pytest.raises(MeshsplatError, match=r"\[T,\d+,3\] \(the source asset"):
        sequence_for_mesh(av.mesh, raw[:2, :-1], source_map=smap)
    run = make_run(av, tmp_path / "run", ds.root)
    from meshsplat.cli.main import main

    assert (
        main(
            [
                "render",
                str(run),
                "--animation",
                "vertices",
                str(npz),
                "--size",
                "24x24",
                "--no-mp4",
                "--no-progress",
                "--threads",
                "1",
                "--out",
                str(tmp_path / "r"),
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "r" / "frames").glob("*.png"))) == raw.shape[0]


# ---------------------------------------------------------------- the source asset re-derives its driving mesh
@pytest.mark.parametrize("smooth,decimate", [(3, None), (0, 0.5)])
def test_gltf_drives_smoothed_or_decimated_avatar(assets, tmp_path, smooth, decimate):
    path = assets / "gltf" / "CesiumMan.glb"
    ds = open_dataset(
        synthesize(path, tmp_path / "ds", rig="orbit", driver_smooth=smooth, driver_decimate=decimate, **TINY)
    )
    av = _avatar(ds)
    smap = read_source_map(ds.root)
    assert not smap.exact
    i = ds.split("test_frames")[0]
    t = ds.frame_info(i)["time"]
    from meshsplat.drivers import GltfDriver

    t0 = GltfDriver(path).time_range()[0]  # render times count from the clip's start
    frames = load_animation(
        AnimationSource("gltf", path, fps=1000.0, seconds=0.0, start=t - t0), av, source_map=smap
    ).frames
    assert torch.allclose(frames[0], ds.vertices(i), atol=1e-4 * float(ds.canonical_vertices.abs().max()))
    with pytest.raises(MeshsplatError, match=r"no source_map.npz"):
        load_animation(AnimationSource("gltf", path, fps=5, seconds=0.2), av)
    with pytest.raises(MeshsplatError, match="not the asset this avatar was synthesized from"):
        load_animation(
            AnimationSource("gltf", assets / "gltf" / "RiggedSimple.glb", fps=5, seconds=0.2), av, source_map=smap
        )
    run = make_run(av, tmp_path / "run", ds.root)  # the CLI finds the map through the run's dataset
    from meshsplat.cli.main import main

    assert (
        main(
            [
                "render",
                str(run),
                "--animation",
                "gltf",
                str(path),
                "--seconds",
                "0.2",
                "--fps",
                "10",
                "--size",
                "16x16",
                "--no-mp4",
                "--no-progress",
                "--threads",
                "1",
                "--out",
                str(tmp_path / "r"),
            ]
        )
        == 0
    )
    if smooth:  # a sequence of the asset's own vertices also drives the smoothed mesh (rotation-aware offsets)
        seq = torch.stack([load_source(path).pose(ds.frame_info(i)["clip"], t)])
        got = sequence_for_mesh(av.mesh, seq, source_map=smap)[0]
        assert float((got - ds.vertices(i)).norm(dim=1).max()) < 0.02 * float(ds.canonical_vertices.norm(dim=1).max())


def test_training_copies_the_source_map_into_the_run(creature, tmp_path):
    from meshsplat.cli.main import main

    _, ds = creature
    rc = main(
        [
            "train",
            str(ds.root),
            "--out",
            str(tmp_path / "run"),
            "--iters",
            "2",
            "--no-progress",
            "--threads",
            "1",
            "--set",
            "model.n_init=50",
            "--set",
            "preview_every=100000",
            "--set",
            "checkpoint_every=100000",
        ]
    )
    assert rc == 0 and (tmp_path / "run" / "source_map.npz").is_file()


# ---------------------------------------------------------------- axes and units
def test_up_axis_choice_and_message(creature, tmp_path, capsys):
    npz = write_creature_npz(tmp_path / "c.npz", frames_per_clip=4)
    out = synthesize(npz, tmp_path / "y", rig="orbit", up="y", progress=True, clip="crawl", test_clips=[], **TINY)
    said = capsys.readouterr().out
    assert "up axis: y (--up)" in said and "mesh size" in said
    as_y = open_dataset(out).canonical_vertices
    turned = creature[1].canonical_vertices  # the asset's own "up": z, turned to y: (x, y, z) -> (x, z, -y)
    want = torch.stack([as_y[:, 0], as_y[:, 2], -as_y[:, 1]], 1)
    for a, b in ((turned.min(0).values, want.min(0).values), (turned.max(0).values, want.max(0).values)):
        assert torch.allclose(a, b, atol=1e-4)
    with pytest.raises(MeshsplatError, match="up: expected 'y' or 'z'"):
        synthesize(npz, tmp_path / "x", up="x", **TINY)


def test_scale_log_is_relative_to_mesh_size(tmp_path):
    from _eval_kit import make_avatar
    from meshsplat.train import Trainer

    logs = []
    for unit in (1.0, 100.0):
        ds = make_dataset(make_avatar(n=80), tmp_path / f"ds{unit:g}")
        if unit != 1.0:  # the same capture in other units: meshes and camera positions scaled
            m = json.loads((ds / "manifest.json").read_text())
            for cam in m["cameras"].values():
                vm = np.asarray(cam["viewmat"])
                vm[:3, 3] *= unit
                cam["viewmat"] = vm.tolist()
            (ds / "manifest.json").write_text(json.dumps(m))
            z = dict(np.load(ds / "canonical.npz"))
            np.savez(ds / "canonical.npz", vertices=z["vertices"] * unit, faces=z["faces"])
            np.save(ds / "vertices.npy", np.load(ds / "vertices.npy") * unit)
        cfg = recipe_config(
            "quality", data=str(ds), out=str(tmp_path / f"run{unit:g}"), iterations=3, device="cpu", progress=False
        )
        cfg.model.n_init = 200
        cfg.loss.lambda_lpips = 0.0
        cfg.loss.scale_max, cfg.loss.scale_ratio = 1e-6, 1.0  # every Gaussian counts: the regulariser is non-zero
        t = Trainer(cfg.validate())
        t.train()
        logs.append((t.history[-1]["scale"], t.history[-1]["loss"]))
    (s1, loss1), (s100, loss100) = logs
    assert s1 > 0 and s100 == pytest.approx(s1, rel=0.2)  # was 100x before
    assert loss100 == pytest.approx(loss1, rel=0.2)  # the optimised objective too


# ---------------------------------------------------------------- defaults from the asset's clips
def test_default_clips_from_motion(tmp_path, capsys):
    d = creature_frames(frames_per_clip=4)
    d["clip_names"] = np.array(["rest", "crawl", "idle"])  # a still clip first, no "Walking"
    v = d["vertices"]
    d["vertices"] = np.concatenate([np.repeat(v[4:5], 4, 0), v], 0)
    d["clip_ranges"] = np.array([[0, 3], [4, 7], [8, 11]])
    np.savez(tmp_path / "three.npz", **d)
    out = synthesize(tmp_path / "three.npz", tmp_path / "ds", rig="orbit", progress=True, **TINY)
    said = capsys.readouterr().out
    meta = open_dataset(out).meta
    assert meta["train_clip"] == "crawl" and meta["test_clips"] == ["idle"]  # the still clip is no test
    assert "training clip: crawl (most motion of 3 clips" in said and "novel-pose clips: idle" in said


# ---------------------------------------------------------------- credits
def test_gltf_copyright_reaches_dataset_and_report(assets, tmp_path):
    import pygltflib

    doc = pygltflib.GLTF2().load(str(assets / "gltf" / "RiggedSimple.glb"))
    doc.asset = pygltflib.Asset(
        version="2.0",
        copyright="(c) 2026 Test Author",
        extras={"license": "CC-BY 4.0", "source": "https://example.org/model"},
    )
    doc.save_binary(str(tmp_path / "credited.glb"))
    ds = open_dataset(synthesize(tmp_path / "credited.glb", tmp_path / "ds", rig="orbit", **TINY))
    assert ds.meta["attribution"] == "(c) 2026 Test Author; license: CC-BY 4.0; source: https://example.org/model"
    from meshsplat.eval import evaluate_run

    run = make_run(_avatar(ds), tmp_path / "run", ds.root)
    m = evaluate_run(run, max_frames_per_split=1, samples_per_split=1, lpips_net=None, progress=False)
    assert m["attribution"].startswith("(c) 2026 Test Author")
    assert "Asset credit: (c) 2026 Test Author" in (run / "eval" / "report.html").read_text()


# ---------------------------------------------------------------- threads
def test_threads_choice(capsys):
    from meshsplat.cli.threads import choose_threads

    assert choose_threads("3") == (3, "--threads")
    n, how = choose_threads("auto")
    assert n >= 1 and how.startswith("auto")
    for bad in ("0", "many"):
        with pytest.raises(MeshsplatError, match="--threads"):
            choose_threads(bad)


def test_threads_flag_on_heavy_commands():
    import argparse

    from meshsplat.cli import demo_cmd, eval_cmd, render_cmd, synth_cmd, train_cmd

    for mod in (synth_cmd, train_cmd, render_cmd, eval_cmd, demo_cmd):
        p = argparse.ArgumentParser()
        mod.add_arguments(p)
        assert any(a.dest == "threads" and a.default == "auto" for a in p._actions), mod.__name__


# ---------------------------------------------------------------- the demo plays one continuous motion
def test_demo_animation_is_one_continuous_motion(creature):
    from meshsplat.demo import continuous_frames

    _, ds = creature
    ids = continuous_frames(ds, 30)
    infos = [ds.frame_info(i) for i in ids]
    assert {f["split"] for f in infos} == {"test_frames"} and len({f["clip"] for f in infos}) == 1
    times = [f["time"] for f in infos]
    assert times == sorted(times) and len(set(times)) == len(times)
    assert len(continuous_frames(ds, 1)) == 1
    # without held-out frames it falls back to the training frames, still in time order
    assert [ds.frame_info(i)["split"] for i in continuous_frames(ds, 3, split="nope")] == ["train"] * 3
    assert not math.isnan(times[0])
