"""Demo training time per iteration of this working tree against an earlier revision's code, in one run.

    python bench/train_speed_revs.py --against REV [--data DIR] [--warmup 300] [--iters 200] [--rounds 3]
                                     [--threads 2] [--name NAME]

``REV``'s ``src/`` is exported (``git archive``) to a temporary folder. Each round trains the default
(``demo_train_config`` with the ``default`` demo sizes, same seed) once with that code and once with this
tree's, each in its own process (``PYTHONPATH`` picks the code), alternating, so a change of the machine's load
hits both alike: ``--warmup`` iterations (past the first densification, the Gaussians near their count in the
middle of the demo's run), then ``--iters`` timed ones. An iteration with LPIPS (every second one by default)
costs more than one without, so a round's figure is the median over consecutive pairs of their mean; the
table gives each round's and the median over rounds. Both codes must have ``meshsplat.demo.demo_train_config``.
``--data`` reuses a generated demo dataset (``OUT/data`` of ``meshsplat demo``). Saves
bench/results/<name>-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

from _machine import machine_info, results_path

ROOT = Path(__file__).resolve().parents[1]


def child(data: str, warmup: int, iters: int, threads: int) -> None:
    """Train in this process with whatever ``meshsplat`` the path gives; print one JSON line."""
    import torch

    torch.set_num_threads(threads)
    import meshsplat
    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.train import Trainer

    out = Path(tempfile.mkdtemp(prefix="train_speed_revs_")) / "run"
    trainer = Trainer(demo_train_config(Path(data), out, PRESETS["default"], [], progress=False))
    for _ in range(warmup):
        trainer.step()
    times = []
    for _ in range(iters):
        t = time.perf_counter()
        trainer.step()
        times.append(time.perf_counter() - t)
    print(json.dumps({"meshsplat": meshsplat.__file__, "gaussians": trainer.num_gaussians, "times": times}))


def export_src(rev: str, dest: Path) -> Path:
    """``rev``'s ``src/`` under ``dest``; its path."""
    tar = dest / "src.tar"
    with tar.open("wb") as f:
        subprocess.run(["git", "-C", str(ROOT), "archive", rev, "src"], stdout=f, check=True)
    with tarfile.open(tar) as t:
        t.extractall(dest, filter="data")
    return dest / "src"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--against", help="the git revision to compare with (e.g. a tag or commit)")
    ap.add_argument("--data", type=Path, default=None, help="a generated demo dataset to reuse")
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--name", default="train_speed_revs")
    ap.add_argument("--child", nargs=4, metavar=("DATA", "WARMUP", "ITERS", "THREADS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        d, w, n, t = args.child
        child(d, int(w), int(n), int(t))
        return
    if not args.against:
        ap.error("--against REV is required")
    tmp = Path(tempfile.mkdtemp(prefix="train_speed_revs_"))
    rev = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", args.against], capture_output=True, text=True, check=True
    ).stdout.strip()
    code = {f"{rev} ({args.against})": export_src(args.against, tmp), "this tree": ROOT / "src"}
    data = args.data
    if data is None:
        from meshsplat.demo import PRESETS, _generate

        data = _generate(tmp / "data", PRESETS["default"], progress=False)
    rounds: dict[str, list[float]] = {name: [] for name in code}
    gaussians: dict[str, int] = {}
    for r in range(args.rounds):
        for name, src in code.items():
            env = dict(os.environ, PYTHONPATH=str(src))
            cmd = [sys.executable, __file__, "--child", str(data), str(args.warmup), str(args.iters), str(args.threads)]
            res = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if res.returncode:
                raise SystemExit(f"{name}: the training child failed:\n{res.stderr[-2000:]}")
            got = json.loads(res.stdout.strip().splitlines()[-1])
            if not got["meshsplat"].startswith(str(src)):
                raise SystemExit(f"{name}: imported {got['meshsplat']}, not the code under {src}")
            t = got["times"]
            rounds[name].append(statistics.median((t[i] + t[i + 1]) / 2 for i in range(0, len(t) - 1, 2)))
            gaussians[name] = got["gaussians"]
            print(f"round {r + 1}: {name:>22} {1000 * rounds[name][-1]:7.1f} ms/iteration", flush=True)
    base, now = (statistics.median(v) for v in rounds.values())
    print(f"\n{'code':>22} {'ms/iteration':>12} {'rounds':>24} {'Gaussians':>9}")
    for name, v in rounds.items():
        per = " ".join(f"{1000 * x:.1f}" for x in v)
        print(f"{name:>22} {1000 * statistics.median(v):12.1f} {per:>24} {gaussians[name]:9d}")
    print(f"this tree: {base / now:.2f}x the speed of {args.against} ({100 * (now / base - 1):+.0f}% time)")
    out = {
        "machine": machine_info(),
        "args": {k: str(v) for k, v in vars(args).items() if k != "child"},
        "revision": rev,
        "rounds_s": rounds,
        "median_s": {name: statistics.median(v) for name, v in rounds.items()},
        "gaussians": gaussians,
        "speedup": base / now,
    }
    path = results_path(args.name)
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"saved {path}")


if __name__ == "__main__":
    main()
