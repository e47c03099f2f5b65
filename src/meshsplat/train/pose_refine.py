"""Pose refinement: trainable per-frame offsets on the tracker's body/head model parameters.

Trackers leave errors of a few degrees; with ``pose_refine.enabled`` every training frame's
parameters (``global_orient``, ``body_pose``, ``transl``, FLAME's ``jaw_pose``/``expression`` ...,
whichever the dataset's model has) get an offset that starts at zero and is optimised with the
avatar, through the differentiable body model. Shared parameters (``betas``, ``static_offset``)
stay fixed, so the canonical mesh does not change. Test frames keep the tracker's parameters.

The optimizer is a lazy (sparse) Adam: every mesh row has its own moments and its own step count, and
an iteration updates only the rows of the frames in its batch (``step(rows)``). A row's offsets thus
follow exactly the Adam trajectory they would have with that frame alone; a frame not drawn does not
move. (One Adam over all rows, stepped every iteration, kept moving every other frame on stale momentum:
7 mm of drift on exactly tracked poses, issue 44.) Every data-parallel rank draws the whole batch, so
every rank steps the same rows with the same all-reduced gradients.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import torch

from meshsplat.data.dataset import AvatarDataset
from meshsplat.errors import MeshsplatError

__all__ = ["PoseRefiner", "ADAM_BETAS", "ADAM_EPS"]

ADAM_BETAS = (0.9, 0.999)  # torch.optim.Adam's defaults
ADAM_EPS = 1e-15  # as the avatar's optimizers


def _float32(a: Any, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a, np.float32), device=device)


def _adam_row(
    x: torch.Tensor, g: torch.Tensor, m: torch.Tensor, v: torch.Tensor, n: int, lr: float, evidence: float = 0.0
) -> None:
    """Step ``n`` (from 1) of ``torch.optim.Adam``'s arithmetic on one row ``x [k]`` in place, its moments ``m``
    and ``v [k]`` updated with the gradient ``g [k]``; ``evidence``: each number's step times
    ``(|m̂| / sqrt(v̂))^evidence`` (0: plain Adam)."""
    b1, b2 = ADAM_BETAS
    step_size = lr / (1 - b1**n)
    bias2_sqrt = (1 - b2**n) ** 0.5
    m.lerp_(g, 1 - b1)
    v.mul_(b2).addcmul_(g, g, value=1 - b2)
    denom = (v.sqrt() / bias2_sqrt).add_(ADAM_EPS)
    if evidence:
        agree = (m.abs() / (1 - b1**n) / denom).clamp_(max=1.0).pow_(evidence)
        x.addcdiv_(m * agree, denom, value=-step_size)
    else:
        x.addcdiv_(m, denom, value=-step_size)


class PoseRefiner:
    """Offsets ``[R, k]`` per refined parameter for the ``R`` distinct meshes of the training frames."""

    GIVE_UP = 3  # fit_guarded: a row whose step was undone this many times in a row is at its best

    def __init__(
        self,
        dataset: AvatarDataset,
        train_ids: list[int],
        names: str,
        lr: float,
        model_dir: str | None,
        device: torch.device,
        prior: float = 0.0,
        evidence: float = 0.0,
    ) -> None:
        if dataset.driver_info is None or dataset.driver_params is None:
            raise MeshsplatError(
                f"pose_refine: {dataset.root} has no body/head model parameters "
                f"({dataset.format_name} layout); pose refinement needs SMPL/SMPL-X/FLAME parameters"
            )
        self.model = dataset.body_model(model_dir, device)
        per_frame = set(dataset.per_frame_param_names)
        params = dataset.driver_params
        rows = sorted({int(dataset.frame_info(i)["mesh"]) for i in train_ids})
        self.row_of = {row: j for j, row in enumerate(rows)}
        wanted = [k.strip() for k in names.split(",") if k.strip()]
        self.names = [k for k in wanted if k in per_frame and k in params]
        if not self.names:
            raise MeshsplatError(
                f"pose_refine.params: none of {wanted} is a per-frame parameter of this "
                f"dataset (it has {sorted(per_frame)})"
            )
        self.rows = {k: _float32(params[k][rows], device) for k in per_frame if k in params}  # [R, k]
        self.shared = {k: _float32(v, device) for k, v in params.items() if k not in per_frame}
        self.offsets = {k: torch.nn.Parameter(torch.zeros_like(self.rows[k])) for k in self.names}
        self.lr = lr
        self.prior = prior  # gradient + prior * offset: a pull towards the tracked parameters
        # each step times (|m| / sqrt(v))^evidence per number: the agreement of its recent gradients (1 when they
        # keep one sign, small when it flips: noise about a right pose); 0: plain Adam
        self.evidence = evidence
        self.exp_avg = {k: torch.zeros_like(v) for k, v in self.rows.items() if k in self.offsets}  # [R, k]
        self.exp_avg_sq = {k: torch.zeros_like(v) for k, v in self.exp_avg.items()}  # [R, k]
        self.steps = [0] * len(rows)  # Adam steps taken by each row
        self.polished = False  # fit once more after training (``fit``), the avatar frozen

    def refines(self, mesh_row: int) -> bool:
        return mesh_row in self.row_of

    def params_of(self, mesh_row: int, detach: bool = False) -> dict[str, torch.Tensor]:
        """Refined parameters of one mesh row (per-frame ones ``[1, k]``)."""
        j = self.row_of[mesh_row]
        out = dict(self.shared)
        for k, v in self.rows.items():
            out[k] = v[j : j + 1]
        for k, off in self.offsets.items():
            out[k] = out[k] + (off[j : j + 1].detach() if detach else off[j : j + 1])
        return out

    def vertices(self, mesh_row: int) -> torch.Tensor:
        """Posed vertices ``[V,3]`` of a training mesh row with its current offsets (differentiable)."""
        return self.model.forward(self.params_of(mesh_row)).vertices[0]

    def step(self, mesh_rows: Iterable[int]) -> None:
        """One Adam step (``torch.optim.Adam``'s arithmetic, betas 0.9/0.999, eps 1e-15) for each refined row
        of ``mesh_rows`` (the batch's frames; a row drawn twice steps once, on its summed gradient), with that
        row's own moments and step count; every other row, and its state, stays as it is. With ``prior`` the
        gradient gains ``prior * offset`` (an L2 pull towards the tracked parameters). Clears the gradients."""
        with torch.no_grad():
            for row in sorted({int(r) for r in mesh_rows if int(r) in self.row_of}):
                j = self.row_of[row]
                self.steps[j] += 1
                for k, off in self.offsets.items():
                    if off.grad is None:
                        continue
                    g = off.grad[j]
                    if self.prior:
                        g = g + self.prior * off.data[j]
                    _adam_row(
                        off.data[j], g, self.exp_avg[k][j], self.exp_avg_sq[k][j], self.steps[j], self.lr, self.evidence
                    )
        for off in self.offsets.values():
            off.grad = None

    def fit(
        self,
        row_error: Callable[[int], torch.Tensor],
        steps: int,
        lr: float,
        on_step: Callable[[], None] | None = None,
    ) -> None:
        """``steps`` Adam steps (rate ``lr``, an optimizer of their own) on the offsets of every row,
        minimising the sum over rows of ``row_error(row)``: a scalar computed from :meth:`vertices` of that
        row (e.g. an avatar's image error there). Gradients reach the offsets only, so the avatar stays as it
        is; one backward per row bounds the memory to one row's renders. ``on_step`` runs after each step."""
        offsets = list(self.offsets.values())
        opt = torch.optim.Adam(offsets, lr=lr, eps=1e-15)
        for _ in range(steps):
            grads = [torch.zeros_like(o) for o in offsets]
            for row in self.row_of:
                parts = self._grads(self._error(row_error, row))
                for g, d in zip(grads, parts, strict=True):
                    if d is not None:
                        g += d
            for o, g in zip(offsets, grads, strict=True):
                o.grad = g
            opt.step()
            opt.zero_grad(set_to_none=True)
            if on_step is not None:
                on_step()

    def fit_guarded(
        self,
        row_error: Callable[[int], torch.Tensor],
        steps: int,
        lr: float,
        min_gain: float,
        project: Callable[[int], None] | None = None,
        on_step: Callable[[], None] | None = None,
    ) -> dict[str, int]:
        """Like :meth:`fit`, but a row keeps a step only where it lowered that row's error by at least the
        fraction ``min_gain``: otherwise the row goes back to its best offsets and its rate halves; a row
        turned back ``GIVE_UP`` times in a row stops. A right pose thus stays where it is (its first steps
        raise its error), a wrong one moves as far as its images ask. Rows have their own Adam moments and
        rate (``lr`` at first). ``project(row)`` runs after each step of a row (e.g. the depth rule). Every
        row ends at the lowest error it was measured at. Returns counts: ``kept`` and ``undone`` steps,
        ``moved`` rows (at least one step kept)."""
        names = list(self.offsets)
        m = {k: torch.zeros_like(v) for k, v in self.offsets.items()}
        v2 = {k: torch.zeros_like(v) for k, v in self.offsets.items()}
        rows = list(self.row_of)
        best_err: dict[int, float] = {}
        best: dict[int, tuple[dict[str, torch.Tensor], tuple[torch.Tensor | None, ...]]] = {}
        rate = {row: lr for row in rows}
        undone_run = {row: 0 for row in rows}
        n = {row: 0 for row in rows}
        counts = {"kept": 0, "undone": 0, "moved": 0}
        moved: set[int] = set()
        for s in range(steps + 1):
            for row in rows:
                if undone_run[row] >= self.GIVE_UP:
                    continue
                j = self.row_of[row]
                err_t = self._error(row_error, row, grad=s < steps)  # the last measure needs no gradient
                err = float(err_t.detach())
                if row not in best_err or err < best_err[row] * (1.0 - min_gain):
                    if row in best_err:
                        counts["kept"] += 1
                        moved.add(row)
                    best_err[row] = err
                    # a backward only for a kept step (an undone one steps on the best offsets' gradient)
                    parts = self._grads(err_t) if s < steps else ()
                    grads = tuple(None if g is None else g[j].clone() for g in parts)  # [k] each: this row's
                    best[row] = ({k: self.offsets[k].data[j].clone() for k in names}, grads)
                    undone_run[row] = 0
                else:  # back to the best offsets, at half the rate
                    counts["undone"] += 1
                    with torch.no_grad():
                        for k in names:
                            self.offsets[k].data[j].copy_(best[row][0][k])
                    rate[row] *= 0.5
                    undone_run[row] += 1
                    if undone_run[row] >= self.GIVE_UP:
                        continue
                if s == steps:
                    continue
                n[row] += 1
                with torch.no_grad():
                    for k, g in zip(names, best[row][1], strict=True):
                        if g is not None:
                            _adam_row(self.offsets[k].data[j], g, m[k][j], v2[k][j], n[row], rate[row])
                if project is not None:
                    project(row)
            if on_step is not None:
                on_step()
        counts["moved"] = len(moved)
        return counts

    def _error(self, row_error: Callable[[int], torch.Tensor], row: int, grad: bool = True) -> torch.Tensor:
        """``row_error(row)``, with its graph to the offsets when ``grad``; one MeshsplatError if it is not finite."""
        with torch.set_grad_enabled(grad):
            err = row_error(row)
        if not torch.isfinite(err):
            raise MeshsplatError(f"pose fit: the image error of mesh row {row} became {float(err)}; use a lower rate")
        return err

    def _grads(self, err: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        """The gradients of ``err`` with respect to the offsets (``[R, k]`` each, None where unused)."""
        return torch.autograd.grad(err, list(self.offsets.values()), allow_unused=True)

    def offset_norms(self) -> dict[str, float]:
        """Mean absolute offset per parameter name (for logs and tests)."""
        return {k: float(v.detach().abs().mean()) for k, v in self.offsets.items()}

    def refined_params(self) -> dict[str, np.ndarray]:
        """All refined per-frame rows ``[R, k]`` plus ``mesh_rows [R]`` (for saving with the run)."""
        out = {
            k: (self.rows[k] + (self.offsets[k].detach() if k in self.offsets else 0)).cpu().numpy() for k in self.rows
        }
        out["mesh_rows"] = np.asarray(sorted(self.row_of, key=lambda k: self.row_of[k]), np.int64)
        return out

    def state_dict(self) -> dict[str, Any]:
        return {
            "offsets": {k: v.detach().cpu() for k, v in self.offsets.items()},
            "exp_avg": {k: v.cpu() for k, v in self.exp_avg.items()},
            "exp_avg_sq": {k: v.cpu() for k, v in self.exp_avg_sq.items()},
            "steps": torch.tensor(self.steps, dtype=torch.int64),
            "polished": self.polished,
        }

    def load_state_dict(self, st: dict[str, Any]) -> None:
        if set(st.get("offsets", {})) != set(self.offsets):
            raise MeshsplatError(
                f"checkpoint: pose refinement parameters {sorted(st.get('offsets', {}))} do not "
                f"match the configuration {sorted(self.offsets)}"
            )
        with torch.no_grad():
            for k, v in st["offsets"].items():
                if v.shape != self.offsets[k].shape:
                    raise MeshsplatError(
                        f"checkpoint: pose offsets {k} have shape {list(v.shape)}, expected "
                        f"{list(self.offsets[k].shape)} (different dataset?)"
                    )
                self.offsets[k].copy_(v)
            if "steps" not in st:  # a checkpoint of the one-Adam-for-all-rows refiner (before issue 44)
                raise MeshsplatError(
                    "checkpoint: its pose refinement state is from an older meshsplat (one optimizer for all "
                    "frames); finish that run with the version that started it, or start a new run"
                )
            for k in self.exp_avg:
                self.exp_avg[k].copy_(st["exp_avg"][k])
                self.exp_avg_sq[k].copy_(st["exp_avg_sq"][k])
            steps = [int(n) for n in st["steps"].tolist()]
            if len(steps) != len(self.steps):
                raise MeshsplatError(
                    f"checkpoint: pose refinement steps for {len(steps)} rows, expected {len(self.steps)} "
                    "(different dataset?)"
                )
            self.steps = steps
        self.polished = bool(st.get("polished", False))
