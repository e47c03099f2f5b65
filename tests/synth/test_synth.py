"""Ground-truth generator: rasterizer correctness, driving meshes, a small end-to-end run."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from meshsplat.camera import look_at
from meshsplat.cli.main import main as cli_main
from meshsplat.data import open_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.io.images import read_image
from meshsplat.render.background import composite
from meshsplat.synth import SynthSpec, rasterize_triangles, synthesize
from meshsplat.synth.driving import cluster_decimate, taubin_smooth, weld
from meshsplat.synth.generate import synth_spec
from meshsplat.synth.raster import sample_texture

K = torch.tensor([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])


def test_zbuffer_two_overlapping_triangles():
    # a big far triangle (z=4) and a small near one (z=2) drawn first / last in both orders
    far = [[-3, -3, 4], [3, -3, 4], [0, 3, 4]]
    near = [[-0.5, -0.5, 2], [0.5, -0.5, 2], [0, 0.5, 2]]
    for order in ([far, near], [near, far]):
        verts = torch.tensor(order[0] + order[1], dtype=torch.float32)
        faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
        fr = rasterize_triangles(verts, faces, K, 64, 64)
        near_id = 0 if order[0] is near else 1
        centre = fr.face[32, 32]
        assert int(centre) == near_id and abs(float(fr.depth[32, 32]) - 2.0) < 1e-5
        # a pixel covered only by the far triangle
        assert int(fr.face[32, 45]) == 1 - near_id and abs(float(fr.depth[32, 45]) - 4.0) < 1e-4
        assert int(fr.face[63, 0]) == -1 and torch.isinf(fr.depth[63, 0])
        # near triangle area in pixels ~ (50 * 1 / 2)^2 / 2
        assert abs(int((fr.face == near_id).sum()) - 312.5) < 30  # edge rows on pixel centres count


def test_perspective_correct_interpolation_analytic():
    # a plane tilted in depth: z = 2 + y, x in [-1, 1], y in [-1, 1]; attribute = world y
    verts = torch.tensor([[-1, -1, 1], [1, -1, 1], [1, 1, 3], [-1, 1, 3]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    fr = rasterize_triangles(verts, faces, K, 64, 64)
    m = fr.mask
    ys = (fr.bary[m][..., None] * verts[faces[fr.face[m]]]).sum(1)[:, 1]
    # ray through pixel centre: y/z = (py + 0.5 - cy) / f; on the plane z = 2 + y  =>  y = 2 r / (1 - r)
    py = torch.nonzero(m)[:, 0].float()
    r = (py + 0.5 - 32) / 50
    expected = 2 * r / (1 - r)
    assert float((ys - expected).abs().max()) < 1e-4
    # depth is the true camera z
    assert float((fr.depth[m] - (2 + expected)).abs().max()) < 1e-4
    # screen-space (affine) interpolation would be visibly wrong here
    assert float((expected - (r * 0 + ys.mean())).abs().max()) > 0.1


def test_texture_bilinear_and_wrap():
    tex = torch.tensor([[[0.0], [1.0]], [[2.0], [3.0]]])  # 2x2
    got = sample_texture(tex, torch.tensor([[0.25, 0.25], [0.5, 0.25], [0.5, 0.5], [1.25, 0.25]]))
    torch.testing.assert_close(got[:, 0], torch.tensor([0.0, 0.5, 1.5, 0.0]))


def test_look_at_is_opencv():
    vm = look_at([0, 0, 5], [0, 0, 0])
    p = vm @ np.array([1.0, 1.0, 0, 1])  # world +x right, +y up
    assert p[0] > 0 and p[1] < 0 and abs(p[2] - 5) < 1e-12
    np.testing.assert_allclose(vm[:3, :3] @ vm[:3, :3].T, np.eye(3), atol=1e-12)


def test_driving_mesh_helpers():
    import trimesh

    m = trimesh.creation.icosphere(3)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    dup = np.concatenate([v, v[:10]])
    f2 = f.copy()
    f2[f2 < 10] += len(v)  # faces use the duplicated copies
    _group, rep, wf = weld([dup], np.concatenate([f, f2[:5]]), 1e-9)
    assert len(rep) == len(v) and wf.max() < len(v)
    noisy = v + np.random.default_rng(0).normal(0, 0.02, v.shape)
    s = taubin_smooth(noisy, f, 10)
    assert np.linalg.norm(s, axis=1).std() < 0.5 * np.linalg.norm(noisy, axis=1).std()
    assert abs(np.linalg.norm(s, axis=1).mean() - 1) < 0.02  # no shrinkage
    nv, nf, near = cluster_decimate(v, f, 0.25)
    assert 0.1 * len(v) < len(nv) < 0.4 * len(v) and nf.max() < len(nv) and len(near) == len(nv)


@pytest.mark.slow
def test_small_synth_round_trip(assets, tmp_path):
    out = synthesize(
        assets / "gltf" / "CesiumMan.glb",
        tmp_path / "cm",
        frames=4,
        resolution=64,
        test_frames=2,
        test_views=1,
        test_view_frames=2,
    )
    ds = open_dataset(out)
    assert {k: len(ds.split(k)) for k in ds.split_names} == {"train": 4, "test_frames": 2, "test_views": 2}
    fr = ds[0]
    assert fr.image.shape == (64, 64, 3) and fr.vertices.shape == ds.canonical_vertices.shape
    fg = fr.mask[..., 0] > 0.5
    assert 0.05 < float(fg.float().mean()) < 0.6
    assert float(fr.image[~(fr.mask[..., 0] > 0)].abs().max()) == 0.0  # black background outside the mask
    assert float(fr.image[fg].mean()) > 0.1
    # upright: the head (max y) projects above the feet (min y)
    v = fr.vertices
    top, bottom = v[v[:, 1].argmax()], v[v[:, 1].argmin()]
    cam_K, viewmat = fr.camera.K, fr.camera.viewmat
    pix = lambda p: cam_K @ (viewmat[:3, :3] @ p + viewmat[:3, 3])  # noqa: E731
    assert (pix(top)[1] / pix(top)[2]) < (pix(bottom)[1] / pix(bottom)[2])
    # the driving mesh projects inside the mask
    proj = (cam_K @ (v @ viewmat[:3, :3].T + viewmat[:3, 3]).T).T
    px = (proj[:, :2] / proj[:, 2:]).long().clamp(0, 63)
    assert float(fr.mask[px[:, 1], px[:, 0], 0].gt(0).float().mean()) > 0.9
    assert ds.meta["train_clip"] == "clip0" and "CesiumMan" in ds.meta["attribution"]


def test_capture_on_one_backdrop_composites_like_one_rendered_on_another(assets, tmp_path):
    """The same capture rendered over black and over white: each, composited over the other's colour
    through its soft mask, is the other (8-bit rounding). Without the manifest's ``backdrop`` the
    edge pixels would keep a fringe of the colour they were rendered over (up to 0.25 off)."""
    kw = dict(frames=2, resolution=64, test_frames=0, test_views=0)
    black = open_dataset(synthesize(assets / "gltf" / "CesiumMan.glb", tmp_path / "b", background=(0, 0, 0), **kw))
    white = open_dataset(synthesize(assets / "gltf" / "CesiumMan.glb", tmp_path / "w", background=(1, 1, 1), **kw))
    assert black.manifest["backdrop"] == [0.0, 0.0, 0.0] and white.manifest["backdrop"] == [1.0, 1.0, 1.0]
    for i in range(len(black)):
        b, w = black[i], white[i]
        assert b.mask is not None and w.mask is not None and torch.equal(b.mask, w.mask)
        edge = (b.mask > 0) & (b.mask < 1)
        assert int(edge.sum()) > 20  # soft edges to test
        on_white = composite(b.image, b.mask, torch.ones(3))
        on_black = composite(w.image, w.mask, torch.zeros(3))
        recorded_w = torch.from_numpy(read_image(white.root / white.manifest["frames"][i]["image"], 3) / 255.0)
        recorded_b = torch.from_numpy(read_image(black.root / black.manifest["frames"][i]["image"], 3) / 255.0)
        assert float((on_white - recorded_w).abs().max()) < 2.5 / 255
        assert float((on_black - recorded_b).abs().max()) < 2.5 / 255


def test_backdrop_key_is_checked(assets, tmp_path):
    out = synthesize(
        assets / "gltf" / "CesiumMan.glb", tmp_path / "c", frames=1, resolution=32, test_frames=0, test_views=0
    )
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["backdrop"] = [0, 0, 2]
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MeshsplatError, match="'backdrop' must be three numbers in \\[0, 1\\]"):
        open_dataset(out)


@pytest.mark.slow
def test_synth_cli_smoothed_decimated_driver(assets, tmp_path):
    rc = cli_main(
        [
            "synth",
            str(assets / "gltf" / "RiggedSimple.glb"),
            "--out",
            str(tmp_path / "rs"),
            "--frames",
            "3",
            "--resolution",
            "48",
            "--rig",
            "orbit",
            "--test-views",
            "1",
            "--driver-smooth",
            "3",
            "--driver-decimate",
            "0.5",
        ]
    )
    assert rc == 0
    ds = open_dataset(tmp_path / "rs")
    assert ds.num_vertices < 0.6 * ds.meta["render_vertices"]
    assert len({ds.frame_info(i)["camera"] for i in ds.split("train")}) == 3
    assert cli_main(["synth", "nope.glb", "--out", str(tmp_path / "x")]) == 2


def test_rendering_some_splits_again_gives_the_same_frames(assets, tmp_path):
    kw = dict(frames=3, resolution=32, test_frames=2, test_views=1, test_view_frames=2)
    full = open_dataset(synthesize(assets / "gltf" / "CesiumMan.glb", tmp_path / "full", **kw))
    part = open_dataset(synthesize(assets / "gltf" / "CesiumMan.glb", tmp_path / "part", splits=["test_views"], **kw))
    assert part.split("train") == [] and len(part) == len(full.split("test_views")) == 2
    # the cost per frame counts the frames rendered, not those planned
    assert part.meta["frames_rendered"] == 2 and full.meta["frames_rendered"] == len(full)
    names = {full.frame_info(i)["name"]: i for i in range(len(full))}
    for j in part.split("test_views"):
        i = names[part.frame_info(j)["name"]]
        assert i in full.split("test_views")
        assert torch.equal(part[j].image, full[i].image) and torch.equal(part[j].mask, full[i].mask)
        assert torch.equal(part[j].camera.viewmat, full[i].camera.viewmat)
    with pytest.raises(MeshsplatError, match="splits: expected some of"):
        synthesize(assets / "gltf" / "CesiumMan.glb", tmp_path / "bad", splits=["test_clip"], **kw)


def test_a_spec_and_its_keywords_make_one_capture(assets, tmp_path):
    spec = SynthSpec(frames=2, resolution=16, test_frames=1, test_views=0)
    a = synthesize(assets / "gltf" / "CesiumMan.glb", tmp_path / "a", spec)
    b = synthesize(
        assets / "gltf" / "CesiumMan.glb", tmp_path / "b", frames=2, resolution=16, test_frames=1, test_views=0
    )
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for f in files:
        if f.name != "manifest.json":  # its meta holds the seconds taken
            assert (a / f).read_bytes() == (b / f).read_bytes(), f
    # keywords override a spec; supersampling follows the resolution it ends with
    assert synth_spec(spec, resolution=512).supersample_factor == 1 and spec.supersample_factor == 2
    assert synth_spec(spec, supersample=3).supersample_factor == 3
    with pytest.raises(TypeError, match="resolutoin"):
        synth_spec(spec, resolutoin=64)
    with pytest.raises(MeshsplatError, match="renderer: expected one of"):
        SynthSpec(renderer="raytrace")
    with pytest.raises(MeshsplatError, match="frames >= 1"):
        SynthSpec(frames=0)
