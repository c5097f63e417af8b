"""Helpers of the batch tests: tiny settings and the session's local Ray."""

from __future__ import annotations

from dataclasses import replace

import pytest

from dbb_capture.background.config import BackgroundConfig
from dbb_capture.batch.config import BatchConfig, DynamicSettings, StaticSettings
from dbb_capture.dynamic.config import RssmConfig, TrainConfig
from dbb_capture.preprocess.inputs import PreprocessConfig
from dbb_capture.static.field import FieldConfig
from dbb_capture.static.run import RunConfig


def tiny_config(static_steps: int = 20, **kw) -> BatchConfig:
    """Settings that take seconds per stage: 32 px crops, 4-frame windows, 20 room steps, a few
    training steps of small models; one CPU per preprocess, so two captures share the 2 cores."""
    pre = PreprocessConfig(crop_size=32, sequence_length=4, background=replace(BackgroundConfig(), steps=20))
    field = FieldConfig(res_start=16, res_max=32, batch_rays=512, upsample_at=(0.3,), tv_points=2048)
    small = RssmConfig(size=32, deter=16, stoch=16, hidden=64, embed=64, enc_depth=8, dec_depth=8)
    return BatchConfig(static=StaticSettings(pre, RunConfig(steps=static_steps), field),
                       dynamic=DynamicSettings(pre, small, TrainConfig(steps=3, batch=2)),
                       preprocess_cpus=1.0, **kw)


def need_ray():
    return pytest.importorskip("ray", reason="Ray is not installed (pip install 'dbb-capture[ray]')")


def start_local_ray():
    """A local Ray with 2 CPUs, started once and kept for the session (a cluster test stops it;
    the next test that needs it starts it again)."""
    ray = need_ray()
    if not ray.is_initialized():
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
                 object_store_memory=200 * 2**20)
    return ray
