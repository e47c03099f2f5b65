"""Synthetic captures from parametric models (stand-in SMPL / SMPL-X / FLAME files): stored driver
parameters reproduce the stored meshes, the dance stands upright, colours, and `--format` plumbing."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch

from _synth_kit import _params_reproduce_meshes
from meshsplat.data import open_dataset
from meshsplat.data.formats import detect_format, open_capture
from meshsplat.drivers.body_models import BodyModel
from meshsplat.errors import MeshsplatError
from meshsplat.synth.body_source import load_model_source, rotate_params
from meshsplat.synth.capture import synth_capture
from meshsplat.synth.generate import synthesize

TINY = dict(frames=3, resolution=48, test_frames=2, test_views=1)


def test_rotate_params_rotates_the_posed_mesh(standin_model_dir):
    model = BodyModel("smpl", standin_model_dir)
    rng = np.random.default_rng(3)
    p = {
        "betas": rng.normal(0, 0.5, 10).astype(np.float32),
        "global_orient": rng.normal(0, 1, (2, 3)),
        "body_pose": rng.normal(0, 0.2, (2, 69)),
        "transl": rng.normal(0, 1, (2, 3)),
    }
    with torch.no_grad():
        j0 = model.forward({"betas": p["betas"]}).joints[0, 0].double().numpy()
        before = model.forward(p).vertices.double().numpy()
        a = 2.0
        R = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        pivot = np.array([0.5, -1.0, 2.0])
        after = model.forward(rotate_params(p, R, pivot, j0)).vertices.double().numpy()
    assert np.abs(after - ((before - pivot) @ R.T + pivot)).max() < 1e-5


def test_smpl_dance_stands_up_and_stores_its_parameters(tmp_path, standin_model_dir):
    out = synthesize("smpl", tmp_path / "d", model_dir=standin_model_dir, **TINY)
    ds = open_dataset(out)
    assert ds.driver_info["type"] == "smpl" and sorted(ds.driver_info["per_frame"]) == [
        "body_pose",
        "global_orient",
        "transl",
    ]
    assert ds.driver_params["betas"].shape == (10,) and np.abs(ds.driver_params["betas"]).max() > 0
    _params_reproduce_meshes(ds, standin_model_dir)
    model = BodyModel("smpl", standin_model_dir)
    J = model.J_regressor.numpy()
    for i in ds.split("train"):
        joints = J @ ds.vertices(i).numpy()
        assert joints[15, 1] > joints[7, 1] + 0.8 and joints[15, 1] > joints[8, 1] + 0.8  # head above the ankles
    assert ds.meta["model"]["type"] == "smpl"


def test_flame_talks_and_nods(tmp_path, standin_model_dir):
    out = synthesize("flame", tmp_path / "f", model_dir=standin_model_dir, **TINY)
    ds = open_dataset(out)
    assert {"train", "test_frames", "test_views", "test_clip"} <= set(ds.split_names)
    assert {ds.frame_info(i)["clip"] for i in ds.split("test_clip")} == {"nod"}
    per_frame = ds.driver_info["per_frame"]
    assert {"expression", "jaw_pose", "neck_pose"} <= set(per_frame)
    jaw = ds.driver_params["jaw_pose"][:, 0]
    assert jaw.max() > 0.02  # the mouth opens
    _params_reproduce_meshes(ds, standin_model_dir)


def test_smplx_source(tmp_path, standin_model_dir):
    src = load_model_source("smplx", standin_model_dir)
    assert src.motions["dance"]["body_pose"].shape[1] == 63
    out = synthesize(
        "smplx", tmp_path / "x", model_dir=standin_model_dir, frames=2, resolution=32, test_frames=1, test_views=0
    )
    _params_reproduce_meshes(open_dataset(out), standin_model_dir)


def test_colours_from_appearance_else_skin_weights(tmp_path, standin_model_dir):
    with_file = load_model_source("smpl", standin_model_dir)
    saved = np.load(standin_model_dir / "smpl" / "appearance.npz")["vertex_colors"]
    assert np.allclose(with_file.vertex_colors.numpy(), saved)
    bare = tmp_path / "models" / "smpl"
    bare.mkdir(parents=True)
    shutil.copyfile(standin_model_dir / "smpl" / "SMPL_NEUTRAL.pkl", bare / "SMPL_NEUTRAL.pkl")
    proc = load_model_source("smpl", tmp_path / "models").vertex_colors
    assert proc.shape == saved.shape and float(proc.min()) >= 0 and float(proc.max()) <= 1
    assert float(proc.std(0).min()) > 0.02  # varies over the body
    assert not np.allclose(proc.numpy(), saved, atol=0.05)


def test_model_source_errors(tmp_path, standin_model_dir):
    with pytest.raises(MeshsplatError, match="driver smoothing/decimation is not available"):
        synthesize("smpl", tmp_path / "a", model_dir=standin_model_dir, driver_smooth=2, **TINY)
    (tmp_path / "empty").mkdir()
    with pytest.raises(MeshsplatError, match="SMPL model file not found"):
        synthesize("smpl", tmp_path / "b", model_dir=tmp_path / "empty", **TINY)
    with pytest.raises(MeshsplatError, match="format: 'obj' is not one of"):
        synth_capture("smpl", tmp_path / "c", format="obj", model_dir=standin_model_dir, **TINY)


@pytest.mark.parametrize("fmt", ["imavatar", "insta", "vhap"])
def test_synth_head_formats_plumbing(tmp_path, standin_model_dir, fmt):
    """`synth flame --format NAME` hands the native dataset to that format's writer; it reads back."""
    out = synth_capture(
        "flame", tmp_path / fmt, format=fmt, native_dir=tmp_path / "native", model_dir=standin_model_dir, **TINY
    )
    assert detect_format(out) == fmt
    back = open_capture(out, model_dir=standin_model_dir)
    assert len(back) > 0 and back.num_vertices == open_dataset(tmp_path / "native").num_vertices
