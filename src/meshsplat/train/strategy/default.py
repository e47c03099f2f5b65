"""Adaptive density control for mesh-embedded Gaussians (3DGS / gsplat ``DefaultStrategy`` API).

Usage, per training iteration ``step`` (1-based), after ``info = rasterize(...).meta``::

    strategy.step_pre_backward(params, optimizers, state, step, info)   # retain means2d grad
    loss.backward(); optimizer steps
    strategy.step_post_backward(params, optimizers, state, step, info, mesh=canonical_mesh)

Field names and units follow gsplat's ``DefaultStrategy`` (1.5) where the meaning is the same
(``refine_start_iter``, ``refine_stop_iter``, ``refine_every``, ``reset_every``, ``grow_grad2d``,
``grow_scale3d``, ``prune_opa``, ``prune_scale3d``, ``prune_scale2d``, ``key_for_gradient``);
``split_n``, ``max_gaussians``, ``enabled`` and ``reset_opa`` are ours. The table of every key is
docs/config.md. Differences from gsplat: steps are 1-based and the refinement window is inclusive
(``refine_start_iter <= step <= refine_stop_iter``); the screen-size prune is on after the first
opacity reset (gsplat gates it with ``refine_scale2d_stop_iter``, off by default); the reset value
is ``reset_opa`` (gsplat: ``2 * prune_opa``).

Statistics: for every Gaussian visible in a view, the norm of the screen-space mean gradient
(``info["means2d"].grad`` scaled by ``0.5 * width`` / ``0.5 * height``, i.e. in NDC units as
3DGS) is summed with a count, and the largest screen radius is kept as a fraction of the image
size (pixels / ``max(width, height)``, as gsplat).

Batches: ``info`` may be a list, one meta per image of the batch (each a one-camera render). The loss
is the batch mean, so each image's screen gradient is scaled back by ``batch_size`` (as gsplat's
``n_cameras`` factor) and counted as one view: statistics accumulate per image. A batch's statistics
are gathered first, passed through ``reduce(grad2d, count, radii)`` (data-parallel training sums them
over processes in place; the radii by max), then added.

Every ``refine_every`` steps in ``[refine_start_iter, refine_stop_iter]``: Gaussians whose mean
gradient exceeds ``grow_grad2d`` are cloned when their largest canonical scale is at most
``grow_scale3d * extent`` and split otherwise (within the ``max_gaussians`` budget, highest
gradients first); then Gaussians with opacity below ``prune_opa`` are removed and, after the
first opacity reset, those whose screen radius exceeds ``prune_scale2d * max(width, height)``
or whose largest scale exceeds ``prune_scale3d * extent``. Every ``reset_every`` steps (until
``refine_stop_iter``) opacities are reset to ``min(opacity, reset_opa)``.

Clone copies the embedding. Split works at the canonical pose: ``split_n`` points are sampled
from each parent Gaussian (mean + R(q) diag(scale) z, z ~ N(0, I)), and RE-EMBEDDED by projecting
them onto the canonical Phong surface (``project_to_surface`` -> face, uv, d); children keep the
parent's rotation, opacity and colour, with canonical scale / (0.8 * split_n).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from meshsplat.embedding import project_to_surface
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.compose import compose
from meshsplat.mesh import MeshPose, TriMesh
from meshsplat.mesh.quaternion import quat_to_matrix
from meshsplat.train.strategy.ops import duplicate, remove, reset_opacity, split_append

__all__ = ["DensifyStrategy"]


@dataclass
class DensifyStrategy:
    refine_start_iter: int = 600
    refine_stop_iter: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    grow_grad2d: float = 2e-4  # gsplat's and the paper's; the quality recipe halves it (1.6-1.8x the Gaussians)
    grow_scale3d: float = 0.01  # relative: clone below, split above (3DGS percent_dense), times extent
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1  # relative: world-size prune after the first opacity reset, times extent
    # screen-size prune after the first opacity reset: 3-sigma radius / max(width, height) above this
    # (gsplat's unit and default; 38.4 px at the demo's 256 px; earlier meshsplat used 20 px)
    prune_scale2d: float = 0.15
    reset_opa: float = 0.01
    split_n: int = 2
    max_gaussians: int = 150_000
    enabled: bool = True
    key_for_gradient: str = "means2d"

    # ---- state -----------------------------------------------------------------------
    def initialize_state(self, extent: float = 1.0) -> dict[str, Any]:
        """Accumulators are allocated lazily on the first update (sized to the params)."""
        return {"grad2d": None, "count": None, "radii": None, "extent": float(extent)}

    def check_sanity(self, params: dict[str, torch.Tensor], optimizers: dict[str, torch.optim.Optimizer]) -> None:
        for key, opt in optimizers.items():
            if key not in params or opt.param_groups[0]["params"][0] is not params[key]:
                raise MeshsplatError(f"optimizers[{key!r}] must hold exactly params[{key!r}]")

    # ---- hooks -----------------------------------------------------------------------
    def step_pre_backward(
        self,
        params: dict[str, torch.Tensor],
        optimizers: Mapping[str, torch.optim.Optimizer],
        state: dict[str, Any],
        step: int,
        info: dict,
    ) -> None:
        m2d = info[self.key_for_gradient]
        if m2d.requires_grad:
            m2d.retain_grad()

    @torch.no_grad()
    def step_post_backward(
        self,
        params: dict[str, torch.Tensor],
        optimizers: Mapping[str, torch.optim.Optimizer],
        state: dict[str, Any],
        step: int,
        info: dict | Sequence[dict],
        *,
        mesh: TriMesh | None = None,
        scale_mode: str = "sqrt_area",
        batch_size: int | None = None,
        reduce: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], None] | None = None,
        final: bool = False,
    ) -> dict[str, int]:
        """Update statistics (``info``: one meta or a list, one per image of this process's share of a
        batch of ``batch_size`` images, default the list's length), then refine / reset on schedule.
        ``final``: the run's last iteration, which neither refines nor resets (no iteration would train
        the new Gaussians or the reset opacities before they are saved). Returns counts of what changed."""
        out = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if not self.enabled or step > self.refine_stop_iter or final:
            return out
        infos = [info] if isinstance(info, dict) else list(info)
        self._update_state(params, state, infos, batch_size or len(infos), reduce)
        if step >= self.refine_start_iter and step % self.refine_every == 0:
            if mesh is None:
                raise MeshsplatError("step_post_backward: mesh (the canonical TriMesh) is needed to split")
            out["cloned"], out["split"] = self._grow(params, optimizers, state, mesh, scale_mode)
            out["pruned"] = self._prune(params, optimizers, state, step)
            n = params["face"].shape[0]
            dev = params["face"].device
            state["grad2d"] = torch.zeros(n, device=dev)
            state["count"] = torch.zeros(n, device=dev)
            state["radii"] = torch.zeros(n, device=dev)
        if self.reset_every > 0 and step % self.reset_every == 0:
            reset_opacity(params, optimizers, self.reset_opa)
            out["reset"] = 1
        return out

    # ---- internals -------------------------------------------------------------------
    def _update_state(
        self,
        params,
        state,
        infos: Sequence[dict],
        batch_size: int,
        reduce: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], None] | None,
    ) -> None:
        grads_seen = [i[self.key_for_gradient].grad is not None for i in infos]
        if not any(grads_seen) and reduce is None:
            return
        n = params["face"].shape[0]
        dev = params["face"].device
        if state["grad2d"] is None or state["grad2d"].shape[0] != n:
            state["grad2d"] = torch.zeros(n, device=dev)
            state["count"] = torch.zeros(n, device=dev)
            state["radii"] = torch.zeros(n, device=dev)
        grad2d, count, radii = torch.zeros(n, device=dev), torch.zeros(n, device=dev), torch.zeros(n, device=dev)
        for info, seen in zip(infos, grads_seen, strict=True):
            if seen:
                self._add_view(info, batch_size, grad2d, count, radii)
        if reduce is not None:
            reduce(grad2d, count, radii)
        state["grad2d"] += grad2d
        state["count"] += count
        state["radii"] = torch.maximum(state["radii"], radii)

    def _add_view(
        self, info: dict, batch_size: int, grad2d: torch.Tensor, count: torch.Tensor, radii: torch.Tensor
    ) -> None:
        """Add one render's screen-gradient norms, view counts and largest radii to the batch's sums."""
        grads = info[self.key_for_gradient].grad.detach().clone()  # [C,N,2]
        n_cams = int(info.get("n_cameras", grads.shape[0])) * batch_size
        grads[..., 0] *= 0.5 * info["width"] * n_cams
        grads[..., 1] *= 0.5 * info["height"] * n_cams
        r = info["radii"]
        if r.ndim == 3:  # [C,N,2]
            sel = (r > 0).all(-1)
            rmax = r.amax(-1)
        else:
            sel = r > 0
            rmax = r
        cam_ids, gs_ids = torch.nonzero(sel, as_tuple=True)
        grad2d.index_add_(0, gs_ids, grads[cam_ids, gs_ids].norm(dim=-1).float())
        count.index_add_(0, gs_ids, torch.ones_like(gs_ids, dtype=torch.float32))
        rmax = rmax[cam_ids, gs_ids].float() / float(max(info["width"], info["height"]))
        radii[gs_ids] = torch.maximum(radii[gs_ids], rmax)

    def _grow(self, params, optimizers, state, mesh, scale_mode) -> tuple[int, int]:
        if state["grad2d"] is None:
            return 0, 0
        extent = state["extent"]
        avg = state["grad2d"] / state["count"].clamp_min(1)
        high = avg > self.grow_grad2d
        smax = params["log_scale"].detach().exp().amax(-1)
        small = smax <= self.grow_scale3d * extent
        is_dupli = high & small
        is_split = high & ~small
        # budget: a clone adds 1, a split adds split_n - 1; keep the highest gradients
        n = params["face"].shape[0]
        budget = max(self.max_gaussians - n, 0)
        cost = is_dupli.long() + is_split.long() * max(self.split_n - 1, 0)
        if int(cost.sum()) > budget:
            cand = torch.nonzero(high).squeeze(1)
            order = cand[torch.argsort(avg[cand], descending=True, stable=True)]
            fits = cost[order].cumsum(0) <= budget
            keep = torch.zeros_like(high)
            keep[order[fits]] = True
            is_dupli &= keep
            is_split &= keep
        n_dupli = int(is_dupli.sum())
        if n_dupli:
            duplicate(params, optimizers, state, is_dupli)
            is_split = torch.cat([is_split, torch.zeros(n_dupli, dtype=torch.bool, device=is_split.device)])
        n_split = int(is_split.sum())
        if n_split:
            self._split(params, optimizers, state, is_split, mesh, scale_mode)
        return n_dupli, n_split

    def _split(self, params, optimizers, state, mask, mesh, scale_mode) -> None:
        sub = {k: v.detach()[mask] for k, v in params.items()}
        verts = mesh.vertices.to(device=params["uv"].device, dtype=params["uv"].dtype)
        g = compose(sub, MeshPose.from_vertices(mesh, verts), scale_mode)
        k = self.split_n
        rot = quat_to_matrix(g.quats)  # [M,3,3]
        z = torch.randn((k,) + g.means.shape, device=g.means.device, dtype=g.means.dtype)
        pts = torch.einsum("mij,kmj->kmi", rot, g.scales * z) + g.means  # [k,M,3]
        face, uv, d = project_to_surface(mesh, verts, pts.reshape(-1, 3))
        new = {
            "face": face.long(),
            "uv": uv,
            "d": d,
            "log_scale": (
                sub["log_scale"]
                - torch.log(torch.tensor(0.8 * k, dtype=sub["log_scale"].dtype, device=sub["log_scale"].device))
            ).repeat(k, 1),
        }
        split_append(params, optimizers, state, mask, new, k)

    def _prune(self, params, optimizers, state, step: int) -> int:
        prune = torch.sigmoid(params["opacity_logit"].detach()) < self.prune_opa
        if self.reset_every > 0 and step > self.reset_every:
            smax = params["log_scale"].detach().exp().amax(-1)
            prune |= smax > self.prune_scale3d * state["extent"]
            if state["radii"] is not None:
                prune |= state["radii"] > self.prune_scale2d
        n_prune = int(prune.sum())
        if n_prune == prune.shape[0]:  # never remove every Gaussian
            return 0
        if n_prune:
            remove(params, optimizers, state, prune)
        return n_prune
