"""A small static and a small dynamic training run, the static run's bundle, and cameras files."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner
from dbb_capture.cli.export import main

from dbb_capture.datasets.transforms import intrinsics_fields

torch.set_num_threads(1)


def run_cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def static_run(tmp_path_factory):
    """A tiny PlenOctree run (a few steps on 24 px views of the synthetic toy)."""
    from conftest import synthetic_object_frames

    from dbb_capture.datasets.transforms import write_transforms
    from dbb_capture.static.field import FieldConfig
    from dbb_capture.static.run import RunConfig, train_run

    folder = tmp_path_factory.mktemp("bundle_static")
    (folder / "ds").mkdir()
    frames, vol = synthetic_object_frames(folder / "ds", n=12, size=24, seed=2)
    write_transforms(folder / "ds" / "transforms.json", frames, vol)
    torch.manual_seed(0)
    cfg = FieldConfig(res_start=16, res_max=32, batch_rays=512, upsample_at=(0.3,), tv_points=2048)
    train_run(folder / "ds", folder / "run", RunConfig(steps=20), cfg, quiet=True)
    return folder, frames


@pytest.fixture(scope="module")
def static_bundle(static_run):
    folder, _ = static_run
    res = run_cli("bundle", folder / "run", "-o", folder / "bundle")
    assert res.exit_code == 0, res.output
    return folder / "bundle"


@pytest.fixture(scope="module")
def dynamic_run(tmp_path_factory):
    from dbb_capture.dynamic.config import RssmConfig, TrainConfig
    from dbb_capture.dynamic.run import train_run
    from dbb_capture.synth.crops import synthetic_crops

    folder = tmp_path_factory.mktemp("bundle_dynamic")
    synthetic_crops(folder / "ds", seconds=3.0, fps=10, size=32, still_steps=1, samples=1)
    small = RssmConfig(size=32, deter=16, stoch=16, hidden=64, embed=64, enc_depth=8, dec_depth=8)
    train_run(folder / "ds", folder / "run", small, TrainConfig(steps=3, batch=2), quiet=True)
    return folder


def write_cameras(frames, path, per_frame=False, drop_intrinsics=False):
    from dbb_capture.geometry.conventions import opengl_from_opencv

    doc = {"frames": [{"file_path": f"images/{f.name}.jpg",
                       "transform_matrix": opengl_from_opencv(f.c2w).tolist()} for f in frames]}
    intr = intrinsics_fields(frames[0].intr)
    if not drop_intrinsics:
        if per_frame:
            for d in doc["frames"]:
                d.update(intr)
        else:
            doc.update(intr)
    path.write_text(json.dumps(doc))
    return path
