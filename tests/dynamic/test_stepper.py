"""The run-time stepper: shapes, TorchScript as eager, the context frame, a view-free transition."""

from __future__ import annotations

from dataclasses import replace

import torch

import pytest

from dbb_capture.core.errors import DbbError
from dbb_capture.dynamic.model import Rssm
from dbb_capture.dynamic.networks import PhaseUp
from dbb_capture.dynamic.stepper import Stepper, rollout, script_stepper

from .conftest import ANCHORED, SMALL, moving_model, random_atlas, scaled


def _eager_and_scripted(m: Rssm, tmp_path, batch: int = 2, steps: int = 6, atlas=None,
                        temperature: float = 1.0, warmup: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Rollouts of ``m`` (with its view anchor's ``atlas``) from the same random frame and views, with
    the same noise, through the eager stepper and through its saved and reloaded TorchScript."""
    path = tmp_path / "stepper.ts"
    script_stepper(m, temperature, atlas, warmup).save(str(path))
    first, views = torch.rand(batch, 4, 32, 32), torch.rand(batch, steps, 3) * 300 - 150
    torch.manual_seed(7)
    eager = rollout(Stepper(m, temperature, atlas, warmup), first, views)
    torch.manual_seed(7)
    return eager, rollout(torch.jit.load(str(path)), first, views)


def test_shapes_range_and_phase_upsampling():
    st = Stepper(Rssm(SMALL).eval())
    assert all(isinstance(u, PhaseUp) for u in st.decoder.ups)
    with torch.no_grad():
        h, z = st.start(torch.rand(3, 4, 32, 32), torch.zeros(3, 3))
        h, z, out = st.step(h, z, torch.zeros(3, 3))
    assert h.shape == (3, 16) and z.shape == (3, 16) and out.shape == (3, 4, 32, 32)
    assert float(out.min()) >= 0 and float(out.max()) <= 1


def test_torchscript_matches_eager(tmp_path):
    for cfg in (SMALL, replace(SMALL, deter=24, osc=4), replace(scaled(keypoints=1.0), keypoints=4, keypoint_maps=True)):
        m = moving_model(cfg=cfg)
        eager, scripted = _eager_and_scripted(m, tmp_path)
        assert eager.shape == (2, 5, 4, 32, 32) and torch.allclose(eager, scripted, atol=1e-5)
    assert float((eager[:, -1] - eager[:, 0]).abs().max()) > 0.05     # the frames do move
    assert torch.jit.load(str(tmp_path / "stepper.ts")).temperature == 1.0


def test_the_temperature_rises_over_the_trained_horizon(tmp_path):
    """From the prior as trained (1) at the context frame to the run-time temperature at step
    ``warmup``, then flat; a temperature below 1 is never exceeded; start() and observe() count again."""
    m = moving_model()
    st = Stepper(m, 3.0, warmup=4)
    first, view = torch.rand(1, 4, 32, 32), torch.zeros(1, 3)
    h, z = st.start(first, view)
    temps = [st.step_temperature()]
    for _ in range(6):
        h, z, _x = st.step(h, z, view)
        temps.append(st.step_temperature())
    assert temps == pytest.approx([1.0, 1.5, 2.0, 2.5, 3.0, 3.0, 3.0])
    st.observe(h, z, first, view)
    assert st.step_temperature() == 1.0
    st.start(first, view)
    assert st.step_temperature() == 1.0
    cool = Stepper(m, 0.5, warmup=4)
    cool.start(first, view)
    assert cool.step_temperature() == 0.5
    assert Stepper(m, 3.0).step_temperature() == 3.0            # no warm-up: flat
    # TorchScript as eager, warm-up included; the warm-up changes the first steps' noise.
    eager, scripted = _eager_and_scripted(m, tmp_path, temperature=3.0, warmup=4)
    flat, _ = _eager_and_scripted(m, tmp_path / "..", temperature=3.0)
    assert torch.allclose(eager, scripted, atol=1e-5) and not torch.allclose(eager[:, 0], flat[:, 0])
    assert torch.jit.load(str(tmp_path / "stepper.ts")).warmup == 4


def test_an_anchored_stepper_carries_its_atlas_and_draws_from_it(tmp_path):
    m = moving_model(cfg=ANCHORED)
    with pytest.raises(DbbError, match="needs its atlas"):
        Stepper(m)
    atlas = random_atlas()
    eager, scripted = _eager_and_scripted(m, tmp_path, atlas=atlas)
    assert torch.allclose(eager, scripted, atol=1e-5)
    # The stepper.ts alone: another atlas changes the frames, so the one inside is the one drawn from.
    other, _ = _eager_and_scripted(m, tmp_path / "..", atlas=random_atlas(seed=1))
    assert float((other - eager).abs().max()) > 0.05


def test_the_transition_does_not_depend_on_the_viewpoint():
    st = Stepper(moving_model())
    st.start(torch.rand(1, 4, 32, 32), torch.tensor([[0.0, 20.0, 0.6]]))    # the context frame
    h0, z0 = torch.randn(1, 16), torch.randn(1, 16)
    torch.manual_seed(3)
    ha, za, xa = st.step(h0, z0, torch.tensor([[0.0, 20.0, 0.6]]))
    st.start(torch.rand(1, 4, 32, 32), torch.tensor([[0.0, 20.0, 0.6]]))
    torch.manual_seed(3)
    hb, zb, xb = st.step(h0, z0, torch.tensor([[120.0, 60.0, 0.9]]))
    assert torch.equal(ha, hb) and torch.equal(za, zb)     # same motion
    assert not torch.allclose(xa, xb)                      # seen from elsewhere


def test_the_context_frame_shows_through():
    st = Stepper(moving_model(2))
    h, z = torch.randn(1, 16), torch.randn(1, 16)
    view = torch.tensor([[10.0, 30.0, 0.6]])
    outs = []
    for first in (torch.zeros(1, 4, 32, 32), torch.ones(1, 4, 32, 32)):
        st.start(first, view)
        torch.manual_seed(4)
        outs.append(st.step(h, z, view)[2])
    assert (outs[1] - outs[0]).abs().mean() > 0.1


def test_observe_and_decode_follow_the_footage_in_torchscript_as_eager(data):
    m = moving_model()
    x = torch.from_numpy(data.rgba[:4]).permute(0, 3, 1, 2).float()[None] / 255.0     # (1, 4, 4, S, S)
    v = torch.from_numpy(data.views[:4])[None]
    outs = []
    for st in (Stepper(m, 0.0), script_stepper(m, 0.0)):
        h, z = st.start(x[:, 0], v[:, 0])
        frames = []
        for t in range(1, 4):
            h, z = st.observe(h, z, x[:, t], v[:, t])
            frames.append(st.decode(h, z, v[:, 0]))
        outs.append(torch.stack(frames))
    assert torch.allclose(outs[0], outs[1], atol=1e-5)
    # The posterior reads the frames: other footage, other states.
    st = Stepper(m, 0.0)
    h, z = st.start(x[:, 0], v[:, 0])
    assert not torch.allclose(st.observe(h, z, x[:, 1], v[:, 1])[1], st.observe(h, z, 1 - x[:, 1], v[:, 1])[1])
