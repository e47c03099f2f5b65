"""Optimizers and learning-rate schedule.

One ``torch.optim.Adam`` per parameter key (gsplat layout: ``optimizers[key]`` holds exactly
the tensor ``params[key]``), eps 1e-15, with the paper's learning rates.

Embedding learning rates. 3DGS multiplies its position lr by the scene extent; we do the same
for the displacement ``d`` (scene units). ``duv`` is barycentric, so one unit moves a Gaussian
by about one edge length: with ``uv_lr_units="world"`` (default) its lr is additionally divided
by the mean edge length, i.e. ``lr_duv = lr * extent / mean_edge``, so that tangential and
normal motion have the same world-space speed as 3DGS positions, whatever the mesh resolution.
``"barycentric"`` uses the raw lr (as the published configuration does, with extent 1).

Colour learning rates. ``lr_color`` (sh0) and ``lr_shN`` are constant unless ``lr_color_final`` is
set: then both decay log-linearly by the factor ``lr_color_final / lr_color`` over the run (no
warm-up), like the embedding's. The schedule depends only on the iteration, so a resumed run
continues it exactly. The global illumination coefficients (``shading.lr``, their own optimizer in
the trainer) stay constant: a handful of numbers fit to every pixel of every frame, Monte Carlo
noise averages out in their gradient, and they are what carries the lighting the albedo is divided by.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch

from meshsplat.train.config import OptimConfig

__all__ = ["expon_lr", "EMBEDDING_KEYS", "COLOR_KEYS", "base_learning_rates", "build_optimizers", "LrSchedule"]

EMBEDDING_KEYS = ("duv", "d")
COLOR_KEYS = ("sh0", "shN")  # decay with optim.lr_color_final (when set)


def expon_lr(
    step: int, lr_init: float, lr_final: float, max_steps: int, lr_delay_steps: int = 0, lr_delay_mult: float = 1.0
) -> float:
    """3DGS ``get_expon_lr_func``: log-linear decay from lr_init to lr_final over max_steps.

    With ``lr_delay_steps > 0`` the lr is additionally scaled by a warm-up that rises from
    ``lr_delay_mult`` to 1 along a quarter sine over the first ``lr_delay_steps`` steps.
    """
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    if lr_delay_steps > 0:
        delay = lr_delay_mult + (1 - lr_delay_mult) * math.sin(0.5 * math.pi * min(max(step / lr_delay_steps, 0), 1))
    else:
        delay = 1.0
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return delay * math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)


def base_learning_rates(cfg: OptimConfig, extent: float, mean_edge: float) -> dict[str, float]:
    """Initial lr per key (embedding lrs already scaled to the mesh)."""
    uv_scale = extent / mean_edge if cfg.uv_lr_units == "world" else 1.0
    return {
        "duv": cfg.lr_embedding * uv_scale,
        "d": cfg.lr_embedding * extent,
        "sh0": cfg.lr_color,
        "shN": cfg.lr_shN,
        "opacity_logit": cfg.lr_opacity,
        "log_scale": cfg.lr_scale,
        "rotation": cfg.lr_rotation,
    }


def build_optimizers(
    params: dict[str, torch.Tensor], lrs: dict[str, float], eps: float = 1e-15
) -> dict[str, torch.optim.Adam]:
    """Adam for every trainable (``requires_grad``) tensor of ``params`` that has an lr: torch's fused kernel
    where the tensor's device has one (CPU since torch 2.4, CUDA), one pass over the tensor instead of a dozen
    elementwise operations (the same arithmetic; the last bit may differ); else torch's default."""
    opts = {}
    for key, p in params.items():
        if key in lrs and isinstance(p, torch.nn.Parameter) and p.requires_grad:
            group = [{"params": [p], "lr": lrs[key], "name": key}]
            try:
                opts[key] = torch.optim.Adam(group, lr=lrs[key], eps=eps, fused=True)
            except RuntimeError:  # no fused Adam for this device (or torch)
                opts[key] = torch.optim.Adam(group, lr=lrs[key], eps=eps)
    return opts


class LrSchedule:
    """Exponential decay of the embedding lrs (``duv``, ``d``) and, with ``lr_color_final`` set, of the
    colour lrs (``sh0``, ``shN``); other keys keep their lr."""

    def __init__(self, cfg: OptimConfig, base: dict[str, float], max_steps: int) -> None:
        self.cfg, self.base, self.max_steps = cfg, dict(base), max_steps

    def lr(self, key: str, step: int) -> float:
        if key in COLOR_KEYS and self.cfg.lr_color_final is not None:
            ratio = self.cfg.lr_color_final / self.cfg.lr_color
            return expon_lr(step, self.base[key], self.base[key] * ratio, self.max_steps)
        if key not in EMBEDDING_KEYS:
            return self.base[key]
        ratio = self.cfg.lr_embedding_final / self.cfg.lr_embedding
        return expon_lr(
            step,
            self.base[key],
            self.base[key] * ratio,
            self.max_steps,
            self.cfg.lr_delay_steps,
            self.cfg.lr_delay_mult,
        )

    def apply(self, optimizers: Mapping[str, torch.optim.Optimizer], step: int) -> dict[str, float]:
        """Set every optimizer's lr for ``step``; returns the lrs set."""
        out = {}
        for key, opt in optimizers.items():
            lr = self.lr(key, step)
            for g in opt.param_groups:
                g["lr"] = lr
            out[key] = lr
        return out
