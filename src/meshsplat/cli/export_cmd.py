"""Export a trained avatar: 3DGS .ply (canonical pose), embedding JSON, canonical mesh OBJ, README.

Examples:
  meshsplat export runs/cesium                     # writes runs/cesium/export/
  meshsplat export runs/cesium --out web/avatar
"""
from __future__ import annotations

import argparse
from pathlib import Path

from meshsplat.cli._guards import check_output_dir

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="training run folder (or a checkpoint file)")
    parser.add_argument("--out", default=None, help="output folder (default RUN/export)")


def run(args: argparse.Namespace) -> int:
    from meshsplat.eval.run import load_run
    from meshsplat.export import export_avatar

    if args.out:
        check_output_dir(args.out)
    r = load_run(args.run, device="cpu")
    out = Path(args.out) if args.out else check_output_dir(r.run_dir / "export")
    res = export_avatar(r.avatar, out, source=str(r.checkpoint), iteration=r.iteration)
    print(f"exported {r.avatar.num_gaussians} Gaussians (iteration {r.iteration}) to {res.folder}:")
    for p in (res.ply, res.embedding, res.mesh, res.readme):
        print(f"  {p.name}")
    return 0
