"""What the first training step after an install waits for: numba compiling the CPU kernels, in CPU seconds.

    python bench/compile_time.py [--threads 1 2] [--repeats 2] [--src OTHER_CHECKOUT/src] [--ahead [--only-ahead]]

Each measurement is a fresh process with an empty numba cache (``NUMBA_CACHE_DIR`` in a new temporary folder):
it builds the trainer of the tiny demo capture (generated once into a temporary folder) with the default recipe,
then times, in CPU time of the process, the trainer's construction, its first step (every kernel training needs
is compiled there) and 30 more steps; numba's compile events give each kernel's share. Then the same with the
cache the first process left (what every later process pays). ``--src`` measures another checkout's ``src``
folder instead (e.g. the commit before a change, from ``git worktree add``), interleaved with this one.
``--ahead`` adds, for each tree on more than one thread, what ``meshsplat train`` does: the kernels compiled
ahead in one process per thread (``train.cpu_kernels.compile_ahead``), then the first step; its CPU time counts
the worker processes too, and its wall clock is the figure a user waits. ``--only-ahead`` measures only that.
Saves bench/results/compile_time-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from _machine import machine_info, results_path

HERE = Path(__file__).resolve().parent
SRC = HERE.parent / "src"

CHILD = r"""
import json, resource, sys, tempfile, time
from pathlib import Path
import torch
from numba.core import event as ev
from meshsplat.demo import PRESETS, demo_train_config
from meshsplat.train import Trainer

torch.set_num_threads(int(sys.argv[2]))
spent = {}
class Listener(ev.Listener):
    def on_start(self, event):
        spent.setdefault(event.data["dispatcher"].py_func.__qualname__, [0.0, 0.0])[1] = time.process_time()
    def on_end(self, event):
        r = spent[event.data["dispatcher"].py_func.__qualname__]
        r[0] += time.process_time() - r[1]
ev.register("numba:compile", Listener())
cfg = demo_train_config(Path(sys.argv[1]), Path(tempfile.mkdtemp()), PRESETS["tiny"], [], progress=False)
t0 = time.process_time()
trainer = Trainer(cfg)
t1 = time.process_time()
ahead = {}
if sys.argv[3] == "ahead":  # what meshsplat train does before its first step
    from meshsplat.train.cpu_kernels import compile_ahead
    w0 = time.perf_counter()
    done = compile_ahead(torch.get_num_threads())
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    ahead = {"wall_s": time.perf_counter() - w0, "workers_cpu_s": kids.ru_utime + kids.ru_stime,
             "parent_cpu_s": time.process_time() - t1, "processes": done["processes"],
             "kernels": len(done["compiled"]), "failed": done["failed"]}
    t1 = time.process_time()
w1 = time.perf_counter()
trainer.step()
first_wall = time.perf_counter() - w1
t2 = time.process_time()
for _ in range(30):
    trainer.step()
t3 = time.process_time()
kernels = {k: round(v[0], 3) for k, v in spent.items() if v[0] >= 0.05 and "<locals>" not in k}
print(json.dumps({"init_s": t1 - t0, "first_step_s": t2 - t1, "first_step_wall_s": first_wall, "step_s": (t3 - t2) / 30,
                  "kernels": kernels, "ahead": ahead}))
"""


def _measure(src: Path, data: Path, threads: int, cache: Path, mode: str = "first-step") -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(src))
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(data), str(threads), mode], env=env, capture_output=True, text=True,
        check=True,
    )  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--src", type=Path, default=None, help="another checkout's src folder, measured beside this one")
    ap.add_argument("--ahead", action="store_true", help="also this tree with the kernels compiled ahead (threads > 1)")
    ap.add_argument("--only-ahead", action="store_true", help="with --ahead: leave out the first-step measurements")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    sys.path.insert(0, str(SRC))
    from meshsplat.demo import PRESETS, _generate

    tmp = Path(tempfile.mkdtemp(prefix="compile_time_"))
    data = _generate(tmp / "data", PRESETS["tiny"], progress=False)
    trees = {"this": SRC} | ({"other": args.src.resolve()} if args.src else {})
    rows, ahead_rows = [], []
    for threads in args.threads:
        for rep in range(args.repeats):
            for name, src in trees.items() if not args.only_ahead else []:
                cache = tmp / f"cache-{name}-{threads}-{rep}"
                cold = _measure(src, data, threads, cache)
                warm = _measure(src, data, threads, cache)
                rows.append({"tree": name, "threads": threads, "repeat": rep, "cold": cold, "warm": warm})
                print(
                    f"{name:>5} threads {threads}: cold first step {cold['first_step_s']:5.1f} s CPU "
                    f"({cold['first_step_wall_s']:5.1f} s wall), from the cache {warm['first_step_s']:4.1f} s, "
                    f"a later step {warm['step_s'] * 1e3:5.1f} ms",
                    flush=True,
                )
            for name, src in trees.items() if args.ahead and threads > 1 else []:
                cache = tmp / f"cache-ahead-{name}-{threads}-{rep}"
                cold = _measure(src, data, threads, cache, "ahead")
                warm = _measure(src, data, threads, cache, "ahead")
                ahead_rows.append({"tree": name, "threads": threads, "repeat": rep, "cold": cold, "warm": warm})
                a = cold["ahead"]
                print(
                    f"{name:>5} ahead threads {threads}: compiled {a['kernels']} kernels in {a['processes']} processes, "
                    f"{a['wall_s']:5.1f} s wall, {a['workers_cpu_s'] + a['parent_cpu_s']:5.1f} s CPU; then the first "
                    f"step {cold['first_step_s']:4.1f} s CPU; next process: ahead {warm['ahead']['wall_s']:4.2f} s, "
                    f"first step {warm['first_step_s']:4.1f} s",
                    flush=True,
                )
    if rows:
        print(
            f"\n{'tree':>5} {'threads':>7} {'cold first step s':>18} {'cached s':>9}  largest kernels (s, first repeat)"
        )
    for name in trees:
        for threads in args.threads:
            mine = [r for r in rows if r["tree"] == name and r["threads"] == threads]
            if not mine:
                continue
            cold = statistics.median(r["cold"]["first_step_s"] for r in mine)
            warm = statistics.median(r["warm"]["first_step_s"] for r in mine)
            top = sorted(mine[0]["cold"]["kernels"].items(), key=lambda kv: -kv[1])[:5]
            print(f"{name:>5} {threads:>7} {cold:18.1f} {warm:9.1f}  " + ", ".join(f"{k} {v:.1f}" for k, v in top))
    path = args.out or results_path("compile_time")
    trees_out = {k: "src" if v == SRC else f"<{v.parent.name}>/src" for k, v in trees.items()}  # no local paths
    for name, threads in sorted({(r["tree"], r["threads"]) for r in ahead_rows}):
        mine = [r for r in ahead_rows if r["tree"] == name and r["threads"] == threads]
        wait = statistics.median(r["cold"]["ahead"]["wall_s"] for r in mine)
        wall = statistics.median(r["cold"]["ahead"]["wall_s"] + r["cold"]["first_step_wall_s"] for r in mine)
        cpu = statistics.median(
            r["cold"]["ahead"]["workers_cpu_s"] + r["cold"]["ahead"]["parent_cpu_s"] + r["cold"]["first_step_s"]
            for r in mine
        )
        print(
            f"{name:>5} ahead {threads:>7}: compiled ahead {wait:.1f} s wall; + first step, cold: {wall:.1f} s wall, "
            f"{cpu:.1f} s CPU"
        )
    out = {"machine": machine_info(), "trees": trees_out, "rows": rows, "ahead": ahead_rows}
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"saved {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
