"""Test-time pose fitting: the body/head-model poses of held-out frames fitted to their own images.

A held-out frame's driving mesh comes from the tracker, so its score mixes two errors: the avatar's
appearance and the tracker's pose. Papers that evaluate on PeopleSnapshot-style captures (Anim-NeRF,
InstantAvatar) fit the test poses to the test images first, with the model frozen, and score
appearance alone. ``fit_test_poses`` does that: for each mesh row seen by the evaluated
frames and by no training frame, offsets on its per-frame parameters (as training's pose refinement)
are optimised with Adam on the L1 error of all that row's images. It uses the test images, so its
numbers are not comparable with tracked-pose ones; ``meshsplat eval`` says which it ran.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from meshsplat.data.dataset import AvatarDataset
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians import Avatar
from meshsplat.render.background import composite
from meshsplat.train.components import PoseRefineConfig
from meshsplat.train.pose_refine import PoseRefiner

__all__ = ["FIT_PARAMS", "fit_test_poses", "rows_to_fit"]

# what training's pose refinement offsets by default (those the capture's model has are used)
FIT_PARAMS = PoseRefineConfig().params


def rows_to_fit(dataset: AvatarDataset, ids: Sequence[int]) -> dict[int, list[int]]:
    """Mesh row -> the frames among ``ids`` that show it, for the rows no training frame shows."""
    trained = (
        {int(dataset.frame_info(i)["mesh"]) for i in dataset.split("train")}
        if "train" in dataset.split_names
        else set()
    )
    rows: dict[int, list[int]] = {}
    for i in ids:
        row = int(dataset.frame_info(i)["mesh"])
        if row not in trained:
            rows.setdefault(row, []).append(int(i))
    return rows


def fit_test_poses(
    avatar: Avatar,
    dataset: AvatarDataset,
    ids: Sequence[int],
    steps: int,
    lr: float = 1e-3,
    model_dir: str | None = None,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    params: str = FIT_PARAMS,
    progress: bool = False,
) -> dict[int, np.ndarray]:
    """Driving meshes ``row -> vertices [V,3]`` of the held-out rows of ``ids`` (:func:`rows_to_fit`), their
    per-frame parameters fitted for ``steps`` Adam steps of rate ``lr`` to the frames' images (on
    ``background [3]``, default white; frames without a mask on black) with ``avatar`` frozen."""
    if steps < 1:
        raise MeshsplatError(f"fit poses: expected at least 1 step, got {steps}")
    if not lr > 0:
        raise MeshsplatError(f"fit poses: the learning rate must be positive, got {lr}")
    if dataset.driver_info is None or dataset.driver_params is None:
        raise MeshsplatError(
            f"--fit-poses: {dataset.root} has no body/head model parameters ({dataset.format_name} layout); "
            "only captures driven by SMPL/SMPL-X/FLAME parameters have poses to fit"
        )
    groups = rows_to_fit(dataset, ids)
    if not groups:
        return {}
    dev = avatar.device
    bg = torch.ones(3) if background is None else background.cpu()
    refiner = PoseRefiner(dataset, [i for f in groups.values() for i in f], params, lr, model_dir, dev)
    shots: dict[int, list] = {}
    for row, frames in groups.items():
        shots[row] = []
        for i in frames:
            fr = dataset[i]
            fbg = bg if fr.mask is not None else torch.zeros(3)
            shots[row].append((fr.camera, fbg.to(dev), composite(fr.image, fr.mask, fbg)))  # kept on the CPU

    def row_error(row: int) -> torch.Tensor:
        verts = refiner.vertices(row)
        errors = [
            (avatar.render(verts, cam, fbg, backend=backend).image - gt.to(dev)).abs().mean()
            for cam, fbg, gt in shots[row]
        ]
        return torch.stack(errors).sum()

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=steps, desc="fit poses", dynamic_ncols=True)
    try:
        refiner.fit(row_error, steps, lr, on_step=None if bar is None else lambda: bar.update(1))
    finally:
        if bar is not None:
            bar.close()
    with torch.no_grad():
        fitted = {row: refiner.vertices(row).cpu().numpy() for row in groups}
    return fitted
