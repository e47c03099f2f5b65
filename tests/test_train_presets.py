"""Training presets: quality is the default, paper stays the published method; config.json versions."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from meshsplat.demo import PRESETS as DEMO_SIZES
from meshsplat.demo import demo_train_config
from meshsplat.errors import MeshsplatError
from meshsplat.train import DEFAULT_PRESET, PRESETS, TrainConfig, apply_overrides, load_config, preset_config
from meshsplat.train import config as config_module
from meshsplat.train.config import CONFIG_FORMAT, CONFIG_VERSION, upgrade_config_dict
from meshsplat.train.presets import preset_differences, preset_overrides


def test_quality_is_the_default_preset():
    assert DEFAULT_PRESET == "quality" and set(PRESETS) == {"quality", "paper"}
    assert preset_config() == preset_config("quality") == TrainConfig()
    q = TrainConfig()
    assert (q.model.shading, q.model.init_color_frames, q.optim.lr_color) == ("sh2", 8, 1e-2)
    assert q.loss.crop_to_subject


def test_paper_preset_is_the_published_method():
    c = preset_config("paper")
    # model: one colour per Gaussian (SH degree 0, no shading), colours from the first training frame
    m = c.model
    assert (m.shading, m.sh_degree, m.init_color, m.init_color_frames) == ("none", 0, "image", 1)
    assert (m.n_init, m.init_opacity, m.init_knn, m.sh_frame) == (10_000, 0.1, 3, "world")
    assert not m.freeze_embedding and not m.antialiased
    # sqrt_area is our documented fix of the published pose scale (README "Where we differ"); area is the paper's
    assert m.scale_mode == "sqrt_area"
    # the paper's (3DGS) learning rates
    o = c.optim
    assert (o.lr_embedding, o.lr_embedding_final, o.lr_delay_mult, o.lr_delay_steps) == (1.6e-4, 1.6e-6, 0.01, 0)
    assert (o.lr_color, o.lr_shN, o.lr_opacity, o.lr_scale, o.lr_rotation) == (2.5e-3, 2.5e-3 / 20, 5e-2, 5e-3, 1e-3)
    assert o.eps == 1e-15 and o.uv_lr_units == "world"
    # L1 + 0.01 LPIPS + the scale regulariser (T_s = 0.004 x bbox diagonal, T_r = 10), nothing else
    los = c.loss
    assert (los.lambda_l1, los.lambda_lpips, los.lambda_scale, los.scale_max, los.scale_ratio) == (
        1.0,
        0.01,
        1.0,
        0.008,
        10.0,
    )
    assert (los.lambda_mse, los.lambda_ssim, los.lambda_mask) == (0.0, 0.0, 0.0)
    assert not los.crop_to_subject  # LPIPS on the full frame
    # the 30k-iteration schedule: densify 600..15000 every 100, opacity reset every 3000
    s = c.strategy
    assert c.iterations == 30_000 and s.enabled
    assert (s.refine_start_iter, s.refine_stop_iter, s.refine_every, s.reset_every) == (600, 15_000, 100, 3000)
    assert (s.grow_grad2d, s.grow_scale3d, s.prune_opa, s.prune_scale3d) == (2e-4, 0.01, 0.005, 0.1)
    assert (s.reset_opa, s.split_n, s.max_gaussians) == (0.01, 2, 150_000)
    # gsplat's 0.15 of the image (docs/config.md: the paper's code used 20 px, 0.078 at 256 px)
    assert s.prune_scale2d == 0.15
    # walking on triangles (Algorithm 1) every 100 iterations, the paper's re-expression
    assert (c.walk.enabled, c.walk.every, c.walk.mode) == (True, 100, "paper")
    assert not c.pose_refine.enabled and c.background == "random"


def test_presets_set_the_same_keys_and_differ_only_there():
    keys = {name: [item.split("=")[0] for item in PRESETS[name]] for name in PRESETS}
    assert keys["quality"] == keys["paper"]

    def flat(c):
        return {f"{s}.{k}": v for s, sec in c.to_dict().items() if isinstance(sec, dict) for k, v in sec.items()}

    q, p = flat(preset_config("quality")), flat(preset_config("paper"))
    assert sorted(k for k in q if q[k] != p[k]) == sorted(keys["paper"])
    # applying a preset's overrides to any config gives that preset's model
    assert apply_overrides(preset_config("quality"), list(preset_overrides("paper"))) == preset_config("paper")
    assert preset_differences(preset_config("paper"), "quality") == [
        "model.shading='none' (the quality preset's: 'sh2')",
        "model.init_color_frames=1 (the quality preset's: 8)",
        "optim.lr_color=0.0025 (the quality preset's: 0.01)",
        "loss.crop_to_subject=False (the quality preset's: True)",
        "loss.lpips_every=1 (the quality preset's: 2)",
        "model.occlusion='none' (the quality preset's: 'key')",
        "pose_refine.auto=False (the quality preset's: True)",
        "optim.lr_shading=0.005 (the quality preset's: 0.05)",
        "model.occlusion_key_soft=0.0 (the quality preset's: 12.0)",
        "model.occlusion_grid=64 (the quality preset's: 96)",
        "loss.lambda_albedo=0.0 (the quality preset's: 0.1)",
        "loss.albedo_reach=8 (the quality preset's: 64)",
        "strategy.grow_grad2d=0.0002 (the quality preset's: 0.0001)",
        "loss.lambda_mask=0.0 (the quality preset's: 0.1)",
        "model.max_offset=0.0 (the quality preset's: 0.15)",
    ]
    assert preset_differences(preset_config("paper"), "paper") == []
    with pytest.raises(MeshsplatError, match="preset: expected one of quality, paper, got 'best'"):
        preset_config("best")


def test_version_1_defaults_are_the_paper_preset():
    paper = preset_config("paper").to_dict()
    # every version's table of changed defaults (VERSION_1_DEFAULTS ... VERSION_9_DEFAULTS): the first value a
    # key had, before its default first changed, is the paper's; a later table holds a later default
    tables = [getattr(config_module, f"VERSION_{v}_DEFAULTS") for v in range(1, CONFIG_VERSION)]
    assert list(config_module._VERSION_DEFAULTS) == tables  # the upgrade applies each, in order
    seen: set[str] = set()
    for table in tables:
        first = {k: v for k, v in table.items() if k not in seen}
        assert {k: paper[k.split(".")[0]][k.split(".")[1]] for k in first} == first
        seen |= set(table)
    assert config_module.VERSION_8_DEFAULTS["model.occlusion_key_soft"] == 8.0  # changed twice: 0, 8, then 12


# The demo's TrainConfig before training presets existed (hand-coded from demo.py of that time): the defaults
# were the paper's, then the sizes' schedule, then QUALITY_OVERRIDES unless quality=False.
_OLD_DEFAULTS = [
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
]
# plus the LPIPS crop, on in the quality preset since config version 3, and LPIPS every second iteration (4)
_OLD_QUALITY = [
    "model.shading=sh2",
    "model.init_color_frames=8",
    "optim.lr_color=1e-2",
    "loss.crop_to_subject=true",
    "loss.lpips_every=2",
    "model.occlusion=key",  # the key light, default since config version 5
    "pose_refine.auto=true",  # since config version 6
    "optim.lr_shading=5e-2",  # since config version 7
    "model.occlusion_key_soft=12",  # 8 since config version 8, 12 since 9
    "model.occlusion_grid=96",  # since config version 9
    "loss.lambda_albedo=0.1",  # since config version 10
    "loss.albedo_reach=64",  # since config version 11
    "strategy.grow_grad2d=1e-4",  # since config version 12
    "loss.lambda_mask=0.1",  # since config version 13
    "model.max_offset=0.15",  # since config version 14
]
_OLD_SCHEDULES = {
    "default": [
        "strategy.refine_start_iter=300",
        "strategy.refine_stop_iter=1200",
        "strategy.refine_every=100",
        "strategy.reset_every=100000",
        "strategy.max_gaussians=40000",
        "walk.every=100",
        "preview_every=250",
        "checkpoint_every=250",
        "log_every=10",
    ],
    "tiny": [
        "strategy.refine_start_iter=20",
        "strategy.refine_stop_iter=50",
        "strategy.refine_every=20",
        "strategy.reset_every=100000",
        "walk.every=20",
        "preview_every=30",
        "checkpoint_every=30",
        "log_every=5",
    ],
}
_OLD_SIZES = {"default": (1500, 10_000), "tiny": (60, 1500)}


@pytest.mark.parametrize("sizes", ["default", "tiny"])
@pytest.mark.parametrize("preset", ["quality", "paper"])
def test_demo_config_is_unchanged_by_presets(sizes, preset):
    iterations, n_init = _OLD_SIZES[sizes]
    old = TrainConfig(data="/d", out="/o", iterations=iterations, device="auto", progress=False)
    old.model.n_init = n_init
    model = _OLD_QUALITY if preset == "quality" else []
    old = apply_overrides(old, _OLD_DEFAULTS + _OLD_SCHEDULES[sizes] + model + ["seed=3"])
    new = demo_train_config(Path("/d"), Path("/o"), DEMO_SIZES[sizes], ["seed=3"], progress=False, preset=preset)
    assert new.to_dict() == old.to_dict()
    if preset == "quality":
        assert demo_train_config(Path("/d"), Path("/o"), DEMO_SIZES[sizes], ["seed=3"], progress=False) == new


def test_config_json_carries_its_format_version(tmp_path):
    cfg = apply_overrides(preset_config("paper"), ["seed=4"])
    cfg.to_json(tmp_path / "config.json")
    doc = json.loads((tmp_path / "config.json").read_text())
    assert (doc["format"], doc["version"]) == (CONFIG_FORMAT, CONFIG_VERSION) == ("meshsplat-train-config", 14)
    assert load_config(tmp_path / "config.json") == cfg
    assert load_config(tmp_path / "config.json", base=preset_config("quality")) == cfg  # full: the base is unused
    # a partial file of this version sits over the base (default: the quality preset)
    (tmp_path / "partial.json").write_text(json.dumps({"version": 7, "seed": 5}))
    assert load_config(tmp_path / "partial.json").model.shading == "sh2"
    assert load_config(tmp_path / "partial.json", base=preset_config("paper")) == apply_overrides(
        preset_config("paper"), ["seed=5"]
    )


def test_config_without_version_is_read_as_older_meshsplat_wrote_it(tmp_path):
    # an older run's config.json: no version, and (before pose-dependent shading) no shading / init_color_frames keys
    old = preset_config("paper").to_dict()
    del old["model"]["shading"], old["model"]["init_color_frames"]
    (tmp_path / "config.json").write_text(json.dumps(old))
    for base in (None, preset_config("quality"), preset_config("paper")):
        assert load_config(tmp_path / "config.json", base=base) == preset_config("paper")
    # a partial one likewise: keys it does not set meant the defaults of then (the paper's)
    (tmp_path / "partial.json").write_text(json.dumps({"model": {"n_init": 500}, "optim": {"lr_color": 0.02}}))
    got = load_config(tmp_path / "partial.json", base=preset_config("quality"))
    assert (got.model.shading, got.model.init_color_frames, got.optim.lr_color, got.model.n_init) == (
        "none",
        1,
        0.02,
        500,
    )
    assert TrainConfig.from_dict({"seed": 1}).model.shading == "none"
    assert "version" not in upgrade_config_dict({"version": 2, "seed": 1})


def test_version_2_config_keeps_the_full_frame_loss(tmp_path):
    # written before loss.crop_to_subject was on by default (a run folder, or a partial file of version 2)
    old = preset_config("quality").to_dict()
    del old["loss"]["crop_to_subject"]
    (tmp_path / "config.json").write_text(json.dumps({"version": 2, **old}))
    got = load_config(tmp_path / "config.json")
    assert not got.loss.crop_to_subject
    assert got == apply_overrides(preset_config("quality"), ["loss.crop_to_subject=false"])
    (tmp_path / "partial.json").write_text(json.dumps({"version": 2, "seed": 5}))
    assert not load_config(tmp_path / "partial.json").loss.crop_to_subject
    (tmp_path / "partial.json").write_text(json.dumps({"version": 4, "seed": 5}))
    assert load_config(tmp_path / "partial.json").loss.crop_to_subject
    # a version-2 dict that sets it keeps its value; an unversioned one (version 1) gets the paper's
    assert TrainConfig.from_dict({"version": 2, "loss": {"crop_to_subject": True}}).loss.crop_to_subject
    assert not TrainConfig.from_dict({"seed": 1}).loss.crop_to_subject


@pytest.mark.parametrize(
    "version, key, old_value, set_value",
    [
        (3, "loss.lpips_every", 1, 3),  # written before loss.lpips_every was 2
        (4, "model.occlusion", "none", "key"),  # before model.occlusion was key
        (5, "pose_refine.auto", False, True),  # before pose_refine.auto was on (the key did not exist yet)
        (6, "optim.lr_shading", 5e-3, 0.05),  # before optim.lr_shading was 5e-2
        (7, "model.occlusion_key_soft", 0.0, 4.0),  # before the key's shadow was soft
        (8, "model.occlusion_grid", 64, 128),  # before the shadow maps had 96 cells a side
        (9, "loss.lambda_albedo", 0.0, 0.5),  # before the albedo prior
        (10, "loss.albedo_reach", 8, 32),  # before the albedo prior reached past the nearest 8
        (11, "strategy.grow_grad2d", 2e-4, 3e-4),  # before densification's threshold was 1e-4
        (12, "loss.lambda_mask", 0.0, 0.3),  # before the mask loss
        (13, "model.max_offset", 0.0, 0.3),  # before offsets were bounded
        (8, "model.occlusion_key_soft", 8.0, 4.0),  # before the key's disk was 12 degrees
    ],
)
def test_older_config_keeps_the_default_it_was_written_with(tmp_path, version, key, old_value, set_value):
    section, name = key.split(".")

    def value(cfg):
        return getattr(getattr(cfg, section), name)

    old = preset_config("quality").to_dict()
    del old[section][name]
    (tmp_path / "config.json").write_text(json.dumps({"version": version, **old}))
    assert load_config(tmp_path / "config.json") == apply_overrides(preset_config("quality"), [f"{key}={old_value}"])
    assert value(TrainConfig.from_dict({"version": version, "seed": 1})) == old_value
    assert value(TrainConfig.from_dict({"version": version, section: {name: set_value}})) == set_value
    # one version later: the default of then (a later table's, for a key changed twice), else today's
    later = [getattr(config_module, f"VERSION_{v}_DEFAULTS") for v in range(version + 1, CONFIG_VERSION)]
    then = next((t[key] for t in later if key in t), value(preset_config("quality")))
    assert value(TrainConfig.from_dict({"version": version + 1, "seed": 1})) == then
    # version 1: the value before the key's first change (the paper's)
    first = next(
        getattr(config_module, f"VERSION_{v}_DEFAULTS")[key]
        for v in range(1, CONFIG_VERSION)
        if key in getattr(config_module, f"VERSION_{v}_DEFAULTS")
    )
    assert value(TrainConfig.from_dict({"seed": 1})) == first


@pytest.mark.parametrize(
    "doc, match",
    [
        ({"version": 15}, r"^config: format version 15 is newer than this meshsplat reads \(14\); update meshsplat"),
        ({"version": "2"}, "version must be a positive integer, got '2'"),
        ({"version": 0}, "version must be a positive integer"),
        ({"version": True}, "version must be a positive integer"),
        ({"format": "meshsplat-checkpoint", "version": 2}, "is not a training config"),
    ],
)
def test_config_versions_refused(tmp_path, doc, match):
    (tmp_path / "c.json").write_text(json.dumps({**doc, "seed": 1}))
    with pytest.raises(MeshsplatError, match=match):
        load_config(tmp_path / "c.json")
