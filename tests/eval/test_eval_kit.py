"""Shared helpers for the eval/render/export tests: a tiny avatar, a dataset rendered from it, a run folder.

The dataset's ground truth is the avatar's own render (on black, with its alpha as the mask), so a
correct evaluation of that avatar scores near-perfect metrics.
"""

from __future__ import annotations

import torch

from _eval_kit import SIZE, deform, make_avatar, make_dataset


def test_kit_dataset_is_consistent(tmp_path):
    from meshsplat.data import open_dataset

    av = make_avatar(n=120)
    ds = open_dataset(make_dataset(av, tmp_path / "ds"))
    assert ds.split_names == ["train", "test_frames", "test_views"]
    fr = ds[4]
    assert fr.image.shape == (SIZE, SIZE, 3) and fr.mask is not None
    cover = float(fr.mask.mean())
    assert 0.05 < cover < 0.95  # the avatar is in view and does not fill it
    assert torch.allclose(fr.vertices, deform(av.mesh.vertices, 0.3), atol=1e-6)
