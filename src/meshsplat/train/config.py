"""Training configuration: the published method's settings, plus one section per training component.

``TrainConfig()`` is the published method (SplattingAvatar, CVPR 2024), and its defaults never move. Features
beyond the paper are components (``meshsplat.train.components``), each with its own section whose ``enabled``
is off by default; a recipe (``meshsplat.train.recipes``; ``quality`` is the default of ``meshsplat train``)
switches components on and sets a few values. ``config.json`` records the recipe's name and every key.

Configs a person writes are JSON or YAML, full or partial (``load_config``): keys a file does not set come from
its recipe. ``--set section.key=value`` strings apply on top (``apply_overrides``). Unknown keys are an error;
nothing is ever evaluated. Sizes marked "relative" are multiplied by the canonical mesh extent (half the
diagonal of its bounding box), so the same values work for a head in metres and a body in centimetres. Every
key, with its type, default, unit and meaning, is in docs/config.md.

The rule for changes (docs/config.md, "Changing the format"): a default never changes and a key never changes
its meaning. A new feature is a new component, off by default; a better recipe changes new runs only (a saved
``config.json`` holds every key); a key whose meaning must change gets a new name, and the old one is refused
naming the new. ``CONFIG_VERSION`` goes up only if a saved file would otherwise read differently, and then the
older version is upgraded next to this note.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from meshsplat.embedding import SCALE_MODES, WALK_MODES
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.compose import SH_FRAMES
from meshsplat.io.dataclass_dict import flat_items, from_dict, merged
from meshsplat.io.json_file import read_config_file
from meshsplat.metrics.lpips_net import LPIPS_PRECISIONS
from meshsplat.render import BACKENDS, BACKGROUNDS
from meshsplat.train.components import (
    AlbedoPriorConfig,
    MaskLossConfig,
    OffsetBoundConfig,
    PoseRefineConfig,
    ShadingConfig,
)
from meshsplat.train.strategy.default import DensifyStrategy

__all__ = [
    "ModelConfig",
    "OptimConfig",
    "LossConfig",
    "StrategyConfig",
    "WalkConfig",
    "TrainConfig",
    "apply_overrides",
    "load_config",
    "config_dict",
    "INIT_COLORS",
    "UV_LR_UNITS",
    "TRAIN_BACKGROUNDS",
    "CONFIG_FORMAT",
    "CONFIG_VERSION",
    "MAX_ITERATIONS",
    "MAX_GAUSSIANS",
]

INIT_COLORS = ("image", "grey")  # model.init_color
UV_LR_UNITS = ("world", "barycentric")  # optim.uv_lr_units
TRAIN_BACKGROUNDS = ("random", *BACKGROUNDS)  # background behind the Gaussians while training
CONFIG_FORMAT = "meshsplat-config"  # the "format" field of config.json
CONFIG_VERSION = 1
_PRE_RELEASE_FORMAT = "meshsplat-train-config"  # written before 0.1.0; its keys were reorganised
MAX_ITERATIONS = 10_000_000
MAX_GAUSSIANS = 20_000_000


@dataclass
class ModelConfig:
    """Gaussian model. Colour is SH: ``sh0`` is the DC term (colour = 0.5 + C0*sh0, as 3DGS)."""

    n_init: int = 10_000
    sh_degree: int = 0
    scale_mode: str = "sqrt_area"  # one of meshsplat.embedding.SCALE_MODES: pose scale modulation
    init_opacity: float = 0.1
    init_color: str = "image"  # INIT_COLORS: "image": colour from the training frames; "grey"
    # "image": the mean over this many training frames, spread over the sequence, of the pixel each point projects
    # to where it faces the camera inside the mask; 1: the first frame's colour (the paper)
    init_color_frames: int = 1
    init_knn: int = 3  # initial isotropic scale = mean distance to this many nearest neighbours
    freeze_embedding: bool = False  # ablation: (duv, d) not optimised, Gaussians stay at (face, uv, 0)
    sh_frame: str = "world"  # SH degree > 0: view direction in "world" (published code) or "triangle" frame
    antialiased: bool = False  # opacity x sqrt(det S / det(S + 0.3 I)) per view (gsplat's "antialiased" mode)


@dataclass
class OptimConfig:
    """Adam (one optimizer per parameter key) with the paper's learning rates."""

    lr_embedding: float = 1.6e-4  # relative: times extent for d; see uv_lr_units for duv
    lr_embedding_final: float = 1.6e-6
    lr_delay_mult: float = 0.01
    lr_delay_steps: int = 0  # 3DGS default: the delay multiplier acts only when this is > 0
    uv_lr_units: str = "world"  # "world": duv lr * extent / mean edge length; "barycentric": raw lr
    lr_color: float = 2.5e-3
    # None: lr_color is constant; a value: log-linear decay of the colour lrs (sh0, shN) from lr_color (times
    # lr_shN / lr_color for shN) to this at the last iteration, like the embedding's (no warm-up)
    lr_color_final: float | None = None
    lr_shN: float = 2.5e-3 / 20.0
    lr_opacity: float = 5e-2
    lr_scale: float = 5e-3
    lr_rotation: float = 1e-3
    eps: float = 1e-15


@dataclass
class LossConfig:
    """L1 + lambda_lpips * LPIPS + lambda_scale * L_scaling (+ optional MSE / SSIM terms)."""

    lambda_l1: float = 1.0
    lambda_lpips: float = 0.01
    lambda_scale: float = 1.0
    scale_max: float = 0.008  # relative: T_s (times extent = 0.004 x bbox diagonal, as losses.SCALE_THRESH_FRACTION)
    scale_ratio: float = 10.0  # T_r: thin when largest / smallest > this
    lambda_mse: float = 0.0
    lambda_ssim: float = 0.0
    # LPIPS and D-SSIM on the box around the subject (mask bbox union rendered-alpha bbox, plus crop_margin,
    # sides rounded up to multiples of 32 px), times its area share; L1/MSE stay full-frame
    crop_to_subject: bool = False
    crop_margin: float = 0.05  # crop_to_subject: margin on every side, a fraction of the image's larger side
    # LPIPS (and D-SSIM) only on iterations it % lpips_every == 0, weighted lpips_every x (the same mean weight)
    lpips_every: int = 1
    # LPIPS's backbone dtype: "float32", "bfloat16" (about 2x faster on CPUs with native bf16, emulated and slower
    # elsewhere) or "auto" (bfloat16 on a CPU with native bf16 instructions, else float32)
    lpips_precision: str = "float32"


# Densification hyperparameters are the fields of the Strategy itself (as gsplat's DefaultStrategy).
StrategyConfig = DensifyStrategy


@dataclass
class WalkConfig:
    """Walking on triangles (Algorithm 1). ``enabled=False``: clip (uv + duv) to the triangle."""

    enabled: bool = True
    every: int = 100
    mode: str = "paper"  # "paper" | "unfold"
    max_crossings: int = 64


@dataclass
class TrainConfig:
    """Everything a training run needs; ``TrainConfig()`` is the published method, ``recipe_config(name)``
    a recipe. Every key (type, default, unit, meaning, gsplat name) is in the table of docs/config.md."""

    recipe: str = "paper"  # the recipe this config started from (meshsplat.train.recipes); a label
    data: str = ""
    data_format: str = ""  # "" = detect; else a name from meshsplat.data.formats.FORMAT_NAMES
    model_dir: str = ""  # body/head model files (SMPL/FLAME); "" = $MESHSPLAT_MODEL_DIR
    drop_bad_frames: bool = False  # leave out the few frames failing the camera check (docs/real-captures.md)
    data_downscale: float = 1.0  # read the capture at 1/N of its size (meshsplat.data.downscale); eval reads it too
    data_gender: str = ""  # reader option: body model gender; "" = the capture's (PeopleSnapshot)
    data_shape: str = ""  # reader option: "per_split" | "train" betas for the test splits; "" = the layout's default
    out: str = "runs/train"
    iterations: int = 30_000
    batch_size: int = 1  # images per iteration (loss averaged over them, lrs times sqrt(batch_size))
    seed: int = 0
    device: str = "auto"  # "auto" = cuda when available
    backend: str = "auto"  # rasterizer backend, one of meshsplat.render.BACKENDS
    background: str = "random"  # "random" per iteration | "white" | "black"
    checkpoint_every: int = 5000
    checkpoint_every_s: float = 900.0  # also checkpoint when this many seconds passed since the last one
    keep_checkpoints: int = 3
    preview_every: int = 1000
    log_every: int = 10
    progress: bool = True
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    strategy: StrategyConfig = field(default_factory=StrategyConfig)
    walk: WalkConfig = field(default_factory=WalkConfig)
    # components (meshsplat.train.components): off by default
    shading: ShadingConfig = field(default_factory=ShadingConfig)
    albedo_prior: AlbedoPriorConfig = field(default_factory=AlbedoPriorConfig)
    mask_loss: MaskLossConfig = field(default_factory=MaskLossConfig)
    offset_bound: OffsetBoundConfig = field(default_factory=OffsetBoundConfig)
    pose_refine: PoseRefineConfig = field(default_factory=PoseRefineConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Any, base: TrainConfig | None = None) -> TrainConfig:
        """From a (full or partial) dict, format fields checked; keys it does not set come from ``base``
        (default ``TrainConfig()``)."""
        d = config_dict(d)
        if base is not None:
            d = merged(base.to_dict(), d)
        return from_dict(cls, d)

    def to_json(self, path: str | Path) -> None:
        """Write ``{"format": CONFIG_FORMAT, "version": CONFIG_VERSION, **to_dict()}`` (every key)."""
        doc = {"format": CONFIG_FORMAT, "version": CONFIG_VERSION, **self.to_dict()}
        Path(path).write_text(json.dumps(doc, indent=2) + "\n")

    def validate(self) -> TrainConfig:
        """``self``, or one MeshsplatError naming the first value out of its range."""
        for ok, msg in self._checks():
            if not ok:
                raise MeshsplatError(f"config: {msg}")
        for key, value in flat_items(self.to_dict()):
            if isinstance(value, float) and not math.isfinite(value):
                raise MeshsplatError(f"config: {key} is {value}; expected a finite number")
            last = key.rsplit(".", 1)[-1]
            if (
                isinstance(value, (int, float))
                and not isinstance(value, bool)
                and value < 0
                and last.startswith(_NON_NEGATIVE)
            ):
                raise MeshsplatError(f"config: {key} must be >= 0, got {value}")
        return self

    def _checks(self) -> list[tuple[bool, str]]:
        m, o, lo, st = self.model, self.optim, self.loss, self.strategy
        checks = [
            (self.iterations >= 1, "iterations must be >= 1"),
            (self.iterations <= MAX_ITERATIONS, f"iterations must be <= {MAX_ITERATIONS:,}"),
            (1 <= self.batch_size <= 4096, "batch_size (images per iteration) must be in 1..4096"),
            (self.data_downscale >= 1, "data_downscale must be >= 1 (2 halves width and height)"),
            (-(2**63) <= self.seed <= 2**63 - 3, f"seed must fit in 63 bits (|seed| < 9.2e18), got {self.seed}"),
            (self.background in TRAIN_BACKGROUNDS, f"background: {'|'.join(TRAIN_BACKGROUNDS)}"),
            (self.backend in BACKENDS, f"backend: {'|'.join(BACKENDS)}"),
            (self.checkpoint_every >= 1 and self.keep_checkpoints >= 1, "checkpoint_every/keep_checkpoints >= 1"),
            (self.checkpoint_every_s > 0, "checkpoint_every_s must be > 0"),
            (self.log_every >= 1 and self.preview_every >= 1, "log_every and preview_every must be >= 1"),
            (m.n_init >= 1, "model.n_init must be >= 1"),
            (
                m.n_init <= MAX_GAUSSIANS and st.max_gaussians <= MAX_GAUSSIANS,
                f"model.n_init and strategy.max_gaussians must be <= {MAX_GAUSSIANS:,}",
            ),
            (0 <= m.sh_degree <= 3, "model.sh_degree must be in 0..3"),
            (m.scale_mode in SCALE_MODES, f"model.scale_mode: {'|'.join(SCALE_MODES)}"),
            (m.init_color in INIT_COLORS, f"model.init_color: {'|'.join(INIT_COLORS)}"),
            (m.init_color_frames >= 1, "model.init_color_frames must be >= 1"),
            (m.sh_frame in SH_FRAMES, f"model.sh_frame: {'|'.join(SH_FRAMES)}"),
            (0 < m.init_opacity < 1, "model.init_opacity must be in (0, 1)"),
            (o.uv_lr_units in UV_LR_UNITS, f"optim.uv_lr_units: {'|'.join(UV_LR_UNITS)}"),
            (
                o.lr_color_final is None or (o.lr_color_final > 0 and o.lr_color > 0),
                "optim.lr_color_final must be > 0 (a log-linear decay from optim.lr_color, which must be > 0 too) "
                "or null (constant colour lr)",
            ),
            (0 <= lo.crop_margin <= 1, "loss.crop_margin must be in [0, 1] (a fraction of the image side)"),
            (lo.lpips_every >= 1, "loss.lpips_every must be >= 1 (1 = LPIPS on every iteration)"),
            (
                lo.lpips_precision in LPIPS_PRECISIONS,
                f"loss.lpips_precision must be one of {', '.join(LPIPS_PRECISIONS)}",
            ),
            (self.walk.mode in WALK_MODES, f"walk.mode: {'|'.join(WALK_MODES)}"),
            (self.walk.every >= 1, "walk.every must be >= 1"),
            (self.walk.max_crossings >= 1, "walk.max_crossings must be >= 1"),
            (st.refine_every >= 1, "strategy.refine_every must be >= 1"),
            (st.split_n >= 1, "strategy.split_n must be >= 1"),
            (st.max_gaussians >= 1, "strategy.max_gaussians must be >= 1"),
            (0 <= st.reset_opa < 1, "strategy.reset_opa must be in [0, 1)"),
            (0 <= st.prune_opa < 1, "strategy.prune_opa must be in [0, 1)"),
            (
                st.prune_scale2d <= 1,
                "strategy.prune_scale2d is a fraction of the image size (max(width, "
                f"height), as gsplat), got {st.prune_scale2d}: a pixel value? divide it by the image size",
            ),
        ]
        for section in (self.shading, self.albedo_prior, self.mask_loss, self.offset_bound, self.pose_refine):
            checks.extend(section.checks())
        return checks


# fields whose name starts with one of these are rates, weights, thresholds or sizes: never negative
_NON_NEGATIVE = (
    "lr",
    "lambda_",
    "scale_",
    "grow_",
    "prune_",
    "reset_",
    "refine_",
    "init_",
    "eps",
    "keep_",
    "max_",
    "n_init",
    "split_",
    "weight",
    "polish_",
)


def config_dict(d: Any) -> dict[str, Any]:
    """A config dict without its "format" / "version" fields, or one MeshsplatError for another file's format, a
    pre-release meshsplat's config or a newer one."""
    if not isinstance(d, dict):
        raise MeshsplatError(f"config: expected an object of sections and keys, got {type(d).__name__}")
    fmt = d.get("format", CONFIG_FORMAT)
    if fmt == _PRE_RELEASE_FORMAT:
        raise MeshsplatError(
            "config: written by a pre-release meshsplat (before 0.1.0), whose keys were reorganised into "
            "recipes and components; train a new run (docs/config.md lists today's keys)"
        )
    if fmt != CONFIG_FORMAT:
        raise MeshsplatError(f"config: format {fmt!r} is not a training config (expected {CONFIG_FORMAT!r})")
    version = d.get("version", CONFIG_VERSION)
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise MeshsplatError(f"config: version must be a positive integer, got {version!r}")
    if version > CONFIG_VERSION:
        raise MeshsplatError(
            f"config: format version {version} is newer than this meshsplat reads ({CONFIG_VERSION}); "
            "update meshsplat to use this config"
        )
    return {k: v for k, v in d.items() if k not in ("format", "version")}


def apply_overrides(cfg: TrainConfig, overrides: list[str] | tuple[str, ...] | None) -> TrainConfig:
    """Return a copy of ``cfg`` with ``section.key=value`` strings applied (values parsed by type)."""
    d = cfg.to_dict()
    for item in overrides or []:
        if "=" not in item:
            raise MeshsplatError(f"--set expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        parts = key.strip().split(".")
        node = d
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                raise MeshsplatError(f"config: unknown section {p!r} in {key!r} (docs/config.md)")
            node = node[p]
        if parts[-1] not in node or isinstance(node[parts[-1]], dict):
            raise MeshsplatError(f"config: unknown key {key!r} (docs/config.md)")
        node[parts[-1]] = value.strip()
    return TrainConfig.from_dict(d)


def load_config(path: str | Path, base: TrainConfig | None = None) -> TrainConfig:
    """Read a JSON or YAML config file (full or partial): keys it does not set come from ``base`` (default
    ``TrainConfig()``, the published method)."""
    return TrainConfig.from_dict(read_config_file(path), base)
