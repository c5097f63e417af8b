"""Evaluation: baselines, motion figures, and the run-time temperature fitted to the footage."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from dbb_capture.core.metrics import psnr
from dbb_capture.dynamic import evaluate as ev
from dbb_capture.dynamic.data import SequenceData, long_training_runs
from dbb_capture.dynamic.evaluate import (
    CALIBRATION_TEMPERATURES,
    RUN_TEMPERATURE,
    calibrate_temperature,
    evaluate,
    fit_amp_limit,
    motion_coherence,
    motion_energy,
    nearest_training_frames,
    score_rollouts,
    still_view_energy,
    still_view_target,
    view_angle_deg,
    with_temperature,
)
from dbb_capture.dynamic.model import Rssm
from dbb_capture.dynamic.rgba import premultiplied, premultiply
from dbb_capture.dynamic.stepper import Stepper, script_stepper

from .conftest import SMALL, moving_model


def test_on_a_static_sequence_copy_first_is_perfect(data):
    still = SequenceData(data.source, np.repeat(data.rgba[:1], 30, 0), np.repeat(data.views[:1], 30, 0),
                         np.array(["train"] * 15 + ["test"] * 15), np.arange(30) / 10.0,
                         [(0, "train"), (15, "test")], 11)
    rep, figs = evaluate(Stepper(Rssm(SMALL).eval()), still, rollout_steps=8)
    assert rep.split == "test" and rep.windows == 1
    assert rep.psnr["copy_first"] == [120.0] * 10 and rep.psnr["near"] == [120.0] * 10
    assert rep.ssim["copy_first"] == pytest.approx([1.0] * 10)
    assert rep.motion["truth_energy"] == 0 and rep.motion["ratio"] is None
    assert rep.mean("psnr", "model") < 40          # an untrained model is not perfect
    assert set(rep.psnr) == {"model", "model_mean", "near", "copy_first"} and figs["long"].shape[:2] == (1, 8)
    assert set(rep.to_json()["psnr_gain_db"]) == {"vs_copy_first", "vs_near"}


def test_a_path_scored_from_its_own_truth(data):
    """A path along training viewpoints whose truth is those very frames: "near" is perfect and
    its views are 0 deg from the training views; the test windows' report says how far theirs are."""
    train = np.flatnonzero(data.splits == "train")[:data.length * 2].reshape(2, data.length)
    ps, _, figs = score_rollouts(Stepper(Rssm(SMALL).eval()), data, data.rgba[train], data.views[train])
    assert set(ps) == {"model", "model_mean", "near", "copy_first"} and len(ps["near"]) == data.length - 1
    assert min(ps["near"]) >= 60 and figs["truth"].shape == (2, data.length, *data.rgba.shape[1:])
    assert np.allclose(view_angle_deg(data.views[train], data.views[train]), 0, atol=1e-4)
    assert view_angle_deg(np.array([[0.0, 0.0, 1.0]]), np.array([[90.0, 0.0, 2.0]]))[0] == pytest.approx(90.0)
    rep, _ = evaluate(Stepper(Rssm(SMALL).eval()), data, max_windows=2, rollout_steps=4)
    assert rep.to_json()["near_gap_deg"] == pytest.approx(rep.near_gap_deg, abs=0.01) and rep.near_gap_deg >= 0


def test_metrics_known_values(crops, data):
    a, b = np.full((8, 8, 4), 0.5), np.full((8, 8, 4), 0.6)
    assert psnr(a, b) == pytest.approx(20.0)
    assert motion_energy(np.stack([a, b, a])) == pytest.approx(0.1)
    # Coherence: a steady change scores 1, back-and-forth jitter -1, a still sequence nothing.
    ramp = np.stack([np.full((8, 8, 4), 0.1 * t) for t in range(5)])
    assert motion_coherence(ramp) == pytest.approx(1.0)
    assert motion_coherence(np.stack([a, b, a, b])) == pytest.approx(-1.0)
    assert motion_coherence(np.stack([a, a, a])) is None
    # The nearest training frame of a training frame's own viewpoint is that frame (or one seen the same way).
    idx = nearest_training_frames(data, data.views[[2, 7]])
    assert np.allclose(data.views[idx][:, :2], data.views[[2, 7]][:, :2], atol=1.0)
    # The still-viewpoint truth moves: the toy's arms and head are never still.
    assert motion_energy(crops.still_truth.astype(float) / 255) > 1e-3


def test_fixed_camera_footage_is_its_own_still_view_truth(data):
    fixed = replace(data, views=np.repeat(data.views[:1], len(data.rgba), 0))
    rep, _figs = evaluate(Stepper(Rssm(SMALL).eval()), fixed, rollout_steps=8)
    # No test windows here: the still rollout starts at frame 0 and frames 1-8 are its truth.
    assert "fixed camera" in rep.motion["truth_source"] and rep.motion["rollouts"] == 1
    assert rep.motion["truth_energy"] == pytest.approx(motion_energy(premultiplied(data.rgba[1:9])), abs=1e-6)
    # A fixed camera's own change is also the temperature fit's target.
    starts, n = long_training_runs(data, 20, 2)
    frames = premultiplied(fixed.rgba[starts[:, None] + np.arange(1, n)[None]])
    assert still_view_target(moving_model(), fixed, starts, n) == pytest.approx(np.abs(np.diff(frames, axis=1)).mean(),
                                                                                rel=1e-4)


def test_the_still_view_target_makes_up_for_the_decoders_smoothing(data):
    """The posterior's states decoded at a still view change less than the object does, by as much
    as the same states decoded at the frames' own views change less than the frames: the target
    is scaled up by that share."""
    m = moving_model()
    starts, n = long_training_runs(data, 20, 2)
    idx = starts[:, None] + np.arange(n)[None]
    x = torch.from_numpy(data.rgba[idx]).permute(0, 1, 4, 2, 3).float() / 255.0
    v = torch.from_numpy(data.views[idx])
    st = Stepper(m.eval(), 0.0)
    with torch.no_grad():
        h, z = st.start(x[:, 0], v[:, 0])
        still, seen = [], []
        for t in range(1, n):
            h, z = st.observe(h, z, x[:, t], v[:, t])
            still.append(premultiply(st.decode(h, z, v[:, 0])).numpy())
            seen.append(premultiply(st.decode(h, z, v[:, t])).numpy())
    real = motion_energy(premultiplied(data.rgba[idx].swapaxes(0, 1)[1:]))
    share = motion_energy(np.stack(seen)) / real
    assert 0.05 < share < 1                     # an untrained decoder smooths the footage's change
    target = still_view_target(m, data, starts, n)
    assert target == pytest.approx(motion_energy(np.stack(still)) / max(share, 0.25), rel=1e-3)


def test_the_mean_column_needs_an_eager_stepper():
    m = Rssm(SMALL).eval()
    st = Stepper(m, 0.7)
    cold = with_temperature(st, 0.0)
    assert cold.temperature == 0.0 and st.temperature == 0.7 and cold.decoder is st.decoder
    assert with_temperature(script_stepper(m), 0.0) is None


def test_calibrated_temperature_moves_the_still_view_as_much_as_the_footage(data, monkeypatch):
    m = moving_model()
    cal = calibrate_temperature(m, data, steps=20, count=2)
    # The target on runs of training frames; the open loop runs all the steps asked from their starts.
    assert cal.steps == 20 and data.length - 1 <= cal.target_steps <= 20 and len(cal.starts) >= 1
    assert all(data.splits[s:s + cal.target_steps + 1].tolist() == ["train"] * (cal.target_steps + 1) for s in cal.starts)
    starts, n = np.array(cal.starts), cal.steps + 1
    assert cal.target == pytest.approx(still_view_target(m, data, starts, cal.target_steps + 1))
    assert cal.energy[1.0] == pytest.approx(still_view_energy(m, data, starts, n, 1.0))
    es = [cal.energy[t] for t in sorted(cal.energy)]
    assert es[-1] > 1.2 * es[0]                     # sampling moves it
    # Footage between what the temperatures tried give: the fitted one meets it.
    mid = 0.5 * (cal.energy[0.5] + cal.energy[2.0])
    monkeypatch.setattr(ev, "still_view_target", lambda *a: mid)
    fit = calibrate_temperature(m, data, steps=20, count=2)
    assert 0.5 < fit.temperature < 2.0 and fit.note is None
    assert still_view_energy(m, data, starts, n, fit.temperature) == pytest.approx(mid, rel=0.25)
    # Beyond them: the nearest one, said so.
    monkeypatch.setattr(ev, "still_view_target", lambda *a: 2 * es[-1])
    hot = calibrate_temperature(m, data, steps=20, count=2)
    monkeypatch.setattr(ev, "still_view_target", lambda *a: 0.0)
    cold = calibrate_temperature(m, data, steps=20, count=2)
    assert hot.temperature == max(CALIBRATION_TEMPERATURES) and "less than the footage" in hot.note
    assert cold.temperature == min(CALIBRATION_TEMPERATURES) and "more than the footage" in cold.note
    # No run of consecutive training frames: the fixed default, said so.
    alternate = replace(data, splits=np.where(np.arange(len(data.splits)) % 2 == 0, "train", "test"))
    none = calibrate_temperature(m, alternate)
    assert none.temperature == RUN_TEMPERATURE and none.target is None and "consecutive" in none.note


def test_the_oscillator_bound_is_the_largest_length_training_reaches(data):
    m = moving_model(cfg=replace(SMALL, deter=24, osc=4))
    fit_amp_limit(m, data)
    limit = m.gru.amp_limit.clone()
    assert limit.shape == (4,) and bool((limit > 0).all())
    # Another sampling of the training windows' filtering states reaches about as far.
    from dbb_capture.dynamic.data import batch
    x, views = batch(data, data.starts("train"), torch.device("cpu"))
    torch.manual_seed(5)
    with torch.no_grad():
        f = m.observe(m.encoder(x.flatten(0, 1)).view(*x.shape[:2], -1), m.encode_view(views))
        amp = torch.stack([m.gru.amplitude(h) for h in f.h]).amax(dim=(0, 1))
        assert 0.5 < float((amp / limit).max()) < 1.25
        # A long open loop stays finite and within the soft bound's 1.5x.
        h, z = f.h[-1], f.z[-1]
        for _ in range(300):
            h = m.transition(h, z)
            z = m.prior_stats(h)[0] * 3.0
    assert bool(torch.isfinite(h).all()) and bool((m.gru.amplitude(h) <= 1.5 * limit + 1e-5).all())
    fit_amp_limit(m, data)                          # fitted again: the same, not bounded by the first fit
    assert torch.allclose(m.gru.amp_limit, limit)
    plain = moving_model()
    fit_amp_limit(plain, data)                      # no oscillator: nothing to do
    assert not hasattr(plain.gru, "amp_limit")


def test_a_temperature_whose_open_loop_is_not_finite_is_left_out(data, monkeypatch):
    m = moving_model()
    real = ev.still_view_energy
    monkeypatch.setattr(ev, "still_view_energy", lambda *a: float("nan") if a[4] >= 3.0 else real(*a))
    cal = calibrate_temperature(m, data, steps=20, count=2)
    assert cal.temperature <= 2.0 and np.isfinite(cal.temperature)
    doc = cal.to_json()
    assert doc["energy_by_temperature"]["3"] is None and doc["energy_by_temperature"]["1"] is not None
    monkeypatch.setattr(ev, "still_view_energy", lambda *a: float("nan"))
    none = calibrate_temperature(m, data, steps=20, count=2)
    assert none.temperature == RUN_TEMPERATURE and "not finite" in none.note
    assert json.loads(json.dumps(none.to_json(), allow_nan=False))["target_energy"] is None
