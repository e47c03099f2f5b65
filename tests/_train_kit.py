"""A tiny capture rendered from a known avatar, and a short training config: shared by the training tests."""

from __future__ import annotations

import math

import pytest
import torch

from meshsplat.camera import Camera
from meshsplat.gaussians import Avatar, init_params, rgb_to_sh0
from meshsplat.mesh import TriMesh
from meshsplat.train import apply_overrides
from meshsplat.train.recipes import recipe_config

W = H = 32


VIEWMAT = torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 4], [0, 0, 0, 1]])  # at z=4 looking at 0


K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])


def posed(verts: torch.Tensor, t: float) -> torch.Tensor:
    a = 0.6 * t
    R = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    return (verts * torch.tensor([1.0, 1.0 + 0.15 * math.sin(2 * t), 1.0])) @ R.T


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("ds") / "sphere")


def make_tiny_dataset(root, size=W):
    """A deforming, turning icosphere textured by a teacher Gaussian avatar (alpha = mask), on ``size``
    x ``size`` images (the sphere about 20 px across, in the middle)."""
    import trimesh

    from meshsplat.data import write_dataset

    m = trimesh.creation.icosphere(subdivisions=2)
    mesh = TriMesh(torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces))
    gen = torch.Generator().manual_seed(123)
    teacher = init_params(mesh, 800, generator=gen)
    with torch.no_grad():
        from meshsplat.gaussians import compose
        from meshsplat.mesh import MeshPose

        pos = compose(teacher, MeshPose.canonical(mesh)).means
        rgb = torch.stack(
            [0.5 + 0.5 * torch.sin(5 * pos[:, 0]), 0.5 + 0.5 * torch.cos(4 * pos[:, 1]), (pos[:, 2] > 0).float()], -1
        )
        teacher["sh0"].copy_(rgb_to_sh0(rgb))
        teacher["opacity_logit"].fill_(3.0)
        teacher["log_scale"].fill_(math.log(0.09))
    av = Avatar(mesh, teacher)
    k = K.clone()
    k[:2, 2] = size / 2
    frames = []
    for i in range(6):
        v = posed(mesh.vertices, float(i))
        with torch.no_grad():
            out = av.render(v, Camera(VIEWMAT, k, size, size), background=torch.zeros(3), backend="torch")
        frames.append({"image": out.image.clamp(0, 1), "mask": out.alpha, "camera_id": "cam0", "vertices": v})
    cams = {"cam0": {"K": k, "viewmat": VIEWMAT, "width": size, "height": size}}
    return write_dataset(root, mesh.vertices, mesh.faces, cams, frames, splits={"train": list(range(6))})


def small_config(data, out, iterations, extra=()):
    cfg = recipe_config(
        "quality", data=str(data), out=str(out), iterations=iterations, device="cpu", backend="torch", progress=False
    )
    return apply_overrides(
        cfg,
        [
            "model.n_init=200",
            "checkpoint_every=10",
            "keep_checkpoints=5",
            "preview_every=10",
            "log_every=1",
            "strategy.refine_start_iter=4",
            "strategy.refine_every=4",
            "strategy.reset_every=12",
            "strategy.grow_grad2d=1e-5",
            "strategy.max_gaussians=500",
            "walk.every=5",
            *extra,
        ],
    )


def tiny_train_argv() -> list[str]:
    """``meshsplat train`` flags for a 30-iteration end-to-end check (densification inside it, no LPIPS)."""
    argv = ["--iters", "30", "--no-progress", "--set", "model.n_init=800", "--set", "loss.lambda_lpips=0"]
    argv += ["--set", "strategy.refine_start_iter=10", "--set", "strategy.refine_stop_iter=25"]
    return argv + ["--set", "strategy.refine_every=10", "--set", "preview_every=1000", "--set", "checkpoint_every=1000"]
