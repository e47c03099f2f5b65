"""The training loop around ``Trainer.step``: the run folder's lock and files, logging, previews, checkpoints on
schedule and on SIGINT/SIGTERM, the progress bar, and the components' work after the last iteration."""

from __future__ import annotations

import signal
import sys
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from meshsplat._numba import numba_available
from meshsplat.data.dataset import AvatarDataset
from meshsplat.gaussians.avatar import AvatarRender
from meshsplat.io.checkpoint import remove_stray_tmp
from meshsplat.io.folder_lock import FolderLock
from meshsplat.io.images import float_to_uint8
from meshsplat.run_folder import RunFolder
from meshsplat.train.components import Component
from meshsplat.train.config import TrainConfig
from meshsplat.train.cpu_kernels import prepare_cpu_kernels, uses_cpu_kernels
from meshsplat.train.distributed import DataParallel
from meshsplat.train.frames import FrameCache
from meshsplat.train.monitor import PROGRESS_FORMAT, TensorBoardMonitor, learning_rates, progress_postfix
from meshsplat.train.resume import StopOnSignal, TrainingInterrupted, signal_name, write_identity
from meshsplat.train.run_log import RunLog

__all__ = ["TrainingLoop", "PROGRESS_WINDOW"]

NO_NUMBA_NOTE = (
    "note: numba is not available here (not installed, or MESHSPLAT_NO_NUMBA set), so training runs on the torch "
    "rasterizer, several times slower on a CPU: pip install numba"
)
PROGRESS_WINDOW = 10  # the progress bar's loss and PSNR: means over this many latest iterations


class TrainingLoop:
    """Mixed into ``Trainer`` (which sets these attributes and methods): ``train()`` and what it writes."""

    cfg: TrainConfig
    dp: DataParallel
    device: torch.device
    folder: RunFolder
    dataset: AvatarDataset
    frames: FrameCache
    components: list[Component]
    params: dict[str, torch.Tensor]
    optimizers: dict[str, Any]
    train_ids: list[int]
    iteration: int
    elapsed: float
    resumed_from: Path | None
    step: Callable[[], dict[str, float]]
    render_frame: Callable[[int, torch.Tensor], tuple[AvatarRender, torch.Tensor]]
    save_checkpoint: Callable[[], Path]

    def _loop_init(self) -> None:
        self.history: list[dict[str, float]] = []
        self.walked_total = 0  # embeddings that changed face (this session)
        self.recent: deque[tuple[float, float]] = deque(maxlen=PROGRESS_WINDOW)  # (loss, psnr) per iteration
        self.monitor: TensorBoardMonitor | None = None  # RUN/tensorboard/ while training (train.monitor)

    @property
    def num_gaussians(self) -> int:
        return int(self.params["face"].shape[0])

    @property
    def recent_train_psnr(self) -> float:
        """Mean PSNR of the latest ``PROGRESS_WINDOW`` iterations of this session (nan before the first)."""
        return sum(x[1] for x in self.recent) / len(self.recent) if self.recent else float("nan")

    @property
    def train_psnr_label(self) -> str:
        """What ``recent_train_psnr`` measures. Not ``meshsplat eval``'s numbers: each value is one training
        frame (not held out; pose-refined when refining) rendered with the parameters before that iteration's
        update, on that iteration's background, averaged over iterations."""
        bg = "random bg" if self.cfg.background == "random" else f"{self.cfg.background} bg"
        return f"train PSNR ({bg}, mean of last {PROGRESS_WINDOW} iters)"

    @property
    def finishing(self) -> bool:
        """Whether training is at its end with a component's work left (e.g. ``pose_refine.polish_steps``)."""
        return self.iteration >= self.cfg.iterations and any(c.finishing for c in self.components)

    def train(self, until: int | None = None) -> Path:
        """Train up to iteration ``until`` (default ``config.iterations``); returns the run dir."""
        end = self.cfg.iterations if until is None else min(int(until), self.cfg.iterations)
        main = self.dp.is_main  # the one process that writes the run folder
        lock = FolderLock(self.folder.lock_path, f"the run {self.folder.root}", parent_ok=True)
        if main:  # one training per run folder (the --nproc launcher holds it for its workers)
            lock.acquire()
        try:
            if main:
                self.folder.root.mkdir(parents=True, exist_ok=True)
                self.cfg.to_json(self.folder.config_path)
                write_identity(self.folder, self.cfg.to_dict(), self.dataset, self.resumed_from is not None)
                RunLog(self.folder.log_path).open(self.iteration)
                remove_stray_tmp(self.folder.checkpoint_dir)
                self.monitor = TensorBoardMonitor.open(self.folder.root, self.iteration)
            return self._train(end, main)
        finally:
            if self.monitor is not None:
                self.monitor.close()
                self.monitor = None
            lock.release()

    def _progress_bar(self, end: int):
        from tqdm import tqdm

        print(f"progress: loss, {self.train_psnr_label}, Gaussians (G)", file=sys.stderr)
        if self.monitor is not None:
            print(f"watch it live: tensorboard --logdir {self.monitor.log_dir}", file=sys.stderr)
        return tqdm(total=end, initial=self.iteration, desc="train", dynamic_ncols=True, bar_format=PROGRESS_FORMAT)

    def _train(self, end: int, main: bool) -> Path:
        cfg = self.cfg
        cpu_auto = uses_cpu_kernels(self.device, cfg.backend)
        if main and self.iteration < end and cpu_auto and not numba_available():
            print(NO_NUMBA_NOTE, file=sys.stderr)
        if self.iteration < end and cpu_auto and numba_available() and self.dp.world == 1:  # (--nproc: its launcher)
            prepare_cpu_kernels(torch.get_num_threads(), cfg.progress)
        bar = self._progress_bar(end) if cfg.progress else None
        t0 = time.perf_counter() - self.elapsed
        last_ckpt = time.perf_counter()
        ckpt: Path | None = None
        try:
            with StopOnSignal() as stop:
                while self.iteration < end:
                    row = self.step()
                    it = self.iteration
                    self.elapsed = row["time_s"] = time.perf_counter() - t0
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
                if self.finishing:
                    self._finish(bar, stop, ckpt)
                    if main:
                        ckpt = self.save_checkpoint()
        finally:
            if bar is not None:
                bar.close()
        return self.folder.root

    def _finish(self, bar, stop: StopOnSignal, ckpt: Path | None) -> None:
        """The components' work after the last iteration (the avatar frozen), stoppable between steps."""

        def check_stop() -> None:  # one process decides alone: no vote between steps
            if stop.signum is not None and not self.dp.active:
                raise TrainingInterrupted(
                    f"stopped by {signal_name(stop.signum)} while fitting the training poses after iteration "
                    f"{self.iteration}; the checkpoint of that iteration is intact: continue with --resume",
                    stop.signum,
                    ckpt,
                )

        for comp in self.components:
            if comp.finishing:
                if bar is not None:
                    bar.set_postfix_str(f"{comp.name}: finishing, the avatar frozen")
                comp.finish(self.training_error, check_stop)

    def training_error(self, idx: int) -> torch.Tensor:
        """The L1 error of training frame ``idx`` rendered now (on white; frames without a mask on black)."""
        white, black = torch.ones(3, device=self.device), torch.zeros(3, device=self.device)
        out, gt = self.render_frame(idx, white if self.frames.frame(idx)[1] is not None else black)
        return (out.image - gt).abs().mean()

    def _log(self, row: dict[str, float]) -> None:
        self.history.append(row)
        RunLog(self.folder.log_path).append(row)
        if self.monitor is not None:
            self.monitor.scalars(row, learning_rates(self.optimizers))

    @torch.no_grad()
    def save_preview(self, idx: int | None = None) -> Path:
        from PIL import Image

        idx = self.train_ids[0] if idx is None else idx
        out, gt = self.render_frame(idx, torch.ones(3, device=self.device))
        img = float_to_uint8(torch.cat([out.image.clamp(0, 1), gt], dim=1))
        path = self.folder.preview_path(self.iteration)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(path)
        if self.monitor is not None:
            self.monitor.preview(img, self.iteration)
        return path
