"""Training presets: named models, each a set of ``TrainConfig`` overrides.

    quality   the default (``TrainConfig()``, ``meshsplat train``): pose-dependent shading
              (model.shading=sh2), colours initialised from 8 frames, colour lr 1e-2, LPIPS on the
              box around the subject and on every second iteration (at twice the weight), and a key light
              found in training whose shadow the posed mesh casts (model.occlusion=key), and the tracked
              poses refined when the capture has SMPL/SMPL-X/FLAME parameters (pose_refine.auto), the lighting
              learned at lr 5e-2 (optim.lr_shading), the key light's shadow soft (a 12-degree area light,
              model.occlusion_key_soft) on 96-cell shadow maps (model.occlusion_grid), and a prior that gives
              nearby Gaussians of one hue one albedo (loss.lambda_albedo), reaching 64 neighbours out
              (loss.albedo_reach), and densification at half the paper's gradient threshold
              (strategy.grow_grad2d 1e-4), and the rendered alpha held to the mask (loss.lambda_mask), and
              Gaussians kept within 0.15 extents of their triangle along its normal (model.max_offset); measured
              in docs/quality.md (bench/quality.py, bench/loss_crop.py, bench/quality_pbr.py)
    paper     the published method (SplattingAvatar, CVPR 2024): one colour per Gaussian from the
              first frame, the paper's learning rates (lr_shading the old 5e-3, a hard key on 64-cell
              maps and no albedo prior (reach 8), all unused without shading),
              LPIPS on the full frame every iteration, densification at the gradient threshold 2e-4, no mask
              loss, offsets unbounded, on the same 30k-iteration schedule

Both set the same keys, so applying a preset's overrides to any config gives that preset's model
(``meshsplat train --resume --preset NAME`` relies on it: the resume check then refuses a preset
other than the run's). Schedules (iterations, when densification runs) are not part of a preset.

    from meshsplat.train import preset_config, train
    cfg = preset_config("paper")
    cfg.data, cfg.out = "path/to/dataset", "runs/paper"
    train(cfg)
"""

from __future__ import annotations

from meshsplat.errors import MeshsplatError
from meshsplat.train.config import TrainConfig, apply_overrides

__all__ = ["PRESETS", "DEFAULT_PRESET", "preset_overrides", "preset_config", "preset_differences"]

PRESETS: dict[str, tuple[str, ...]] = {
    "quality": (
        "model.shading=sh2",
        "model.init_color_frames=8",
        "optim.lr_color=1e-2",
        "loss.crop_to_subject=true",
        "loss.lpips_every=2",
        "model.occlusion=key",
        "pose_refine.auto=true",
        "optim.lr_shading=5e-2",
        "model.occlusion_key_soft=12",
        "model.occlusion_grid=96",
        "loss.lambda_albedo=0.1",
        "loss.albedo_reach=64",
        "strategy.grow_grad2d=1e-4",
        "loss.lambda_mask=0.1",
        "model.max_offset=0.15",
    ),
    "paper": (
        "model.shading=none",
        "model.init_color_frames=1",
        "optim.lr_color=2.5e-3",
        "loss.crop_to_subject=false",
        "loss.lpips_every=1",
        "model.occlusion=none",
        "pose_refine.auto=false",
        "optim.lr_shading=5e-3",
        "model.occlusion_key_soft=0",
        "model.occlusion_grid=64",
        "loss.lambda_albedo=0",
        "loss.albedo_reach=8",
        "strategy.grow_grad2d=2e-4",
        "loss.lambda_mask=0",
        "model.max_offset=0",
    ),
}
DEFAULT_PRESET = "quality"


def preset_overrides(name: str) -> tuple[str, ...]:
    """The ``key=value`` overrides of preset ``name``; one MeshsplatError for an unknown name."""
    if name not in PRESETS:
        raise MeshsplatError(f"preset: expected one of {', '.join(PRESETS)}, got {name!r}")
    return PRESETS[name]


def preset_config(name: str = DEFAULT_PRESET) -> TrainConfig:
    """A new ``TrainConfig`` of preset ``name`` (the defaults with its overrides applied)."""
    return apply_overrides(TrainConfig(), list(preset_overrides(name)))


def preset_differences(cfg: TrainConfig, name: str) -> list[str]:
    """``"key=value (the NAME preset's: value)"`` for each key of preset ``name`` that ``cfg`` sets otherwise."""
    want = preset_config(name).to_dict()
    have = cfg.to_dict()
    out = []
    for item in preset_overrides(name):
        section, key = item.split("=", 1)[0].split(".")
        if have[section][key] != want[section][key]:
            out.append(f"{section}.{key}={have[section][key]!r} (the {name} preset's: {want[section][key]!r})")
    return out
