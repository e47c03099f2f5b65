"""Render preview scenes with the torch backend to a PNG for a visual check.

Left: a tilted ring of 12 anisotropic Gaussians (near ones must hide far ones).
Right: the benchmark's avatar-like scene (2k Gaussians) and its expected depth.

    python bench/raster_scene.py [--out bench/results/raster_scene.png]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _raster_scenes import avatar_scene, ring_scene  # noqa: E402
from meshsplat.render import rasterize  # noqa: E402


def _to_u8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def render_preview(size: int = 192) -> np.ndarray:
    ring = rasterize(**ring_scene(size), backend="torch").colors[0]
    av = rasterize(**avatar_scene(2000, size), render_mode="RGB+ED", backend="torch")
    rgb, depth, alpha = av.colors[0, ..., :3], av.colors[0, ..., 3], av.alphas[0, ..., 0]
    d = depth[alpha > 0.5]
    dn = ((depth - d.min()) / (d.max() - d.min() + 1e-9)).clamp(0, 1)
    depth_img = torch.where(alpha[..., None] > 0.5, (1 - dn)[..., None].expand(-1, -1, 3), torch.ones(1, 1, 3))
    return np.concatenate([_to_u8(ring), _to_u8(rgb), _to_u8(depth_img)], axis=1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "raster_scene.png")
    ap.add_argument("--size", type=int, default=192)
    args = ap.parse_args(argv)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(render_preview(args.size)).save(args.out)
    print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
