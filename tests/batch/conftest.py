"""Batches on a local Ray: one ``ray.init(num_cpus=2)`` per session (Ray's testing guide), tiny
settings, and a first batch over three small captures (one corrupted) shared by the tests."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from .tiny import start_local_ray, tiny_config


@pytest.fixture
def local_ray():
    return start_local_ray()


@pytest.fixture(scope="session")
def batch_captures(tmp_path_factory, plate_capture, tiny_dynamic_capture) -> Path:
    """CAPTURES_DIR: a static capture whose object.json has no kind (the default says static), a
    dynamic one (its object.json says so), one with a corrupted video, and a folder of notes."""
    root = tmp_path_factory.mktemp("batch") / "captures"
    shutil.copytree(plate_capture, root / "static")
    obj = json.loads((root / "static" / "object.json").read_text())
    obj.pop("kind", None)
    (root / "static" / "object.json").write_text(json.dumps(obj))
    shutil.copytree(tiny_dynamic_capture, root / "dynamic")
    broken = root / "broken"
    broken.mkdir()
    for f in ("board.json", "object.json"):
        shutil.copyfile(tiny_dynamic_capture / f, broken / f)
    (broken / "video.mp4").write_bytes((tiny_dynamic_capture / "video.mp4").read_bytes()[:3000])
    (root / "notes").mkdir()
    (root / "notes" / "todo.txt").write_text("not a capture")
    return root


@pytest.fixture(scope="session")
def first_batch(batch_captures, tmp_path_factory):
    """The first batch over ``batch_captures`` (outputs and summary). Tests that use its outputs
    copy them, or leave them as they found them (every bundle verified)."""
    start_local_ray()
    from dbb_capture.batch.run import run_batch

    out = tmp_path_factory.mktemp("batch") / "out"
    return out, run_batch(batch_captures, out, tiny_config())
