"""Shared test helpers: the third-party data folder, and small synthetic captures made once."""

from __future__ import annotations

from pathlib import Path

import pytest

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
    from dbb_capture.synth.scene import SynthConfig
    from dbb_capture.synth.capture import write_capture

    out = tmp_path_factory.mktemp("captures") / "static"
    write_capture(SynthConfig(kind="static", seconds=2.0, fps=5, width=320, height=240,
                              background_seconds=1.0, seed=3), out)
    return out


@pytest.fixture(scope="session")
def tiny_dynamic_capture(tmp_path_factory) -> Path:
    """A 3-second 320x240 dynamic capture (no clean plate), rendered once per test session."""
    from dbb_capture.synth.scene import SynthConfig
    from dbb_capture.synth.capture import write_capture

    out = tmp_path_factory.mktemp("captures") / "dynamic"
    write_capture(SynthConfig(kind="dynamic", seconds=3.0, fps=5, width=320, height=240,
                              background_seconds=None, seed=4), out)
    return out
