"""Topology edits on a parameter dict that keep every per-Gaussian tensor aligned.

Each op rewrites every entry of ``params`` (trainable Parameters AND embedding state ``face``,
``uv``), the Adam moments (``exp_avg``, ``exp_avg_sq``; new rows zero) of every optimizer in
``optimizers`` (one per key, holding exactly ``params[key]``), and the per-Gaussian tensors of
the strategy ``state``. Resized tensors are new ``Parameter`` objects swapped into the optimizer;
in-place edits (opacity reset) keep the same objects.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch

__all__ = ["PER_GAUSSIAN_STATE", "update_all", "duplicate", "remove", "split_append", "reset_opacity", "zero_moments"]

_MOMENTS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")


@torch.no_grad()
def update_all(
    params: dict[str, torch.Tensor],
    optimizers: Mapping[str, torch.optim.Optimizer],
    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
    optstate_fn: Callable[[str, torch.Tensor], torch.Tensor],
) -> None:
    """Replace ``params[key]`` by ``param_fn(key, p)`` and each moment by ``optstate_fn(key, m)``."""
    for key in list(params):
        old = params[key]
        new = param_fn(key, old.detach())
        if isinstance(old, torch.nn.Parameter):
            new = torch.nn.Parameter(new, requires_grad=old.requires_grad)
        params[key] = new
        opt = optimizers.get(key)
        if opt is None:
            continue
        group = opt.param_groups[0]
        assert group["params"][0] is old, f"optimizer for {key!r} does not hold params[{key!r}]"
        st = opt.state.pop(old, None)
        group["params"][0] = new
        if st:
            opt.state[new] = {k: optstate_fn(key, v) if k in _MOMENTS else v for k, v in st.items()}


PER_GAUSSIAN_STATE = ("grad2d", "count", "radii")


def _update_state(state: dict, fn: Callable[[torch.Tensor], torch.Tensor], n: int) -> None:
    """Apply ``fn`` to the per-Gaussian accumulators of a strategy state (when allocated)."""
    for k in PER_GAUSSIAN_STATE:
        v = state.get(k)
        if isinstance(v, torch.Tensor):
            assert v.shape[0] == n, f"strategy state {k!r} has {v.shape[0]} rows, params have {n}"
            state[k] = fn(v)


@torch.no_grad()
def duplicate(
    params: dict[str, torch.Tensor],
    optimizers: Mapping[str, torch.optim.Optimizer],
    state: dict[str, Any],
    mask: torch.Tensor,
) -> None:
    """Append a copy of every Gaussian where ``mask [N]`` (embedding copied too; new moments 0)."""
    n = mask.shape[0]
    sel = torch.nonzero(mask).squeeze(1)
    update_all(
        params, optimizers, lambda k, p: torch.cat([p, p[sel]]), lambda k, m: torch.cat([m, torch.zeros_like(m[sel])])
    )
    _update_state(state, lambda v: torch.cat([v, torch.zeros_like(v[sel])]), n)


@torch.no_grad()
def remove(
    params: dict[str, torch.Tensor],
    optimizers: Mapping[str, torch.optim.Optimizer],
    state: dict[str, Any],
    mask: torch.Tensor,
) -> None:
    """Delete every Gaussian where ``mask [N]``."""
    n = mask.shape[0]
    keep = torch.nonzero(~mask).squeeze(1)
    update_all(params, optimizers, lambda k, p: p[keep], lambda k, m: m[keep])
    _update_state(state, lambda v: v[keep], n)


@torch.no_grad()
def split_append(
    params: dict[str, torch.Tensor],
    optimizers: Mapping[str, torch.optim.Optimizer],
    state: dict[str, Any],
    mask: torch.Tensor,
    new_values: dict[str, torch.Tensor],
    repeats: int,
) -> None:
    """Replace the Gaussians where ``mask [N]`` by ``repeats`` children each (appended at the end).

    Children take ``new_values[key]`` ([repeats*M, ...], ordered repeat-major) where given and
    a copy of the parent's value otherwise; ``duv`` of children is zero. New moments are zero.
    """
    n = mask.shape[0]
    sel = torch.nonzero(mask).squeeze(1)
    keep = torch.nonzero(~mask).squeeze(1)

    def child(k: str, p: torch.Tensor) -> torch.Tensor:
        if k in new_values:
            return new_values[k].to(device=p.device, dtype=p.dtype)
        if k == "duv":
            return torch.zeros((repeats * sel.numel(),) + p.shape[1:], dtype=p.dtype, device=p.device)
        return p[sel].repeat((repeats,) + (1,) * (p.ndim - 1))

    def opt_fn(k: str, m: torch.Tensor) -> torch.Tensor:
        return torch.cat([m[keep], torch.zeros((repeats * sel.numel(),) + m.shape[1:], dtype=m.dtype, device=m.device)])

    update_all(params, optimizers, lambda k, p: torch.cat([p[keep], child(k, p)]), opt_fn)
    _update_state(
        state,
        lambda v: torch.cat(
            [v[keep], torch.zeros((repeats * sel.numel(),) + v.shape[1:], dtype=v.dtype, device=v.device)]
        ),
        n,
    )


@torch.no_grad()
def zero_moments(optimizers: Mapping[str, torch.optim.Optimizer], key: str, rows: torch.Tensor | None = None) -> None:
    """Zero the Adam moments of ``key`` (all rows, or ``rows``: bool mask [N] / index tensor)."""
    opt = optimizers.get(key)
    if opt is None:
        return
    p = opt.param_groups[0]["params"][0]
    st = opt.state.get(p)
    if not st:
        return
    for name in _MOMENTS:
        if name in st:
            if rows is None:
                st[name].zero_()
            else:
                st[name][rows] = 0


@torch.no_grad()
def reset_opacity(
    params: dict[str, torch.Tensor], optimizers: Mapping[str, torch.optim.Optimizer], value: float
) -> None:
    """opacity <- min(opacity, value), in place; opacity moments zeroed."""
    logit = torch.logit(torch.tensor(value, dtype=params["opacity_logit"].dtype)).item()
    params["opacity_logit"].clamp_(max=logit)
    zero_moments(optimizers, "opacity_logit")
