"""Checks shared by the synthetic-capture tests."""

from __future__ import annotations

import torch

from meshsplat.drivers.body_models import BodyModel


def _params_reproduce_meshes(ds, model_dir, atol=1e-5):
    info = ds.driver_info
    model = BodyModel(info["type"], model_dir, gender=info["gender"])
    for i in range(len(ds)):
        with torch.no_grad():
            v = model.forward(ds.frame_params(i)).vertices[0]
        assert (v - ds.vertices(i)).abs().max() < atol, i
