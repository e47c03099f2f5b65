"""What reproducible MKL math (``MKL_CBWR=AUTO,STRICT``, set by ``import meshsplat``) costs and buys.

    python bench/reproducible_math.py [--data DIR] [--rounds 3] [--iters 60] [--warmup 30] [--threads 2]

MKL reads ``MKL_CBWR`` once per process, so each measurement is a child process; the two settings
alternate, ``--rounds`` times each (a change of the machine's load hits both alike):

- ``off``: ``MKL_CBWR=`` (empty: MKL's default, code paths chosen by buffer alignment);
- ``strict``: ``MKL_CBWR=AUTO,STRICT`` (meshsplat's default).

Each child times ``--iters`` training iterations of the demo's default on the demo capture after
``--warmup`` (mean over pairs of iterations, one with LPIPS and one without), then repeats one LPIPS
backward pass 30 times on a 32 x 32 image (the case that made the resume tests flaky: AlexNet's last
layers at 1 x 1) and counts the distinct gradients (1 = reproducible). ``--data`` reuses a generated
demo dataset (``OUT/data`` of ``meshsplat demo``). Saves bench/results/reproducible_math-<host>.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SETTINGS = {"off": "", "strict": "AUTO,STRICT"}
LPIPS_REPEATS = 30


def child(data: Path, iters: int, warmup: int, threads: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.train import Trainer
    from meshsplat.train.losses import make_perceptual_loss

    cfg = demo_train_config(data, Path(tempfile.mkdtemp()) / "run", PRESETS["default"], progress=False)
    tr = Trainer(cfg)
    for _ in range(warmup):
        tr.step()
    times = []
    for _ in range(iters):
        t = time.perf_counter()
        tr.step()
        times.append(time.perf_counter() - t)
    pairs = [(times[i] + times[i + 1]) / 2 for i in range(0, len(times) - 1, 2)]
    loss = make_perceptual_loss("alex").build()
    gen = torch.Generator().manual_seed(0)
    a, b = torch.rand(32, 32, 3, generator=gen), torch.rand(32, 32, 3, generator=gen)
    grads = set()
    for _ in range(LPIPS_REPEATS):
        x = a.clone().requires_grad_(True)
        loss(x, b).backward()
        assert x.grad is not None
        grads.add(hashlib.md5(x.grad.numpy().tobytes()).hexdigest())
    return {"iter_s": statistics.median(pairs), "distinct_lpips_grads": len(grads)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=None, help="a generated demo dataset to reuse")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--iters", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.data, args.iters, args.warmup, args.threads)))
        return
    from _machine import machine_info, results_path

    if args.data is None:
        from meshsplat.demo import PRESETS, _generate

        args.data = _generate(Path(tempfile.mkdtemp(prefix="repro_math_")) / "data", PRESETS["default"], progress=False)
    runs: dict[str, list[dict]] = {name: [] for name in SETTINGS}
    cmd = [sys.executable, __file__, "--child", "--data", str(args.data), "--iters", str(args.iters)]
    cmd += ["--warmup", str(args.warmup), "--threads", str(args.threads)]
    for _ in range(args.rounds):
        for name, value in SETTINGS.items():
            env = {**os.environ, "MKL_CBWR": value}
            out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
            runs[name].append(json.loads(out.strip().splitlines()[-1]))
    rows = []
    for name, rs in runs.items():
        times = [r["iter_s"] for r in rs]
        rows.append(
            {
                "setting": name,
                "MKL_CBWR": SETTINGS[name],
                "median_iter_s": statistics.median(times),
                "iter_s": times,
                "distinct_lpips_grads": [r["distinct_lpips_grads"] for r in rs],
            }
        )
    base = rows[0]["median_iter_s"]
    print(
        f"{'setting':>8} {'MKL_CBWR':>12} {'ms/iter':>8} {'vs off':>7}  distinct 32x32 LPIPS grads (of {LPIPS_REPEATS})"
    )
    for r in rows:
        r["ratio_vs_off"] = r["median_iter_s"] / base
        print(
            f"{r['setting']:>8} {r['MKL_CBWR'] or '(empty)':>12} {1000 * r['median_iter_s']:8.1f} "
            f"{r['ratio_vs_off']:6.3f}x  {r['distinct_lpips_grads']}"
        )
    result = {"machine": machine_info(), "args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}
    path = args.out or results_path("reproducible_math")
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"saved {path}")


if __name__ == "__main__":
    main()
