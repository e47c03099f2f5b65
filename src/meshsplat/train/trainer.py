"""Training loop: mesh-embedded Gaussians fitted to images of a posed mesh sequence.

Writes the run folder ``config.out`` (layout: ``meshsplat.run_folder``): ``config.json``, checkpoints (last
``keep_checkpoints`` kept), ``log.csv`` (``meshsplat.train.run_log``) and previews; components add their files.

Per iteration (1-based ``it``): set lrs; next training frame (shuffled without replacement per epoch, seeded);
pose the canonical mesh with the frame's vertices; compose; rasterize on a random background (also blended into
the ground truth through the mask); the paper's loss ``L1 + λ_lpips LPIPS + λ_scale L_scale (+ λ_mse MSE + λ_ssim
D-SSIM)`` (``meshsplat.train.losses``; L_scale on the canonical scales in mesh extents), plus each enabled
component's term; backward; Adam steps; components' steps; densification; every ``walk.every`` iterations
walking on triangles. The features beyond the paper are components (``meshsplat.train.components``): the
trainer calls their hooks and keeps none of their state.

A checkpoint (``meshsplat.io.load_checkpoint``) holds ``iteration``, ``config``, ``avatar``
(``Avatar.state_dict()``), ``optimizers``, ``strategy_state``, ``rng``, ``data_order``, ``elapsed_s`` and
``components`` (each enabled component's state). Resuming from it on CPU continues bit for bit.
"""

from __future__ import annotations

import math
import random
from pathlib import Path

import numpy as np
import torch

from meshsplat._device import resolve_device
from meshsplat.data.formats import open_capture, reader_options
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.avatar import Avatar, AvatarRender
from meshsplat.gaussians.params import init_params, num_gaussians
from meshsplat.gaussians.shading import Shading
from meshsplat.mesh import TriMesh, mean_edge_length, mesh_extent
from meshsplat.metrics import psnr
from meshsplat.render.background import background_color, composite
from meshsplat.run_folder import RunFolder, check_training_target
from meshsplat.train.checkpoints import TrainerCheckpoints
from meshsplat.train.components import COMPONENTS, Component
from meshsplat.train.components.shading import ShadingComponent
from meshsplat.train.config import TrainConfig, config_dict
from meshsplat.train.distributed import DataParallel
from meshsplat.train.frames import FrameCache
from meshsplat.train.loop import TrainingLoop
from meshsplat.train.losses import avatar_loss, make_perceptual_loss, subject_crop
from meshsplat.train.optim import LrSchedule, base_learning_rates, build_optimizers
from meshsplat.train.resume import (
    check_resume_config,
    check_same_capture,
    load_resume_checkpoint,
    refuse_existing_run,
)
from meshsplat.train.run_log import LOGGED_PARTS
from meshsplat.train.strategy import walk_embeddings

__all__ = ["Trainer", "train"]


class Trainer(TrainingLoop, TrainerCheckpoints):
    """Builds everything from a ``TrainConfig``; ``train()`` (``meshsplat.train.loop``) runs to
    ``config.iterations``.

    ``resume=True`` continues from the newest checkpoint in ``RUN/checkpoints`` (starts fresh when there is
    none); it refuses unreadable checkpoints and config changes outside ``train.resume.SAFE_CHANGES``
    (``resume_notes`` lists the safe ones applied). Without ``resume`` a folder that already holds checkpoints
    is refused. ``data`` and ``out`` are stored as absolute paths.
    """

    def __init__(self, config: TrainConfig, resume: bool = False) -> None:
        self.cfg = cfg = TrainConfig.from_dict(config.validate().to_dict())  # own copy
        if not cfg.data:
            raise MeshsplatError("config: data (the dataset folder) is not set")
        cfg.data = str(Path(cfg.data).expanduser().resolve())
        cfg.out = str(Path(cfg.out).expanduser().resolve())
        if cfg.model_dir:  # absolute, as data: render --motion from another folder finds it
            cfg.model_dir = str(Path(cfg.model_dir).expanduser().resolve())
        self.folder = RunFolder(cfg.out)
        self.dp, self.device = DataParallel.from_env(resolve_device(cfg.device))
        self.dp.check_batch(cfg.batch_size)
        if self.dp.is_main:  # a capture, a foreign folder or a run in training is refused before any work
            check_training_target(cfg.out, cfg.data)
        else:
            cfg.progress = False
        self.dataset = open_capture(
            cfg.data,
            format=cfg.data_format or None,
            model_dir=cfg.model_dir or None,
            drop_bad_frames=cfg.drop_bad_frames,
            downscale=cfg.data_downscale,
            **reader_options(cfg.data_gender, cfg.data_shape),
        )
        rule = self.dataset.meta.get("split_rule")
        # which rule chose the splits (a reader's guess, e.g. without config.json): the command prints it
        self.split_note = f"{cfg.data}: splits from {rule}" if rule else None
        self.train_ids = list(self.dataset.split("train"))
        if not self.train_ids:
            raise MeshsplatError(f"{cfg.data}: the 'train' split is empty")
        cano = torch.as_tensor(self.dataset.canonical_vertices, dtype=torch.float32)
        self.mesh = TriMesh(cano.to(self.device), torch.as_tensor(self.dataset.faces).long().to(self.device))
        self.extent = mesh_extent(self.mesh.vertices)
        self.strategy = cfg.strategy
        self.lr_factor = math.sqrt(cfg.batch_size)  # gsplat's rule for batches: lr times sqrt(batch size)
        self.lrs = base_learning_rates(cfg.optim, self.extent, mean_edge_length(self.mesh.vertices, self.mesh.faces))
        if cfg.batch_size > 1:
            self.lrs = {k: v * self.lr_factor for k, v in self.lrs.items()}
        self.schedule = LrSchedule(cfg.optim, self.lrs, cfg.iterations)
        self.frames = FrameCache(self.dataset, self.device)
        self.iteration = 0
        self._loop_init()
        self.components, self.notes = self._build_components()
        # built now: nothing may draw random numbers after seeding or restoring the generators
        self.perceptual = (
            make_perceptual_loss("alex", precision=cfg.loss.lpips_precision).build(self.device)
            if cfg.loss.lambda_lpips
            else None
        )
        self.elapsed = 0.0
        self.resume_notes: list[str] = []
        loaded = load_resume_checkpoint(self.folder) if resume else None
        if not resume:
            refuse_existing_run(self.folder)
        self.resumed_from: Path | None = None if loaded is None else loaded[0]
        if loaded is None:
            self._fresh_start()
        else:
            check_same_capture(self.folder, self.dataset, cfg.data)
            self.resume_notes = check_resume_config(config_dict(loaded[1].get("config")), cfg.to_dict(), loaded[0])
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

    # ---- what components read (meshsplat.train.components.TrainingState) -------------------------------------
    @property
    def iterations(self) -> int:
        return self.cfg.iterations

    @property
    def model_dir(self) -> str | None:
        return self.cfg.model_dir or None

    @property
    def eps(self) -> float:
        return self.cfg.optim.eps

    @property
    def clamp_to_face(self) -> bool:
        return not self.cfg.walk.enabled

    @property
    def shading(self) -> Shading | None:
        comp = self.component("shading")
        return comp.shading if isinstance(comp, ShadingComponent) else None

    def component(self, name: str) -> Component | None:
        """The enabled component ``name``, or None."""
        return next((c for c in self.components if c.name == name), None)

    # ---- setup -------------------------------------------------------------------------------------------------
    def _build_components(self) -> tuple[list[Component], list[str]]:
        """The enabled components in hook order, and one note for each one that said why it is on or stays off."""
        comps, notes = [], []
        for cls, _ in COMPONENTS:
            section = getattr(self.cfg, cls.name)
            if section.enabled:
                comp, note = cls.build(section, self)
                comps += [comp] if comp is not None else []
                notes += [note] if note else []
        return comps, notes

    def _fresh_start(self) -> None:
        cfg = self.cfg
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % 2**32)
        random.seed(cfg.seed)
        if self.device.type == "cuda":
            torch.cuda.manual_seed_all(cfg.seed)
        self.params = init_params(
            self.mesh,
            cfg.model.n_init,
            sh_degree=cfg.model.sh_degree,
            init_opacity=cfg.model.init_opacity,
            knn=cfg.model.init_knn,
            colors_fn=self.frames.colors_fn(self.mesh, self.train_ids, cfg.model.init_color_frames)
            if cfg.model.init_color == "image"
            else None,
            generator=torch.Generator().manual_seed(cfg.seed),
            trainable_embedding=not cfg.model.freeze_embedding,
        )
        self.optimizers = build_optimizers(self.params, self.lrs, cfg.optim.eps)
        for comp in self.components:
            comp.start()
        self.strategy_state = self.strategy.initialize_state(self.extent)
        self.order_gen = torch.Generator().manual_seed(cfg.seed + 1)
        self.bg_gen = torch.Generator().manual_seed(cfg.seed + 2)
        self.order = torch.randperm(len(self.train_ids), generator=self.order_gen)
        self.order_pos = 0

    # ---- one iteration -----------------------------------------------------------------------------------------
    def _next_index(self) -> int:
        if self.order_pos >= len(self.order):
            self.order = torch.randperm(len(self.train_ids), generator=self.order_gen)
            self.order_pos = 0
        idx = self.train_ids[int(self.order[self.order_pos])]
        self.order_pos += 1
        return idx

    def _background(self) -> torch.Tensor:
        """This iteration's background [3]: random per iteration (seeded), or the configured colour."""
        bg = torch.rand(3, generator=self.bg_gen) if self.cfg.background == "random" else None
        return (background_color(self.cfg.background) if bg is None else bg).to(self.device)

    def avatar(self) -> Avatar:
        """The current model as an ``Avatar`` (shares the parameter tensors)."""
        m = self.cfg.model
        return Avatar(
            self.mesh,
            self.params,
            m.scale_mode,
            clamp_to_face=self.clamp_to_face,
            shading=self.shading,
            sh_frame=m.sh_frame,
            antialiased=m.antialiased,
        )

    def render_frame(self, idx: int, background: torch.Tensor) -> tuple[AvatarRender, torch.Tensor]:
        """Render training frame ``idx`` on ``background [3]`` (in a component's pose when one gives it).
        Returns (render, ground truth [H,W,3] composited on the same background)."""
        image, mask, camera, _ = self.frames.frame(idx)
        avatar = self.avatar()
        posed = next((v for v in (c.posed(idx) for c in self.components) if v is not None), None)
        out = avatar.render(
            self.frames.pose(idx, avatar, self.shading) if posed is None else posed,
            camera,
            background,
            backend=self.cfg.backend,
        )
        return out, composite(image, mask, background)

    @property
    def perceptual_due(self) -> bool:
        """Whether this iteration (1-based, already counted by ``step``) computes LPIPS and D-SSIM: every
        ``loss.lpips_every``-th one, so a resumed run skips the same iterations."""
        return self.iteration % self.cfg.loss.lpips_every == 0

    def _image_loss(
        self, out: AvatarRender, gt: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The training loss of one rendered image and its parts: the paper's terms, then the components'."""
        L = self.cfg.loss
        k = L.lpips_every if self.perceptual_due else 0  # the perceptual terms every k-th iteration, k x weight
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
            crop=subject_crop(mask, out.alpha, L.crop_margin) if L.crop_to_subject and k else None,
        )
        for comp in self.components:
            term = comp.loss(out, mask) if comp.log_column is not None and comp.weight else None
            if term is not None:
                loss = loss + comp.weight * term
                parts[str(comp.log_column)] = term.detach()
        return loss, parts

    def _trained_tensors(self) -> list[torch.Tensor]:
        """Every tensor an optimizer steps (the gradients data-parallel training all-reduces)."""
        out = [p for opt in self.optimizers.values() for g in opt.param_groups for p in g["params"]]
        return out + [t for comp in self.components for t in comp.parameters()]

    def step(self) -> dict[str, float]:
        """Run one training iteration (``batch_size`` images; this process renders its share); returns its
        logged values (means over the batch)."""
        cfg = self.cfg
        self.iteration = it = self.iteration + 1
        lrs = self.schedule.apply(self.optimizers, it)
        batch, backgrounds = [], []
        for _ in range(cfg.batch_size):  # every process draws the whole batch: generators stay in step
            idx = self._next_index()
            batch.append(idx)
            has_mask = self.frames.frame(idx)[1] is not None
            backgrounds.append(self._background() if has_mask else torch.zeros(3, device=self.device))
        B = cfg.batch_size
        metas = []
        logged = torch.zeros(len(LOGGED_PARTS) + 2, dtype=torch.float64)  # loss, psnr, parts: sums
        for j in self.dp.share(B):
            out, gt = self.render_frame(batch[j], backgrounds[j])
            self.strategy.step_pre_backward(self.params, self.optimizers, self.strategy_state, it, out.meta)
            loss, parts = self._image_loss(out, gt, self.frames.frame(batch[j])[1])
            if not torch.isfinite(loss):
                raise MeshsplatError(f"iteration {it}: loss is {float(loss)} (diverged); try lower learning rates")
            (loss if B == 1 else loss / B).backward()
            metas.append(out.meta)
            with torch.no_grad():
                logged[0] += float(loss.detach())
                logged[1] += float(psnr(out.image.detach().clamp(0, 1), gt))
            for k, name in enumerate(LOGGED_PARTS):
                logged[k + 2] += float(parts[name]) if name in parts else 0.0
        self.dp.all_reduce_grads(self._trained_tensors())
        logged = self.dp.sum(logged) / B
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        for comp in self.components:
            comp.after_step(it, batch)
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
            w = cfg.walk
            changed = walk_embeddings(
                self.params, self.optimizers, self.mesh, walk=w.enabled, mode=w.mode, max_crossings=w.max_crossings
            )
            walked = int(changed.sum())
            self.walked_total += walked
        self.dp.check_same("the number of Gaussians", num_gaussians(self.params))
        row = {"iteration": it, "loss": float(logged[0]), "psnr": float(logged[1])}
        row |= {"n_gaussians": num_gaussians(self.params), "walked": walked}
        row |= {"lr_duv": lrs.get("duv", 0.0), "lr_d": lrs.get("d", 0.0)}
        row |= {name: float(logged[k + 2]) for k, name in enumerate(LOGGED_PARTS)}
        if not self.perceptual_due:  # not computed this iteration: nan here, an empty cell in log.csv
            for name, weight in (("lpips", cfg.loss.lambda_lpips), ("dssim", cfg.loss.lambda_ssim)):
                if weight:
                    row[name] = math.nan
        row["scale"] /= self.extent  # relative to the mesh size (as optimised), so assets in cm and m compare
        return row


def train(config: TrainConfig, resume: bool = False) -> Path:
    """Train (or resume) the run described by ``config``; returns the run directory."""
    return Trainer(config, resume=resume).train()
