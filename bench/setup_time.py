"""`make demo` from a fresh clone, timed: its virtual environment, then (``--demo``) the demo itself.

    python bench/setup_time.py [--against REV] [--rounds 2] [--demo] [--keep-caches]

Each measurement clones this repository's HEAD (or ``--against``'s commit) into an empty temporary folder and runs
``make .venv/.installed-demo`` there (what ``make demo`` builds before it runs anything), with pip's and uv's caches
in new empty folders (``PIP_CACHE_DIR``, ``UV_CACHE_DIR``: packages are fetched again from the index, as on a new
machine; ``--keep-caches`` leaves the user's caches in place). ``--demo`` then runs ``make demo`` in the same clone
and reads its phase times (synth, train, eval) and held-out metrics from its summary. The trees alternate round
by round so that a change of load hits both alike. Wall clock and the CPU time of the child processes.
Saves bench/results/setup_time-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from _machine import machine_info, results_path

REPO = Path(__file__).resolve().parent.parent


def _clone(rev: str, where: Path) -> Path:
    subprocess.run(["git", "clone", "-q", "--no-checkout", str(REPO), str(where)], check=True)
    subprocess.run(["git", "-C", str(where), "checkout", "-q", rev], check=True)
    return where


def _timed(cmd: list[str], cwd: Path, env: dict) -> tuple[float, float, str]:
    """(wall s, CPU s of the children, output) of ``cmd``; stops with the output's tail when it fails (the clone
    and its logs are removed afterwards)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    text = (out.stdout + out.stderr).replace("\r", "\n")
    if out.returncode:
        tail = "\n".join(text.splitlines()[-20:])
        raise SystemExit(f"{' '.join(cmd)} failed (exit {out.returncode}); the end of its output:\n{tail}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, text


def _demo_summary(text: str) -> dict:
    """The phase times and held-out metrics of ``meshsplat demo``'s closing summary."""
    out: dict = {}
    if m := re.search(r"time \(s\): (.*)", text):
        out["phases_s"] = {k: float(v) for k, v in re.findall(r"(\w+) ([\d.]+)", m.group(1))}
    for split in ("test_frames", "test_views"):
        if m := re.search(rf"{split}\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", text):
            out[split] = [float(x) for x in m.groups()]  # full PSNR SSIM LPIPS, in the mask PSNR SSIM LPIPS
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--against", default=None, help="another commit, measured alternately with HEAD")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--demo", action="store_true", help="also run `make demo` in each clone")
    ap.add_argument("--keep-caches", action="store_true", help="use the user's pip and uv caches")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    def commit(rev: str) -> str:
        out = subprocess.run(["git", "-C", str(REPO), "rev-parse", rev], capture_output=True, text=True, check=True)
        return out.stdout.strip()

    trees = {"this": commit("HEAD")} | ({"against": commit(args.against)} if args.against else {})
    rows = []
    for rnd in range(args.rounds):
        for name, rev in trees.items():
            tmp = Path(tempfile.mkdtemp(prefix="setup_time_"))
            try:
                clone = _clone(rev, tmp / "meshsplat")
                env = dict(os.environ)
                if not args.keep_caches:
                    env |= {"PIP_CACHE_DIR": str(tmp / "pip-cache"), "UV_CACHE_DIR": str(tmp / "uv-cache")}
                wall, cpu, _ = _timed(["make", ".venv/.installed-demo"], clone, env)
                row = {"tree": name, "rev": rev, "round": rnd, "venv_wall_s": wall, "venv_cpu_s": cpu}
                if args.demo:
                    dwall, dcpu, text = _timed(["make", "demo"], clone, env)
                    row |= {"demo_wall_s": dwall, "demo_cpu_s": dcpu, **_demo_summary(text)}
                rows.append(row)
                demo = f", demo {row['demo_wall_s']:.1f} s" if args.demo else ""
                print(f"round {rnd} {name:>7}: venv {wall:.1f} s wall ({cpu:.1f} s CPU){demo}", flush=True)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
    print(f"\n{'tree':>7} {'venv s (median)':>16} {'CPU s':>7} {'make demo s':>12}")
    for name in trees:
        mine = [r for r in rows if r["tree"] == name]

        def med(key: str, mine: list = mine) -> float:
            return statistics.median(r[key] for r in mine)

        total = f"{med('venv_wall_s') + med('demo_wall_s'):12.1f}" if args.demo else f"{'-':>12}"
        print(f"{name:>7} {med('venv_wall_s'):16.1f} {med('venv_cpu_s'):7.1f} {total}")
    out = {"machine": machine_info(), "args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}
    path = args.out or results_path("setup_time")
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"saved {path}")


if __name__ == "__main__":
    main()
