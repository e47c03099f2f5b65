"""Subjects the cameras cannot see and absurd but finite numbers, in every reader and driver: a focal length
of 1e9, a subject behind the camera, a mirrored (z-flipped) viewmat; expression or shape coefficients of 1e30,
poses in degrees, NaN in stored driver parameters, all-zero skinning weights. Each is refused in one line
that says what was expected (``meshsplat.plausible``, the cameras check at the door)."""

from __future__ import annotations

import json
import pickle
import re
import shutil
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from _head_captures import native_flame_dataset, tiny_flame, write_tiny_flame
from _peoplesnapshot import make_capture
from meshsplat.animation.motion import load_motion
from meshsplat.data import open_dataset
from meshsplat.data.formats import format_module, open_capture
from meshsplat.drivers.body_models import BodyModel
from meshsplat.drivers.gltf import GltfDriver
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.paths import asset
from meshsplat.plausible import focal_problem, parameter_problems, sequence_gaps, skinning_problem

HEAD_LAYOUTS = ("native", "imavatar", "insta", "vhap", "meshseq")
FLIP_Z = np.diag([1.0, 1.0, -1.0, 1.0])  # a mirror: z negated, det -1
TURN = np.diag([-1.0, 1.0, -1.0, 1.0])  # turned 180 degrees about y: the subject is behind the camera


def _bad_camera(kind: str, K: np.ndarray, vm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K, vm = K.copy(), vm.copy()
    if kind == "focal 1e9":
        K[0, 0] = K[1, 1] = 1e9
    elif kind == "behind":
        vm = TURN @ vm
    else:
        vm = FLIP_Z @ vm
    return K, vm


def _one_line(exc: pytest.ExceptionInfo) -> str:
    """The message's first line, which must say it all (a capture's message may list more problems below)."""
    text = str(exc.value)
    assert "Traceback" not in text and "allow_pickle" not in text and text.strip(), text
    return text.splitlines()[0]


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    return write_tiny_flame(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="module")
def native(tmp_path_factory, model_dir):
    return native_flame_dataset(
        tmp_path_factory.mktemp("native") / "cap", model_dir, rows=4, views=1, scale=4.0, transl=False,
        n_betas=100, n_expr=50,
    )  # fmt: skip


def _open(root: Path, layout: str, model_dir: Path):
    kw = {"flame_version": "2020"} if layout == "vhap" else {}
    return open_capture(root, format=layout, model_dir=model_dir, **kw)


def _with_camera(native: Path, layout: str, kind: str, out: Path) -> Path:
    """``native``'s capture in ``layout`` with its one camera made wrong in the way ``kind`` names."""
    if layout == "native":
        shutil.copytree(native, out)
        manifest = json.loads((out / "manifest.json").read_text())
        cam = manifest["cameras"]["0"]
        K, vm = _bad_camera(kind, np.asarray(cam["K"]), np.asarray(cam["viewmat"]))
        cam["K"], cam["viewmat"] = K.tolist(), vm.tolist()
        (out / "manifest.json").write_text(json.dumps(manifest))
        return out
    src = open_dataset(native)
    cam = src.manifest["cameras"]["0"]
    K, vm = _bad_camera(kind, np.asarray(cam["K"]), np.asarray(cam["viewmat"]))
    cam["K"], cam["viewmat"] = K.tolist(), vm.tolist()
    w, h = src._cameras["0"][2:]
    src._cameras["0"] = (K, vm, w, h)
    return format_module(layout).write(src, out)


@pytest.mark.parametrize("kind", ["focal 1e9", "behind", "flip z"])
@pytest.mark.parametrize("layout", HEAD_LAYOUTS)
def test_a_camera_that_cannot_see_the_subject_is_refused_by_every_reader(native, model_dir, layout, kind, tmp_path):
    try:
        root = _with_camera(native, layout, kind, tmp_path / layout)
    except MeshsplatError as exc:  # a writer that cannot even store the camera refuses in one line
        assert "\n" not in str(exc)
        return
    with pytest.raises(MeshsplatError) as e:
        _open(root, layout, model_dir)
    text = _one_line(e)
    expected = {
        "focal 1e9": r"focal length|outside the image|does not see the subject",
        "behind": r"behind|does not see the subject",
        "flip z": r"rotation matrix|behind|does not see the subject|mirror",
    }[kind]
    assert re.search(expected, text), text


@pytest.mark.parametrize("kind", ["focal 1e9", "behind", "flip z"])
def test_peoplesnapshot_camera_that_cannot_see_the_subject(kind, tmp_path, standin_model_dir):
    root = make_capture(tmp_path / "ps")
    z = dict(np.load(root / "cameras.npz"))
    K, vm = _bad_camera(kind, z["intrinsic"].astype(np.float64), z["extrinsic"].astype(np.float64))
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=vm, height=z["height"], width=z["width"])
    with pytest.raises(MeshsplatError) as e:
        open_capture(root, format="peoplesnapshot", model_dir=standin_model_dir)
    _one_line(e)


def test_focal_problem_range():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    assert focal_problem(K, 640, 480) is None
    assert "field of view" in focal_problem(np.diag([1e9, 1e9, 1.0]), 640, 480)
    assert "expected" in focal_problem(np.diag([1.2, 1.2, 1.0]), 640, 480)  # a normalised focal length


# ---------------------------------------------------------------- parameters


def test_parameter_problems_name_the_key_the_frames_and_the_range():
    ok = {"global_orient": np.full((4, 3), 0.5), "betas": np.ones(10), "expression": np.zeros((4, 50))}
    assert parameter_problems(ok) == []
    degrees = {"body_pose": np.zeros((6, 69))}
    degrees["body_pose"][2:5, 3] = 45.0
    (line,) = parameter_problems(degrees)
    assert line.startswith("body_pose:") and "frames 2\u20134" in line and "degrees" in line
    (line,) = parameter_problems({"expression": np.full((3, 50), 1e30)})
    assert "1e+30" in line and "expected at most 50" in line
    nan = np.zeros((5, 3))
    nan[3, 1] = np.nan
    (line,) = parameter_problems({"transl": nan})
    assert "NaN" in line and "frame 3" in line


def _params_file(native: Path) -> Path:
    manifest = json.loads((native / "manifest.json").read_text())
    return native / manifest["driver"]["params"]


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("expression", 1e30, "expected at most 50"),
        ("jaw_pose", 30.0, "degrees given for radians"),
        ("global_orient", np.nan, "NaN"),
    ],
)
def test_native_stored_driver_parameters_out_of_range(native, model_dir, tmp_path, key, value, match):
    root = shutil.copytree(native, tmp_path / "cap")
    p = _params_file(root)
    z = dict(np.load(p))
    z[key] = z[key].copy()
    z[key][1, 0] = value
    np.savez(p, **z)
    with pytest.raises(MeshsplatError, match=match) as e:
        open_dataset(root)
    assert key in _one_line(e)


def test_imavatar_expression_1e30_and_poses_in_degrees(native, model_dir, tmp_path):
    src = open_dataset(native)
    for key, value, match in (("expression", 1e30, "expected at most 50"), ("pose", 40.0, "degrees")):
        root = format_module("imavatar").write(src, tmp_path / key)
        data = json.loads((root / "flame_params.json").read_text())
        data["frames"][1][key][6] = value  # pose[6:9]: the jaw
        (root / "flame_params.json").write_text(json.dumps(data))
        with pytest.raises(MeshsplatError, match=match) as e:
            _open(root, "imavatar", model_dir)
        assert "flame_params.json" in _one_line(e)


def test_vhap_expression_1e30_names_the_timestep_file(native, model_dir, tmp_path):
    root = format_module("vhap").write(open_dataset(native), tmp_path / "vhap")
    f = sorted((root / "flame_param").glob("*.npz"))[2]
    z = dict(np.load(f))
    z["expr"] = np.full_like(z["expr"], 1e30)
    np.savez(f, **z)
    with pytest.raises(MeshsplatError, match="expr: coefficients up to 1e\\+30") as e:
        _open(root, "vhap", model_dir)
    assert f.name in _one_line(e)


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"thetas": np.full((8, 72), 30.0)}, "degrees"),
        ({"betas": np.full((1, 10), 1e30)}, "expected at most 50"),
    ],
)
def test_peoplesnapshot_poses_in_degrees_or_absurd_betas(tmp_path, standin_model_dir, kw, match):
    root = make_capture(tmp_path / "ps", **kw)
    with pytest.raises(MeshsplatError, match=match) as e:
        open_capture(root, format="peoplesnapshot", model_dir=standin_model_dir)
    _one_line(e)


@pytest.mark.parametrize("value, match", [(90.0, "degrees"), (np.nan, "NaN"), (np.inf, "NaN")])
def test_motion_npz_in_degrees_or_not_finite(tmp_path, standin_model_dir, value, match):
    poses = np.zeros((5, 72), np.float32)
    poses[3, 5] = value
    np.savez(tmp_path / "m.npz", poses=poses, trans=np.zeros((5, 3), np.float32))
    model = BodyModel("smpl", standin_model_dir)
    with pytest.raises(MeshsplatError, match=match) as e:
        load_motion(tmp_path / "m.npz", model)
    assert "m.npz" in _one_line(e)


# ---------------------------------------------------------------- skinning weights


def test_model_file_with_all_zero_skinning_weights(tmp_path):
    d = tmp_path / "flame"
    d.mkdir()
    model = tiny_flame()
    model["weights"] = np.zeros_like(model["weights"])
    with open(d / "FLAME_NEUTRAL.pkl", "wb") as fh:
        pickle.dump(model, fh, protocol=2)
    with pytest.raises(MeshsplatError, match="every vertex has all-zero weights") as e:
        BodyModel("flame", tmp_path, flame_version="2020")
    _one_line(e)


def _zero_skin_weights(glb: bytes) -> bytes:
    """The GLB with every WEIGHTS_0 accessor's bytes set to zero."""
    n_json = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20 : 20 + n_json])
    bin_start = 20 + n_json + 8
    out = bytearray(glb)
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            acc = prim["attributes"].get("WEIGHTS_0")
            if acc is None:
                continue
            a = doc["accessors"][acc]
            view = doc["bufferViews"][a["bufferView"]]
            size = {5126: 4, 5121: 1, 5123: 2}[a["componentType"]] * 4
            stride = view.get("byteStride", size)
            start = bin_start + view.get("byteOffset", 0) + a.get("byteOffset", 0)
            for i in range(a["count"]):
                out[start + i * stride : start + i * stride + size] = bytes(size)
    return bytes(out)


def test_gltf_skin_with_all_zero_weights(tmp_path):
    src = asset("gltf/RiggedSimple.glb")
    GltfDriver(src)  # as shipped: plausible
    bad = tmp_path / "zero_weights.glb"
    bad.write_bytes(_zero_skin_weights(Path(src).read_bytes()))
    with pytest.raises(MeshsplatError, match="all-zero weights") as e:
        GltfDriver(bad)
    assert "zero_weights.glb" in _one_line(e)


def test_skinning_problem():
    assert skinning_problem(np.eye(4)) is None
    w = np.eye(4)
    w[2] = 0
    assert "1 of 4 vertices" in skinning_problem(w)
    assert "negative" in skinning_problem(-np.eye(3))
    assert skinning_problem(np.full((2, 2), np.nan)).startswith("skinning weights: 4 NaN")


# ---------------------------------------------------------------- conflicts said, not resolved silently


def test_insta_transforms_files_disagreeing_on_a_frame_are_refused(native, model_dir, tmp_path):
    root = format_module("insta").write(open_dataset(native), tmp_path / "insta")
    names = sorted(p.name for p in root.glob("transforms*.json"))
    assert "transforms.json" in names and "transforms_train.json" in names, names
    split = json.loads((root / "transforms_train.json").read_text())
    split["frames"][0]["transform_matrix"][0][3] += 0.5  # the camera moved half a unit in one file only
    (root / "transforms_train.json").write_text(json.dumps(split))
    with pytest.raises(
        MeshsplatError, match=r"transforms_train\.json disagrees with transforms\.json on transform_matrix"
    ):
        _open(root, "insta", model_dir)
    split["frames"][0]["transform_matrix"][0][3] -= 0.5 - 1e-9  # equal up to rounding: fine
    (root / "transforms_train.json").write_text(json.dumps(split))
    _open(root, "insta", model_dir)


def _drop_timestep(root: Path, t: int) -> None:
    for f in root.glob("transforms*.json"):
        data = json.loads(f.read_text())
        data["frames"] = [fr for fr in data["frames"] if fr["timestep_index"] != t]
        f.write_text(json.dumps(data))


def test_vhap_timestep_gap_is_a_note_naming_it(model_dir, tmp_path):
    src = native_flame_dataset(tmp_path / "n", model_dir, rows=6, views=1, scale=4.0, transl=False)
    root = format_module("vhap").write(open_dataset(src), tmp_path / "vhap")
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshsplatWarning)
        _open(root, "vhap", model_dir)  # no gap, no note
    _drop_timestep(root, 2)
    with pytest.warns(MeshsplatWarning, match=r"timesteps jump from 1 to 3: 1 missing"):
        ds = _open(root, "vhap", model_dir)
    assert len(ds) == 5


def test_vhap_motion_folder_gap_is_a_note(tmp_path, model_dir):
    folder = tmp_path / "flame_param"
    folder.mkdir()
    for t in (0, 1, 2, 7, 8):
        np.savez(folder / f"{t:05d}.npz", translation=np.zeros((1, 3)), rotation=np.zeros((1, 3)),
                 neck_pose=np.zeros((1, 3)), jaw_pose=np.zeros((1, 3)), eyes_pose=np.zeros((1, 6)),
                 shape=np.zeros(100), expr=np.zeros((1, 50)))  # fmt: skip
    model = BodyModel("flame", model_dir, flame_version="2020")
    with pytest.warns(MeshsplatWarning, match=r"frame files jump from 2 to 7: 4 missing"):
        load_motion(folder, model)


def test_sequence_gaps_know_a_stride():
    assert sequence_gaps([0, 2, 4, 6, 8]) is None  # subsampled every second frame
    assert "4 to 8 (stride 2): 1 missing" in sequence_gaps([0, 2, 4, 8, 10])
    assert sequence_gaps([3, 1]) is None
