"""Training: the NaN guard, learning, weight decay, the weights' average, latent-only steps, checkpoints."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from dbb_capture.core.errors import DbbError
from dbb_capture.dynamic import train as training
from dbb_capture.dynamic.config import TrainConfig
from dbb_capture.dynamic.model import Rssm
from dbb_capture.dynamic.train import TrainState, read_checkpoint, train

from .conftest import SMALL


def test_nan_guard_skips_bad_steps_and_gives_up_when_diverged(data, monkeypatch):
    real = training.sequence_loss
    calls = {"n": 0}

    def flaky(model, x, v, a=None):
        calls["n"] += 1
        loss, parts = real(model, x, v, a)
        return (loss * float("nan"), parts) if calls["n"] <= 3 else (loss, parts)

    monkeypatch.setattr(training, "sequence_loss", flaky)
    m = Rssm(SMALL)
    tc = TrainConfig(steps=5, batch=2, max_bad_steps=4)
    st = train(TrainState.new(m, tc), data, tc)
    assert st.bad_steps == 3 and st.step == 5
    assert all(torch.isfinite(p).all() for p in m.parameters())
    monkeypatch.setattr(training, "sequence_loss", lambda model, x, v, a=None: (real(model, x, v, a)[0] * float("nan"), {}))
    with pytest.raises(DbbError, match="diverged"):
        train(TrainState.new(m, tc), data, replace(tc, steps=10))


def test_weights_that_end_not_finite_are_refused_not_written(data, monkeypatch, tmp_path):
    tc = TrainConfig(steps=1, batch=2, ema=0.0)
    st = TrainState.new(Rssm(SMALL), tc)
    ck = tmp_path / "checkpoint.pt"
    real_step = st.opt.step

    def poisoned_step(*a, **k):         # a step that is taken but leaves a weight NaN
        real_step(*a, **k)
        with torch.no_grad():
            next(st.model.parameters()).view(-1)[0] = float("nan")

    monkeypatch.setattr(st.opt, "step", poisoned_step)
    with pytest.raises(DbbError, match="diverged: 1 weight tensors"):
        train(st, data, tc, ckpt=ck)
    assert read_checkpoint(ck).step == 0        # the checkpoint from before the first step


def test_tiny_overfit_loss_drops(data):
    torch.manual_seed(0)
    tc = TrainConfig(steps=40, batch=4, lr=2e-3, augment="none")      # the same windows, learned
    st = train(TrainState.new(Rssm(SMALL), tc), data, tc)
    first, last = st.history[0], st.history[-1]
    assert [h["step"] for h in st.history] == [1, 10, 20, 30, 40]
    # (Losses weighted toward moving pixels, on random windows: noisier than a plain error.)
    assert last["rec"] < 0.65 * first["rec"] and last["first_step"] < 0.8 * first["first_step"]


def test_weight_decay_shrinks_the_weights_it_does_not_need():
    # AdamW's decoupled decay: with a zero loss, every step multiplies the weights by 1 - lr x decay.
    m = Rssm(SMALL)
    w0 = m.prior[0].weight.detach().clone()
    for decay, factor in ((0.0, 1.0), (0.5, (1 - 1e-3 * 0.5) ** 3)):
        m.prior[0].weight.data.copy_(w0)
        opt = TrainState.new(m, TrainConfig(lr=1e-3, weight_decay=decay)).opt
        for _ in range(3):
            opt.zero_grad()
            (0.0 * sum(p.sum() for p in m.parameters())).backward()
            opt.step()
        assert torch.allclose(m.prior[0].weight, w0 * factor, atol=1e-7)


def test_moving_average_of_the_weights_is_the_run_model():
    m = Rssm(SMALL)
    st = TrainState.new(m, TrainConfig())
    w = m.prior[0].weight
    st.update_ema(0.9)                                 # starts as the weights
    w0 = w.detach().clone()
    with torch.no_grad():
        w.add_(1.0)
    st.update_ema(0.9)                                 # bias-corrected: (0.9 w0 + 1 w1) / 1.9
    assert torch.allclose(st.ema["prior.0.weight"], w0 + 1 / 1.9, atol=1e-6)
    assert torch.allclose(st.run_model().prior[0].weight, w0 + 1 / 1.9, atol=1e-6)
    assert torch.equal(m.prior[0].weight, w0 + 1.0)    # training keeps its own weights
    for _ in range(200):                               # long after: the plain exponential average
        st.update_ema(0.9)
    assert torch.allclose(st.ema["prior.0.weight"], w0 + 1.0, atol=1e-5)


def test_dynamics_steps_train_the_transition_and_prior_alone_on_their_own_windows(data, monkeypatch):
    """After one step with dynamics_steps the encoder, posterior and decoder are those of a run
    without them, the dynamics are not; those steps read windows of 1 + dynamics_horizon frames."""
    runs = {}
    for extra in (0, 3):
        torch.manual_seed(0)
        tc = TrainConfig(steps=1, batch=2, dynamics_steps=extra, ema=0.0)
        runs[extra] = train(TrainState.new(Rssm(SMALL), tc), data, tc).model.state_dict()
    for name, w in runs[0].items():
        assert torch.equal(w, runs[3][name]) == (name.split(".")[0] not in ("z_in", "gru", "prior")), name
    seen = {"full": [], "latent": []}
    full, latent = training.sequence_loss, training.latent_loss
    monkeypatch.setattr(training, "sequence_loss", lambda m, x, v, a=None: seen["full"].append(x.shape[1]) or full(m, x, v, a))
    monkeypatch.setattr(training, "latent_loss", lambda m, x, v, a=None: seen["latent"].append(x.shape[1]) or latent(m, x, v, a))
    long_len = training.training_windows(data, 12)[1]
    tc = TrainConfig(steps=2, batch=2, dynamics_steps=2, dynamics_horizon=12, ema=0.0)
    train(TrainState.new(Rssm(SMALL), tc), data, tc)
    assert long_len > data.length and seen == {"full": [data.length] * 2, "latent": [long_len] * 4}


def test_checkpoints_resume_the_state_and_refuse_older_ones(data, tmp_path):
    tc = TrainConfig(steps=2, batch=2)
    ck = tmp_path / "checkpoint.pt"
    st = train(TrainState.new(Rssm(SMALL), tc), data, tc, ckpt=ck)
    back = TrainState.load(ck, tc, torch.device("cpu"))
    assert (back.step, back.history, back.ema_updates, back.train_config) == (2, st.history, 2, st.train_config)
    assert all(torch.equal(v, st.model.state_dict()[k]) for k, v in back.model.state_dict().items())
    assert back.opt.state_dict()["state"].keys() == st.opt.state_dict()["state"].keys()
    old = {k: v for k, v in torch.load(ck, weights_only=False).items() if k not in ("format", "version")}
    torch.save(old, tmp_path / "old.pt")
    with pytest.raises(DbbError, match="older version: train the run again"):
        read_checkpoint(tmp_path / "old.pt")
