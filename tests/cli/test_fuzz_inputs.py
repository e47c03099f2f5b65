"""Fuzzing the files users hand us: a dataset manifest, run checkpoints and the embedding JSON.

Hypothesis puts random JSON values (or tensors) into every field of a valid file; reading it must
end either in a valid load or in one MeshsplatError, never in another exception.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest
import torch

from _fuzz_kit import DELETE, JSON_VALUES, _paths, _set

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from _train_kit import make_tiny_dataset, small_config  # noqa: E402
from meshsplat.camera import Camera  # noqa: E402
from meshsplat.data import open_dataset  # noqa: E402
from meshsplat.errors import MeshsplatError  # noqa: E402
from meshsplat.io.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from meshsplat.io.embedding_json import read_embedding_json, write_embedding_json  # noqa: E402
from meshsplat.run_folder import load_run  # noqa: E402


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("fuzz") / "ds")


@pytest.fixture(scope="module")
def run_ckpt(dataset, tmp_path_factory):
    from meshsplat.train import Trainer

    out = tmp_path_factory.mktemp("fuzz") / "run"
    Trainer(small_config(dataset, out, 4, ["model.n_init=60", "checkpoint_every=4"])).train()
    return out / "checkpoints" / "ckpt_00000004.pt"


def _must_be_clean(fn):
    try:
        return fn()
    except MeshsplatError as exc:
        assert str(exc).strip(), "empty error message"
        return None


def test_fuzz_manifest(dataset):
    manifest = json.loads((Path(dataset) / "manifest.json").read_text())
    paths = [p for p in _paths(manifest) if p[:1] != ("frames",) or len(p) < 2 or p[1] == 0]

    @settings(max_examples=150, deadline=None)
    @given(path=st.sampled_from(paths), value=JSON_VALUES | st.just(DELETE))
    def check(path, value):
        if value is DELETE and not path:
            return
        doc = _set(manifest, path, value)
        with tempfile.TemporaryDirectory() as d:
            # copies, not symlinks: a link out of the folder is a file outside it (refused)
            for name in os.listdir(dataset):
                if name != "manifest.json":
                    src = Path(dataset) / name
                    (shutil.copytree if src.is_dir() else shutil.copy)(src, Path(d) / name)
            (Path(d) / "manifest.json").write_text(json.dumps(doc))

            def load():
                ds = open_dataset(d)
                for i in range(len(ds)):
                    fr = ds[i]
                    assert fr.image.shape == (fr.camera.height, fr.camera.width, 3)
                    assert torch.isfinite(fr.vertices).all()
                for name in ds.split_names:
                    assert all(0 <= i < len(ds) for i in ds.split(name))
                assert isinstance(ds.meta, dict)
                return ds

            _must_be_clean(load)

    check()


def _random_leaf():
    tensors = st.builds(
        lambda shape, kind: (
            torch.zeros(shape, dtype=kind).fill_(float("nan"))
            if kind.is_floating_point and shape and shape[0] == 2
            else torch.zeros(shape, dtype=kind)
        ),
        st.lists(st.integers(0, 5), max_size=3).map(tuple),
        st.sampled_from([torch.float32, torch.float64, torch.int64, torch.bool, torch.uint8]),
    )
    plain = st.none() | st.booleans() | st.integers(-5, 10**6) | st.floats() | st.text(max_size=8)
    return tensors | plain | st.lists(plain, max_size=3) | st.dictionaries(st.text(max_size=5), plain, max_size=3)


def test_fuzz_checkpoint_fields(run_ckpt):
    state = load_checkpoint(run_ckpt)
    paths = [p for p in _paths(state, ()) if p and p[0] in ("avatar", "iteration", "config")]

    @settings(max_examples=120, deadline=None)
    @given(path=st.sampled_from(paths), value=_random_leaf() | st.just(DELETE))
    def check(path, value):
        doc = _set(state, path, value)
        with tempfile.TemporaryDirectory() as d:
            p = save_checkpoint(Path(d) / "checkpoints" / "ckpt_00000004.pt", doc)

            def load():
                r = load_run(Path(d))
                av = r.avatar
                n = av.num_gaussians
                assert all(v.shape[0] == n for v in av.params.values())
                v = av.mesh.vertices
                with torch.no_grad():
                    cam = Camera(
                        torch.eye(4) + torch.tensor([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 4.0], [0, 0, 0, 0]]),
                        torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]),
                        16,
                        16,
                    )
                    out = av.render(v, cam, backend="torch")
                assert torch.isfinite(out.image).all()

            _must_be_clean(load)
            assert p.is_file()

    check()


def test_fuzz_checkpoint_bytes(run_ckpt):
    data = run_ckpt.read_bytes()

    @settings(max_examples=60, deadline=None)
    @given(
        cut=st.integers(0, len(data)),
        flips=st.lists(st.tuples(st.integers(0, len(data) - 1), st.integers(1, 255)), max_size=4),
    )
    def check(cut, flips):
        b = bytearray(data[:cut] if cut < len(data) // 2 else data)
        for i, x in flips:
            if i < len(b):
                b[i] ^= x
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "ckpt_00000001.pt"
            p.write_bytes(bytes(b))
            _must_be_clean(lambda: load_run(p))

    check()


def test_fuzz_embedding_json(tmp_path):
    import trimesh

    from meshsplat.gaussians import init_params
    from meshsplat.mesh import TriMesh

    m = trimesh.creation.icosphere(subdivisions=1)
    mesh = TriMesh(torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces))
    params = init_params(mesh, 7, sh_degree=1, generator=torch.Generator().manual_seed(0))
    docs = {}
    for enc in ("base64", "list"):
        p = write_embedding_json(tmp_path / f"{enc}.json", params, meta={"scale_mode": "sqrt_area"}, encoding=enc)
        docs[enc] = json.loads(p.read_text())
    cases = [(enc, path) for enc, doc in docs.items() for path in _paths(doc) if path]

    @settings(max_examples=150, deadline=None)
    @given(case=st.sampled_from(cases), value=JSON_VALUES | st.just(DELETE))
    def check(case, value):
        enc, path = case
        doc = _set(docs[enc], path, value)
        with tempfile.TemporaryDirectory() as d:
            f = Path(d) / "e.json"
            f.write_text(json.dumps(doc))

            def load():
                out, meta = read_embedding_json(f)
                n = out["face"].shape[0]
                assert all(t.shape[0] == n for t in out.values())
                assert out["face"].dtype == torch.long and all(
                    t.dtype == torch.float32 and torch.isfinite(t).all() for k, t in out.items() if k != "face"
                )
                assert isinstance(meta, dict)

            _must_be_clean(load)

    check()
