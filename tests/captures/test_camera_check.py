"""Cameras checked at the door (data/camera_check.py) and upright default cameras (dataset.up / front).

The capture: PeopleSnapshot-style, stand-in SMPL turned 180 degrees about x (as trackers leave it in the
OpenCV camera frame: y down), a camera looking at it from the front-left, masks from the projected mesh.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from PIL import Image

from _eval_kit import make_run
from _peoplesnapshot import H, K, W, make_capture
from meshsplat.camera import look_at, orbit_cameras
from meshsplat.cli.main import main
from meshsplat.data.camera_check import group_ids
from meshsplat.data.formats import open_capture
from meshsplat.data.formats import peoplesnapshot as ps
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.gaussians.params import init_params
from meshsplat.mesh import TriMesh
from meshsplat.paths import assets_dir
from meshsplat.viewer.bundle import read_viewer_bundle

EYE = np.array([1.8, -0.2, -4.6])  # world y points down: the camera is slightly above the pelvis
EXTRINSIC = look_at(EYE, [0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0])


def _project(vm, pts):
    pc = pts @ vm[:3, :3].T + vm[:3, 3]
    uv = pc @ K.T
    return uv[:, :2] / uv[:, 2:]


def _upright_capture(root, model_dir, n=8, extrinsic=EXTRINSIC):
    """Body upright in a y-down world (global orient pi about x), masks = the projected mesh (dilated)."""
    thetas = np.zeros((n, 72))
    thetas[:, 0] = math.pi
    thetas[:, 3 * 16 + 2] = np.linspace(-0.4, 0.4, n)  # the left arm moves
    make_capture(root, n=n, thetas=thetas)
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=EXTRINSIC, height=np.array(H), width=np.array(W))
    ds = ps.read(root, model_dir=model_dir, check_masks=False)
    for i in range(len(ds)):
        uv = _project(EXTRINSIC, ds.vertices(i).double().numpy())
        m = np.zeros((H, W), np.uint8)
        for du in (-1, 0, 1):
            for dv in (-1, 0, 1):
                c = np.clip(np.floor(uv + [du, dv]).astype(int), 0, [W - 1, H - 1])
                m[c[:, 1], c[:, 0]] = 255
        Image.fromarray(m).save(root / "masks" / f"mask_{ds.frame_info(i)['frame_index']:04d}.png")
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=extrinsic, height=np.array(H), width=np.array(W))
    return root


def _with_extrinsic(root, extrinsic):
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=extrinsic, height=np.array(H), width=np.array(W))
    return root


@pytest.fixture()
def capture(tmp_path, standin_model_dir):
    return _upright_capture(tmp_path / "cap", standin_model_dir)


def test_a_right_capture_opens_and_knows_its_up_and_front(capture, standin_model_dir):
    ds = ps.read(capture, model_dir=standin_model_dir)
    assert len(ds) == 8 and ds.dropped_frames == []
    assert torch.allclose(ds.up, torch.tensor([0.0, -1.0, 0.0]))  # y down, as the camera sees it
    cam = ds.camera("0").center.numpy()
    center = ds.vertices(0).numpy().mean(0)
    f = ds.front.numpy()
    assert abs(float(f @ ds.up.numpy())) < 1e-6 and float(f @ (cam - center)) > 0  # level, the camera's side


@pytest.mark.parametrize(
    "fix, match",
    [
        (lambda e: np.diag([1.0, -1, -1, 1]) @ e, r"y and z axes are flipped"),
        (lambda e: np.diag([-1.0, -1, 1, 1]) @ e, r"rolled by 180 degrees"),
        (np.linalg.inv, r"camera-to-world, given where world-to-camera"),
    ],
    ids=["flipped-y-z", "rolled-180", "camera-to-world"],
)
def test_a_wrong_camera_is_refused_naming_the_mix_up(capture, standin_model_dir, fix, match):
    _with_extrinsic(capture, fix(EXTRINSIC))
    with pytest.raises(MeshsplatError, match=r"wrong camera: camera '0' does not see the subject on 8 of 8") as e:
        ps.read(capture, model_dir=standin_model_dir)
    assert "\n" not in str(e.value)
    assert e.match(match)
    with pytest.raises(MeshsplatError, match=match):  # dropping frames does not hide a wrong camera
        ps.read(capture, model_dir=standin_model_dir, drop_bad_frames=True)


def test_a_wrong_camera_stops_train_before_any_work(capture, standin_model_dir, tmp_path, capsys):
    _with_extrinsic(capture, np.diag([1.0, -1, -1, 1]) @ EXTRINSIC)
    args = ["train", str(capture), "--out", str(tmp_path / "run"), "--model-dir", str(standin_model_dir)]
    assert main([*args, "--iters", "2", "--no-progress", "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert "y and z axes are flipped" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_few_bad_frames_are_listed_and_dropped_with_the_flag(capture, standin_model_dir, tmp_path, capsys):
    for idx in (3, 4):  # these masks show the subject elsewhere (a tracking failure)
        m = np.zeros((H, W), np.uint8)
        m[:8, :8] = 255
        Image.fromarray(m).save(capture / "masks" / f"mask_{idx:04d}.png")
    with pytest.raises(
        MeshsplatError, match=r"2 of 8 frames .*off the mask: image_0003.png, image_0004.png\).*--drop-bad-frames"
    ):
        ps.read(capture, model_dir=standin_model_dir)
    with pytest.warns(UserWarning, match="left out 2 of 8 frames"):
        ds = open_capture(capture, model_dir=standin_model_dir, drop_bad_frames=True)
    assert len(ds) == 6 and ds.dropped_frames == ["image_0003", "image_0004"]
    assert [ds.frame_info(i)["name"] for i in ds.split("train")] == [
        "image_0000",
        "image_0001",
        "image_0002",
        "image_0005",
    ]
    assert ds.split("test_frames") == [4, 5]
    assert torch.equal(ds.vertices(3), ps.read(capture, model_dir=standin_model_dir, check_masks=False).vertices(5))
    # the command line: import refuses in one line naming the flag, and drops them with it
    out = tmp_path / "native"
    assert main(["import", str(capture), "--out", str(out), "--model-dir", str(standin_model_dir)]) == 2
    assert "--drop-bad-frames" in capsys.readouterr().err
    argv = ["import", str(capture), "--out", str(out), "--model-dir", str(standin_model_dir), "--drop-bad-frames"]
    assert main(argv) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "left out" in line]
    assert len(notes) == 1 and notes[0].startswith("note: ") and "image_0003.png, image_0004.png" in notes[0]
    assert len(open_capture(out)) == 6


def test_every_frame_is_checked_against_its_mask(tmp_path, standin_model_dir):
    """40 frames, three badly tracked ones spread over them (a sample of 32 missed such frames): all three
    are named by their image."""
    cap = _upright_capture(tmp_path / "cap40", standin_model_dir, n=40)
    for idx in (1, 20, 38):
        m = np.zeros((H, W), np.uint8)
        m[:8, :8] = 255
        Image.fromarray(m).save(cap / "masks" / f"mask_{idx:04d}.png")
    with pytest.raises(MeshsplatError) as err:
        ps.read(cap, model_dir=standin_model_dir)
    msg = str(err.value)
    assert "3 of 40 frames" in msg and "image_0001.png, image_0020.png, image_0038.png" in msg and "\n" not in msg


def test_an_empty_mask_is_refused_naming_the_flag_and_dropped_with_it(capture, standin_model_dir):
    """A frame whose subject left the view (empty mask): refused in one line that says how to leave it out;
    with ``--drop-bad-frames`` left out like a badly tracked one."""
    Image.fromarray(np.zeros((H, W), np.uint8)).save(capture / "masks" / "mask_0005.png")
    with pytest.raises(MeshsplatError) as err:
        ps.read(capture, model_dir=standin_model_dir)
    msg = str(err.value)
    assert "empty mask" in msg and "left the view" in msg and "--drop-bad-frames" in msg
    with pytest.warns(UserWarning, match=r"left out 1 of 8 frames \(empty mask, the subject left the view: image_0005"):
        ds = ps.read(capture, model_dir=standin_model_dir, drop_bad_frames=True)
    assert len(ds) == 7 and ds.dropped_frames == ["image_0005"]


def test_the_front_is_the_camera_side_also_in_a_y_up_world():
    """A +y-up world whose camera looks along +z sees the subject from -z: that is its front (not +z)."""
    from meshsplat.camera import capture_front

    for eye, want in (([0.0, 0.3, -4.0], [0.0, 0.0, -1.0]), ([0.0, 0.3, 4.0], [0.0, 0.0, 1.0])):
        vm = look_at(np.array(eye), [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
        np.testing.assert_allclose(capture_front(vm, [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]), want, atol=1e-9)


def test_group_ids():
    assert group_ids([9, 3, 4, 5, 12, 13]) == "3\u20135, 9, 12\u201313"
    assert group_ids(range(0, 40, 2), limit=3) == "0, 2, 4 and 17 more"


def test_geometry_only_without_masks(capture, standin_model_dir):
    """check_masks=False reads no mask: a rolled camera is not caught, a flipped one (behind) still is."""
    _with_extrinsic(capture, np.diag([-1.0, -1, 1, 1]) @ EXTRINSIC)
    assert len(ps.read(capture, model_dir=standin_model_dir, check_masks=False)) == 8
    _with_extrinsic(capture, np.diag([1.0, -1, -1, 1]) @ EXTRINSIC)
    with pytest.raises(MeshsplatError, match="behind the camera"):
        ps.read(capture, model_dir=standin_model_dir, check_masks=False)


# ---------------------------------------------------------------- upright by default
def _colour_avatar(ds) -> Avatar:
    """Gaussians red on the upper half of the body (canonical +y), green on its left side (+x), blue else."""
    mesh = TriMesh(ds.canonical_vertices, ds.faces)
    cano = ds.canonical_vertices
    mid_y = float(cano[:, 1].median())

    def colours(face, uv):
        c = cano[ds.faces[face]].mean(1)
        return torch.stack([(c[:, 1] > mid_y).float(), (c[:, 0] > 0).float(), torch.full_like(c[:, 0], 0.5)], 1)

    g = torch.Generator().manual_seed(0)
    p = init_params(mesh, 3000, init_opacity=0.99, colors_fn=colours, generator=g)
    with torch.no_grad():
        p["log_scale"].add_(0.7)
    return Avatar(mesh, p, "sqrt_area")


def _upright_and_front(png) -> None:
    img = np.asarray(Image.open(png).convert("RGB")).astype(float) / 255
    body = img.sum(2) < 2.9  # on white
    rows, cols = np.nonzero(body)
    assert len(rows) > 50
    red = img[..., 0][body] > 0.5
    green = img[..., 1][body] > 0.5
    # upright: the upper body (red) above the lower (not red); from the front: its left (green) on the image right
    assert rows[red].mean() < rows[~red].mean() - 3, "upside down"
    assert cols[green].mean() > cols[~green].mean() + 1, "seen from behind"


def test_render_motion_default_and_orbit_cameras_are_upright_from_the_front(capture, standin_model_dir, tmp_path):
    ds = ps.read(capture, model_dir=standin_model_dir)
    run = make_run(_colour_avatar(ds), tmp_path / "run", capture)
    cfg = json.loads((run / "config.json").read_text())
    cfg.update(data_format="peoplesnapshot", model_dir=str(standin_model_dir))
    (run / "config.json").write_text(json.dumps(cfg))
    motion = str(assets_dir() / "motion" / "aist_demo.npz")
    base = ["render", str(run), "--animation", "motion", motion, "--size", "64x64", "--no-progress", "--no-mp4"]
    assert main([*base, "--frames", "1", "--out", str(tmp_path / "default")]) == 0
    _upright_and_front(tmp_path / "default" / "frames" / "frame_00000.png")
    assert main([*base, "--frames", "4", "--orbit", "360", "--out", str(tmp_path / "orbit")]) == 0
    _upright_and_front(tmp_path / "orbit" / "frames" / "frame_00000.png")
    img = np.asarray(Image.open(tmp_path / "orbit" / "frames" / "frame_00002.png").convert("RGB")).astype(float) / 255
    body = img.sum(2) < 2.9  # half way round: from behind, still upright
    rows, _ = np.nonzero(body)
    red = img[..., 0][body] > 0.5
    assert rows[red].mean() < rows[~red].mean() - 3


def test_orbit_cameras_turn_about_the_capture_up(capture, standin_model_dir):
    ds = ps.read(capture, model_dir=standin_model_dir)
    v = ds.vertices(0)
    up = ds.up.numpy()
    head, feet = v[int(np.argmax(v.numpy() @ up))], v[int(np.argmin(v.numpy() @ up))]
    for cam in orbit_cameras([v], 64, 64, num_frames=6, orbit_deg=360, up=ds.up, front=ds.front):
        vm = cam.viewmat.double().numpy()
        (_, hv), (_, fv) = _project(vm, torch.stack([head, feet]).double().numpy())
        assert hv < fv  # the head above the feet in every view
    # +y up (the old default) shows this capture upside down
    vm = orbit_cameras([v], 64, 64)[0].viewmat.double().numpy()
    assert _project(vm, head[None].double().numpy())[0, 1] > _project(vm, feet[None].double().numpy())[0, 1]


def test_view_default_camera_is_upright_from_the_front(capture, standin_model_dir, tmp_path):
    ds = ps.read(capture, model_dir=standin_model_dir)
    run = make_run(_colour_avatar(ds), tmp_path / "run", capture)
    cfg = json.loads((run / "config.json").read_text())
    cfg.update(data_format="peoplesnapshot", model_dir=str(standin_model_dir))
    (run / "config.json").write_text(json.dumps(cfg))
    motion = str(assets_dir() / "motion" / "aist_demo.npz")
    assert (
        main(["view", str(run), "--animation", "motion", motion, "--frames", "2", "--out", str(tmp_path / "viewer")])
        == 0
    )
    header, _ = read_viewer_bundle(tmp_path / "viewer")
    cam = header["camera"]
    assert np.allclose(cam["up"], [0, -1, 0]) and np.allclose(cam["front"], ds.front.numpy(), atol=1e-6)
    vm = np.asarray(cam["viewmat"])
    v = ds.vertices(0).double().numpy()
    head, feet = v[np.argmax(v @ cam["up"])], v[np.argmin(v @ cam["up"])]
    assert _project(vm, head[None])[0, 1] < _project(vm, feet[None])[0, 1]
    # from the front: the subject's left (+x of the body, +x of this world) on the image right
    assert _project(vm, np.array([[1.0, 0, 0]]))[0, 0] > _project(vm, np.array([[-1.0, 0, 0]]))[0, 0]


def test_a_k_written_for_a_larger_image_is_refused_saying_it_was_not_scaled(capture, standin_model_dir):
    big = K.copy()
    big[:2] *= 2  # K of the 2x larger original, images downscaled without it
    np.savez(capture / "cameras.npz", intrinsic=big, extrinsic=EXTRINSIC, height=np.array(H), width=np.array(W))
    with pytest.raises(MeshsplatError) as err:
        ps.read(capture, model_dir=standin_model_dir)
    msg = str(err.value)
    assert re.search(r"K looks written for a \d+x\d+ image \(2 times larger\)", msg), msg
    assert "not scaled with the images" in msg and "multiply its first two rows by 0.5" in msg


def test_a_mislabelled_known_subject_folder_is_not_told_about_a_config_json(tmp_path, standin_model_dir):
    """A folder named after a published subject but holding another capture: the split-relative poses do
    not match that subject's ranges; the message names the ranges the folder name chose, and the way out."""
    from _peoplesnapshot import make_capture

    root = make_capture(tmp_path / "male-3-casual", n=6)
    (root / "config.json").unlink()
    (root / "poses").mkdir()
    z = dict(betas=np.zeros((1, 10)), global_orient=np.zeros((3, 3)), body_pose=np.zeros((3, 69)))
    np.savez(root / "poses" / "anim_nerf_train.npz", transl=np.zeros((3, 3)), **z)
    with pytest.raises(MeshsplatError) as err:
        ps.read(root, model_dir=standin_model_dir)
    msg = str(err.value)
    assert "anim_nerf_train.npz" in msg and "InstantAvatar's male-3-casual ranges" in msg
    assert "in config.json" not in msg and "rename it, or add a config.json" in msg


def test_no_progress_still_says_which_rule_chose_the_splits(tmp_path, standin_model_dir, capsys):
    from _peoplesnapshot import make_capture

    root = make_capture(tmp_path / "my-subject", n=6)
    (root / "config.json").unlink()
    args = ["train", str(root), "--out", str(tmp_path / "run"), "--iters", "1", "--no-progress", "--device", "cpu"]
    args += ["--model-dir", str(standin_model_dir), "--gender", "neutral", "--no-refine-pose"]
    assert main([*args, "--set", "model.n_init=100", "loss.lambda_lpips=0"]) == 0
    out = capsys.readouterr().out
    assert out.count("splits from no config.json: the last 20%") == 1


def test_an_absurd_intrinsic_rasterizes_without_overflow():
    """Hypothesis found it: a skew of 3.2e19 put triangle corners past int64; the silhouette's bounding boxes
    overflowed into negative sample counts (a ValueError deep in numpy). Boxes are clipped to the grid first."""
    from meshsplat.data.camera_check import _silhouette

    verts = np.array([[-0.5, 0.2, 0.0], [0.5, 0.2, 0.0], [0.0, 0.8, 0.0]])  # y > 0: a huge skew moves every corner
    faces = np.array([[0, 1, 2]])
    vm = np.eye(4)
    vm[2, 3] = 3.0  # the triangle 3 units in front of an OpenCV camera looking along +z
    for skew in (0.0, 3.2125885782776046e19, 1e21, 1e300):
        intr = np.array([[64.0, skew, 32.0], [0.0, 64.0, 32.0], [0.0, 0.0, 1.0]])
        sil = _silhouette(vm, intr, 64, 64, verts, faces, (8, 8), 8)
        assert sil.dtype == bool and sil.shape[0] >= 8
        if skew == 0.0:
            assert sil.any()
