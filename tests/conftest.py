"""Shared test helpers: the third-party data folder, small synthetic captures, training runs
and bundles made once per session, a ring of cameras around an object and the error between two rotations."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from dbb_capture.capture.board import BoardSpec
from dbb_capture.datasets.records import Frame, ObjectVolume
from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.transforms import look_at
from dbb_capture.synth.capture import write_capture
from dbb_capture.synth.scene import SynthConfig

# Without a terminal, progress prints plain lines (dbb_capture.core.progress): not in the suite,
# whose tests read commands' output line by line; tests of progress ask for them.
os.environ.setdefault("DBB_PROGRESS_SECONDS", "0")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO / ".." / "shared" / "data"


def shared_data(*parts: str) -> Path:
    """Path into ``../shared/data``; skips the test with a reason where it is absent (a user's clone)."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"third-party data {p} not present (only CI and developers have ../shared)")
    return p


@pytest.fixture(scope="session")
def tiny_static_capture(tmp_path_factory) -> Path:
    """A 2-second 320x240 static capture with clean plate, rendered once per test session."""
    out = tmp_path_factory.mktemp("captures") / "static"
    write_capture(SynthConfig(kind="static", seconds=2.0, fps=5, width=320, height=240,
                              background_seconds=1.0, seed=3), out)
    return out


@pytest.fixture(scope="session")
def tiny_dynamic_capture(tmp_path_factory) -> Path:
    """A 3-second 320x240 dynamic capture (no clean plate), rendered once per test session."""
    out = tmp_path_factory.mktemp("captures") / "dynamic"
    write_capture(SynthConfig(kind="dynamic", seconds=3.0, fps=5, width=320, height=240,
                              background_seconds=None, seed=4), out)
    return out


UP = np.array([0.0, 0.0, -1.0])


def ring_cameras(center, n=12, dist=0.6, el_deg=40.0) -> np.ndarray:
    """``n`` OpenCV camera-to-world poses (n, 4, 4) on an arc of +-60 degrees around ``center``."""
    out = []
    for a in np.linspace(-60, 60, n):
        a, e = np.radians(a), np.radians(el_deg)
        eye = center + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), -np.sin(e)])
        out.append(look_at(eye, center, UP))
    return np.stack(out)


def small_intrinsics() -> Intrinsics:
    """A 320x240 pinhole without distortion (the synthetic test captures' size)."""
    return Intrinsics(320, 240, 260.0, 260.0, 159.5, 119.5)


@pytest.fixture(scope="session")
def plate_capture(tmp_path_factory) -> Path:
    """A 2-second 320x240 static capture with a 2-second clean plate."""
    out = tmp_path_factory.mktemp("bg") / "cap"
    write_capture(SynthConfig(kind="static", seconds=2.0, fps=6, width=320, height=240,
                              background_seconds=2.0, seed=21), out)
    return out


def rotation_error_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (degrees) of the rotation between ``Ra`` and ``Rb`` (each (3, 3))."""
    return math.degrees(math.acos(float(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


@pytest.fixture(scope="session")
def distorted_capture(tmp_path_factory) -> Path:
    """A 2 s, 5 fps, 320x240 capture with a coarse board (readable at that size), lens distortion."""
    out = tmp_path_factory.mktemp("poses") / "cap"
    board = BoardSpec(5, 4, 0.07, 0.05, "DICT_4X4_50")
    write_capture(SynthConfig(kind="static", seconds=2.0, fps=5, width=320, height=240, board=board,
                              background_seconds=None, seed=5, dist=(-0.1, 0.03, 0.0, 0.0, 0.0)), out)
    return out


def synthetic_object_frames(folder, n=24, size=32, seed=0) -> tuple[list[Frame], ObjectVolume]:
    """RGBA renders (size x size px, written to ``folder``) of the synthetic toy from known poses
    around it, every 8th (from the 4th) held out; and the sphere that holds it."""
    import cv2

    from dbb_capture.synth.objects import make_object
    from dbb_capture.synth.render import render_object_rgba

    model = make_object("static", BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"), np.random.default_rng(seed))
    c, r = model.bounding_sphere(np.array([0.0]))
    f = size * 1.2
    intr = Intrinsics(size, size, f, f, (size - 1) / 2, (size - 1) / 2)
    dist = 1.1 * r / math.sin(math.atan(0.5 / 1.2))
    rng = np.random.default_rng(seed + 1)
    frames = []
    for i in range(n):
        az, el = 2 * math.pi * i / n + rng.uniform(0, 0.2), rng.uniform(0.15, 1.2)
        eye = c + dist * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), -math.sin(el)])
        c2w = look_at(eye, c, np.array([0, 0, -1.0]))
        p = folder / f"{i:03d}.png"
        cv2.imwrite(str(p), cv2.cvtColor(render_object_rgba(model, intr, c2w, 0.0, samples=2), cv2.COLOR_RGBA2BGRA))
        frames.append(Frame(f"{i:03d}", p, c2w, intr, "test" if i % 8 == 3 else "train"))
    return frames, ObjectVolume(tuple(float(v) for v in c), float(r) * 1.05)


def gltf_reports(*paths: Path) -> list[dict]:
    """The Khronos glTF validator's report of each file (``scripts/validate_gltf.mjs``, npm's
    ``gltf-validator`` installed by the set-up); skips the test with a reason where there is none."""
    import json
    import shutil
    import subprocess

    if shutil.which("node") is None or not (REPO / "node_modules" / "gltf-validator").is_dir():
        pytest.skip("the glTF validator is not installed (needs node and `npm ci`, which scripts/setup.sh runs)")
    res = subprocess.run(["node", str(REPO / "scripts" / "validate_gltf.mjs"), *map(str, paths)],
                         capture_output=True, text=True, timeout=120, cwd=REPO)
    assert res.returncode == 0, res.stderr
    return [json.loads(line) for line in res.stdout.splitlines()]


@pytest.fixture(scope="session")
def static_run(tmp_path_factory):
    """A tiny PlenOctree run (a few steps on 24 px views of the synthetic toy)."""
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


@pytest.fixture(scope="session")
def static_bundle(static_run):
    from dbb_capture.bundle.build import make_bundle

    folder, _ = static_run
    make_bundle(folder / "run", folder / "bundle")
    return folder / "bundle"


@pytest.fixture(scope="session")
def dynamic_run(tmp_path_factory):
    from dbb_capture.dynamic.config import RssmConfig, TrainConfig
    from dbb_capture.dynamic.run import train_run
    from dbb_capture.synth.crops import synthetic_crops

    folder = tmp_path_factory.mktemp("bundle_dynamic")
    synthetic_crops(folder / "ds", seconds=3.0, fps=10, size=32, still_steps=1, samples=1)
    small = RssmConfig(size=32, deter=16, stoch=16, hidden=64, embed=64, enc_depth=8, dec_depth=8)
    train_run(folder / "ds", folder / "run", small, TrainConfig(steps=3, batch=2), quiet=True)
    return folder


@pytest.fixture(scope="session")
def dynamic_bundle(dynamic_run, tmp_path_factory):
    from dbb_capture.bundle.build import make_bundle

    # Its own folder: tests of the bundle command write bundles beside the run.
    out = tmp_path_factory.mktemp("dynamic_bundle") / "bundle"
    make_bundle(dynamic_run / "run", out)
    return out
