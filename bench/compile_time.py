"""What the first training step after an install waits for: numba compiling the CPU kernels, in CPU seconds.

    python bench/compile_time.py [--threads 1 2] [--repeats 2] [--src OTHER_CHECKOUT/src]

Each measurement is a fresh process with an empty numba cache (``NUMBA_CACHE_DIR`` in a new temporary folder):
it builds the trainer of the tiny demo capture (generated once into a temporary folder) with the default recipe,
then times, in CPU time of the process, the trainer's construction, its first step (every kernel training needs
is compiled there) and 30 more steps; numba's compile events give each kernel's share. Then the same with the
cache the first process left (what every later process pays). ``--src`` measures another checkout's ``src``
folder instead (e.g. the commit before a change, from ``git worktree add``), interleaved with this one.
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
import json, sys, tempfile, time
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
trainer.step()
t2 = time.process_time()
for _ in range(30):
    trainer.step()
t3 = time.process_time()
kernels = {k: round(v[0], 3) for k, v in spent.items() if v[0] >= 0.05 and "<locals>" not in k}
print(json.dumps({"init_s": t1 - t0, "first_step_s": t2 - t1, "step_s": (t3 - t2) / 30, "kernels": kernels}))
"""


def _measure(src: Path, data: Path, threads: int, cache: Path) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(src))
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(data), str(threads)], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--src", type=Path, default=None, help="another checkout's src folder, measured beside this one")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    sys.path.insert(0, str(SRC))
    from meshsplat.demo import PRESETS, _generate

    tmp = Path(tempfile.mkdtemp(prefix="compile_time_"))
    data = _generate(tmp / "data", PRESETS["tiny"], progress=False)
    trees = {"this": SRC} | ({"other": args.src.resolve()} if args.src else {})
    rows = []
    for threads in args.threads:
        for rep in range(args.repeats):
            for name, src in trees.items():
                cache = tmp / f"cache-{name}-{threads}-{rep}"
                cold = _measure(src, data, threads, cache)
                warm = _measure(src, data, threads, cache)
                rows.append({"tree": name, "threads": threads, "repeat": rep, "cold": cold, "warm": warm})
                print(
                    f"{name:>5} threads {threads}: cold first step {cold['first_step_s']:5.1f} s CPU, "
                    f"from the cache {warm['first_step_s']:4.1f} s, a later step {warm['step_s'] * 1e3:5.1f} ms",
                    flush=True,
                )
    print(f"\n{'tree':>5} {'threads':>7} {'cold first step s':>18} {'cached s':>9}  largest kernels (s, first repeat)")
    for name in trees:
        for threads in args.threads:
            mine = [r for r in rows if r["tree"] == name and r["threads"] == threads]
            cold = statistics.median(r["cold"]["first_step_s"] for r in mine)
            warm = statistics.median(r["warm"]["first_step_s"] for r in mine)
            top = sorted(mine[0]["cold"]["kernels"].items(), key=lambda kv: -kv[1])[:5]
            print(f"{name:>5} {threads:>7} {cold:18.1f} {warm:9.1f}  " + ", ".join(f"{k} {v:.1f}" for k, v in top))
    path = args.out or results_path("compile_time")
    trees_out = {k: str(v) for k, v in trees.items()}
    path.write_text(json.dumps({"machine": machine_info(), "trees": trees_out, "rows": rows}, indent=1) + "\n")
    print(f"saved {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
