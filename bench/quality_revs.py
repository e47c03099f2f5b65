"""Held-out quality and training time of this working tree against an earlier revision's code, on the same captures.

    python bench/quality_revs.py --against REV [--capture NAME=DIR ...] [--demo] [--preset default]
                                 [--threads 2] [--set KEY=VALUE ...] [--name NAME]

For a change of the code with no setting to switch it (a kernel replacing torch operations), the control is the
code before it: ``REV``'s ``src/`` is exported (``git archive``), and every capture is trained once with each code,
one after the other, each in its own process (``PYTHONPATH`` picks the code), with the demo's model and schedule
(``meshsplat.demo.demo_train_config`` at ``--preset``'s sizes, the default recipe, ``--set`` overrides), then scored
by ``meshsplat.eval.evaluate_run`` on the capture's held-out splits. ``--demo`` adds the demo's own capture
(generated). Training seconds include numba's first compile when a code's kernels are not cached yet: run twice to
time cached kernels. Prints a table and saves bench/results/<name>-<host>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import machine_info, results_path
from train_speed_revs import ROOT, export_src

KEYS = ("psnr", "ssim", "lpips", "psnr_mask", "ssim_mask", "lpips_mask")


def child(data: str, out: str, preset: str, threads: int, sets: list[str]) -> None:
    """Train and evaluate in this process with whatever ``meshsplat`` the path gives; print one JSON line."""
    import torch

    torch.set_num_threads(threads)
    import meshsplat
    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.eval import evaluate_run
    from meshsplat.train import Trainer

    cfg = demo_train_config(Path(data), Path(out), PRESETS[preset], sets, progress=False)
    t = time.perf_counter()
    trainer = Trainer(cfg)
    trainer.train()
    seconds = time.perf_counter() - t
    splits = evaluate_run(Path(out))["splits"]
    metrics = {name: {k: s.get(k) for k in KEYS} for name, s in splits.items()}
    print(json.dumps({"meshsplat": meshsplat.__file__, "train_s": seconds, "gaussians": trainer.num_gaussians,
                      "metrics": metrics}))  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", help="the git revision to compare with (e.g. a commit)")
    ap.add_argument("--capture", action="append", default=[], metavar="NAME=DIR", help="a capture (repeatable)")
    ap.add_argument("--demo", action="store_true", help="the demo's generated capture too")
    ap.add_argument("--preset", default="default", help="the demo preset whose model and schedule train")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides for every run")
    ap.add_argument("--name", default="quality_revs")
    ap.add_argument("--child", nargs=4, metavar=("DATA", "OUT", "PRESET", "THREADS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        d, o, p, t = args.child
        child(d, o, p, int(t), args.set)
        return
    if not args.against:
        ap.error("--against REV is required")
    captures = dict(c.split("=", 1) for c in args.capture)
    tmp = Path(tempfile.mkdtemp(prefix="quality_revs_"))
    if args.demo:
        from meshsplat.demo import PRESETS, _generate

        captures["demo"] = str(_generate(tmp / "demo_data", PRESETS[args.preset], progress=False))
    if not captures:
        ap.error("give --capture NAME=DIR or --demo")
    rev = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", args.against], capture_output=True, text=True, check=True
    ).stdout.strip()
    code = {rev: export_src(args.against, tmp), "this tree": ROOT / "src"}
    rows = []
    for cap, data in captures.items():
        for name, src in code.items():
            out = tmp / f"{cap}_{name.replace(' ', '_')}"
            env = dict(os.environ, PYTHONPATH=str(src))
            cmd = [sys.executable, __file__, "--child", data, str(out), args.preset, str(args.threads)]
            res = subprocess.run([*cmd, "--set", *args.set] if args.set else cmd, env=env, capture_output=True,
                                 text=True)  # fmt: skip
            if res.returncode:
                raise SystemExit(f"{cap}, {name}: the training child failed:\n{res.stderr[-2000:]}")
            got = json.loads(res.stdout.strip().splitlines()[-1])
            if not got["meshsplat"].startswith(str(src)):
                raise SystemExit(f"{name}: imported {got['meshsplat']}, not the code under {src}")
            rows.append({"capture": cap, "code": name, **{k: v for k, v in got.items() if k != "meshsplat"}})
            print(f"{cap} {name}: trained in {got['train_s']:.1f} s", flush=True)
    print(f"\n{'capture':>10} {'code':>10} {'train s':>8} {'G':>6}  split: PSNR / in-mask PSNR / in-mask LPIPS")
    for r in rows:
        parts = [
            f"{s}: {m['psnr']:.2f} / {m['psnr_mask']:.2f} / {m['lpips_mask']:.4f}" for s, m in r["metrics"].items()
        ]
        print(f"{r['capture']:>10} {r['code']:>10} {r['train_s']:8.1f} {r['gaussians']:6d}  " + "; ".join(parts))
    kept = {k: str(v) for k, v in vars(args).items() if k not in ("child", "capture")}  # no local paths
    result = {"machine": machine_info(), "args": kept, "captures": list(captures), "revision": rev, "rows": rows}
    path = results_path(args.name)
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"saved {path}")


if __name__ == "__main__":
    main()
