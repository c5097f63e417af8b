"""A field trained once on the synthetic toy (50 steps, coarse to fine, 24 px views)."""

from __future__ import annotations

import pytest
import torch
from conftest import synthetic_object_frames

from dbb_capture.static.rays import build_ray_bank
from dbb_capture.static.train import Budget, TrainState, new_field, train

from .synthetic import TINY


@pytest.fixture(scope="session")
def trained(tmp_path_factory):
    """(frames, volume, the state after 50 steps, its folder holding ``ckpt.pt``)."""
    folder = tmp_path_factory.mktemp("synth_object")
    frames, vol = synthetic_object_frames(folder, n=16, size=24)
    bank = build_ray_bank([f for f in frames if f.split == "train"], 1, vol)
    torch.manual_seed(0)
    state = TrainState(new_field(TINY, vol, torch.device("cpu")))
    state = train(state, bank, Budget(steps=50), checkpoint=folder / "ckpt.pt")
    return frames, vol, state, folder
