"""Training configuration: one dataclass per component, composed in ``TrainConfig``.

Configs round-trip through plain JSON dicts (``to_dict`` / ``from_dict``; unknown keys are an
error, nothing is ever evaluated) and accept command-line overrides such as
``strategy.refine_every=200`` or ``walk.enabled=false`` (``apply_overrides``).

Sizes marked "relative" are multiplied by the canonical mesh extent (half the diagonal of its
bounding box) so that the same defaults work for a head in metres and a body in centimetres.
Every key, with its type, default, unit and meaning, is in docs/config.md. The defaults are the
``quality`` preset; ``meshsplat.train.presets`` also has ``paper``, the published method.

``config.json`` carries ``{"format": CONFIG_FORMAT, "version": CONFIG_VERSION}`` beside the keys.
A version-2 dict was written before ``loss.crop_to_subject`` was on by default (``VERSION_2_DEFAULTS``),
a version-3 dict before ``loss.lpips_every`` was 2 (``VERSION_3_DEFAULTS``), a version-4 dict before
``model.occlusion`` was ``key`` (``VERSION_4_DEFAULTS``), a version-5 dict before ``pose_refine.auto``
was on (``VERSION_5_DEFAULTS``), a version-6 dict before ``optim.lr_shading`` was 5e-2 (``VERSION_6_DEFAULTS``),
a version-7 dict before ``model.occlusion_key_soft`` was 8 (``VERSION_7_DEFAULTS``), a version-8 dict before
``model.occlusion_grid`` was 96 and ``model.occlusion_key_soft`` 12 (``VERSION_8_DEFAULTS``), a version-9 dict
before ``loss.lambda_albedo`` was 0.1 (``VERSION_9_DEFAULTS``), a version-10 dict before ``loss.albedo_reach`` was 64
(``VERSION_10_DEFAULTS``), a version-11 dict before ``strategy.grow_grad2d`` was 1e-4 (``VERSION_11_DEFAULTS``).
A dict without a version is version 1, written by an older meshsplat: when the defaults were the
paper's (``VERSION_1_DEFAULTS``), with the strategy keys ``refine_start`` / ``refine_stop`` (now
gsplat's ``refine_start_iter`` / ``refine_stop_iter``) and ``prune_scale2d`` in pixels (now a
fraction of the image size): ``upgrade_config_dict`` reads it as it was written (see there).
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from meshsplat.embedding import SCALE_MODES, WALK_MODES
from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.compose import SH_FRAMES
from meshsplat.gaussians.shading import OCCLUSION_MODES, SHADING_MODES, SHADING_NORMALS, SPECULAR_MODES
from meshsplat.io.json_file import read_json_object
from meshsplat.render import BACKENDS, BACKGROUNDS
from meshsplat.train.albedo_prior import MAX_REACH, NEIGHBOURS
from meshsplat.train.strategy.default import DensifyStrategy

__all__ = [
    "ModelConfig",
    "OptimConfig",
    "LossConfig",
    "StrategyConfig",
    "WalkConfig",
    "PoseRefineConfig",
    "TrainConfig",
    "apply_overrides",
    "load_config",
    "upgrade_config_dict",
    "is_legacy_config",
    "RENAMED_KEYS",
    "INIT_COLORS",
    "UV_LR_UNITS",
    "TRAIN_BACKGROUNDS",
    "CONFIG_FORMAT",
    "CONFIG_VERSION",
    "VERSION_1_DEFAULTS",
    "VERSION_2_DEFAULTS",
    "VERSION_3_DEFAULTS",
    "VERSION_4_DEFAULTS",
    "VERSION_5_DEFAULTS",
    "VERSION_6_DEFAULTS",
    "VERSION_7_DEFAULTS",
    "VERSION_8_DEFAULTS",
    "VERSION_9_DEFAULTS",
    "VERSION_10_DEFAULTS",
    "VERSION_11_DEFAULTS",
    "config_version",
]

INIT_COLORS = ("image", "grey")  # model.init_color
UV_LR_UNITS = ("world", "barycentric")  # optim.uv_lr_units
TRAIN_BACKGROUNDS = ("random", *BACKGROUNDS)  # background behind the Gaussians while training
# keys renamed to gsplat's DefaultStrategy names (old name -> new name)
RENAMED_KEYS = {
    "strategy.refine_start": "strategy.refine_start_iter",
    "strategy.refine_stop": "strategy.refine_stop_iter",
}
CONFIG_FORMAT = "meshsplat-train-config"  # the "format" field of config.json
# 1: no "format"/"version" fields (older meshsplat; defaults were the paper's). 2: the quality defaults.
# 3: loss.crop_to_subject on by default (docs/quality.md, "Losses where the subject is").
# 4: loss.lpips_every 2 by default (docs/rendering.md, "Training on CPU").
# 5: model.occlusion key by default (docs/quality.md, "A key light found in training").
# 6: pose_refine.auto on by default (docs/real-captures.md, "Pose refinement").
# 7: optim.lr_shading 5e-2 by default (docs/quality.md, "The lighting's learning rate").
# 8: model.occlusion_key_soft 8 by default (docs/quality.md, "Soft key shadows").
# 9: model.occlusion_grid 96 and model.occlusion_key_soft 12 by default (docs/quality.md, "Finer key shadow maps").
# 10: loss.lambda_albedo 0.1 by default (docs/quality.md, "An albedo prior").
# 11: loss.albedo_reach 64 by default (docs/quality.md, "The albedo prior's reach").
# 12: strategy.grow_grad2d 1e-4 by default (docs/quality.md, "More Gaussians: a lower densification threshold").
# 13: loss.lambda_mask 0.1 by default (docs/quality.md, "The silhouette in the loss").
# 14: model.max_offset 0.15 by default (docs/quality.md, "Gaussians kept near their triangle").
CONFIG_VERSION = 14
# Keys whose default changed since version 1, with their version-1 value: a version-1 dict that does not
# set one of them meant this value (frozen history: never edit; the `paper` preset sets the same values).
VERSION_1_DEFAULTS = {"model.shading": "none", "model.init_color_frames": 1, "optim.lr_color": 2.5e-3}
# Keys whose default changed since version 2, with their version-2 value (a version-1 dict gets them too).
VERSION_2_DEFAULTS = {"loss.crop_to_subject": False}
# Keys whose default changed since version 3, with their version-3 value (older dicts get them too).
VERSION_3_DEFAULTS = {"loss.lpips_every": 1}
# Keys whose default changed since version 4, with their version-4 value (older dicts get them too).
VERSION_4_DEFAULTS = {"model.occlusion": "none"}
# Keys whose default changed since version 5, with their version-5 value (older dicts get them too).
VERSION_5_DEFAULTS = {"pose_refine.auto": False}
# Keys whose default changed since version 6, with their version-6 value (older dicts get them too).
VERSION_6_DEFAULTS = {"optim.lr_shading": 5e-3}
# Keys whose default changed since version 7, with their version-7 value (older dicts get them too).
VERSION_7_DEFAULTS = {"model.occlusion_key_soft": 0.0}
# Keys whose default changed since version 8, with their version-8 value (older dicts get them too).
VERSION_8_DEFAULTS = {"model.occlusion_grid": 64, "model.occlusion_key_soft": 8.0}
# Keys whose default changed since version 9, with their version-9 value (older dicts get them too).
VERSION_9_DEFAULTS = {"loss.lambda_albedo": 0.0}
# Keys whose default changed since version 10, with their version-10 value (older dicts get them too).
VERSION_10_DEFAULTS = {"loss.albedo_reach": 8}
# Keys whose default changed since version 11, with their version-11 value (older dicts get them too).
VERSION_11_DEFAULTS = {"strategy.grow_grad2d": 2e-4}
# Keys whose default changed since version 12, with their version-12 value (older dicts get them too).
VERSION_12_DEFAULTS = {"loss.lambda_mask": 0.0}
# Keys whose default changed since version 13, with their version-13 value (older dicts get them too).
VERSION_13_DEFAULTS = {"model.max_offset": 0.0}
# One table per version before today's (tests/test_train_presets.py checks the count).
_VERSION_DEFAULTS: tuple[dict[str, Any], ...] = (
    VERSION_1_DEFAULTS,
    VERSION_2_DEFAULTS,
    VERSION_3_DEFAULTS,
    VERSION_4_DEFAULTS,
    VERSION_5_DEFAULTS,
    VERSION_6_DEFAULTS,
    VERSION_7_DEFAULTS,
    VERSION_8_DEFAULTS,
    VERSION_9_DEFAULTS,
    VERSION_10_DEFAULTS,
    VERSION_11_DEFAULTS,
    VERSION_12_DEFAULTS,
    VERSION_13_DEFAULTS,
)


@dataclass
class ModelConfig:
    """Gaussian model. Colour is SH: ``sh0`` is the DC term (colour = 0.5 + C0*sh0, as 3DGS)."""

    n_init: int = 10_000
    sh_degree: int = 0
    scale_mode: str = "sqrt_area"  # one of meshsplat.embedding.SCALE_MODES: pose scale modulation
    init_opacity: float = 0.1
    init_color: str = "image"  # INIT_COLORS: "image": colour from the first training frame; "grey"
    init_knn: int = 3  # initial isotropic scale = mean distance to this many nearest neighbours
    freeze_embedding: bool = False  # ablation: (duv, d) not optimised, Gaussians stay at (face, uv, 0)
    # relative: |d| (the offset along the normal) kept <= this x extent after every step; 0: unbounded (the paper;
    # before config version 14)
    max_offset: float = 0.15
    # Colour initialisation from several frames ("image" only): average over this many training frames,
    # spread over the sequence, of the pixel each point projects to where it faces the camera inside the mask.
    # The paper's: 1 (the first frame's colour; the `paper` preset).
    init_color_frames: int = 8
    # Pose-dependent shading (meshsplat.gaussians.shading): "none" (paper: one colour per Gaussian) or "sh2":
    # the SH colour is an albedo, times a learned 2nd-order SH irradiance of the Gaussian's posed normal.
    shading: str = "sh2"
    shading_normal: str = "phong"  # "phong": the embedding's interpolated normal | "axis": shortest Gaussian axis
    sh_frame: str = "world"  # SH degree > 0: view direction in "world" (published code) or "triangle" frame
    antialiased: bool = False  # opacity x sqrt(det S / det(S + 0.3 I)) per view (gsplat's "antialiased" mode)
    # Shadows from the posed driving mesh (needs shading != "none"): "none" | "directions": learned lights from
    # occlusion_directions fixed directions, each Gaussian's visibility on an occlusion_grid^2 depth grid per direction.
    # "key": the same directions, then one key light found among them in stages of occlusion_key_iter iterations
    # (shading.align_key: its direction the intensity²-weighted mean near the strongest, narrowed by rings of
    # candidates), the rest folded into the SH2 irradiance; one key light from 3 x occlusion_key_iter on.
    occlusion: str = "key"
    occlusion_directions: int = 16
    occlusion_grid: int = 96  # cells per side of each shadow map (64 before config version 9)
    occlusion_key_iter: int = 300
    # "key": the light's angular radius (degrees): once aligned, its shadow is the mean of 12 shadow maps over that
    # disk (an area light's soft shadow); 0: one map (hard). Unused by the other occlusion modes.
    occlusion_key_soft: float = 12.0  # 8 in config version 8
    # Added light (needs shading != "none"): "none" | "sh2": colour = albedo * E(n) + SH9(n) . specular, a learned
    # [9,3] added, not albedo-multiplied (a glossy highlight on a coloured surface); zero at the start.
    specular: str = "none"


@dataclass
class OptimConfig:
    """Adam (one optimizer per parameter key) with the paper's learning rates, except ``lr_color``
    (the paper's 2.5e-3 in the ``paper`` preset)."""

    lr_embedding: float = 1.6e-4  # relative: times extent for d; see uv_lr_units for duv
    lr_embedding_final: float = 1.6e-6
    lr_delay_mult: float = 0.01
    lr_delay_steps: int = 0  # 3DGS default: the delay multiplier acts only when this is > 0
    uv_lr_units: str = "world"  # "world": duv lr * extent / mean edge length; "barycentric": raw lr
    lr_color: float = 1e-2
    # None: lr_color is constant; a value: log-linear decay of the colour lrs (sh0, shN) from lr_color (times
    # lr_shN / lr_color for shN) to this at the last iteration, like the embedding's (no warm-up)
    lr_color_final: float | None = None
    lr_shN: float = 2.5e-3 / 20.0
    lr_opacity: float = 5e-2
    lr_scale: float = 5e-3
    lr_rotation: float = 1e-3
    lr_shading: float = 5e-2  # the illumination coefficients (model.shading != "none")
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
    # L1 between the rendered alpha and the ground-truth mask (frames with masks). 0: off (the paper; before
    # config version 13)
    lambda_mask: float = 0.1
    # LPIPS and D-SSIM on the box around the subject (mask bbox union rendered-alpha bbox, plus crop_margin,
    # sides rounded up to multiples of 32 px), times its area share; L1/MSE stay full-frame. The paper (preset): false.
    crop_to_subject: bool = True
    crop_margin: float = 0.05  # crop_to_subject: margin on every side, a fraction of the image's larger side
    # LPIPS (and D-SSIM) only on iterations it % lpips_every == 0, weighted lpips_every x (the same mean weight);
    # the other iterations skip the perceptual net (L1/MSE/scale/mask every iteration). The paper (preset): 1.
    lpips_every: int = 2
    # Shaded avatars: weight of the albedo prior (meshsplat.train.albedo_prior): nearby Gaussians of one hue share
    # one albedo, so the light moves out of the albedo into the lighting. 0: off (the paper; before config version 10).
    lambda_albedo: float = 0.1
    # The albedo prior's neighbours: each Gaussian's 8 nearest, and with a reach above 8 another 8 spread evenly by
    # rank over its `albedo_reach` nearest (meshsplat.train.albedo_prior). 8: the nearest only (config version 10).
    albedo_reach: int = 64


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
class PoseRefineConfig:
    """Per-frame refinement of the tracker's body/head model parameters (training frames only).

    Each training frame's parameters named in ``params`` (those the dataset's model has) get a
    trainable offset, starting at zero, optimised with Adam at ``lr`` (radians for poses, model
    units for translation and expression). Test frames keep the tracker's parameters.
    """

    enabled: bool = False  # refine; a capture without body/head-model parameters is refused
    # refine when the capture's meshes come from SMPL/SMPL-X/FLAME parameters and the model files are found
    # (else train without, saying why); the paper (preset): false
    auto: bool = True
    lr: float = 3e-4  # bench/pose_refine.py: 3e-4 best of 3e-4, 1e-3, 5e-3 (diverges) at the demo budget
    params: str = "global_orient,body_pose,transl,neck_pose,jaw_pose,expression"
    # weight of a pull of each offset towards zero (its gradient gains prior * offset): keeps a pose where its
    # images say nothing (e.g. depth in a monocular capture); 0: none (bench/reports/pose_refine.md)
    prior: float = 0.0
    # after the last iteration: this many Adam steps on the refined poses alone, the avatar frozen, on the
    # training images (docs/quality.md, "the training poses, fitted the same way after training"); 0: none
    polish_steps: int = 0
    polish_lr: float = 1e-3


@dataclass
class TrainConfig:
    """Everything a training run needs; ``TrainConfig()`` is the ``quality`` preset
    (``meshsplat.train.presets``). Every key (type, default, unit, meaning, gsplat name) is
    in the table of docs/config.md (tests/test_config_doc.py keeps it complete)."""

    data: str = ""
    data_format: str = ""  # "" = detect; else a name from meshsplat.data.formats.FORMAT_NAMES
    model_dir: str = ""  # body/head model files (SMPL/FLAME); "" = $MESHSPLAT_MODEL_DIR
    drop_bad_frames: bool = False  # leave out the few frames failing the camera check (docs/real-captures.md)
    data_downscale: float = 1.0  # read the capture at 1/N of its size (meshsplat.data.downscale); eval reads it too
    data_gender: str = ""  # reader option: body model gender; "" = the capture's (PeopleSnapshot)
    data_shape: str = ""  # reader option: "per_split" | "train" betas for the test splits; "" = the layout's default
    out: str = "runs/train"
    iterations: int = 30_000
    # images per iteration (loss averaged over them, lrs times sqrt(batch_size)); docs/config.md "Batches"
    batch_size: int = 1
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
    pose_refine: PoseRefineConfig = field(default_factory=PoseRefineConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(
        cls,
        d: dict[str, Any],
        image_size: int | typing.Callable[[], int] | None = None,
        base: TrainConfig | None = None,
    ) -> TrainConfig:
        """From a (full or partial) dict, upgraded first (``upgrade_config_dict``: a dict without a
        "version" is read as version 1, where unset keys meant the paper's values); keys it does not
        set come from ``base`` (default ``TrainConfig()``, the quality preset)."""
        upgraded = upgrade_config_dict(d, image_size)
        if base is not None and isinstance(upgraded, dict):
            upgraded = _merged(base.to_dict(), upgraded)
        return _from_dict(cls, upgraded, "")

    def to_json(self, path: str | Path) -> None:
        """Write ``{"format": CONFIG_FORMAT, "version": CONFIG_VERSION, **to_dict()}`` (every key)."""
        doc = {"format": CONFIG_FORMAT, "version": CONFIG_VERSION, **self.to_dict()}
        Path(path).write_text(json.dumps(doc, indent=2) + "\n")

    def validate(self) -> TrainConfig:
        checks = [
            (self.iterations >= 1, "iterations must be >= 1"),
            (1 <= self.batch_size <= 4096, "batch_size (images per iteration) must be in 1..4096"),
            (self.data_downscale >= 1, "data_downscale must be >= 1 (2 halves width and height)"),
            (self.model.n_init >= 1, "model.n_init must be >= 1"),
            (0 <= self.model.sh_degree <= 3, "model.sh_degree must be in 0..3"),
            (self.model.scale_mode in SCALE_MODES, f"model.scale_mode: {'|'.join(SCALE_MODES)}"),
            (self.model.init_color in INIT_COLORS, f"model.init_color: {'|'.join(INIT_COLORS)}"),
            (self.model.init_color_frames >= 1, "model.init_color_frames must be >= 1"),
            (self.model.max_offset >= 0, "model.max_offset must be >= 0 (0: unbounded)"),
            (self.model.shading in SHADING_MODES, f"model.shading: {'|'.join(SHADING_MODES)}"),
            (self.model.shading_normal in SHADING_NORMALS, f"model.shading_normal: {'|'.join(SHADING_NORMALS)}"),
            (self.model.sh_frame in SH_FRAMES, f"model.sh_frame: {'|'.join(SH_FRAMES)}"),
            (self.model.occlusion in OCCLUSION_MODES, f"model.occlusion: {'|'.join(OCCLUSION_MODES)}"),
            (
                self.model.occlusion == "none" or self.model.shading != "none",
                "model.occlusion needs model.shading (the shadowed lights add to its irradiance)",
            ),
            (self.model.specular in SPECULAR_MODES, f"model.specular: {'|'.join(SPECULAR_MODES)}"),
            (
                self.model.specular == "none" or self.model.shading != "none",
                "model.specular needs model.shading (the added light is a term of the shaded colour)",
            ),
            (1 <= self.model.occlusion_directions <= 256, "model.occlusion_directions must be in 1..256"),
            (8 <= self.model.occlusion_grid <= 1024, "model.occlusion_grid must be in 8..1024"),
            (self.model.occlusion_key_iter >= 1, "model.occlusion_key_iter must be >= 1"),
            (0.0 <= self.model.occlusion_key_soft <= 45.0, "model.occlusion_key_soft must be in 0..45 (degrees)"),
            (self.optim.lr_shading > 0, "optim.lr_shading must be > 0"),
            (
                self.optim.lr_color_final is None or (self.optim.lr_color_final > 0 and self.optim.lr_color > 0),
                "optim.lr_color_final must be > 0 (a log-linear decay from optim.lr_color, which must be > 0 too) "
                "or null (constant colour lr)",
            ),
            (self.loss.lambda_mask >= 0, "loss.lambda_mask must be >= 0"),
            (self.loss.lambda_albedo >= 0, "loss.lambda_albedo must be >= 0"),
            (
                NEIGHBOURS <= self.loss.albedo_reach <= MAX_REACH,
                f"loss.albedo_reach must be in {NEIGHBOURS}..{MAX_REACH}",
            ),
            (0 <= self.loss.crop_margin <= 1, "loss.crop_margin must be in [0, 1] (a fraction of the image side)"),
            (self.loss.lpips_every >= 1, "loss.lpips_every must be >= 1 (1 = LPIPS on every iteration)"),
            (0 < self.model.init_opacity < 1, "model.init_opacity must be in (0, 1)"),
            (self.optim.uv_lr_units in UV_LR_UNITS, f"optim.uv_lr_units: {'|'.join(UV_LR_UNITS)}"),
            (self.background in TRAIN_BACKGROUNDS, f"background: {'|'.join(TRAIN_BACKGROUNDS)}"),
            (self.backend in BACKENDS, f"backend: {'|'.join(BACKENDS)}"),
            (self.walk.mode in WALK_MODES, f"walk.mode: {'|'.join(WALK_MODES)}"),
            (self.walk.every >= 1, "walk.every must be >= 1"),
            (self.strategy.refine_every >= 1, "strategy.refine_every must be >= 1"),
            (self.strategy.split_n >= 1, "strategy.split_n must be >= 1"),
            (self.checkpoint_every >= 1 and self.keep_checkpoints >= 1, "checkpoint_every/keep_checkpoints >= 1"),
            (self.pose_refine.lr > 0, "pose_refine.lr must be > 0"),
            (self.pose_refine.prior >= 0, "pose_refine.prior must be >= 0"),
            (0 <= self.pose_refine.polish_steps <= 100_000, "pose_refine.polish_steps must be in [0, 100000]"),
            (self.pose_refine.polish_lr > 0, "pose_refine.polish_lr must be > 0"),
            (self.checkpoint_every_s > 0, "checkpoint_every_s must be > 0"),
            (self.log_every >= 1 and self.preview_every >= 1, "log_every and preview_every must be >= 1"),
            (self.walk.max_crossings >= 1, "walk.max_crossings must be >= 1"),
            (self.strategy.max_gaussians >= 1, "strategy.max_gaussians must be >= 1"),
            (0 <= self.strategy.reset_opa < 1, "strategy.reset_opa must be in [0, 1)"),
            (0 <= self.strategy.prune_opa < 1, "strategy.prune_opa must be in [0, 1)"),
            (
                self.strategy.prune_scale2d <= 1,
                "strategy.prune_scale2d is a fraction of the image size (max(width, "
                f"height), as gsplat), got {self.strategy.prune_scale2d}: a pixel value? divide it by the image size",
            ),
            (self.iterations <= MAX_ITERATIONS, f"iterations must be <= {MAX_ITERATIONS:,}"),
            (-(2**63) <= self.seed <= 2**63 - 3, f"seed must fit in 63 bits (|seed| < 9.2e18), got {self.seed}"),
            (
                self.model.n_init <= MAX_GAUSSIANS and self.strategy.max_gaussians <= MAX_GAUSSIANS,
                f"model.n_init and strategy.max_gaussians must be <= {MAX_GAUSSIANS:,}",
            ),
        ]
        for ok, msg in checks:
            if not ok:
                raise MeshsplatError(f"config: {msg}")
        for key, value in _flat_items(self.to_dict()):
            if isinstance(value, float) and not math.isfinite(value):
                raise MeshsplatError(f"config: {key} is {value}; expected a finite number")
            if (
                isinstance(value, (int, float))
                and not isinstance(value, bool)
                and value < 0
                and key.rsplit(".", 1)[-1].startswith(_NON_NEGATIVE)
            ):
                raise MeshsplatError(f"config: {key} must be >= 0, got {value}")
        return self


MAX_ITERATIONS = 10_000_000
MAX_GAUSSIANS = 20_000_000
# fields whose name starts with one of these are rates, weights, thresholds or sizes: never negative
_NON_NEGATIVE = (
    "lr_",
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
)


def _merged(base: dict, over: dict) -> dict:
    """``base`` with the keys of ``over`` set in it (nested dicts merged key by key)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _flat_items(d: dict, prefix: str = ""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flat_items(v, f"{prefix}{k}.")
        else:
            yield prefix + k, v


def _from_dict(cls, d: Any, prefix: str):
    if not isinstance(d, dict):
        raise MeshsplatError(f"config: {prefix or 'root'} must be an object, got {type(d).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise MeshsplatError(f"config: unknown key(s) {', '.join(prefix + k for k in unknown)}")
    kwargs = {}
    for name, value in d.items():
        tp = hints[name]
        if dataclasses.is_dataclass(tp):
            kwargs[name] = _from_dict(tp, value, f"{prefix}{name}.")
        else:
            kwargs[name] = _coerce(value, tp, prefix + name)
    return cls(**kwargs)


def _coerce(value: Any, tp: Any, key: str):
    args = typing.get_args(tp)
    if len(args) == 2 and type(None) in args:  # Optional[X]: None, "none" or "null" (JSON / --set), else an X
        if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null")):
            return None
        tp = next(a for a in args if a is not type(None))
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return value.lower() in ("true", "1", "yes", "on")
        raise MeshsplatError(f"config: {key} expects true/false, got {value!r}")
    try:
        if tp is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            if isinstance(value, bool):
                raise ValueError
            if isinstance(value, str) and "e" in value.lower():  # 3e4 is a whole number; 2.5e0 and 1e999 are not
                f = float(value)
                if not math.isfinite(f) or not f.is_integer():
                    raise ValueError
                return int(f)
            return int(value)
        if tp is float:
            if isinstance(value, bool):
                raise ValueError
            f = float(value)
            if not math.isfinite(f):
                raise MeshsplatError(f"config: {key} is {value!r}; expected a finite number")
            return f
        if tp is str:
            return str(value)
    except MeshsplatError:
        raise
    except (TypeError, ValueError, OverflowError):
        raise MeshsplatError(f"config: {key} expects {tp.__name__}, got {value!r}") from None
    return value


def apply_overrides(cfg: TrainConfig, overrides: list[str] | None) -> TrainConfig:
    """Return a copy of ``cfg`` with ``section.key=value`` strings applied (values parsed by type)."""
    d = cfg.to_dict()
    for item in overrides or []:
        if "=" not in item:
            raise MeshsplatError(f"--set expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        if key.strip() in RENAMED_KEYS:
            raise MeshsplatError(f"config: {key.strip()} was renamed to {RENAMED_KEYS[key.strip()]} (gsplat's name)")
        parts = key.strip().split(".")
        node = d
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                raise MeshsplatError(f"config: unknown section {p!r} in {key!r}")
            node = node[p]
        if parts[-1] not in node or isinstance(node[parts[-1]], dict):
            raise MeshsplatError(f"config: unknown key {key!r}")
        node[parts[-1]] = value.strip()
    return TrainConfig.from_dict(d)


def load_config(
    path: str | Path, image_size: int | typing.Callable[[], int] | None = None, base: TrainConfig | None = None
) -> TrainConfig:
    """Read a JSON config file (a full or partial ``TrainConfig`` dict) as it was written: keys a
    versioned file does not set come from ``base`` (default ``TrainConfig()``); a file without a
    version is an older meshsplat's (see ``upgrade_config_dict``). ``image_size``: see there (needed
    only for some configs written by older versions)."""
    d = read_json_object(path, "a training config (a JSON object)")
    return TrainConfig.from_dict(d, image_size, base)


def _legacy_prune_can_act(st: dict) -> bool:
    """Whether an old strategy section ever reached the screen-size prune (after the first opacity
    reset, at a refinement step no later than refine_stop)."""
    try:
        enabled = _coerce(st.get("enabled", True), bool, "strategy.enabled")
        reset = _coerce(st.get("reset_every", DensifyStrategy.reset_every), int, "strategy.reset_every")
        stop = _coerce(st.get("refine_stop", DensifyStrategy.refine_stop_iter), int, "strategy.refine_stop")
    except MeshsplatError:
        return True
    return bool(enabled) and 0 < reset < stop


def is_legacy_config(d: Any) -> bool:
    """Whether ``d`` is a config dict written by an older version (strategy keys before gsplat's names)."""
    st = d.get("strategy") if isinstance(d, dict) else None
    return isinstance(st, dict) and bool({"refine_start", "refine_stop"} & set(st))


def config_version(d: dict) -> int:
    """The format version of a config dict: its "version" (1 when absent); one MeshsplatError for
    another file's "format", a version that is not a positive integer, or one newer than this meshsplat's."""
    fmt = d.get("format", CONFIG_FORMAT)
    if fmt != CONFIG_FORMAT:
        raise MeshsplatError(f"config: format {fmt!r} is not a training config (expected {CONFIG_FORMAT!r})")
    version = d.get("version", 1)
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise MeshsplatError(f"config: version must be a positive integer, got {version!r}")
    if version > CONFIG_VERSION:
        raise MeshsplatError(
            f"config: format version {version} is newer than this meshsplat reads "
            f"({CONFIG_VERSION}); update meshsplat to use this config"
        )
    return version


def upgrade_config_dict(d: Any, image_size: int | typing.Callable[[], int] | None = None) -> Any:
    """A config dict as written (any version, see ``config_version``) in today's keys and meaning,
    without its "format" / "version" fields (a copy; non-dicts are returned unchanged).

    Version 1 (no "version" field; older meshsplat, whose defaults were the paper's): each key of
    ``VERSION_1_DEFAULTS`` the dict does not set gets its version-1 value, so a run of an older
    version (or an older partial file) keeps its meaning under today's defaults. Likewise a dict of
    version v or older gets each key of ``VERSION_v_DEFAULTS`` it does not set (versions 1 and 2:
    ``loss.crop_to_subject`` false; ... versions 1 to 13: ``model.max_offset`` 0), the earliest
    table's value for a key changed twice.

    A version-1 dict may also hold the strategy keys ``refine_start`` or ``refine_stop``. They become
    ``refine_start_iter`` / ``refine_stop_iter``, and its ``prune_scale2d`` (then in pixels) becomes
    pixels / ``image_size`` (the largest side of the training images; an int, or a callable
    asked only when needed). When that prune could never act under the old config (opacity
    reset off or after ``refine_stop``, as in every demo run) the value is dropped for today's
    default, which changes nothing. Otherwise, without ``image_size``, one MeshsplatError says so.
    """
    if not isinstance(d, dict):
        return d
    version = config_version(d)
    d = {k: v for k, v in d.items() if k not in ("format", "version")}
    for v, table in enumerate(_VERSION_DEFAULTS, start=1):
        if version <= v:  # written before table v's keys changed: the earliest table's value wins
            d = _with_defaults(d, table)
    if not is_legacy_config(d) or version > 1:
        return d
    st = dict(d["strategy"])
    for old, new in RENAMED_KEYS.items():
        o, n = old.split(".", 1)[1], new.split(".", 1)[1]
        if o in st:
            if n in st:
                raise MeshsplatError(f"config: both {old} (its old name) and {new} are set; keep {new}")
            st[n] = st.pop(o)
    if "prune_scale2d" in st:
        pixels = st.pop("prune_scale2d")
        if _legacy_prune_can_act(dict(d["strategy"])):
            size = image_size() if callable(image_size) else image_size
            if size is None:
                raise MeshsplatError(
                    f"config: strategy.prune_scale2d={pixels!r} is in pixels in this config from an "
                    "older meshsplat; today it is a fraction of the image size: set it to "
                    "pixels / max(width, height) (e.g. 20/256 = 0.078), or pass image_size"
                )
            st["prune_scale2d"] = _coerce(pixels, float, "strategy.prune_scale2d") / float(size)
    return {**d, "strategy": st}


def _with_defaults(d: dict, defaults: dict[str, Any]) -> dict:
    """``d`` with each key of ``defaults`` it does not set (and whose section is a dict or absent) set."""
    out = dict(d)
    for key, value in defaults.items():
        section, name = key.split(".")
        sec = out.get(section, {})
        if isinstance(sec, dict) and name not in sec:
            out[section] = {**sec, name: value}
    return out
