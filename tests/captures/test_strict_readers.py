"""Every reader as strict as the native one: files from outside the capture, per-file alpha decisions,
numpy files that cannot be read, grouped one-line refusals, atomic writes, the run's model_dir."""

from __future__ import annotations

import errno
import json
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from _head_captures import native_flame_dataset, write_tiny_flame
from meshsplat.animation.motion import load_motion
from meshsplat.data import open_dataset
from meshsplat.data.formats import format_module, open_capture
from meshsplat.data.manifest import Problems
from meshsplat.drivers.body_models import BodyModel
from meshsplat.drivers.mesh_sequence import read_mesh_sequence
from meshsplat.errors import MeshsplatError
from meshsplat.io.arrays import read_npy, read_npz
from meshsplat.io.atomic import atomic_write, write_text_atomic, write_with
from meshsplat.io.images import read_image, write_png
from meshsplat.run_folder import LoadedRun, RunFolder

LAYOUTS = ("imavatar", "insta", "vhap", "meshseq")
OUTSIDE = "outside the dataset folder"


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    return write_tiny_flame(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="module")
def captures(tmp_path_factory, model_dir):
    """The same FLAME subject written in each layout (one folder per layout)."""
    base = tmp_path_factory.mktemp("captures")
    src = open_dataset(
        native_flame_dataset(
            base / "native", model_dir, rows=4, views=1, scale=4.0, transl=False, n_betas=100, n_expr=50
        )
    )
    return {name: format_module(name).write(src, base / name) for name in LAYOUTS}


def _open(root: Path, layout: str, model_dir: Path, **kw):
    if layout == "vhap":
        kw.setdefault("flame_version", "2020")
    return open_capture(root, format=layout, model_dir=model_dir, **kw)


def _json_paths(root: Path, layout: str) -> list[tuple[str, str, str]]:
    """``(json file, frame key, path value)`` of frame 0 in each of the layout's JSON files."""
    names = {
        "imavatar": ["flame_params.json"],
        "meshseq": ["cameras.json"],
    }.get(layout) or sorted(p.name for p in root.glob("transforms*.json"))
    keys = ("file_path", "mesh_path", "fg_mask_path", "flame_param_path", "image", "mask")
    out = []
    for name in names:
        frames = json.loads((root / name).read_text()).get("frames") or []
        # a frame listed again in a split file is read from transforms.json (the first file naming it):
        # there, only a changed file_path makes a new frame whose files are read
        used = keys if name in names[:1] else ("file_path",)
        if frames:
            out += [(name, k, frames[0][k]) for k in used if isinstance(frames[0].get(k), str)]
    return out


def _copy_with(captures, layout: str, tmp: Path, name: str, key: str, value) -> Path:
    """The layout's capture copied to ``tmp/subject``, a second subject beside it (``tmp/other``), frame 0's
    ``key`` in ``name`` set to ``value(original)`` there and wherever another JSON file of the capture
    lists the same record."""
    root, other = tmp / "subject", tmp / "other"
    for p in (root, other):
        if not p.exists():
            shutil.copytree(captures[layout], p)
    original = json.loads((root / name).read_text())["frames"][0][key]
    new = value(root, original)
    for path in root.glob("*.json"):
        doc = json.loads(path.read_text())
        frames = doc.get("frames") if isinstance(doc, dict) else None
        for fr in frames or []:
            if fr.get(key) == original:
                fr[key] = new
        path.write_text(json.dumps(doc))
    return root


def _escapes(root: Path, rel: str):
    rel = rel[2:] if rel.startswith("./") else rel
    other = root.parent / "other"
    link = root / "linked"
    if not link.exists():
        link.symlink_to(other, target_is_directory=True)
    return {
        "dotdot": f"../other/{rel}",
        "nested": "/".join([rel.split("/")[0], "..", "..", "other", rel]),
        "absolute": str(other / rel),
        "symlink": f"linked/{rel}",
    }


@pytest.mark.parametrize("layout", LAYOUTS)
def test_paths_out_of_the_capture_are_refused_like_native(captures, model_dir, layout, tmp_path, monkeypatch):
    monkeypatch.delenv("MESHSPLAT_ALLOW_OUTSIDE_FILES", raising=False)
    assert len(_open(captures[layout], layout, model_dir)) > 0  # the capture as written opens
    fields = _json_paths(captures[layout], layout)
    assert fields, "the layout's JSON names files"
    for n, (name, key, _) in enumerate(fields):
        for style in ("dotdot", "absolute", "symlink"):
            work = tmp_path / f"{n}_{style}"
            root = _copy_with(captures, layout, work, name, key, lambda r, v, s=style: _escapes(r, v)[s])
            with pytest.raises(MeshsplatError, match=OUTSIDE) as err:
                _open(root, layout, model_dir)
            assert "or set MESHSPLAT_ALLOW_OUTSIDE_FILES=1 to allow it" in str(err.value), (name, key, style)
    # the same opt-in as the native reader: the environment variable, or allow_outside=True
    work = tmp_path / "allowed"
    name, key, _ = fields[0]
    root = _copy_with(captures, layout, work, name, key, lambda r, v: _escapes(r, v)["dotdot"])
    with pytest.raises(MeshsplatError, match=OUTSIDE):
        _open(root, layout, model_dir)
    assert len(_open(root, layout, model_dir, allow_outside=True)) > 0
    monkeypatch.setenv("MESHSPLAT_ALLOW_OUTSIDE_FILES", "1")
    assert len(_open(root, layout, model_dir)) > 0


def test_fuzz_escaping_paths_in_every_readers_json(captures, model_dir, tmp_path_factory, monkeypatch):
    monkeypatch.delenv("MESHSPLAT_ALLOW_OUTSIDE_FILES", raising=False)
    cases = [(layout, *f[:2]) for layout in LAYOUTS for f in _json_paths(captures[layout], layout)]

    @settings(max_examples=24, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(case=st.sampled_from(cases), style=st.sampled_from(["dotdot", "nested", "absolute", "symlink"]))
    def check(case, style):
        layout, name, key = case
        work = tmp_path_factory.mktemp("fuzz")
        root = _copy_with(captures, layout, work, name, key, lambda r, v: _escapes(r, v)[style])
        with pytest.raises(MeshsplatError) as err:
            _open(root, layout, model_dir)
        msg = str(err.value)
        assert OUTSIDE in msg and "Traceback" not in msg, (layout, name, key, style, msg)

    check()


def _rgba_images(root: Path, folder: str, masks: str | None, rgb_frames: set[int]) -> None:
    """Images of ``root/folder`` as RGBA (mask in alpha) except the ``rgb_frames``-th ones; masks removed."""
    for j, img in enumerate(sorted((root / folder).glob("*.png"))):
        rgb = read_image(img, 3)
        mask = read_image(root / masks / img.name, 1) if masks else np.full(rgb.shape[:2] + (1,), 255, np.uint8)
        write_png(img, rgb if j in rgb_frames else np.dstack([rgb, mask[..., 0]]))
    if masks:
        shutil.rmtree(root / masks)


def test_one_rgb_image_among_rgba_is_refused_naming_the_frames(captures, model_dir, tmp_path):
    # IMavatar: the masks are the images' alpha; an RGB frame no longer drops every frame's mask
    root = tmp_path / "ima"
    shutil.copytree(captures["imavatar"], root)
    ds = _open(root, "imavatar", model_dir)
    assert all(ds.frame_info(i)["mask_kind"] == "alpha" for i in range(len(ds)))
    names = sorted((root / "image").glob("*.png"), key=lambda p: int(p.stem))
    write_png(names[1], read_image(names[1], 3))
    with pytest.raises(MeshsplatError) as err:
        _open(root, "imavatar", model_dir)
    first = str(err.value).splitlines()[0]
    assert "frame 1 is RGB but frames 0, 2\u20133 are RGBA" in first and "must agree" in first
    # INSTA: RGBA images (no mask folder) with frames 0 and 1 RGB
    root = tmp_path / "insta"
    shutil.copytree(captures["insta"], root)
    _rgba_images(root, "images", "masks", {0, 1})
    with pytest.raises(MeshsplatError, match=r"frames 0\u20131 are RGB but frame"):
        _open(root, "insta", model_dir)
    # every frame RGB: no alpha, no masks, opens
    _rgba_images(root, "images", None, {0, 1, 2, 3})
    for img in (root / "images").glob("*.png"):
        write_png(img, read_image(img, 3))
    assert _open(root, "insta", model_dir)[0].mask is None


def test_vhap_rgb_among_rgba_and_mask_alpha_required(captures, model_dir, tmp_path):
    root = tmp_path / "vhap"
    shutil.copytree(captures["vhap"], root)
    _rgba_images(root, "images", "fg_masks", {2})
    for p in root.glob("transforms*.json"):
        doc = json.loads(p.read_text())
        for fr in doc["frames"]:
            fr.pop("fg_mask_path", None)
        p.write_text(json.dumps(doc))
    with pytest.raises(MeshsplatError, match=r"frame 2 is RGB but frames 0\u20131, 3 are RGBA"):
        _open(root, "vhap", model_dir)
    with pytest.raises(MeshsplatError, match=r"frame 2 is RGB"):
        _open(root, "vhap", model_dir, mask="alpha")
    assert _open(root, "vhap", model_dir, mask="none")[2].mask is None


# ---------------------------------------------------------------- numpy files
def _one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and "allow_pickle" not in msg and msg.strip(), msg
    return msg


def test_truncated_corrupt_object_and_empty_npz_are_one_line(tmp_path):
    good = tmp_path / "mesh.npz"
    np.savez(good, faces=np.array([[0, 1, 2]]), vertices=np.zeros((2, 3, 3), np.float32))
    data = good.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    garbled = tmp_path / "garbled.npz"
    garbled.write_bytes(data[:40] + bytes(len(data) - 40))
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    obj = tmp_path / "object.npz"
    np.savez(obj, faces=np.array([[0, 1, 2]], dtype=object), vertices=np.zeros((1, 3, 3)))
    for p, words in ((cut, "truncated or corrupt"), (garbled, "truncated or corrupt"), (empty, "empty")):
        with pytest.raises(MeshsplatError) as err:
            read_npz(p)
        assert words in _one_line(err) and str(p) in str(err.value)
        with pytest.raises(MeshsplatError) as err:
            read_mesh_sequence(p)
        _one_line(err)
    with pytest.raises(MeshsplatError) as err:
        read_mesh_sequence(obj)
    assert "'faces' holds Python objects" in _one_line(err) and "never unpickles" in str(err.value)
    npy = tmp_path / "objects.npy"
    np.save(npy, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    for mmap in (False, True):
        with pytest.raises(MeshsplatError) as err:
            read_npy(npy, mmap=mmap)
        assert "holds Python objects" in _one_line(err)
    assert read_npz(good)["vertices"].shape == (2, 3, 3)
    assert isinstance(zipfile.ZipFile(good).namelist(), list)  # the good one is a real archive


def test_motion_files_empty_corrupt_or_one_of_another_shape(tmp_path, model_dir):
    flame = BodyModel("flame", model_dir)
    rows = lambda n, w: np.zeros((n, w), np.float32)  # noqa: E731
    keys = {"rotation": 3, "neck_pose": 3, "jaw_pose": 3, "eyes_pose": 6, "translation": 3}
    empty = tmp_path / "empty.npz"
    np.savez(empty, expr=rows(0, 50), **{k: rows(0, w) for k, w in keys.items()})
    with pytest.raises(MeshsplatError) as err:
        load_motion(empty, flame)
    assert "no frames" in _one_line(err)
    zero = tmp_path / "zero.npz"
    zero.write_bytes(b"")
    with pytest.raises(MeshsplatError) as err:
        load_motion(zero, flame)
    assert "empty" in _one_line(err)
    folder = tmp_path / "flame_param"
    folder.mkdir()
    for t in range(5):
        np.savez(
            folder / f"{t:05d}.npz", expr=rows(1, 80 if t == 3 else 50), **{k: rows(1, w) for k, w in keys.items()}
        )
    with pytest.raises(MeshsplatError) as err:
        load_motion(folder, flame)
    msg = _one_line(err)
    assert "expression has another shape in 1 of 5 files (00003.npz" in msg


def test_vhap_timestep_file_of_another_shape_or_corrupt(captures, model_dir, tmp_path):
    root = tmp_path / "vhap"
    shutil.copytree(captures["vhap"], root)
    files = sorted((root / "flame_param").glob("*.npz"))
    z = dict(np.load(files[1]))
    z["expr"] = np.zeros((1, 80), np.float32)
    np.savez(files[1], **z)
    with pytest.raises(MeshsplatError) as err:
        _open(root, "vhap", model_dir)
    assert "expr has shape [80] in timestep 1 but [100] in the other 3" in str(err.value).splitlines()[0]
    files[2].write_bytes(files[2].read_bytes()[:100])
    with pytest.raises(MeshsplatError) as err:
        _open(root, "vhap", model_dir)
    assert "truncated or corrupt" in str(err.value) and "Traceback" not in str(err.value)


# ---------------------------------------------------------------- grouped refusals
def test_problems_group_identical_lines_and_cap_the_list(tmp_path):
    p = Problems(tmp_path)
    for i in range(3, 18):
        p.add(f"frame {i} ('{i:04d}')", f"mask file masks/{i:04d}.png is missing")
    for i in range(20):
        p.add(f"camera 'c{i}'", f"odd problem number {i}")  # not numbered frames: listed, then capped
    p.add("frame 40 ('0040')", "empty mask masks/0040.png (no foreground pixel)")
    with pytest.raises(MeshsplatError) as err:
        p.raise_if_any()
    lines = str(err.value).splitlines()
    assert lines[0].startswith(f"invalid dataset {tmp_path} (36 problems): frames 3\u201317: mask file masks/0003.png")
    assert "alike for the other 14" in lines[0]
    assert len(lines) == 1 + Problems.MAX_LISTED + 1 and lines[-1] == "  - ... and 13 more"
    one = Problems(tmp_path)
    one.add("frame 2 ('x')", "image file images/x.png is missing")
    with pytest.raises(MeshsplatError) as err:
        one.raise_if_any()
    assert (
        str(err.value) == f"invalid dataset {tmp_path} (1 problem): frame 2 ('x'): image file images/x.png is missing"
    )


def test_missing_masks_of_many_frames_are_one_line(captures, model_dir, tmp_path):
    root = tmp_path / "meshseq"
    shutil.copytree(captures["meshseq"], root)
    doc = json.loads((root / "cameras.json").read_text())
    for fr in doc["frames"]:
        fr["mask"] = "masks/gone_" + Path(fr["mask"]).name
    (root / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(MeshsplatError) as err:
        _open(root, "meshseq", model_dir)
    lines = str(err.value).splitlines()
    assert len(lines) == 1 and "frames 0\u20133: mask file masks/gone_" in lines[0], lines


# ---------------------------------------------------------------- atomic writes, model_dir
def test_atomic_write_leaves_no_truncated_file(tmp_path):
    target = tmp_path / "avatar.bin"
    target.write_bytes(b"previous")

    def full_disk(fh):
        fh.write(b"half of the data")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError), atomic_write(target) as fh:
        full_disk(fh)
    assert target.read_bytes() == b"previous" and sorted(os.listdir(tmp_path)) == ["avatar.bin"]

    def half_then_fail(path: Path) -> None:
        path.write_text("partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError):
        write_with(tmp_path / "new.ply", half_then_fail)
    assert sorted(os.listdir(tmp_path)) == ["avatar.bin"]
    write_text_atomic(tmp_path / "index.html", "<html></html>")
    assert (tmp_path / "index.html").read_text() == "<html></html>"
    assert sorted(os.listdir(tmp_path)) == ["avatar.bin", "index.html"]


def test_relative_model_dir_of_older_runs(tmp_path, monkeypatch):
    runs = tmp_path / "runs"
    (runs / "models" / "flame").mkdir(parents=True)
    run_dir = runs / "r1"
    run_dir.mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    folder = RunFolder(run_dir)

    def loaded(value) -> LoadedRun:
        return LoadedRun(folder, run_dir / "ckpt.pt", None, None, {"model_dir": value})  # type: ignore[arg-type]

    assert loaded("models").model_dir() == runs / "models"  # relative to the run folder's parent
    assert loaded(str(runs / "models")).model_dir() == runs / "models"
    assert loaded("").model_dir() is None
    assert loaded("gone").model_dir("given") == Path("given")
    with pytest.raises(MeshsplatError) as err:
        loaded("gone").model_dir()
    msg = _one_line(err)
    assert "config key model_dir" in msg and "--model-dir" in msg


def test_insta_without_canonical_obj_refuses_a_first_mesh_from_outside(captures, model_dir, tmp_path, monkeypatch):
    monkeypatch.delenv("MESHSPLAT_ALLOW_OUTSIDE_FILES", raising=False)
    root = _copy_with(
        captures, "insta", tmp_path, "transforms.json", "mesh_path", lambda r, v: _escapes(r, v)["dotdot"]
    )
    (root / "canonical.obj").unlink()
    with pytest.raises(MeshsplatError, match=f"mesh '../other/meshes/00000.obj' lies {OUTSIDE}"):
        _open(root, "insta", model_dir)
    assert len(_open(root, "insta", model_dir, allow_outside=True)) == 4


@pytest.mark.parametrize(
    ("layout", "name", "key"),
    [
        ("insta", "transforms.json", "mesh_path"),
        ("insta", "transforms.json", "file_path"),
        ("vhap", "transforms.json", "fg_mask_path"),
        ("vhap", "transforms.json", "flame_param_path"),
        ("vhap", "transforms.json", "file_path"),
        ("meshseq", "cameras.json", "image"),
        ("meshseq", "cameras.json", "mask"),
    ],
)
@pytest.mark.parametrize("value", [True, 5, ["a.png"], {"path": "a.png"}], ids=["bool", "int", "list", "object"])
def test_a_path_field_that_is_not_a_string_is_refused_in_one_line(
    captures, model_dir, tmp_path, layout, name, key, value
):
    """A frame's path field holding a bool, a number, a list or an object is one clear line (the fuzz test found
    ``mesh_path: true`` failing deep inside the INSTA reader)."""
    root = _copy_with(captures, layout, tmp_path, name, key, lambda r, v: value)
    with pytest.raises(MeshsplatError) as err:
        _open(root, layout, model_dir)
    msg = str(err.value)  # a capture's problems come as one list: "invalid dataset ... (N problems): ..."
    assert msg.startswith("invalid dataset") or "\n" not in msg, msg
    assert "Traceback" not in msg and key in msg.splitlines()[0], msg


@pytest.mark.parametrize(
    ("layout", "key", "value"),
    [
        ("insta", "w", 640.7),
        ("insta", "h", True),
        ("vhap", "timestep_index", 1.5),
        ("vhap", "timestep_index", True),
        ("vhap", "camera_index", "0"),
        ("vhap", "w", False),
    ],
)
def test_a_count_that_is_not_a_whole_number_is_refused(captures, model_dir, tmp_path, layout, key, value):
    """An image size or a timestep that is a fraction, a bool or a string is named, not rounded (``int(640.7)``
    is 640, ``int(True)`` is 1); a whole float (``512.0``, as some writers give) reads."""
    root = tmp_path / "cap"
    shutil.copytree(captures[layout], root)
    first = json.loads((root / "transforms.json").read_text())
    image, good = first["frames"][0]["file_path"], first["frames"][0].get(key, first.get(key))

    def set_everywhere(v) -> None:  # frame 0 as every transforms file lists it
        for path in root.glob("transforms*.json"):
            doc = json.loads(path.read_text())
            for fr in doc.get("frames") or []:
                if fr.get("file_path") == image:
                    fr[key] = v
            path.write_text(json.dumps(doc))

    set_everywhere(float(good))  # a whole float reads
    assert len(_open(root, layout, model_dir)) > 0
    set_everywhere(value)
    with pytest.raises(MeshsplatError) as err:
        _open(root, layout, model_dir)
    assert f"{key} must be a whole number, got {value!r}" in str(err.value), str(err.value)


@pytest.mark.parametrize("value", [640.7, True, "640"])
def test_a_mesh_sequence_camera_size_that_is_not_a_whole_number_is_refused(captures, model_dir, tmp_path, value):
    root = tmp_path / "meshseq"
    shutil.copytree(captures["meshseq"], root)
    doc = json.loads((root / "cameras.json").read_text())
    cid = next(iter(doc["cameras"]))
    doc["cameras"][cid]["width"] = float(doc["cameras"][cid]["width"])  # a whole float reads
    (root / "cameras.json").write_text(json.dumps(doc))
    assert len(_open(root, "meshseq", model_dir)) > 0
    doc["cameras"][cid]["width"] = value
    (root / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(MeshsplatError) as err:
        _open(root, "meshseq", model_dir)
    assert f"width must be a whole number, got {value!r}" in str(err.value), str(err.value)
