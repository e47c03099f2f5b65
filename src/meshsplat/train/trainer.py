"""Training loop: mesh-embedded Gaussians fitted to images of a posed mesh sequence.

Writes the run folder ``config.out`` (layout: ``meshsplat.run_folder``): ``config.json``, checkpoints
(last ``keep_checkpoints`` kept), ``log.csv`` (one row per ``log_every`` iterations, see LOG_COLUMNS),
previews and, with pose refinement, ``refined_params.npz``.

A checkpoint (``meshsplat.io.load_checkpoint``) holds ``iteration``, ``config`` (dict),
``avatar`` (``Avatar.state_dict()``: canonical mesh, params, scale_mode, ...), ``optimizers``
(per key ``Adam.state_dict()``), ``strategy_state``, ``rng`` (torch CPU/CUDA, numpy, python,
background and data-order generators), ``data_order`` and ``elapsed_s``. Resuming from it on CPU
continues bit for bit.

Per iteration (1-based ``it``): set lrs; next training frame (shuffled without replacement per
epoch, seeded); pose the canonical mesh with the frame's vertices; compose; rasterize with a
random background (also blended into the ground truth through the mask); loss
``L1 + λ_lpips LPIPS + λ_scale L_scale (+ λ_mse MSE + λ_ssim D-SSIM)``, L_scale on the canonical
(pose-independent) scales with T_s = ``loss.scale_max * extent``, measured in mesh extents (so an
asset in centimetres and the same in metres train and log alike; extent ≈ 1 on the paper's bodies)
(+ λ_mask |alpha - mask|); with ``loss.crop_to_subject`` LPIPS and D-SSIM on the box around the subject
(``losses.subject_crop``: mask and rendered alpha), times its area share; with ``loss.lpips_every`` = k
both only on iterations ``it % k == 0``, times k (log.csv leaves their cells empty on the others); backward; Adam steps; densification strategy; every ``walk.every``
iterations walking on triangles.

With ``model.shading`` on, the learned illumination (``Shading.coeffs``, and with ``model.occlusion`` the
non-negative ``Shading.light``, clamped after each step; with ``model.specular`` the added ``Shading.specular``) has its own Adam
(``lr_shading``), stored in checkpoints under ``shading_optimizer``; the avatar state carries the
illumination itself.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import random
import signal
import sys
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meshsplat._device import resolve_device
from meshsplat._numba import numba_available
from meshsplat.data.formats import open_capture, reader_options
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.avatar import Avatar, AvatarRender
from meshsplat.gaussians.compose import effective_uv
from meshsplat.gaussians.init_colors import first_view_colors, mean_view_colors
from meshsplat.gaussians.params import EMBEDDING_STATE_KEYS, init_params, num_gaussians
from meshsplat.gaussians.shading import Shading
from meshsplat.io.atomic import write_text_atomic
from meshsplat.io.checkpoint import remove_stray_tmp, save_checkpoint
from meshsplat.io.folder_lock import FolderLock
from meshsplat.io.images import float_to_uint8
from meshsplat.mesh import MeshPose, TriMesh, bbox_diagonal
from meshsplat.metrics import psnr
from meshsplat.render.background import background_color, composite
from meshsplat.run_folder import RunFolder, capture_identity, check_training_target, identity_differences
from meshsplat.train.albedo_prior import REFRESH_EVERY, albedo_neighbours, albedo_smoothness
from meshsplat.train.config import TrainConfig, is_legacy_config, upgrade_config_dict
from meshsplat.train.distributed import DataParallel
from meshsplat.train.losses import avatar_loss, make_perceptual_loss, subject_crop
from meshsplat.train.monitor import PROGRESS_FORMAT, TensorBoardMonitor, learning_rates, progress_postfix
from meshsplat.train.optim import LrSchedule, base_learning_rates, build_optimizers
from meshsplat.train.pose_refine import PoseRefiner
from meshsplat.train.resume import (
    SAFE_CHANGES,
    StopOnSignal,
    TrainingInterrupted,
    capture_rng,
    check_resume_config,
    load_resume_checkpoint,
    refuse_existing_run,
    restore_rng,
    signal_name,
)
from meshsplat.train.strategy import walk_embeddings

__all__ = [
    "Trainer",
    "train",
    "mesh_extent",
    "mean_edge_length",
    "LOG_COLUMNS",
    "PROGRESS_WINDOW",
]

_FRAME_CACHE_BYTES = 2 * 1024**3  # decoded training frames (and their posed meshes) kept in memory
_LOGGED_PARTS = ("l1", "lpips", "scale", "mse", "dssim", "mask", "albedo")  # loss parts in log.csv
PROGRESS_WINDOW = 10  # the progress bar's loss and PSNR: means over this many latest iterations

LOG_COLUMNS = (
    "iteration",
    "loss",
    "l1",
    "lpips",
    "scale",
    "mse",
    "dssim",
    "psnr",
    "n_gaussians",
    "walked",
    "lr_duv",
    "lr_d",
    "time_s",
    "mask",
    "albedo",  # the albedo prior's value (loss.lambda_albedo), unweighted
)


def _cell(value: float | int) -> str | float | int:
    """A ``log.csv`` cell: floats to 6 significant digits; nan (a term not computed on that iteration, see
    ``loss.lpips_every``) as an empty cell."""
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.6g}"
    return value


def mesh_extent(vertices: torch.Tensor) -> float:
    """Half the bounding-box diagonal: the 'scene extent' of an avatar (≈1 for a 1.7 m body)."""
    return 0.5 * bbox_diagonal(vertices)


def mean_edge_length(vertices: torch.Tensor, faces: torch.Tensor) -> float:
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return float((vertices[e[:, 0]] - vertices[e[:, 1]]).norm(dim=-1).mean())


class Trainer:
    """Builds everything from a ``TrainConfig``; ``train()`` runs to ``config.iterations``.

    ``resume=True`` continues from the newest checkpoint in ``RUN/checkpoints`` (starts fresh
    when there is none); it refuses unreadable checkpoints and config changes outside
    ``train.resume.SAFE_CHANGES`` (``resume_notes`` lists the safe ones applied). Without
    ``resume`` a folder that already holds checkpoints is refused. ``data`` and ``out`` are
    stored as absolute paths. SIGINT/SIGTERM during ``train()`` checkpoint, then raise
    ``TrainingInterrupted``.
    """

    def __init__(self, config: TrainConfig, resume: bool = False) -> None:
        self.cfg = TrainConfig.from_dict(config.validate().to_dict())  # own copy
        if not self.cfg.data:
            raise MeshsplatError("config: data (the dataset folder) is not set")
        self.cfg.data = str(Path(self.cfg.data).expanduser().resolve())
        self.cfg.out = str(Path(self.cfg.out).expanduser().resolve())
        if self.cfg.model_dir:  # absolute, as data: render --motion from another folder finds it
            self.cfg.model_dir = str(Path(self.cfg.model_dir).expanduser().resolve())
        self.folder = RunFolder(self.cfg.out)
        self.dp, self.device = DataParallel.from_env(resolve_device(self.cfg.device))
        self.dp.check_batch(self.cfg.batch_size)
        if self.dp.is_main:  # a capture, a foreign folder or a run in training is refused before any work
            check_training_target(self.cfg.out, self.cfg.data)
        if not self.dp.is_main:
            self.cfg.progress = False
        self.dataset = open_capture(
            self.cfg.data,
            format=self.cfg.data_format or None,
            model_dir=self.cfg.model_dir or None,
            drop_bad_frames=self.cfg.drop_bad_frames,
            downscale=self.cfg.data_downscale,
            **reader_options(self.cfg.data_gender, self.cfg.data_shape),
        )
        rule = self.dataset.meta.get("split_rule")
        # which rule chose the splits (a reader's guess, e.g. without config.json): the command prints it
        self.split_note = f"{self.cfg.data}: splits from {rule}" if rule else None
        self.train_ids = list(self.dataset.split("train"))
        if not self.train_ids:
            raise MeshsplatError(f"{self.cfg.data}: the 'train' split is empty")
        cano = torch.as_tensor(self.dataset.canonical_vertices, dtype=torch.float32)
        self.mesh = TriMesh(cano.to(self.device), torch.as_tensor(self.dataset.faces).long().to(self.device))
        self.extent = mesh_extent(self.mesh.vertices)
        self.mean_edge = mean_edge_length(self.mesh.vertices, self.mesh.faces)
        self.strategy = self.cfg.strategy
        self.lr_factor = math.sqrt(self.cfg.batch_size)  # gsplat's rule for batches: lr times sqrt(batch size)
        self.lrs = base_learning_rates(self.cfg.optim, self.extent, self.mean_edge)
        if self.cfg.batch_size > 1:
            self.lrs = {k: v * self.lr_factor for k, v in self.lrs.items()}
        self.schedule = LrSchedule(self.cfg.optim, self.lrs, self.cfg.iterations)
        self.refiner, self.pose_refine_note = self._pose_refiner()
        self.perceptual = None
        if self.cfg.loss.lambda_lpips:
            # built now: nothing may draw random numbers after seeding or restoring the generators
            self.perceptual = make_perceptual_loss("alex").build(self.device)
        self._frame_cache: dict[int, tuple] = {}
        self._pose_cache: dict[int, MeshPose] = {}  # training frames' posed meshes (not refined ones)
        self._cache_bytes = 0
        self.iteration = 0
        self.elapsed = 0.0
        self.history: list[dict[str, float]] = []
        self.walked_total = 0  # embeddings that changed face (this session)
        self.recent: deque[tuple[float, float]] = deque(maxlen=PROGRESS_WINDOW)  # (loss, psnr) per iteration
        self.shading: Shading | None = None
        self.shading_opt: torch.optim.Adam | None = None
        self.monitor: TensorBoardMonitor | None = None  # RUN/tensorboard/ while training (train.monitor)
        self.albedo_nb: torch.Tensor | None = None  # the albedo prior's neighbours [N,k] (loss.lambda_albedo)
        self.albedo_nb_iteration = 0  # the iteration that searched them

        self.resume_notes: list[str] = []
        loaded = None
        if resume:
            loaded = load_resume_checkpoint(self.folder)
        else:
            refuse_existing_run(self.folder)
        if loaded is not None:
            self._check_same_capture()
            old = upgrade_config_dict(loaded[1].get("config"), lambda: self.dataset.largest_image_side(self.train_ids))
            self.resume_notes = check_resume_config(old, self.cfg.to_dict(), loaded[0])
            before, now = loaded[1].get("torch_threads"), torch.get_num_threads()
            if isinstance(before, int) and before != now:  # sums split differently: the same run to rounding only
                self.resume_notes.append(
                    f"torch threads: {before} -> {now} (not bit-identical to an uninterrupted run; "
                    f"--threads {before} keeps it so)"
                )
            try:
                self._restore(loaded[1])
            except MeshsplatError:
                raise
            except (KeyError, TypeError, ValueError, IndexError, AttributeError, RuntimeError) as exc:
                raise MeshsplatError(
                    f"cannot resume from {loaded[0]}: the checkpoint is incomplete or "
                    f"inconsistent ({type(exc).__name__}: {str(exc)[:160]})"
                ) from None
            self.resumed_from: Path | None = loaded[0]
        else:
            self.resumed_from = None
            self._fresh_start()

    # ---- setup -----------------------------------------------------------------------
    def _pose_refiner(self) -> tuple[PoseRefiner | None, str | None]:
        """The refiner of ``pose_refine.enabled`` (refusing a capture it cannot refine) or of
        ``pose_refine.auto`` (when the capture's meshes come from body/head-model parameters and the model
        files are found), and a one-line note of what auto decided (None when there was nothing to decide)."""
        pr = self.cfg.pose_refine
        has_params = self.dataset.driver_info is not None and self.dataset.driver_params is not None
        if not pr.enabled and not (pr.auto and has_params):
            return None, None
        try:
            refiner = PoseRefiner(
                self.dataset,
                self.train_ids,
                pr.params,
                pr.lr * self.lr_factor,
                self.cfg.model_dir or None,
                self.device,
                prior=pr.prior,
            )
        except MeshsplatError as exc:
            if pr.enabled:
                raise
            return None, f"pose refinement off, the tracker's poses are kept: {exc}"
        kind = str((self.dataset.driver_info or {}).get("type", "model")).upper()
        return (
            refiner,
            f"pose refinement on: {', '.join(refiner.names)} of {len(refiner.row_of)} training meshes ({kind})",
        )

    def _fresh_start(self) -> None:
        cfg = self.cfg
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % 2**32)
        random.seed(cfg.seed)
        if self.device.type == "cuda":
            torch.cuda.manual_seed_all(cfg.seed)
        gen = torch.Generator().manual_seed(cfg.seed)
        colors_fn = self._image_colors if cfg.model.init_color == "image" else None
        self.params = init_params(
            self.mesh,
            cfg.model.n_init,
            sh_degree=cfg.model.sh_degree,
            init_opacity=cfg.model.init_opacity,
            knn=cfg.model.init_knn,
            colors_fn=colors_fn,
            generator=gen,
            trainable_embedding=not cfg.model.freeze_embedding,
        )
        self.optimizers = build_optimizers(self.params, self.lrs, cfg.optim.eps)
        if cfg.model.shading != "none":
            self._set_shading(
                Shading(
                    normal=cfg.model.shading_normal,
                    device=self.device,
                    occlusion=cfg.model.occlusion,
                    directions=cfg.model.occlusion_directions,
                    grid=cfg.model.occlusion_grid,
                    specular=cfg.model.specular,
                    key_soft=cfg.model.occlusion_key_soft if cfg.model.occlusion == "key" else 0.0,
                )
            )
        self.strategy_state = self.strategy.initialize_state(self.extent)
        self.order_gen = torch.Generator().manual_seed(cfg.seed + 1)
        self.bg_gen = torch.Generator().manual_seed(cfg.seed + 2)
        self.order = torch.randperm(len(self.train_ids), generator=self.order_gen)
        self.order_pos = 0

    def _image_colors(self, face: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """Initial colour [N,3] of the embedded points: the first training frame's pixel
        (``model.init_color_frames`` = 1) or the mean over that many frames spread over the sequence."""
        k = min(self.cfg.model.init_color_frames, len(self.train_ids))
        if self.cfg.model.init_color_frames == 1:
            return first_view_colors(self.mesh, self._frame(self.train_ids[0]), face, uv)
        picks = sorted({self.train_ids[round(x)] for x in np.linspace(0, len(self.train_ids) - 1, k)})
        return mean_view_colors(self.mesh, (self._frame(i) for i in picks), face, uv)

    def _align_key(self, it: int) -> None:
        """``model.occlusion=key``: the next stage every ``occlusion_key_iter`` iterations, all that are left
        at the last iteration (a short run ends with one key light too)."""
        sh, every = self.shading, self.cfg.model.occlusion_key_iter
        if sh is None or sh.occlusion != "key" or sh.key_aligned:
            return
        stage = sh.key_stage
        while not sh.key_aligned and (it >= every * (sh.key_stage + 1) or it == self.cfg.iterations):
            sh.align_key()
        if sh.key_stage != stage:  # new tensors: a new optimizer
            self._set_shading(sh)

    def _set_shading(self, shading: Shading) -> None:
        shading.coeffs = torch.nn.Parameter(shading.coeffs.detach().clone().to(self.device))
        if shading.light is not None:
            shading.light = torch.nn.Parameter(shading.light.detach().clone().to(self.device))
        if shading.specular is not None:
            shading.specular = torch.nn.Parameter(shading.specular.detach().clone().to(self.device))
        self.shading = shading
        self.shading_opt = torch.optim.Adam(
            shading.parameters(), lr=self.cfg.optim.lr_shading * self.lr_factor, eps=self.cfg.optim.eps
        )

    # ---- data ------------------------------------------------------------------------
    def _frame(self, idx: int) -> tuple:
        """(image [H,W,3], mask [H,W,1]|None, camera, vertices [V,3]) on device (float32)."""
        hit = self._frame_cache.get(idx)
        if hit is not None:
            return hit
        fr = self.dataset[idx]
        dev = self.device
        item = (
            fr.image.to(dev, torch.float32),
            None if fr.mask is None else fr.mask.to(dev, torch.float32),
            fr.camera.to(dev, torch.float32),
            fr.vertices.to(dev, torch.float32),
        )
        size = sum(t.numel() * 4 for t in item if isinstance(t, torch.Tensor)) + 4 * (16 + 9)
        if self._cache_bytes + size <= _FRAME_CACHE_BYTES:
            self._frame_cache[idx] = item
            self._cache_bytes += size
        return item

    def _pose(self, idx: int, avatar: Avatar, verts: torch.Tensor) -> MeshPose:
        """Training frame ``idx``'s ``MeshPose`` of its (fixed) ``verts [V,3]``: posed once, kept within the
        frame cache's budget (posing the mesh is a few milliseconds of every iteration otherwise)."""
        hit = self._pose_cache.get(idx)
        if hit is not None:
            return hit
        pose = avatar.pose(verts)
        size = sum(t.numel() * t.element_size() for t in (pose.vertex_normals, pose.vertex_quats, pose.area_ratio))
        sh = self.shading
        dirs = None if sh is None else sh.shadow_directions()
        if sh is not None and dirs is not None:  # the shadow maps the pose will keep (float64 when compiled)
            size += dirs.shape[0] * sh.grid**2 * 8
        if self._cache_bytes + size <= _FRAME_CACHE_BYTES:
            self._pose_cache[idx] = pose
            self._cache_bytes += size
        return pose

    def _next_index(self) -> int:
        if self.order_pos >= len(self.order):
            self.order = torch.randperm(len(self.train_ids), generator=self.order_gen)
            self.order_pos = 0
        idx = self.train_ids[int(self.order[self.order_pos])]
        self.order_pos += 1
        return idx

    def _background(self) -> torch.Tensor:
        """This iteration's background [3]: random per iteration (seeded), or the configured colour."""
        if self.cfg.background == "random":
            bg = torch.rand(3, generator=self.bg_gen)
        else:
            bg = background_color(self.cfg.background)
        return bg.to(self.device)

    # ---- one iteration ---------------------------------------------------------------
    @property
    def clamp_to_face(self) -> bool:
        return not self.cfg.walk.enabled

    def render_frame(self, idx: int, background: torch.Tensor) -> tuple[AvatarRender, torch.Tensor]:
        """Render training frame ``idx`` on ``background [3]`` through ``Avatar.render`` (pose-refined
        vertices when refining). Returns (render, ground truth [H,W,3] composited on the same background)."""
        image, mask, camera, verts = self._frame(idx)
        avatar = self.avatar()
        row = int(self.dataset.frame_info(idx)["mesh"]) if self.refiner is not None else -1
        posed: torch.Tensor | MeshPose
        if self.refiner is not None and self.refiner.refines(row):
            posed = self.refiner.vertices(row)  # changes every step: posed anew
        else:
            posed = self._pose(idx, avatar, verts)
        out = avatar.render(posed, camera, background, backend=self.cfg.backend)
        return out, composite(image, mask, background)

    def _image_loss(
        self, out: AvatarRender, gt: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The training loss of one rendered image and its parts."""
        L = self.cfg.loss
        # loss.lpips_every = k: the perceptual terms on every k-th iteration only, k times their weight
        k = L.lpips_every if self.perceptual_due else 0
        crop = subject_crop(mask, out.alpha, L.crop_margin) if L.crop_to_subject and k else None
        loss, parts = avatar_loss(
            out.image,
            gt,
            self.params["log_scale"].exp(),
            thresh_scale=L.scale_max * self.extent,
            thresh_ratio=L.scale_ratio,
            lambda_l1=L.lambda_l1,
            lambda_lpips=L.lambda_lpips * k,
            lambda_scale=L.lambda_scale / self.extent,
            lambda_mse=L.lambda_mse,
            lambda_dssim=L.lambda_ssim * k,
            perceptual=self.perceptual,
            crop=crop,
        )
        if L.lambda_mask and mask is not None:
            mask_l1 = (out.alpha - mask).abs().mean()
            loss = loss + L.lambda_mask * mask_l1
            parts["mask"] = mask_l1.detach()
        if L.lambda_albedo and self.shading is not None:
            prior = albedo_smoothness(self.params["sh0"], self._albedo_neighbours())
            loss = loss + L.lambda_albedo * prior
            parts["albedo"] = prior.detach()
        return loss, parts

    def _albedo_neighbours(self) -> torch.Tensor:
        """Each Gaussian's neighbours on the canonical mesh ``[N,k]`` for the albedo prior (``loss.albedo_reach``):
        searched again every ``REFRESH_EVERY`` iterations and whenever the count changed (kept in checkpoints, so
        a resumed run uses the same ones)."""
        n, it = num_gaussians(self.params), self.iteration
        nb = self.albedo_nb
        if nb is None or nb.shape[0] != n or (it % REFRESH_EVERY == 1 and self.albedo_nb_iteration != it):
            uv = effective_uv(self.params, self.clamp_to_face)
            self.albedo_nb = albedo_neighbours(
                self.mesh.vertices, self.mesh.faces, self.params["face"], uv, self.cfg.loss.albedo_reach
            )
            self.albedo_nb_iteration = it
        assert self.albedo_nb is not None
        return self.albedo_nb

    @property
    def perceptual_due(self) -> bool:
        """Whether this iteration (``self.iteration``, 1-based, already counted by ``step``) computes LPIPS and
        D-SSIM: every ``loss.lpips_every``-th one. Depends on the iteration counter only, so a resumed run
        skips the same iterations."""
        return self.iteration % self.cfg.loss.lpips_every == 0

    def _trained_tensors(self) -> list[torch.Tensor]:
        """Every tensor an optimizer steps (the gradients data-parallel training all-reduces)."""
        out = [p for opt in self.optimizers.values() for g in opt.param_groups for p in g["params"]]
        if self.shading is not None:
            out.extend(self.shading.parameters())
        if self.refiner is not None:
            out.extend(self.refiner.offsets.values())
        return out

    def step(self) -> dict[str, float]:
        """Run one training iteration (``batch_size`` images; this process renders its share); returns
        its logged values (means over the batch)."""
        cfg = self.cfg
        self.iteration += 1
        it = self.iteration
        lrs = self.schedule.apply(self.optimizers, it)
        batch, backgrounds = [], []
        for _ in range(cfg.batch_size):  # every process draws the whole batch: generators stay in step
            idx = self._next_index()
            _, mask, _, _ = self._frame(idx)
            batch.append(idx)
            backgrounds.append(self._background() if mask is not None else torch.zeros(3, device=self.device))
        B = cfg.batch_size
        metas = []
        logged = torch.zeros(len(_LOGGED_PARTS) + 2, dtype=torch.float64)  # loss, psnr, parts: sums
        for j in self.dp.share(B):
            idx = batch[j]
            out, gt = self.render_frame(idx, backgrounds[j])
            self.strategy.step_pre_backward(self.params, self.optimizers, self.strategy_state, it, out.meta)
            loss, parts = self._image_loss(out, gt, self._frame(idx)[1])
            if not torch.isfinite(loss):
                raise MeshsplatError(f"iteration {it}: loss is {float(loss)} (diverged); try lower learning rates")
            (loss if B == 1 else loss / B).backward()
            metas.append(out.meta)
            with torch.no_grad():
                logged[0] += float(loss.detach())
                logged[1] += float(psnr(out.image.detach().clamp(0, 1), gt))
            for k, name in enumerate(_LOGGED_PARTS):
                logged[k + 2] += float(parts[name]) if name in parts else 0.0
        self.dp.all_reduce_grads(self._trained_tensors())
        logged = self.dp.sum(logged) / B
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        if cfg.model.max_offset > 0:  # Gaussians stay near their triangle (a projection, like the lighting's)
            with torch.no_grad():
                bound = cfg.model.max_offset * self.extent
                self.params["d"].clamp_(-bound, bound)
        if self.shading_opt is not None:
            self.shading_opt.step()
            self.shading_opt.zero_grad(set_to_none=True)
            if self.shading is not None:
                self.shading.project()
                self._align_key(it)
        if self.refiner is not None:  # the batch's rows only: a frame not drawn keeps its pose and its Adam state
            self.refiner.step(int(self.dataset.frame_info(i)["mesh"]) for i in batch)
        self.strategy.step_post_backward(
            self.params,
            self.optimizers,
            self.strategy_state,
            it,
            metas,
            mesh=self.mesh,
            scale_mode=cfg.model.scale_mode,
            batch_size=B,
            reduce=self.dp.reduce_statistics if self.dp.active else None,
            final=it == cfg.iterations,
        )
        walked = 0
        if it % cfg.walk.every == 0 and not cfg.model.freeze_embedding:
            changed = walk_embeddings(
                self.params,
                self.optimizers,
                self.mesh,
                walk=cfg.walk.enabled,
                mode=cfg.walk.mode,
                max_crossings=cfg.walk.max_crossings,
            )
            walked = int(changed.sum())
            self.walked_total += walked
        self.dp.check_same("the number of Gaussians", num_gaussians(self.params))
        row = {
            "iteration": it,
            "loss": float(logged[0]),
            "psnr": float(logged[1]),
            "n_gaussians": num_gaussians(self.params),
            "walked": walked,
            "lr_duv": lrs.get("duv", 0.0),
            "lr_d": lrs.get("d", 0.0),
        }
        for k, name in enumerate(_LOGGED_PARTS):
            row[name] = float(logged[k + 2])
        if not self.perceptual_due:  # not computed this iteration: nan here, an empty cell in log.csv
            for name, weight in (("lpips", cfg.loss.lambda_lpips), ("dssim", cfg.loss.lambda_ssim)):
                if weight:
                    row[name] = math.nan
        row["scale"] /= self.extent  # relative to the mesh size (as optimised), so assets in cm and m compare
        return row

    # ---- loop ------------------------------------------------------------------------
    def _compiles_cpu_kernels(self) -> bool:
        """Whether steps render with numba's compiled kernels, whose first use in a process loads them (or, on
        a fresh install, compiles them for about half a minute): CPU, backend auto or numba, numba present."""
        return self.device.type == "cpu" and self.cfg.backend in ("auto", "numba") and numba_available()

    def train(self, until: int | None = None) -> Path:
        """Train up to iteration ``until`` (default ``config.iterations``); returns the run dir."""
        cfg = self.cfg
        end = cfg.iterations if until is None else min(int(until), cfg.iterations)
        main = self.dp.is_main  # the one process that writes the run folder
        lock = FolderLock(self.folder.lock_path, f"the run {self.folder.root}", parent_ok=True)
        if main:  # one training per run folder (the --nproc launcher holds it for its workers)
            lock.acquire()
        try:
            if main:
                self.folder.root.mkdir(parents=True, exist_ok=True)
                cfg.to_json(self.folder.config_path)
                self._write_identity()
                self._open_log()
                remove_stray_tmp(self.folder.checkpoint_dir)
                self.monitor = TensorBoardMonitor.open(self.folder.root, self.iteration)
            return self._train(end, main)
        finally:
            if self.monitor is not None:
                self.monitor.close()
                self.monitor = None
            lock.release()

    def _train(self, end: int, main: bool) -> Path:
        cfg = self.cfg
        bar = None
        if cfg.progress:
            from tqdm import tqdm

            print(f"progress: loss, {self.train_psnr_label}, Gaussians (G)", file=sys.stderr)
            if self.monitor is not None:
                print(f"watch it live: tensorboard --logdir {self.monitor.log_dir}", file=sys.stderr)
            if self.iteration < end and self._compiles_cpu_kernels():
                print(
                    "first step: loading the compiled CPU kernels (after an install: compiling, ~30 s)", file=sys.stderr
                )
            bar = tqdm(total=end, initial=self.iteration, desc="train", dynamic_ncols=True, bar_format=PROGRESS_FORMAT)
        t0 = time.perf_counter() - self.elapsed
        last_ckpt = time.perf_counter()
        ckpt: Path | None = None
        try:
            with StopOnSignal() as stop:
                while self.iteration < end:
                    row = self.step()
                    if self.refiner is not None:
                        self.refiner.polished = False  # the poses moved with the avatar: fit them again at the end
                    it = self.iteration
                    self.elapsed = time.perf_counter() - t0
                    row["time_s"] = self.elapsed
                    self.recent.append((row["loss"], row["psnr"]))
                    stopping = stop.signum is not None
                    if self.dp.active:  # a signal seen by any process stops all at the same iteration
                        stopping = bool(self.dp.sum(torch.tensor([float(stopping)])) > 0)
                    if main and (it % cfg.log_every == 0 or it == end):
                        self._log(row)
                    if main and (it % cfg.preview_every == 0 or it == cfg.iterations):
                        self.save_preview()
                    due = time.perf_counter() - last_ckpt >= cfg.checkpoint_every_s or stopping
                    if main and (it % cfg.checkpoint_every == 0 or it == cfg.iterations or due):
                        ckpt = self.save_checkpoint()
                        last_ckpt = time.perf_counter()
                    if stopping:
                        signum = stop.signum or signal.SIGTERM
                        raise TrainingInterrupted(
                            f"stopped by {signal_name(signum)} at iteration {it}; checkpoint "
                            f"{ckpt} written: continue with --resume",
                            signum,
                            ckpt,
                        )
                    if bar is not None:
                        bar.update(1)
                        loss_mean = sum(x[0] for x in self.recent) / len(self.recent)
                        bar.set_postfix_str(
                            progress_postfix(loss_mean, self.recent_train_psnr, int(row["n_gaussians"]))
                        )
                if self.polish_due:
                    steps = cfg.pose_refine.polish_steps
                    if bar is not None:
                        bar.set_postfix_str(f"fitting the training poses, the avatar frozen ({steps} steps)")

                    def check_stop() -> None:  # one process decides alone: no vote between steps
                        if stop.signum is not None and not self.dp.active:
                            raise TrainingInterrupted(
                                f"stopped by {signal_name(stop.signum)} while fitting the training poses after "
                                f"iteration {self.iteration}; the checkpoint of that iteration is intact: "
                                "continue with --resume",
                                stop.signum,
                                ckpt,
                            )

                    self.polish_poses(on_step=check_stop)
                    if main:
                        ckpt = self.save_checkpoint()
        finally:
            if bar is not None:
                bar.close()
        return self.folder.root

    def _check_same_capture(self) -> None:
        """On resume: the capture is the one the run was trained on (``RUN/run.json``; runs without it pass)."""
        old = self.folder.identity()
        if not isinstance(old, dict) or not isinstance(old.get("capture"), dict):
            return
        differ = identity_differences(old["capture"], capture_identity(self.dataset))
        if differ:
            raise MeshsplatError(
                f"cannot resume {self.folder.root}: it was trained on {old.get('data', 'another capture')}, and "
                f"{self.cfg.data} is another capture ({', '.join(differ)} differ); resume with the run's own "
                "capture, or train this one into a new --out"
            )

    def _write_identity(self) -> None:
        """``RUN/run.json``: the capture this run trains and a digest of its recipe (every config key but
        those a resume may change); kept on resume."""
        if self.resumed_from is not None and self.folder.identity_path.is_file():
            return
        recipe = {k: v for k, v in self.cfg.to_dict().items() if k not in SAFE_CHANGES}
        record = {
            "data": self.cfg.data,
            "data_format": self.dataset.format_name,
            "capture": capture_identity(self.dataset),
            "recipe": hashlib.sha256(json.dumps(recipe, sort_keys=True, default=str).encode()).hexdigest()[:16],
        }
        write_text_atomic(self.folder.identity_path, json.dumps(record, indent=1) + "\n")

    @property
    def polish_due(self) -> bool:
        """Whether training is at its end with refined poses still to fit once more (``pose_refine.polish_steps``)."""
        return (
            self.refiner is not None
            and self.cfg.pose_refine.polish_steps > 0
            and not self.refiner.polished
            and self.iteration >= self.cfg.iterations
        )

    def polish_poses(self, on_step: Callable[[], None] | None = None) -> None:
        """Fit the refined training poses for ``pose_refine.polish_steps`` more steps with the avatar frozen:
        the L1 error of every training image rendered in its row's pose (on white; frames without a mask on
        black), a backward per mesh row and step (``PoseRefiner.fit``)."""
        assert self.refiner is not None
        frames: dict[int, list[int]] = {}
        for i in self.train_ids:
            frames.setdefault(int(self.dataset.frame_info(i)["mesh"]), []).append(i)
        white, black = torch.ones(3, device=self.device), torch.zeros(3, device=self.device)

        def row_error(row: int) -> torch.Tensor:
            errors = []
            for i in frames[row]:
                out, gt = self.render_frame(i, white if self._frame(i)[1] is not None else black)
                errors.append((out.image - gt).abs().mean())
            return torch.stack(errors).sum()

        pr = self.cfg.pose_refine
        self.refiner.fit(row_error, pr.polish_steps, pr.polish_lr, on_step)
        self.refiner.polished = True

    @property
    def num_gaussians(self) -> int:
        return num_gaussians(self.params)

    @property
    def recent_train_psnr(self) -> float:
        """Mean PSNR of the latest ``PROGRESS_WINDOW`` iterations of this session (nan before the first):
        what the progress bar shows, labelled by ``train_psnr_label``."""
        return sum(x[1] for x in self.recent) / len(self.recent) if self.recent else float("nan")

    @property
    def train_psnr_label(self) -> str:
        """What ``recent_train_psnr`` measures. Not ``meshsplat eval``'s numbers: each value is one training
        frame (not held out; pose-refined when refining) rendered with the parameters before that
        iteration's update, on that iteration's background (``background``: a random colour by default;
        frames without a mask keep their recorded background, on black), averaged over iterations."""
        bg = "random bg" if self.cfg.background == "random" else f"{self.cfg.background} bg"
        return f"train PSNR ({bg}, mean of last {PROGRESS_WINDOW} iters)"

    # ---- outputs ---------------------------------------------------------------------
    def _open_log(self) -> None:
        path = self.folder.log_path
        rows = []
        if path.exists():  # keep the rows up to the resumed iteration
            with open(path, newline="") as fh:
                rows = [
                    r
                    for r in csv.DictReader(fh)
                    if r.get("iteration", "").isdigit() and int(r["iteration"]) <= self.iteration
                ]
        with open(path, "w", newline="") as fh:
            wr = csv.DictWriter(fh, fieldnames=LOG_COLUMNS)
            wr.writeheader()
            for r in rows:
                wr.writerow({k: r.get(k, "") for k in LOG_COLUMNS})

    def _log(self, row: dict[str, float]) -> None:
        self.history.append(row)
        with open(self.folder.log_path, "a", newline="") as fh:
            csv.DictWriter(fh, fieldnames=LOG_COLUMNS).writerow({k: _cell(row[k]) for k in LOG_COLUMNS})
        if self.monitor is not None:
            self.monitor.scalars(row, learning_rates(self.optimizers))

    @torch.no_grad()
    def save_preview(self, idx: int | None = None) -> Path:
        from PIL import Image

        idx = self.train_ids[0] if idx is None else idx
        bg = torch.ones(3, device=self.device)
        out, gt = self.render_frame(idx, bg)
        pair = torch.cat([out.image.clamp(0, 1), gt], dim=1)
        img = float_to_uint8(pair)
        path = self.folder.preview_path(self.iteration)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(path)
        if self.monitor is not None:
            self.monitor.preview(img, self.iteration)
        return path

    def avatar(self) -> Avatar:
        """The current model as an ``Avatar`` (shares the parameter tensors)."""
        return Avatar(
            self.mesh,
            self.params,
            self.cfg.model.scale_mode,
            clamp_to_face=self.clamp_to_face,
            shading=self.shading,
            sh_frame=self.cfg.model.sh_frame,
            antialiased=self.cfg.model.antialiased,
        )

    def state_dict(self) -> dict[str, Any]:
        rng = capture_rng({"order": self.order_gen, "background": self.bg_gen}, self.device)
        strat = {k: (v.detach().cpu() if isinstance(v, torch.Tensor) else v) for k, v in self.strategy_state.items()}
        return {
            "iteration": self.iteration,
            "elapsed_s": self.elapsed,
            "config": self.cfg.to_dict(),
            "avatar": self.avatar().state_dict(),
            "trainable": sorted(k for k, v in self.params.items() if getattr(v, "requires_grad", False)),
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
            "strategy_state": strat,
            "rng": rng,
            "data_order": {"order": self.order.clone(), "pos": self.order_pos},
            "pose_refine": None if self.refiner is None else self.refiner.state_dict(),
            "shading_optimizer": None if self.shading_opt is None else self.shading_opt.state_dict(),
            "albedo_prior": None
            if self.albedo_nb is None
            else {"neighbours": self.albedo_nb.cpu(), "iteration": self.albedo_nb_iteration},
            "torch_threads": torch.get_num_threads(),  # a resume on another count matches only to rounding
        }

    def save_checkpoint(self) -> Path:
        if self.refiner is not None:  # the refined parameters, readable without torch
            arrays: dict[str, Any] = self.refiner.refined_params()
            np.savez(self.folder.refined_params_path, **arrays)
        return save_checkpoint(
            self.folder.checkpoint_path(self.iteration), self.state_dict(), keep_last=self.cfg.keep_checkpoints
        )

    def _restore(self, st: dict[str, Any]) -> None:
        dev = self.device
        av = st["avatar"]
        trainable = set(st.get("trainable", []))
        self.params = {}
        for k, v in av["params"].items():
            v = v.to(dev)
            self.params[k] = v if k in EMBEDDING_STATE_KEYS else torch.nn.Parameter(v, requires_grad=k in trainable)
        self.optimizers = build_optimizers(self.params, self.lrs, self.cfg.optim.eps)
        if set(self.optimizers) != set(st["optimizers"]):
            raise MeshsplatError(
                "checkpoint: optimizer keys do not match the configuration "
                f"({sorted(st['optimizers'])} vs {sorted(self.optimizers)})"
            )
        for k, opt in self.optimizers.items():
            opt.load_state_dict(st["optimizers"][k])
        self.strategy_state = {
            k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in st["strategy_state"].items()
        }
        if is_legacy_config(st.get("config")) and isinstance(self.strategy_state.get("radii"), torch.Tensor):
            # older versions kept the screen radii in pixels; today a fraction of the image size
            self.strategy_state["radii"] = self.strategy_state["radii"] / self.dataset.largest_image_side(
                self.train_ids
            )
        gens = restore_rng(st["rng"], ("order", "background"), dev)
        self.order_gen, self.bg_gen = gens["order"], gens["background"]
        if self.refiner is not None:
            if not st.get("pose_refine"):
                raise MeshsplatError(
                    "checkpoint: it was trained without pose refinement; resume without "
                    "pose_refine.enabled or start a new run"
                )
            self.refiner.load_state_dict(st["pose_refine"])
        elif st.get("pose_refine"):
            why = f" ({self.pose_refine_note})" if self.pose_refine_note else ""
            raise MeshsplatError(
                f"checkpoint: it was trained with pose refinement, which this configuration does not do{why}; "
                "resume with the same settings and model files (--model-dir) or start a new run"
            )
        sh_state = av.get("shading")
        if (sh_state is None) != (self.cfg.model.shading == "none"):
            raise MeshsplatError(
                "checkpoint: its shading does not match model.shading in the configuration; "
                "resume with the run's own config.json or start a new run"
            )
        if sh_state is not None:
            shading = Shading.from_state_dict(sh_state, dev)
            assert shading is not None  # sh_state is not None
            if shading.occlusion != self.cfg.model.occlusion:
                raise MeshsplatError(
                    f"checkpoint: its occlusion ({shading.occlusion}) does not match model.occlusion "
                    f"({self.cfg.model.occlusion}); resume with the run's own config.json or start a new run"
                )
            if shading.specular_mode != self.cfg.model.specular:
                raise MeshsplatError(
                    f"checkpoint: its specular ({shading.specular_mode}) does not match model.specular "
                    f"({self.cfg.model.specular}); resume with the run's own config.json or start a new run"
                )
            self._set_shading(shading)
            if st.get("shading_optimizer"):
                assert self.shading_opt is not None  # made by _set_shading
                self.shading_opt.load_state_dict(st["shading_optimizer"])
        self.order = st["data_order"]["order"].clone()
        self.order_pos = int(st["data_order"]["pos"])
        self.iteration = int(st["iteration"])
        self.elapsed = float(st.get("elapsed_s", 0.0))
        # absent before the albedo prior existed: searched at the next step. Saved after a densification they
        # still index the Gaussians before it: the next step searches again, as the uninterrupted run did
        prior = st.get("albedo_prior")
        if prior is not None:
            nb = prior["neighbours"]
            if (
                not isinstance(nb, torch.Tensor)
                or nb.dtype != torch.long
                or nb.ndim != 2
                or (nb.numel() and not 0 <= int(nb.min()) <= int(nb.max()) < nb.shape[0])
            ):
                raise MeshsplatError(
                    "checkpoint: its albedo prior's neighbours are not indices of its Gaussians (a damaged file); "
                    "resume from an earlier checkpoint or start a new run"
                )
            self.albedo_nb, self.albedo_nb_iteration = nb.to(dev), int(prior["iteration"])


def train(config: TrainConfig, resume: bool = False) -> Path:
    """Train (or resume) the run described by ``config``; returns the run directory."""
    return Trainer(config, resume=resume).train()
