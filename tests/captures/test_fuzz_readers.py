"""Property test over every capture reader: mutate one of a capture's files (a JSON value or path, an npz
array's dtype, shape or magnitude, a truncated or missing file) and open it. Opening must end in a
successful read or one MeshsplatError whose first line says it all, never in another exception."""

from __future__ import annotations

import json
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from _fuzz_kit import DELETE, JSON_VALUES, _paths, _set  # noqa: E402
from _head_captures import native_flame_dataset, write_tiny_flame  # noqa: E402
from _peoplesnapshot import make_capture  # noqa: E402
from meshsplat.data import open_dataset  # noqa: E402
from meshsplat.data.formats import format_module, open_capture  # noqa: E402
from meshsplat.errors import MeshsplatError  # noqa: E402

pytestmark = pytest.mark.slow

LAYOUTS = ("native", "imavatar", "insta", "vhap", "meshseq", "peoplesnapshot")
PATHS = st.sampled_from(
    ["../other/images/0.png", "/etc/passwd", "", ".", "images", "missing.png", "/".join(["a", "..", "..", "b"])]
)
DTYPES = st.sampled_from(["float16", "float64", "int8", "uint8", "bool", "complex64", "<U3", "object"])
MAGNITUDES = st.sampled_from([0.0, -1.0, 57.3, 1e30, -1e30, np.nan, np.inf, 1e-30])


@pytest.fixture(scope="module")
def captures(tmp_path_factory, standin_model_dir):
    """One small valid capture per layout, and the model folder each is read with."""
    base = tmp_path_factory.mktemp("fuzz_readers")
    heads = write_tiny_flame(base / "models")
    native = native_flame_dataset(
        base / "native", heads, rows=3, views=1, scale=4.0, transl=False, n_betas=100, n_expr=50
    )
    out = {"native": (native, heads)}
    for name in ("imavatar", "insta", "vhap", "meshseq"):
        out[name] = (format_module(name).write(open_dataset(native), base / name), heads)
    out["peoplesnapshot"] = (make_capture(base / "peoplesnapshot", n=5), standin_model_dir)
    return out


def _data_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() and p.suffix in (".json", ".npz", ".npy", ".obj", ".png"))


def _mutate_json(path: Path, data, where: tuple, value) -> None:
    path.write_text(json.dumps(_set(data, where, value)))


def _mutate_npz(path: Path, key: str, how: str, draw) -> None:
    z = dict(np.load(path, allow_pickle=False))
    a = z[key]
    if how == "delete":
        del z[key]
    elif how == "dtype":
        dtype = draw(DTYPES)
        z[key] = np.array(a.tolist(), dtype=object) if dtype == "object" else a.astype(dtype)
    elif how == "shape":
        shape = draw(st.sampled_from(["flat", "extra", "empty", "scalar", "rows"]))
        z[key] = {
            "flat": a.reshape(-1),
            "extra": a[None],
            "empty": a[:0] if a.ndim else a.reshape(-1)[:0],  # a 0-d array has no rows to cut
            "scalar": np.asarray(a.reshape(-1)[:1].sum() if a.size else 0),
            "rows": np.concatenate([a, a]) if a.ndim else a,
        }[shape]
    else:
        b = np.array(a, np.float64)
        if b.size:
            b.reshape(-1)[draw(st.integers(0, b.size - 1))] = draw(MAGNITUDES)
        z[key] = b
    np.savez(path, **z)  # object arrays are pickled: the readers must refuse them


def _open(root: Path, layout: str, model_dir: Path):
    kw = {"flame_version": "2020"} if layout == "vhap" else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return open_capture(root, format=layout, model_dir=model_dir, **kw)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_mutated_capture_files_read_or_refuse_in_one_line(captures, layout):
    src, model_dir = captures[layout]
    _open(src, layout, model_dir)  # the unmutated capture reads
    files = [p.relative_to(src) for p in _data_files(src)]

    @settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(data=st.data())
    def check(data):
        with tempfile.TemporaryDirectory() as d:
            root = Path(d) / "cap"
            shutil.copytree(src, root)
            rel = data.draw(st.sampled_from(files), "file")
            path = root / rel
            what = data.draw(st.sampled_from(["content", "truncate", "remove"]), "what")
            if what == "remove":
                path.unlink()
            elif what == "truncate":
                raw = path.read_bytes()
                path.write_bytes(raw[: data.draw(st.integers(0, max(len(raw) - 1, 0)), "cut")])
            elif path.suffix == ".json":
                doc = json.loads(path.read_text())
                wheres = [w for w in _paths(doc) if w]
                if wheres:
                    where = data.draw(st.sampled_from(wheres[:200]), "where")
                    value = data.draw(JSON_VALUES | PATHS | st.just(DELETE), "value")
                    _mutate_json(path, doc, where, value)
            elif path.suffix == ".npz":
                keys = sorted(np.load(path).files)
                if keys:
                    how = data.draw(st.sampled_from(["delete", "dtype", "shape", "magnitude"]), "how")
                    _mutate_npz(path, data.draw(st.sampled_from(keys), "key"), how, data.draw)
            try:
                ds = _open(root, layout, model_dir)
                assert len(ds) > 0  # a successful read reads (images are decoded lazily: may refuse here)
                assert np.isfinite(ds[0].vertices.numpy()).all()
            except MeshsplatError as exc:
                text = str(exc)
                first = text.splitlines()[0] if text.strip() else ""
                assert first.strip() and "Traceback" not in text and "allow_pickle" not in text, text
                if not text.startswith("invalid dataset"):  # a capture's grouped list may follow its first line
                    assert "\n" not in text, text

    check()


@pytest.mark.parametrize("layout", ("imavatar", "insta", "vhap", "meshseq"))
def test_a_successful_read_reads_the_values_written(captures, layout):
    """A read that succeeds must read right: every frame of a capture written in ``layout`` from the native
    one projects its mesh to the same pixels and has the same image and mask (a transposed K, a flipped
    image, a mask off by a row or a mesh of another frame fails here, where the test above sees success)."""
    native, model_dir = captures["native"]
    src, _ = captures[layout]
    ref, got = _open(native, "native", model_dir), _open(src, layout, model_dir)
    assert len(got) == len(ref)
    names = {ref.frame_info(i).get("name", str(i)): i for i in range(len(ref))}
    for j in range(len(got)):
        i = names.get(got.frame_info(j).get("name", str(j)), j)
        a, b = ref[i], got[j]
        pa, _ = a.camera.project(a.vertices)
        pb, _ = b.camera.project(b.vertices)
        assert (a.camera.width, a.camera.height) == (b.camera.width, b.camera.height)
        np.testing.assert_allclose(pb.numpy(), pa.numpy(), atol=2e-2, err_msg=f"{layout} frame {j}: projection")
        np.testing.assert_allclose(b.image.numpy(), a.image.numpy(), atol=1 / 255 + 1e-6, err_msg=f"{layout} image {j}")
        if a.mask is not None:
            assert b.mask is not None, f"{layout} frame {j}: mask lost"
            np.testing.assert_allclose(
                b.mask.numpy(), a.mask.numpy(), atol=1 / 255 + 1e-6, err_msg=f"{layout} mask {j}"
            )
