"""Train a mesh-embedded Gaussian avatar on a dataset (writes RUN/{config.json,checkpoints,log.csv,previews}).

Recipes (--recipe): quality (default: the published method plus the components shading, albedo_prior,
mask_loss, offset_bound and pose_refine) or paper (the published method); docs/config.md.
Configuration precedence: the recipe, then --config FILE (JSON or YAML, full or partial; or RUN/config.json
with --resume), then --set KEY=VALUE overrides, then flags. train prints what differs from the recipe. --set takes several pairs; put it after the dataset:
  meshsplat train DATA --out RUN --set strategy.refine_every=200 walk.enabled=false
A recipe named with --resume must be the run's (the resume check refuses another one).
--resume continues bit for bit from the newest checkpoint in RUN/checkpoints (on the run's torch thread
count: another one is noted, and --threads N keeps it); it refuses unreadable checkpoints and config
changes other than paths, device/backend, logging/checkpoint cadence and --iters. Ctrl-C or SIGTERM write a checkpoint before stopping; checkpoints are also written every
checkpoint_every_s seconds (default 900).
--nproc N trains with N processes (torch.distributed: gloo on CPU, NCCL on CUDA), each rendering its
share of every batch (needs --set batch_size=N or more); the same command also runs under torchrun.
docs/scale-out.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from meshsplat.cli._guards import check_memory, check_output_dir, check_range
from meshsplat.cli._options import (
    add_downscale_option,
    add_drop_bad_frames_option,
    add_reader_arguments,
    add_render_options,
    render_options,
)
from meshsplat.cli.threads import add_threads_argument, apply_threads
from meshsplat.data.formats import detect_format, format_module
from meshsplat.data.source_map import copy_source_map
from meshsplat.errors import MeshsplatError
from meshsplat.io.json_file import read_config_file
from meshsplat.run_folder import RunFolder, check_training_target
from meshsplat.train.budget import plan_budget
from meshsplat.train.config import TrainConfig, apply_overrides, config_dict, load_config
from meshsplat.train.launch import launch
from meshsplat.train.recipes import DEFAULT_RECIPE, RECIPES, recipe_config, recipe_differences, recipe_overrides
from meshsplat.train.trainer import Trainer

__all__ = ["add_arguments", "run", "build_config"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dataset",
        help="capture folder: native (docs/dataset-format.md) or PeopleSnapshot, "
        "IMavatar, INSTA, VHAP/GaussianAvatars, meshseq (your images + cameras + mesh sequence; "
        "docs/formats/); the layout is detected",
    )
    parser.add_argument(
        "--format",
        default=None,
        help="capture layout (default: detect); one of native, meshseq, peoplesnapshot, imavatar, insta, vhap",
    )
    parser.add_argument(
        "--model-dir",
        default=None,
        help="folder with your SMPL/SMPL-X/FLAME model files (default $MESHSPLAT_MODEL_DIR)",
    )
    add_reader_arguments(parser)
    add_drop_bad_frames_option(parser)
    refine = parser.add_mutually_exclusive_group()
    refine.add_argument(
        "--refine-pose",
        action="store_true",
        help="optimise the tracker's per-frame pose/expression parameters of the training frames; the default "
        "(pose_refine.enabled) already does when the capture has SMPL/SMPL-X/FLAME parameters and the model files "
        "are found; with this flag a capture without them is refused",
    )
    refine.add_argument(
        "--no-refine-pose", action="store_true", help="keep the tracker's poses (pose_refine.enabled=false)"
    )
    parser.add_argument("--out", required=True, help="run directory")
    add_downscale_option(parser, "1, or data_downscale of --config (stored in RUN/config.json; eval reads it)")
    schedule = parser.add_mutually_exclusive_group()
    schedule.add_argument("--iters", type=int, default=None, help="total iterations (default 30000)")
    schedule.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="a time budget: measures this machine on a few iterations, then scales the schedule (iterations, "
        "densification, checkpoints) to end within N minutes, and says what it chose; docs/config.md",
    )
    parser.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --out")
    parser.add_argument(
        "--recipe",
        choices=tuple(RECIPES),
        default=None,
        help=f"training recipe (default {DEFAULT_RECIPE}; paper: the published method); docs/config.md",
    )
    parser.add_argument(
        "--config",
        default=None,
        help="config file, JSON or YAML (.yaml/.yml), full or partial: its keys over the recipe "
        "(a file may name its recipe: recipe: paper)",
    )
    parser.add_argument(
        "--set",
        nargs="+",
        action=_SetAction,
        default=[],
        metavar="KEY=VALUE",
        help="override config values, e.g. --set strategy.refine_every=200 walk.enabled=false "
        "(several after one --set, or repeated; put --set after the dataset)",
    )
    add_render_options(parser, device=None, backend=False, background=False)
    parser.add_argument(
        "--seed", type=int, default=None, help="random seed (the config's seed key; same seed, same run)"
    )
    parser.add_argument(
        "--nproc",
        type=int,
        default=1,
        help="train with N local processes (data-parallel over each batch; set batch_size >= N); docs/scale-out.md",
    )
    add_threads_argument(parser)


class _SetAction(argparse.Action):
    """``--set KEY=VALUE [KEY=VALUE ...]``: extends the list; an item without "=" (a dataset swallowed
    after ``--set``) is one clear parser error."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> None:
        items = list(values) if isinstance(values, list) else [str(values)]
        for item in items:
            if "=" not in item:
                raise argparse.ArgumentError(
                    self,
                    f"expected KEY=VALUE, got {item!r}; --set takes every word up to "
                    "the next option, so put the dataset before --set "
                    "(meshsplat train DATA --out RUN --set a.b=1 c.d=2)",
                )
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), *items])


def build_config(args: argparse.Namespace) -> TrainConfig:
    """TrainConfig from the recipe, the config file, --set overrides and flags (in that order)."""
    out = Path(args.out)
    run = RunFolder(out)
    opts = render_options(args)
    config_file = args.config or (run.config_path if args.resume and run.config_path.is_file() else None)
    named = config_dict(read_config_file(config_file)).get("recipe") if config_file else None
    if args.config and args.recipe and named not in (None, args.recipe):
        raise MeshsplatError(f"--recipe {args.recipe} and {args.config} (recipe: {named}) differ; keep one")
    cfg = recipe_config(args.recipe or (str(named) if named is not None else DEFAULT_RECIPE))
    if config_file:
        cfg = load_config(config_file, base=cfg)
        if args.resume and args.recipe:  # compared with the checkpoint's config by the resume check
            cfg = apply_overrides(cfg, list(recipe_overrides(args.recipe)))
    cfg = apply_overrides(cfg, args.set)
    cfg.data = str(args.dataset)
    if args.format is not None:
        cfg.data_format = args.format
    if args.model_dir is not None:
        cfg.model_dir = str(args.model_dir)
    if args.gender is not None:
        cfg.data_gender = args.gender
    if args.shape is not None:
        cfg.data_shape = args.shape
    if args.refine_pose:
        cfg.pose_refine.enabled = cfg.pose_refine.required = True
    if args.no_refine_pose:
        cfg.pose_refine.enabled = False
    if args.drop_bad_frames:
        cfg.drop_bad_frames = True
    if args.downscale is not None:
        cfg.data_downscale = args.downscale
    cfg.out = str(out)
    if args.iters is not None:
        cfg.iterations = args.iters
    if opts.device is not None:
        cfg.device = opts.device
    if args.seed is not None:
        cfg.seed = args.seed
    if not opts.progress:
        cfg.progress = False
    return cfg.validate()


def recipe_summary(cfg: TrainConfig, shown: int = 6) -> str:
    """A few lines: the recipe and the keys this run sets otherwise (every key is in RUN/config.json)."""
    diffs = recipe_differences(cfg)
    head = f"recipe {cfg.recipe}" + (f", {len(diffs)} key(s) set otherwise:" if diffs else " as it is")
    more = (
        [f"  ... and {len(diffs) - shown} more (all keys: {RunFolder(cfg.out).config_path})"]
        if len(diffs) > shown
        else []
    )
    return "\n".join([head, *(f"  {d}" for d in diffs[:shown]), *more])


def run(args: argparse.Namespace) -> int:
    if not Path(args.dataset).exists():
        raise MeshsplatError(f"dataset not found: {args.dataset}")
    check_output_dir(args.out)
    check_training_target(args.out, args.dataset)  # a capture, a foreign folder or a run in training: refused
    check_range("--iters", args.iters, "train --iters")
    cfg = build_config(args)
    if not args.resume:
        print(recipe_summary(cfg))
    apply_threads(args)
    fmt = cfg.data_format or detect_format(cfg.data)
    print(f"{cfg.data}: {format_module(fmt).DESCRIPTION} ({fmt})" + ("" if cfg.data_format else ", detected"))
    cfg.data_format = fmt
    n = max(cfg.model.n_init, min(cfg.strategy.max_gaussians, 4 * cfg.model.n_init))
    check_memory(
        f"training with model.n_init={cfg.model.n_init}" + (f" in {args.nproc} processes" if args.nproc > 1 else ""),
        (2e8 + 1200.0 * n) * max(1, args.nproc),
        "lower model.n_init / strategy.max_gaussians",
    )
    if args.minutes is not None:
        check_range("--minutes", args.minutes, "train --minutes")
        if args.resume or args.nproc != 1:
            raise MeshsplatError(
                "--minutes plans a new run in one process; a resumed run keeps its schedule (give --iters to "
                "change it), and --nproc needs --iters"
            )
        cfg, budget = plan_budget(cfg, args.minutes)
        print(budget.summary())
    if args.nproc != 1:
        copy_source_map(cfg.data, cfg.out)
        print(f"training with {args.nproc} processes, batch_size {cfg.batch_size}")
        run_dir = launch(cfg, args.nproc, resume=args.resume)
        print(f"done: {run_dir}")
        print(f"held-out metrics (test frames, one background; docs/quality.md): meshsplat eval {run_dir}")
        return 0
    trainer = Trainer(cfg, resume=args.resume)
    try:
        return _train_and_report(trainer, cfg, args)
    finally:
        trainer.dp.close()  # under torchrun: leave the process group before exiting


def _train_and_report(trainer: Trainer, cfg: TrainConfig, args: argparse.Namespace) -> int:
    if not trainer.dp.is_main:  # under torchrun: rank 0 writes and reports
        trainer.train()
        return 0
    copy_source_map(cfg.data, cfg.out)  # the run alone can then be animated by the source asset
    if trainer.resumed_from is not None:
        print(f"resuming from {trainer.resumed_from} (iteration {trainer.iteration})")
        for note in trainer.resume_notes:
            print(
                f"  changed on resume: {note}"
                + (" (the learning-rate schedule follows the new total)" if note.startswith("iterations:") else "")
            )
    elif args.resume:
        print(f"no checkpoint in {RunFolder(cfg.out).checkpoint_dir}: starting a new run")
    if trainer.split_note:  # also with --no-progress: it says which frames are held out
        print(trainer.split_note)
    for note in trainer.notes:
        print(note)
    if trainer.iteration >= cfg.iterations and not trainer.finishing:
        print(f"already at iteration {trainer.iteration} >= {cfg.iterations}; nothing to do")
        return 0
    if cfg.data_downscale != 1:
        cam = trainer.dataset.frame_camera(trainer.train_ids[0])
        print(f"downscale {cfg.data_downscale:g}: training images {cam.width}x{cam.height}, K scaled to match")
    run_dir = trainer.train()
    summary = f"done: {run_dir} (iteration {trainer.iteration}, {trainer.num_gaussians} Gaussians)"
    if trainer.recent:
        summary += f"; {trainer.train_psnr_label} {trainer.recent_train_psnr:.2f} dB"
    print(summary)
    print(f"held-out metrics (test frames, one background; docs/quality.md): meshsplat eval {run_dir}")
    return 0
