"""Train, evaluate and export many captures on Ray: one line per job in a jobs file (YAML, JSON or text).

Examples:
  meshsplat batch jobs.yaml --out runs/fleet                  # an embedded local Ray, all cores
  meshsplat batch jobs.txt --out runs/fleet --workers 2
  meshsplat batch jobs.yaml --out runs/fleet --address auto   # an existing Ray cluster (ray start)
Each job writes DIR/NAME/ (run/, export/, result.json); DIR/results.{json,csv,html} is the table
(metrics, times, Gaussians, failures with their reason). Running the same command again skips finished
jobs and resumes unfinished ones from their last checkpoint; a job whose worker dies is retried from
there. Needs the [ray] extra. Jobs file keys and the cluster setup: docs/scale-out.md.
"""

from __future__ import annotations

import argparse

from meshsplat.errors import MeshsplatError
from meshsplat.fleet.batch import run_batch

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("jobs", help="jobs file: .yaml/.yml, .json or .txt (one capture path [KEY=VALUE ...] per line)")
    parser.add_argument("--out", required=True, help="folder for every job's results and the results table")
    parser.add_argument(
        "--address", default=None, help="Ray cluster to use (e.g. auto, ray://HOST:10001); default local"
    )
    parser.add_argument("--workers", type=int, default=None, help="local Ray: jobs at once (CPUs; default all cores)")
    parser.add_argument("--retries", type=int, default=3, help="times a job whose worker died is retried (default 3)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if args.workers is not None and args.workers < 1:
        raise MeshsplatError(f"--workers: expected at least 1, got {args.workers}")
    if args.retries < 0:
        raise MeshsplatError(f"--retries: expected 0 or more, got {args.retries}")
    rows = run_batch(
        args.jobs,
        args.out,
        address=args.address,
        workers=args.workers,
        retries=args.retries,
        progress=not args.no_progress,
    )
    for r in rows:
        if r.get("status") != "ok":
            print(f"  {r['name']}: failed: {r.get('reason')}")
    print(f"results: {args.out}/results.html (also .json, .csv)")
    return 0 if all(r.get("status") == "ok" for r in rows) else 1
