"""``synthesize(light_dir=...)`` / ``meshsplat synth --light``: the capture's light comes from the direction asked
for, recorded in its meta (the many-light benchmark, bench/key_light.py, relies on both)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshsplat.data import open_dataset
from meshsplat.errors import MeshsplatError
from meshsplat.synth import synthesize
from meshsplat.synth.generate import SynthSpec


def test_the_light_direction_lights_the_capture_and_is_recorded(assets, tmp_path):
    kw = dict(frames=2, resolution=48, test_frames=0, test_views=0)
    glb = assets / "gltf" / "CesiumMan.glb"
    front = open_dataset(synthesize(glb, tmp_path / "f", **kw))
    back = open_dataset(synthesize(glb, tmp_path / "b", light_dir=(0.0, 2.0, -2.0), **kw))
    np.testing.assert_allclose(
        front.meta["light_dir"], np.array([0.35, 0.75, 0.55]) / np.linalg.norm([0.35, 0.75, 0.55])
    )
    np.testing.assert_allclose(back.meta["light_dir"], [0.0, 2**-0.5, -(2**-0.5)], atol=1e-12)
    a, b = front[0], back[0]
    assert a.mask is not None and b.mask is not None and torch.equal(a.mask, b.mask)  # the same shot, other light
    inside = (a.mask > 0.99).reshape(a.image.shape[:2])
    assert float((a.image - b.image).abs()[inside].mean()) > 0.05
    with pytest.raises(MeshsplatError, match="light_dir"):
        SynthSpec(light_dir=(0.0, 0.0, 0.0))
