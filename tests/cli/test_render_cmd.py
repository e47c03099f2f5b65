"""meshsplat render: drivers -> vertex frames (with vertex matching), cameras, frames + MP4, CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from _eval_kit import SIZE, deform, make_avatar, make_dataset, make_run
from meshsplat import animate, camera
from meshsplat.animation import AnimationSource, load_animation
from meshsplat.animation.avatar_match import sequence_for_mesh
from meshsplat.errors import MeshsplatError


@pytest.fixture(scope="module")
def avatar():
    return make_avatar(n=150)


def _project(cam, pts):
    pc = pts @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
    uv = pc @ cam.K.T
    return uv[:, :2] / uv[:, 2:], pc[:, 2]


def test_orbit_cameras_frame_the_animation(avatar):
    frames = [deform(avatar.mesh.vertices, t) for t in (0.0, 0.5, 1.0)]
    cams = camera.orbit_cameras(frames, 64, 48, orbit_deg=360, elevation_deg=20)
    assert len(cams) == 3
    centres = torch.stack([-c.viewmat[:3, :3].T @ c.viewmat[:3, 3] for c in cams])
    allv = torch.cat(frames)
    mid = (allv.min(0).values + allv.max(0).values) / 2
    d = (centres - mid).norm(dim=1)
    assert torch.allclose(d, d[0].expand(3), rtol=1e-5)  # constant distance
    az = [math.degrees(math.atan2(float(c[0] - mid[0]), float(c[2] - mid[2]))) % 360 for c in centres]
    assert np.allclose(az, [0, 120, 240], atol=1e-3)  # 360 degrees over 3 frames
    for cam, v in zip(cams, frames, strict=True):
        px, z = _project(cam, v)
        assert (z > 0).all()
        assert (px[:, 0] > 0).all() and (px[:, 0] < 64).all() and (px[:, 1] > 0).all() and (px[:, 1] < 48).all()


def test_render_animation_writes_frames_and_video(avatar, tmp_path):
    frames = [deform(avatar.mesh.vertices, t) for t in (0.0, 0.5, 1.0)]
    cam = camera.orbit_cameras(frames, SIZE, SIZE)[0]
    res = animate.render_animation(avatar, frames, cam, tmp_path, fps=10, background="black")
    assert res.num_frames == 3 and len(res.pngs) == 3
    from PIL import Image

    imgs = [np.asarray(Image.open(p)) for p in res.pngs]
    assert imgs[0].shape == (SIZE, SIZE, 3)
    assert imgs[0][0, 0].tolist() == [0, 0, 0]  # background corner
    assert np.abs(imgs[0].astype(int) - imgs[2]).max() > 30  # the pose changes the image
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        assert res.mp4 is None and res.error
    else:
        assert res.mp4 is not None and res.mp4.stat().st_size > 0
    with pytest.raises(MeshsplatError, match="cameras"):
        animate.render_animation(avatar, frames, [cam], tmp_path / "b", write_mp4=False)


def test_sequence_and_blendshape_drivers(avatar, tmp_path):
    from meshsplat.drivers import BlendshapeDriver

    seq = torch.stack([deform(avatar.mesh.vertices, t) for t in (0.1, 0.2)])
    np.save(tmp_path / "seq.npy", seq.numpy())
    frames = sequence_for_mesh(avatar.mesh, tmp_path / "seq.npy")
    assert len(frames) == 2 and torch.equal(frames[1], seq[1])
    with pytest.raises(MeshsplatError, match=r"\[T,42,3\]"):
        sequence_for_mesh(avatar.mesh, np.zeros((2, 41, 3), np.float32))
    nan = seq.numpy().copy()
    nan[1, 5] = np.nan  # NaN edges compare as no stretch: named as NaN, not as another mesh
    with pytest.raises(MeshsplatError, match=r"frame 1: contains 3 NaN/Inf values") as err:
        sequence_for_mesh(avatar.mesh, nan)
    assert "does not match" not in str(err.value)

    # a blend-shape model on a superset of the avatar's vertices, shuffled: matched by rest position
    v = avatar.mesh.vertices
    extra = torch.tensor([[5.0, 5.0, 5.0], [6.0, 5.0, 5.0], [5.0, 6.0, 5.0]])
    perm = torch.randperm(45)
    neutral = torch.cat([v, extra])[perm]
    deltas = torch.randn(2, 45, 3)
    faces = torch.tensor([[42, 43, 44]])
    inv = torch.argsort(perm)
    model = BlendshapeDriver(neutral, inv[faces], deltas, names=["jaw", "smile"])
    (tmp_path / "w.json").write_text(json.dumps({"names": ["smile"], "weights": [[0.0], [0.5]]}))
    frames = load_animation(AnimationSource("blendshapes", model, weights=tmp_path / "w.json"), avatar).frames
    assert len(frames) == 2
    assert torch.allclose(frames[0], v)
    assert torch.allclose(frames[1], v + 0.5 * deltas[1][inv[:42]], atol=1e-6)
    with pytest.raises(MeshsplatError, match=r"\[T,2\]"):
        load_animation(AnimationSource("blendshapes", model, weights=np.zeros((3, 5))), avatar)


def test_gltf_driver_vertex_count_and_matching(avatar, assets):
    """The raw RiggedSimple glTF has seam duplicates; an avatar on its welded mesh is still driven."""
    from meshsplat.drivers import GltfDriver
    from meshsplat.gaussians import Avatar, init_params
    from meshsplat.mesh import TriMesh
    from meshsplat.synth.driving import weld

    path = assets / "gltf" / "RiggedSimple.glb"
    with pytest.raises(MeshsplatError, match="does not drive the avatar's mesh"):
        load_animation(AnimationSource("gltf", path, fps=5, seconds=0.2), avatar)
    drv = GltfDriver(path)
    rest = drv.rest_vertices().numpy().astype(np.float64)
    tol = 1e-6 * float(np.linalg.norm(rest.max(0) - rest.min(0)))
    t0, t1 = drv.time_range()
    probes = [rest] + [drv.vertices_at(t0 + (t1 - t0) * f).numpy().astype(np.float64) for f in (0.3, 0.7)]
    _, rep, wfaces = weld(probes, drv.faces.numpy(), tol)  # as meshsplat.synth welds its driving mesh
    assert len(rep) < drv.num_vertices
    rest_pos = torch.from_numpy(rest[rep]).float()
    assert (torch.cdist(rest_pos, rest_pos) + 1e3 * torch.eye(len(rep))).min() < 1e-6  # coincident vertices exist
    mesh = TriMesh(rest_pos, torch.from_numpy(wfaces).long())
    welded = Avatar(mesh, init_params(mesh, 50))
    frames = load_animation(
        AnimationSource("gltf", path, clip=drv.clips[0], fps=10, seconds=1.0, start=0.5), welded
    ).frames
    assert len(frames) == 10
    for i in (0, 9):
        want = drv.vertices_at(drv.time_range()[0] + 0.5 + i / 10)[torch.from_numpy(rep)]
        assert torch.allclose(frames[i], want, atol=1e-5)
    assert not torch.allclose(frames[0], frames[9], atol=1e-3)  # it animates
    full = load_animation(AnimationSource("gltf", path, fps=4), welded).frames  # whole clip, end included
    assert len(full) == math.floor(drv.duration() * 4 + 1e-6) + 1


def test_cli_render(tmp_path, capsys):
    from meshsplat.cli.main import main

    av = make_avatar(n=120)
    ds = make_dataset(av, tmp_path / "ds")
    run = make_run(av, tmp_path / "run", ds)
    np.save(tmp_path / "seq.npy", torch.stack([deform(av.mesh.vertices, t) for t in (0, 1)]).numpy())
    out = tmp_path / "orbit"
    rc = main(
        [
            "render",
            str(run),
            "--animation",
            "vertices",
            str(tmp_path / "seq.npy"),
            "--orbit",
            "90",
            "--size",
            "24x16",
            "--out",
            str(out),
            "--no-progress",
            "--no-mp4",
        ]
    )
    assert rc == 0
    from PIL import Image

    pngs = sorted((out / "frames").glob("*.png"))
    assert len(pngs) == 2 and Image.open(pngs[0]).size == (24, 16)
    # the dataset's own frames and cameras reproduce its ground truth
    out2 = tmp_path / "split"
    assert (
        main(
            [
                "render",
                str(run),
                "--animation",
                "dataset",
                "--split",
                "test_frames",
                "--out",
                str(out2),
                "--no-progress",
                "--no-mp4",
                "--background",
                "black",
            ]
        )
        == 0
    )
    from meshsplat.data import open_dataset

    d = open_dataset(ds)
    fr = d[d.split("test_frames")[0]]
    got = np.asarray(Image.open(out2 / "frames" / "frame_00000.png")).astype(np.float32) / 255
    want = (fr.image * fr.mask).numpy()
    assert np.abs(got - want).max() < 0.03
    assert (
        main(
            [
                "render",
                str(run),
                "--animation",
                "vertices",
                str(tmp_path / "seq.npy"),
                "--camera",
                "dataset:side",
                "--out",
                str(tmp_path / "cam"),
                "--no-progress",
                "--no-mp4",
            ]
        )
        == 0
    )
    assert Image.open(tmp_path / "cam" / "frames" / "frame_00001.png").size == (SIZE, SIZE)
    capsys.readouterr()
    assert (
        main(
            [
                "render",
                str(run),
                "--animation",
                "vertices",
                str(tmp_path / "seq.npy"),
                "--camera",
                "dataset:nope",
                "--out",
                str(tmp_path / "bad"),
            ]
        )
        == 2
    )
    assert "not a camera" in capsys.readouterr().err
    assert (
        main(["render", str(tmp_path / "missing"), "--animation", "vertices", "x.npy", "--out", str(tmp_path / "m")])
        == 2
    )
    assert "run not found" in capsys.readouterr().err
