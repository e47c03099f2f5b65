"""Export a trained avatar: splats in the canonical pose (3DGS .ply by default; --format ply, splat,
spz, gltf, comma-separated or repeated), embedding JSON, canonical mesh OBJ, README.

Examples:
  meshsplat export runs/cesium                     # writes runs/cesium/export/
  meshsplat export runs/cesium --out web/avatar --format ply,spz,gltf
"""

from __future__ import annotations

import argparse
from pathlib import Path

from meshsplat.cli._guards import check_output_dir
from meshsplat.cli._options import add_run_argument
from meshsplat.errors import MeshsplatError
from meshsplat.export import SPLAT_FORMATS, export_avatar
from meshsplat.run_folder import load_run

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_argument(parser, dataset=False)
    parser.add_argument("--out", default=None, help="output folder (default RUN/export)")
    parser.add_argument(
        "--format",
        action="append",
        default=None,
        metavar="FMT",
        help="ply (default), splat, spz or gltf; comma-separated or repeated",
    )


def run(args: argparse.Namespace) -> int:
    formats = [f.strip() for item in (args.format or ["ply"]) for f in item.split(",") if f.strip()]
    unknown = [f for f in formats if f not in SPLAT_FORMATS]
    if unknown or not formats:
        raise MeshsplatError(f"--format: expected some of {', '.join(SPLAT_FORMATS)}, got {unknown or 'none'}")
    if args.out:
        check_output_dir(args.out)
    r = load_run(args.run, device="cpu", allow_older=args.allow_older_checkpoint)
    out = Path(args.out) if args.out else check_output_dir(r.folder.export_dir)
    res = export_avatar(r.avatar, out, source=str(r.checkpoint), iteration=r.iteration, formats=formats)
    print(f"exported {r.avatar.num_gaussians} Gaussians (iteration {r.iteration}) to {res.folder}:")
    for p in (*res.splats.values(), res.embedding, res.mesh, res.readme):
        print(f"  {p.name}")
    return 0
