"""Scale-out on this machine: 4 tiny captures trained one after another vs ``meshsplat batch`` on a local
Ray with 2 workers; and the time per iteration of ``--nproc 2`` vs one process, both at batch size 2.

    python bench/scale_out.py [--iters 40] [--nproc-iters 30]

The captures are the tiny demo capture (64 px, 12 frames; four copies under their own names); every job
is the quality preset at tiny sizes (``model.n_init=500``, torch backend, one thread per job), trained,
evaluated and exported. Sequential = ``meshsplat.fleet.runner.run_job`` for each job in this process;
batch = ``meshsplat.fleet.batch.run_batch`` with ``workers=2``, Ray's start-up included (and reported
apart). Per-iteration times come from the runs' ``log.csv`` (``time_s`` at every iteration), median
over the iterations after the first 5. Saves bench/results/scale_out-<host>.json.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import torch

from _machine import machine_info, results_path
from meshsplat.demo import PRESETS, _generate
from meshsplat.fleet.batch import run_batch
from meshsplat.fleet.jobs import job_config, read_jobs
from meshsplat.fleet.runner import run_job
from meshsplat.train import Trainer
from meshsplat.train.launch import launch

SMALL = ["backend=torch", "model.n_init=500", "strategy.max_gaussians=2000", "log_every=1", "preview_every=100000"]


def _per_iteration(run: Path, skip: int = 5) -> float:
    with open(run / "log.csv", newline="") as fh:
        t = [float(r["time_s"]) for r in csv.DictReader(fh)]
    return statistics.median(b - a for a, b in zip(t[skip:], t[skip + 1 :], strict=False))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--iters", type=int, default=40, help="iterations per capture (fleet part)")
    ap.add_argument("--nproc-iters", type=int, default=30, help="iterations of the --nproc part")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="scale_out_"))
    first = _generate(tmp / "cap0", PRESETS["tiny"], progress=False)
    for i in range(1, 4):
        shutil.copytree(first, tmp / f"cap{i}")
    jobs_file = tmp / "jobs.json"
    defaults = {"iterations": args.iters, "device": "cpu", "threads": 1, "set": SMALL}
    jobs_file.write_text(json.dumps({"defaults": defaults, "jobs": [f"cap{i}" for i in range(4)]}))
    jobs = read_jobs(jobs_file)

    torch.set_num_threads(1)
    t = time.perf_counter()
    seq = [run_job(job, tmp / "sequential") for job in jobs]
    t_seq = time.perf_counter() - t
    import ray

    t = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    t_ray_start = time.perf_counter() - t
    t = time.perf_counter()
    par = run_batch(jobs_file, tmp / "batch", progress=False)
    t_batch = time.perf_counter() - t
    ray.shutdown()
    assert all(r["status"] == "ok" for r in seq + par), [r["reason"] for r in seq + par if r["status"] != "ok"]

    cfg = job_config(jobs[0], tmp / "one")
    cfg.iterations, cfg.batch_size = args.nproc_iters, 2
    Trainer(cfg).train()
    one = _per_iteration(tmp / "one")
    cfg.out = str(tmp / "two")
    launch(cfg, 2)
    two = _per_iteration(tmp / "two")

    rows = [
        {"what": "4 captures, sequential (1 process)", "wall_s": t_seq},
        {"what": "4 captures, meshsplat batch (local Ray, 2 workers)", "wall_s": t_batch + t_ray_start},
        {"what": "  of which Ray start-up", "wall_s": t_ray_start},
        {"what": "per iteration, batch_size 2, 1 process (median)", "wall_s": one},
        {"what": "per iteration, batch_size 2, --nproc 2 (median)", "wall_s": two},
    ]
    print(f"{'':52} {'seconds':>9}")
    for r in rows:
        print(f"{r['what']:52} {r['wall_s']:9.3f}")
    print(f"fleet speed-up {t_seq / (t_batch + t_ray_start):.2f}x; --nproc 2 speed-up per iteration {one / two:.2f}x")
    out = {"machine": machine_info(), "args": vars(args), "rows": rows}
    path = results_path("scale_out")
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"saved {path}")
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
