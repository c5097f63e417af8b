"""Settings by name, presets as files, validation."""

from __future__ import annotations

from dataclasses import asdict, replace

import pytest

from dbb_capture.core.errors import DbbError
from dbb_capture.dynamic.config import (
    LOSS_SCALES,
    PRESETS_DIR,
    RssmConfig,
    TrainConfig,
    apply_preset,
    configs_from_settings,
    leak_at_frame_rate,
    model_changes,
    preset_names,
    read_preset,
    setting_names,
)

from .conftest import SMALL, scaled


def test_settings_by_name_take_their_types():
    names = setting_names()
    assert len(names) <= 44 and len(set(names)) == len(names)
    assert {f"loss_scales.{k}" for k in LOSS_SCALES} <= set(names)
    assert not {"size", "batch", "seed", "minutes", "steps", "loss_scales"} & set(names)   # options of their own
    cfg, tcfg = configs_from_settings(["warp_leak=0.05", "keypoints_frozen=true", "loss_scales.energy=100",
                                       "dynamics_horizon=30", "augment=none", "osc=4", "dynamics_horizon=none"])
    assert (cfg.warp_leak, cfg.keypoints_frozen, cfg.osc) == (0.05, True, 4)
    assert cfg.loss_scales == {**LOSS_SCALES, "energy": 100.0}
    assert (tcfg.augment, tcfg.dynamics_horizon) == ("none", None)          # a later pair wins
    assert RssmConfig().loss_scales == LOSS_SCALES and RssmConfig().loss_scales is not LOSS_SCALES
    for bad, what in (("warp_leek=0.1", "no such setting"), ("warp_leak=lots", "not a number"),
                      ("osc=2.5", "not a whole number"), ("keypoints_frozen=yes", "true or false"),
                      ("compose=accum", "no such setting"), ("size=32", "no such setting"),
                      ("loss_scales.open_loop=1", "no such setting"), ("warp_leak", "NAME=VALUE")):
        with pytest.raises(DbbError, match=what):
            configs_from_settings([bad])


def test_presets_are_files_and_expand_under_later_settings():
    assert preset_names() == sorted(p.stem for p in PRESETS_DIR.glob("*.toml")) and "swing" in preset_names()
    cfg, tcfg = apply_preset("swing")
    # The swing preset: keypoints, oscillator modes, latent-only steps on long windows, keypoint maps.
    assert read_preset("swing") == {
        "deter": 96, "osc": 16, "osc_keep_min": 0.999, "keypoints": 16, "keypoints_frozen": True,
        "keypoint_maps": True, "keypoint_teacher": True, "keypoint_horizon": 10, "warp_leak": 0.1, "warp_leak_fps": 10.0,
        "dynamics_steps": 1, "dynamics_horizon": 60,
        "loss_scales.energy": 100.0, "loss_scales.sharp": 100.0, "loss_scales.keypoints": 100.0,
        "loss_scales.keypoint_spread": 100.0}
    assert cfg.keypoint_maps and cfg.keypoint_teacher and tcfg.dynamics_horizon == 60
    assert cfg.scale("sharp") == 100.0 and cfg.scale("rec") == 1.0
    cfg.validate()
    cfg, _ = configs_from_settings(["osc=8"], cfg, tcfg)
    assert cfg.osc == 8 and cfg.deter == 96                  # a later setting wins over the preset's
    with pytest.raises(DbbError, match="no preset named 'wobble'"):
        apply_preset("wobble")
    from dbb_capture.cli import train as cli

    opt = next(p for p in cli.rssm.params if p.name == "preset")
    assert list(opt.type.choices) == preset_names()          # the command offers each preset file


def test_validation_names_the_setting():
    for bad, what in ((replace(SMALL, size=48), "frame size"), (scaled(keypoints=1.0), "loss_scales.keypoints"),
                      (replace(SMALL, keypoints=4, keypoint_maps=True), "keypoint_maps"),
                      (replace(scaled(keypoints=1.0), keypoints=4, keypoint_teacher=True), "keypoint_teacher"),
                      (replace(SMALL, keypoint_map_std=0.0), "keypoint_map_std"), (replace(SMALL, keypoints=-1), "keypoints"),
                      (replace(SMALL, deter=16, osc=8), "osc"), (replace(SMALL, osc_keep_min=1.0), "osc_keep_min"),
                      (replace(SMALL, warp_leak=1.0), "warp_leak"), (replace(SMALL, warp_leak_fps=-1.0), "warp_leak_fps"),
                      (scaled(sharp=-1.0), "loss_scales.sharp"), (replace(SMALL, loss_scales={"rec": 1.0}), "loss_scales"),
                      (replace(SMALL, max_step_flow=0.0), "max_step_flow")):
        with pytest.raises(DbbError, match=what):
            bad.validate()
    for bad, what in ((TrainConfig(augment="flip,spin"), "augment"), (TrainConfig(weight_decay=-1.0), "weight_decay"),
                      (TrainConfig(ema=1.0), "ema"), (TrainConfig(dynamics_horizon=0), "dynamics_horizon")):
        with pytest.raises(DbbError, match=what):
            bad.validate()
    TrainConfig(augment="flip,reverse,shift").validate()
    # The defaults that met the bars (docs/decisions.md: weight_decay, ema).
    assert (TrainConfig().weight_decay, TrainConfig().ema) == (0.25, 0.995)


def test_configs_read_back_and_older_ones_are_refused():
    cfg = scaled(energy=3.0)
    back = RssmConfig.from_json(asdict(cfg))
    assert back == cfg and back.loss_scales is not cfg.loss_scales
    with pytest.raises(DbbError, match="not an RSSM model config of this version"):
        RssmConfig.from_json({**asdict(SMALL), "compose": "accum"})
    # A model written before a loss term existed trained without it: the term reads back as off.
    old = asdict(scaled(energy=3.0))
    del old["loss_scales"]["keypoint_spread"]
    assert RssmConfig.from_json(old) == cfg


def test_warp_leak_per_second_is_rescaled_to_the_footage_frame_rate():
    # 0.1 a frame at 10 frames/s leaves 0.9 ** 10 of a displacement after one second; at 30 frames/s
    # the same second takes 30 frames, so the leak per frame is 1 - 0.9 ** (1 / 3) ~ 0.0345.
    cfg = replace(SMALL, warp_leak=0.1, warp_leak_fps=10.0)
    at30 = leak_at_frame_rate(cfg, 30.0)
    assert at30.warp_leak == pytest.approx(1.0 - 0.9 ** (1.0 / 3.0)) and at30.warp_leak_fps == 30.0
    assert (1.0 - at30.warp_leak) ** 30 == pytest.approx(0.9 ** 10)
    assert leak_at_frame_rate(at30, 30.0) == at30                 # applying it again changes nothing
    assert leak_at_frame_rate(cfg, 10.0).warp_leak == pytest.approx(0.1)
    plain = replace(SMALL, warp_leak=0.1)                         # the default: a leak per frame
    assert leak_at_frame_rate(plain, 30.0) == plain and leak_at_frame_rate(cfg, None) == cfg


def test_a_resumed_model_is_compared_with_the_run_after_its_leak_is_rescaled():
    """What a resumed command asks of the model against the run's own: the same preset again is no
    change (its leak per frame rescaled to the footage as training did); another value is named."""
    asked = replace(SMALL, warp_leak=0.1, warp_leak_fps=10.0)
    run = leak_at_frame_rate(asked, 30.0)
    assert model_changes(run, asked) == [] and model_changes(run, run) == []
    more = replace(asked, deter=SMALL.deter * 2, loss_scales={**asked.loss_scales, "energy": 5.0})
    assert model_changes(run, more) == [f"deter {SMALL.deter * 2} (the run's {SMALL.deter})",
                                        "loss_scales.energy 5 (the run's 0)"]
