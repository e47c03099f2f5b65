"""The compiled composition against torch's on a real training state: the same loss, the same gradients?

    python bench/compose_grad_parity.py --data CAPTURE [--until 600] [--frames 3] [--threads 2] [--name NAME]

The unit tests compare ``compose(..., compiled=True)`` with torch's operations on small synthetic Gaussians. This
trains a capture (the demo's model and schedule, ``meshsplat.demo.demo_train_config``) to iteration ``--until`` in a
temporary folder, then for ``--frames`` training frames renders and back-propagates the training loss twice from
that one state: once with the compiled placement and irradiance (``gaussians._compose_numba``,
``gaussians._shading_numba``, the default on CPU) and once with torch's operations (``compose``'s ``compiled``
switched off through its ``numba_available`` lookup, which only this script patches). Each frame is done on a plain
iteration and on one that computes LPIPS and D-SSIM. Printed per trained tensor (the Gaussians' parameters and the
components' tensors, e.g. the learned irradiance): the relative difference ``|g_c - g_t| / |g_t|`` and the cosine.
A systematic difference in a gradient shows as a relative difference far above rounding (1e-5) on every frame;
rounding shows as ~1e-6 to 1e-5, larger only where a Gaussian crosses a cut (a pixel's alpha threshold) between
the two renders. Saves bench/results/<name>-<host>.json.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import shutil
import tempfile
from pathlib import Path

from _machine import machine_info, results_path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a capture folder")
    ap.add_argument("--until", type=int, default=600, help="train to this iteration first")
    ap.add_argument("--frames", type=int, default=3, help="training frames compared (spread over the split)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--name", default="compose_grad_parity")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.train import Trainer

    compose_module = importlib.import_module("meshsplat.gaussians.compose")  # the package re-exports the function
    real_available = compose_module.numba_available

    tmp = Path(tempfile.mkdtemp(prefix="compose_grad_parity_"))
    cfg = demo_train_config(Path(args.data), tmp / "run", PRESETS["default"], [], progress=False)
    trainer = Trainer(cfg)
    trainer.train(until=args.until)
    every = trainer.cfg.loss.lpips_every

    def gradients(compiled: bool, idx: int, perceptual: bool) -> tuple[float, torch.Tensor, dict]:
        compose_module.numba_available = real_available if compiled else (lambda: False)
        tensors = trainer._trained_tensors()
        names = {id(t): k for k, t in trainer.params.items()}
        for t in tensors:
            t.grad = None
        out, gt = trainer.render_frame(idx, torch.full((3,), 0.5))
        at = trainer.iteration  # the perceptual terms are due on multiples of lpips_every
        trainer.iteration = every * (at // every + 1) if perceptual else every * (at // every + 1) + 1
        if not perceptual and every == 1:
            trainer.iteration = at  # every iteration computes them: no plain one to compare
        try:
            loss, _ = trainer._image_loss(out, gt, trainer.frames.frame(idx)[1])
        finally:
            trainer.iteration = at
        loss.backward()
        grads = {names.get(id(t), f"component {j} {list(t.shape)}"): t.grad.detach().clone() for j, t in
                 enumerate(tensors) if t.grad is not None}  # fmt: skip
        return float(loss.detach()), out.image.detach().clone(), grads

    ids = list(trainer.train_ids)
    frames = [ids[round(k * (len(ids) - 1) / max(args.frames - 1, 1))] for k in range(args.frames)]
    rows = []
    try:
        for idx in frames:
            for perceptual in (False, True):
                lc, ic, gc = gradients(True, idx, perceptual)
                lt, it, gt_ = gradients(False, idx, perceptual)
                for name in gt_:
                    a, b = gc[name].double(), gt_[name].double()
                    rel = float((a - b).norm() / b.norm().clamp_min(1e-30))
                    cos = float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-30))
                    rows.append({"frame": int(idx), "perceptual": perceptual, "tensor": name,
                                 "norm": float(b.norm()), "rel_diff": rel, "cosine": cos,
                                 "loss_compiled": lc, "loss_torch": lt,
                                 "image_max_diff": float((ic - it).abs().max())})  # fmt: skip
    finally:
        compose_module.numba_available = real_available
        shutil.rmtree(tmp, ignore_errors=True)

    print(f"{args.data}: trained to iteration {trainer.iteration}, {trainer.num_gaussians} Gaussians")
    print(
        f"{'frame':>6} {'LPIPS':>6} {'image max diff':>14} {'tensor':>22} {'|g| torch':>10} {'rel diff':>9} {'cosine':>9}"
    )
    for r in rows:
        print(f"{r['frame']:>6} {('yes' if r['perceptual'] else 'no'):>6} {r['image_max_diff']:>14.2e} "
              f"{r['tensor']:>22} {r['norm']:>10.3e} {r['rel_diff']:>9.2e} {r['cosine']:>9.6f}")  # fmt: skip
    worst = max((r["rel_diff"] for r in rows), default=math.nan)
    print(f"largest relative difference: {worst:.2e}")
    path = results_path(args.name)
    data = {"capture": Path(args.data).name, "until": args.until, "threads": args.threads,
            "gaussians": trainer.num_gaussians, "rows": rows, "machine": machine_info()}  # fmt: skip
    path.write_text(json.dumps(data, indent=1))
    print(f"saved {path}")


if __name__ == "__main__":
    main()
