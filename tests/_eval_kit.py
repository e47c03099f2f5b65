"""A known avatar, its capture and its run folder, for the eval, render and export tests."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import torch

from meshsplat.camera import Camera
from meshsplat.gaussians import Avatar, init_params
from meshsplat.io import save_checkpoint
from meshsplat.mesh import TriMesh
from meshsplat.run_folder import RunFolder

SIZE = 32


def make_avatar(n: int = 300, sh_degree: int = 0, clamp_to_face: bool = False, seed: int = 0) -> Avatar:
    """Icosphere (42 vertices) with ``n`` coloured, displaced, rotated Gaussians."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=1)
    mesh = TriMesh(torch.tensor(ico.vertices, dtype=torch.float32), torch.tensor(ico.faces, dtype=torch.long))
    g = torch.Generator().manual_seed(seed)
    p = init_params(
        mesh,
        n,
        sh_degree=sh_degree,
        init_opacity=0.6,
        generator=g,
        colors_fn=lambda f, uv: torch.rand(f.shape[0], 3, generator=g),
    )
    with torch.no_grad():
        p["d"].copy_(0.05 * torch.randn(n, generator=g))
        p["duv"].copy_(0.15 * torch.randn(n, 2, generator=g))  # some leave their triangle
        p["rotation"].copy_(torch.randn(n, 4, generator=g))
        p["log_scale"].add_(0.3 * torch.randn(n, 3, generator=g))
        p["opacity_logit"].add_(torch.randn(n, generator=g))
        if "shN" in p:
            p["shN"].copy_(0.2 * torch.randn(p["shN"].shape, generator=g))
    return Avatar(mesh, p, "sqrt_area", clamp_to_face=clamp_to_face)


def deform(verts: torch.Tensor, t: float) -> torch.Tensor:
    """A smooth non-rigid pose: twist about +y, stretch and shift, amount ``t``."""
    y = verts[:, 1:2]
    ang = t * 1.2 * y
    c, s = torch.cos(ang), torch.sin(ang)
    x, z = verts[:, 0:1], verts[:, 2:3]
    out = torch.cat([c * x + s * z, y * (1 + 0.3 * t), -s * x + c * z], 1)
    return out + torch.tensor([0.1 * t, 0.0, 0.0])


def camera(azimuth_deg: float, size: int = SIZE) -> tuple[np.ndarray, np.ndarray]:
    from meshsplat.camera import intrinsics, look_at, orbit_position

    vm = look_at(orbit_position(np.zeros(3), 4.5, math.radians(azimuth_deg), math.radians(15)), np.zeros(3))
    return intrinsics(size, size, 35.0), vm


def make_dataset(avatar: Avatar, root: Path) -> Path:
    """Splits train [0,1], test_frames [2,3], test_views [4]; ground truth = the avatar's render
    (colour un-premultiplied, alpha as the mask: ``image*mask + bg*(1-mask)`` is its render on ``bg``)."""
    from meshsplat.data import DatasetWriter

    cams = {"front": camera(0), "side": camera(70), "back": camera(160)}
    plan = [("front", 0.0), ("side", 0.3), ("front", 0.6), ("side", 0.9), ("back", 0.3)]
    with DatasetWriter(root, avatar.mesh.vertices, avatar.mesh.faces, meta={"test": True}) as w:
        for cid, (K, vm) in cams.items():
            w.add_camera(cid, K, vm, SIZE, SIZE)
        for cid, t in plan:
            v = deform(avatar.mesh.vertices, t)
            K, vm = cams[cid]
            r = avatar.render(v, Camera.from_numpy(vm, K, SIZE, SIZE), torch.zeros(3))
            a = r.alpha.clamp(0, 1)
            straight = torch.where(a > 1e-4, r.image / a.clamp_min(1e-4), torch.zeros(()))  # un-premultiplied
            w.add_frame(straight.clamp(0, 1), cid, vertices=v, mask=a, clip="wobble", time=t)
        w.set_split("train", [0, 1])
        w.set_split("test_frames", [2, 3])
        w.set_split("test_views", [4])
    return root


def make_run(avatar: Avatar, run: Path, dataset: Path | None, iteration: int = 7) -> Path:
    """A run folder as the trainer writes it: config.json, checkpoints/ckpt_*.pt, log.csv."""
    folder = RunFolder(run)
    save_checkpoint(folder.checkpoint_path(iteration), {"iteration": iteration, "avatar": avatar.state_dict()})
    folder.config_path.write_text(json.dumps({"data": str(dataset) if dataset else "", "out": str(run)}))
    with open(folder.log_path, "w", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=["iteration", "loss", "psnr", "n_gaussians"])
        wr.writeheader()
        for it in range(1, iteration + 1):
            wr.writerow({"iteration": it, "loss": 0.1 / it, "psnr": 20 + it, "n_gaussians": 300 + 10 * it})
    return run
