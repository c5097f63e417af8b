"""RSSM stage: shapes, TorchScript stepper, viewpoint-free transition, NaN guard, resume, learning, metrics."""

from __future__ import annotations

from dataclasses import replace
import json
import math

import numpy as np
import pytest
import torch

from dbb_capture.dynamic import rssm as rssm
from dbb_capture.core.errors import DbbError

# One thread: the CI machine has 2 cores and other tests run beside these.
torch.set_num_threads(1)

# The mechanisms below are tested on the blend composite with the open loop's pixel loss (the
# defaults before the eleventh round); the current defaults have their own tests.
SMALL = rssm.RssmConfig(size=32, deter=16, stoch=16, hidden=64, embed=64, enc_depth=8, dec_depth=8,
                        compose="blend", warp_leak=0.0, motion_weight_of="truth", open_loop_scale=1.0,
                        first_step_scale=0.0)
DEFAULTS = replace(rssm.RssmConfig(), size=32, deter=16, stoch=16, hidden=64, embed=64, enc_depth=8, dec_depth=8)


@pytest.fixture(scope="module")
def crops(tmp_path_factory):
    """A 3-second 32x32 crops.json of the synthetic dynamic toy (10 fps), with still-view truth."""
    return rssm.synthetic_crops(tmp_path_factory.mktemp("rssm") / "ds", seconds=3.0, fps=10, size=32,
                                still_steps=12, samples=1)


@pytest.fixture(scope="module")
def data(crops):
    return rssm.load_sequences(crops.root, 32)


def test_dataset_reads_crops_json_windows_and_viewpoints(crops, data):
    doc = json.loads((crops.root / "crops.json").read_text())
    assert data.rgba.shape == (len(doc["frames"]), 32, 32, 4)
    assert data.length == 11
    assert [s for s, _ in data.windows] == [s["start"] for s in doc["sequences"]]
    assert len(data.starts("train")) > 0 and len(data.starts("test")) == 0  # test split is < 11 frames here
    assert np.allclose(data.views[5], [doc["frames"][5]["viewpoint"][k]
                                       for k in ("azimuth_deg", "elevation_deg", "distance_m")], atol=1e-3)
    assert data.rgba[..., 3].max() == 255 and data.rgba[..., 3].min() == 0    # object with a matte


def test_shapes_and_loss_parts():
    torch.manual_seed(0)
    m = rssm.Rssm(SMALL)
    x = torch.rand(2, 11, 4, 32, 32)
    v = torch.rand(2, 11, 3) * 40
    loss, parts = rssm.sequence_loss(m, x, v)
    assert loss.ndim == 0 and math.isfinite(loss.item())
    assert set(parts) == {"loss", "rec", "open_loop", "kl_dyn", "kl_rep", "overshoot"}
    # The defaults (eleventh round): accumulated warp, no open-loop pixel loss, the first step alone.
    assert (DEFAULTS.compose, DEFAULTS.warp_leak, DEFAULTS.motion_weight_of, DEFAULTS.open_loop_scale,
            DEFAULTS.first_step_scale) == ("accum", 0.1, "both", 0.0, 1.0)
    parts = rssm.sequence_loss(rssm.Rssm(DEFAULTS), x, v)[1]
    assert set(parts) == {"loss", "rec", "first_step", "kl_dyn", "kl_rep", "overshoot"}
    st = rssm.Stepper(m)
    h, z = st.start(torch.rand(3, 4, 32, 32), torch.zeros(3, 3))
    h, z, out = st.step(h, z, torch.zeros(3, 3))
    assert h.shape == (3, 16) and z.shape == (3, 16) and out.shape == (3, 4, 32, 32)
    assert float(out.detach().min()) >= 0 and float(out.detach().max()) <= 1
    assert rssm.view_encoding(v, 4).shape == (2, 11, 16)


@pytest.mark.parametrize("compose", ["blend", "accum"])
def test_open_loop_frames_are_not_decoded_when_no_loss_scores_them(compose):
    # open_loop_scale=0 (PlaNet: the prior learns from the KL and overshooting) skips the open
    # loop's decoding: the same loss as a vanishing weight, without the "open_loop" term's cost.
    x = torch.rand(2, 11, 4, 32, 32)
    v = torch.rand(2, 11, 3) * 40
    out = {}
    for scale in (0.0, 1e-9):
        torch.manual_seed(0)
        m = rssm.Rssm(replace(SMALL, compose=compose, open_loop_scale=scale))
        torch.manual_seed(1)
        out[scale] = rssm.sequence_loss(m, x, v)
    (l0, p0), (l1, p1) = out[0.0], out[1e-9]
    assert "open_loop" not in p0 and "open_loop" in p1
    assert l0.item() == pytest.approx(l1.item(), rel=1e-6)
    for k in ("rec", "kl_dyn", "overshoot"):
        assert p0[k] == pytest.approx(p1[k], rel=1e-6)
    # The run-time step 1 alone (first_step_scale) adds its reconstruction and trains the prior.
    torch.manual_seed(0)
    m = rssm.Rssm(replace(SMALL, compose=compose, open_loop_scale=0.0, first_step_scale=0.5))
    torch.manual_seed(1)
    l2, p2 = rssm.sequence_loss(m, x, v)
    assert l2.item() == pytest.approx(l0.item() + 0.5 * p2["first_step"], rel=1e-5)
    torch.manual_seed(0)
    m0 = rssm.Rssm(replace(SMALL, compose=compose, open_loop_scale=0.0))
    torch.manual_seed(1)
    rssm.sequence_loss(m0, x, v)[0].backward()
    l2.backward()
    assert not torch.allclose(m.prior[-1].weight.grad, m0.prior[-1].weight.grad)


def _eager_and_scripted_rollouts(m: rssm.Rssm, tmp_path, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Five-step rollouts of ``m`` (32 px) from the same random frame and views, with the same
    noise, through the eager stepper and through its saved and reloaded TorchScript."""
    path = tmp_path / "stepper.ts"
    rssm.script_stepper(m).save(str(path))
    ts = torch.jit.load(str(path))
    first, views = torch.rand(batch, 4, 32, 32), torch.rand(batch, 6, 3) * 60
    torch.manual_seed(7)
    eager = rssm.rollout(rssm.Stepper(m), first, views)
    torch.manual_seed(7)
    return eager, rssm.rollout(ts, first, views)


def test_torchscript_round_trip_matches_eager(tmp_path):
    torch.manual_seed(1)
    eager, scripted = _eager_and_scripted_rollouts(rssm.Rssm(SMALL).eval(), tmp_path, 2)
    assert eager.shape == (2, 5, 4, 32, 32)
    assert torch.allclose(eager, scripted, atol=1e-5)


def test_transition_does_not_depend_on_the_viewpoint():
    m = rssm.Rssm(SMALL).eval()
    # Structural: nothing in the transition has room for a viewpoint input.
    assert m.z_in[0].in_features == SMALL.stoch and m.gru.input_size == SMALL.hidden
    assert m.prior[0].in_features == SMALL.deter
    st = rssm.Stepper(m)
    st.start(torch.rand(1, 4, 32, 32), torch.tensor([[0.0, 20.0, 0.6]]))    # the context frame
    h0, z0 = torch.randn(1, 16), torch.randn(1, 16)
    torch.manual_seed(3)
    ha, za, xa = st.step(h0, z0, torch.tensor([[0.0, 20.0, 0.6]]))
    torch.manual_seed(3)
    hb, zb, xb = st.step(h0, z0, torch.tensor([[120.0, 60.0, 0.9]]))
    assert torch.equal(ha, hb) and torch.equal(za, zb)     # same motion
    assert not torch.allclose(xa, xb)                      # seen from elsewhere


def test_nan_guard_skips_bad_steps_and_gives_up_when_diverged(data, monkeypatch):
    real = rssm.sequence_loss
    calls = {"n": 0}

    def flaky(model, x, v):
        calls["n"] += 1
        loss, parts = real(model, x, v)
        return (loss * float("nan"), parts) if calls["n"] <= 3 else (loss, parts)

    monkeypatch.setattr(rssm, "sequence_loss", flaky)
    m = rssm.Rssm(SMALL)
    tc = rssm.TrainConfig(steps=5, batch=2, max_bad_steps=4)
    st = rssm.train(rssm.TrainState(m, rssm._optimizer(m, tc)), data, tc)
    assert st.bad_steps == 3 and st.step == 5
    assert all(torch.isfinite(p).all() for p in m.parameters())
    monkeypatch.setattr(rssm, "sequence_loss", lambda model, x, v: (real(model, x, v)[0] * float("nan"), {}))
    with pytest.raises(DbbError, match="diverged"):
        rssm.train(rssm.TrainState(m, rssm._optimizer(m, tc)), data, replace_steps(tc, 10))


def replace_steps(tc, n):

    return replace(tc, steps=n)


def test_tiny_overfit_loss_drops(data):
    torch.manual_seed(0)
    m = rssm.Rssm(SMALL)
    tc = rssm.TrainConfig(steps=40, batch=4, lr=2e-3, augment="none")      # the same windows, learned
    st = rssm.train(rssm.TrainState(m, rssm._optimizer(m, tc)), data, tc)
    first, last = st.history[0], st.history[-1]
    # (Losses weighted toward moving pixels, on random frames of the windows: noisier than a plain error.)
    assert last["rec"] < 0.65 * first["rec"]
    assert last["open_loop"] < 0.65 * first["open_loop"]


def test_run_folder_cli_resume_and_eval(crops, tmp_path):
    from click.testing import CliRunner
    from dbb_capture.cli import train as cli

    out = tmp_path / "run"
    r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(out), "--size", "32", "--steps", "3",
                                      "--batch", "2", "--threads", "1"])
    assert r.exit_code == 0, r.output
    assert "open-loop PSNR" in r.output
    for f in ("run.json", "model.pt", "stepper.ts", "checkpoint.pt", "report/eval.json", "report/plots.png",
              "report/strip.png", "report/rollout.png"):
        assert (out / f).is_file(), f
    meta = json.loads((out / "run.json").read_text())
    assert meta["training"]["steps"] == 3 and meta["model"]["config"]["size"] == 32
    cal = meta["stepper"]["temperature_calibration"]       # fitted to the footage by default
    assert cal["steps"] >= 10 and cal["temperature"] == meta["stepper"]["temperature"]
    assert "run-time temperature" in r.output
    ev = meta["eval"]
    assert ev["split"] == "train" and len(ev["psnr_db"]["model"]) == 10
    assert set(ev["mean_psnr_db"]) == {"model", "model_mean", "near", "copy_first"}
    with pytest.raises(DbbError, match="already exists"):
        rssm.train_run(crops.root, out, SMALL, rssm.TrainConfig(steps=3, batch=2), quiet=True)
    meta2 = rssm.train_run(crops.root, out, SMALL, rssm.TrainConfig(steps=5, batch=2), resume=True, quiet=True)
    assert meta2["training"]["steps"] == 5 and meta2["training"]["final"]["step"] == 5
    assert meta2["model"]["config"] == meta["model"]["config"]       # resumed, not restarted with SMALL
    ts = torch.jit.load(str(out / "stepper.ts"))
    h, z = ts.start(torch.rand(1, 4, 32, 32), torch.zeros(1, 3))
    assert ts.step(h, z, torch.zeros(1, 3))[2].shape == (1, 4, 32, 32)
    r = CliRunner().invoke(cli.main, ["rssm-eval", str(out), "--temperature", "0.5"])
    assert r.exit_code == 0, r.output
    st = json.loads((out / "run.json").read_text())["stepper"]
    assert st["temperature"] == 0.5 and st["temperature_calibration"] is None     # set by hand
    assert torch.jit.load(str(out / "stepper.ts")).temperature == 0.5
    assert not (out / ".report.partial").exists() and (out / "report" / "eval.json").is_file()
    r = CliRunner().invoke(cli.main, ["rssm-eval", str(out), "--calibrate"])
    assert r.exit_code == 0, r.output
    st = json.loads((out / "run.json").read_text())["stepper"]
    assert st["temperature_calibration"]["temperature"] == st["temperature"]
    assert torch.jit.load(str(out / "stepper.ts")).temperature == st["temperature"]
    r = CliRunner().invoke(cli.main, ["rssm-eval", str(out), "--calibrate", "--temperature", "1"])
    assert r.exit_code == 2 and "not both" in r.output
    # Settings other than the defaults, by name; a wrong one is one clear line.
    r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(tmp_path / "acc"), "--size", "32",
                                      "--steps", "2", "--batch", "2", "--threads", "1", "--set", "compose=accum",
                                      "--set", "warp_leak=0.1", "--set", "augment=none"])
    assert r.exit_code == 0, r.output
    cfg = json.loads((tmp_path / "acc" / "run.json").read_text())["model"]["config"]
    assert cfg["compose"] == "accum" and cfg["warp_leak"] == 0.1 and cfg["size"] == 32
    # --resume keeps the run's training settings (augment=none) unless told otherwise (--batch here).
    r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(tmp_path / "acc"), "--steps", "3",
                                      "--batch", "3", "--threads", "1", "--resume"])
    assert r.exit_code == 0, r.output
    _cfg, tcfg = rssm.resume_configs(tmp_path / "acc")
    assert tcfg.augment == "none" and tcfg.batch == 3 and tcfg.steps == 3
    assert json.loads((tmp_path / "acc" / "run.json").read_text())["training"]["steps"] == 3
    for bad in ("warp_leek=0.1", "warp_leak=lots", "compose"):
        r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(tmp_path / "y"), "--set", bad])
        lines = [ln for ln in r.output.splitlines() if ln.strip()]
        assert r.exit_code == 2 and len(lines) == 1 and "--set" in lines[0], r.output
    assert not (tmp_path / "y").exists()
    r = CliRunner().invoke(cli.main, ["rssm", str(tmp_path / "missing"), "-o", str(tmp_path / "x")])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error:"), r.output
    assert not (tmp_path / "x").exists()


def test_presets_expand_under_later_settings():
    from dbb_capture.cli import train as cli

    cfg, tcfg = rssm.configs_from_settings(["preset=swing", "osc=8"])
    assert cfg.keypoint_maps and cfg.keypoint_teacher and cfg.compose == "accum" and tcfg.dynamics_horizon == 60
    assert cfg.osc == 8                                    # a later pair wins over the preset's
    with pytest.raises(DbbError, match="no such preset"):
        rssm.configs_from_settings(["preset=wobble"])
    opt = next(p for p in cli.rssm.params if p.name == "preset")
    assert set(opt.type.choices) == set(rssm.PRESETS)      # the command offers each preset


def test_eval_on_a_static_sequence_copy_first_is_perfect(data):
    still = rssm.SequenceData(data.source, np.repeat(data.rgba[:1], 30, 0), np.repeat(data.views[:1], 30, 0),
                              np.array(["train"] * 15 + ["test"] * 15), np.arange(30) / 10.0,
                              [(0, "train"), (15, "test")], 11)
    rep, _figs = rssm.evaluate(rssm.Stepper(rssm.Rssm(SMALL).eval()), still, rollout_steps=8)
    assert rep.split == "test" and rep.windows == 1
    assert rep.psnr["copy_first"] == [120.0] * 10 and rep.psnr["near"] == [120.0] * 10
    assert rep.ssim["copy_first"] == pytest.approx([1.0] * 10)
    assert rep.motion["truth_energy"] == 0 and rep.motion["ratio"] is None
    assert rep.mean("psnr", "model") < 40          # an untrained model is not perfect


def test_metrics_known_values(crops, data):
    a, b = np.full((8, 8, 4), 0.5), np.full((8, 8, 4), 0.6)
    assert rssm.psnr(a, b) == pytest.approx(20.0)
    assert rssm.motion_energy(np.stack([a, b, a])) == pytest.approx(0.1)
    # Coherence: a steady change scores 1, back-and-forth jitter -1, a still sequence nothing.
    ramp = np.stack([np.full((8, 8, 4), 0.1 * t) for t in range(5)])
    assert rssm.motion_coherence(ramp) == pytest.approx(1.0)
    assert rssm.motion_coherence(np.stack([a, b, a, b])) == pytest.approx(-1.0)
    assert rssm.motion_coherence(np.stack([a, a, a])) is None
    # The nearest training frame of a training frame's own viewpoint is that frame (or one seen the same way).
    idx = rssm.nearest_training_frames(data, data.views[[2, 7]])
    assert np.allclose(data.views[idx][:, :2], data.views[[2, 7]][:, :2], atol=1.0)
    # The still-viewpoint truth moves: the toy's arms and head are never still.
    assert rssm.motion_energy(crops.still_truth.astype(float) / 255) > 1e-3


def test_bad_inputs(tmp_path, crops):
    with pytest.raises(DbbError):
        rssm.RssmConfig(size=48).validate()
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": [{"file_path": "a.png"}]}))
    with pytest.raises(DbbError, match="crops.json"):
        rssm.load_sequences(tmp_path)
    with pytest.raises(DbbError, match="nothing to resume"):
        rssm.train_run(crops.root, tmp_path / "none", SMALL, rssm.TrainConfig(steps=1), resume=True)


def test_fixed_camera_footage_is_its_own_still_view_truth(data):
    fixed = rssm.SequenceData(data.source, data.rgba, np.repeat(data.views[:1], len(data.rgba), 0), data.splits,
                              data.times, data.windows, data.length)
    assert rssm.fixed_camera(fixed) and not rssm.fixed_camera(data)
    rep, _figs = rssm.evaluate(rssm.Stepper(rssm.Rssm(SMALL).eval()), fixed, rollout_steps=8)
    # No test windows here: the still rollout starts at frame 0 and frames 1-8 are its truth.
    assert "fixed camera" in rep.motion["truth_source"] and rep.motion["rollouts"] == 1
    truth = rssm._pm_np(data.rgba[1:9])
    assert rep.motion["truth_energy"] == pytest.approx(rssm.motion_energy(truth), abs=1e-6)


def test_skip_path_decodes_from_the_context_frame_and_old_runs_load():
    torch.manual_seed(2)
    m = rssm.Rssm(SMALL).eval()
    st = rssm.Stepper(m)
    h, z = torch.randn(1, 16), torch.randn(1, 16)
    view = torch.tensor([[10.0, 30.0, 0.6]])
    outs = []
    for first in (torch.zeros(1, 4, 32, 32), torch.ones(1, 4, 32, 32)):
        st.start(first, view)
        torch.manual_seed(4)
        outs.append(st.step(h, z, view)[2])
    assert (outs[1] - outs[0]).abs().mean() > 0.1           # the context frame shows through
    # A run written before the skip path (decoder "convs" Sequential, no "skip" in its config) loads.
    old_cfg = {k: v for k, v in vars(replace_cfg(SMALL, skip=False)).items() if k != "skip"}
    old = rssm.Rssm(rssm.RssmConfig.from_json(old_cfg))
    state = {}
    for k, v in old.state_dict().items():
        if k.startswith("decoder.ups."):
            i, rest = k[len("decoder.ups."):].split(".", 1)
            k = f"decoder.convs.{2 * int(i)}.{rest}"
        state[k] = v
    assert not old.cfg.skip and any(k.startswith("decoder.convs.") for k in state)
    fresh = rssm.Rssm(rssm.RssmConfig.from_json(old_cfg))
    fresh.load_state_dict(state)
    assert torch.equal(fresh.decoder.ups[-1].weight, old.decoder.ups[-1].weight)


def replace_cfg(cfg, **kw):

    return replace(cfg, **kw)


def test_training_windows_are_long_runs_of_consecutive_training_frames(data):
    starts, length = rssm.training_windows(data, 30)
    # 24 training frames here: the longest windows that still give >= 12 starts.
    n_train = int((data.splits == "train").sum())
    assert data.length < length <= n_train and len(starts) >= n_train // 2
    idx = starts[:, None] + np.arange(length)[None]
    assert (data.splits[idx] == "train").all()
    assert np.allclose(np.diff(data.times[idx], axis=1), 0.1)
    assert rssm.training_windows(data, None) == (pytest.approx(data.starts("train")), data.length)
    # A gap in time (a dropped frame) splits the runs: no window crosses it.
    n = 60
    times = np.arange(n) / 10.0 + np.where(np.arange(n) >= 20, 1.0, 0.0)
    gapped = rssm.SequenceData(data.source, data.rgba[np.arange(n) % len(data.rgba)], np.zeros((n, 3), np.float32),
                               np.array(["train"] * n), times, [(0, "train")], 11)
    starts, length = rssm.training_windows(gapped, 30)
    assert length > 11 and len(starts) >= 30
    assert all(s + length <= 20 or s >= 20 for s in starts)


def test_open_loop_starts_after_two_frames_and_motion_weights(monkeypatch):
    torch.manual_seed(0)
    x = torch.rand(2, 11, 4, 32, 32)
    v = torch.rand(2, 11, 3) * 40
    for k, n_open in ((0, 10), (1, 9), (3, 7)):
        m = rssm.Rssm(replace_cfg(SMALL, open_loop_from=k))
        decoded = []
        real = m.decoder.forward
        monkeypatch.setattr(m.decoder, "forward", lambda f, c, p: decoded.append(len(f)) or real(f, c, p))
        rssm.sequence_loss(m, x, v)
        # Filtering frames, then the open loop (and, from k >= 1, frame 1 from the prior: prior_first).
        assert decoded == [2 * 11, 2 * (n_open + (k >= 1))]
    # A long window is decoded sparsely: decode_frames (+ 1 filtering) frames, the transition runs all 30 steps.
    decoded.clear()
    rssm.sequence_loss(m, torch.rand(2, 31, 4, 32, 32), torch.rand(2, 31, 3))
    assert decoded == [2 * 11, 2 * (10 + 1)]
    ti = rssm._decoded(31, 10, 4, torch.device("cpu"))
    assert len(ti) == 10 and ti.min() >= 4 and ti.max() <= 30 and bool((ti.diff() > 0).all())
    w = rssm.motion_weights(torch.stack([torch.zeros(4, 8, 8), torch.zeros(4, 8, 8), torch.ones(4, 8, 8)])[None], 10.0)
    assert w.shape == (1, 3, 1, 8, 8)
    assert torch.equal(w[0, :2], torch.ones(2, 1, 8, 8)) and torch.equal(w[0, 2], torch.full((1, 8, 8), 11.0))
    # The same model with and without the weights: changing pixels count more.
    torch.manual_seed(0)
    m = rssm.Rssm(replace_cfg(SMALL, motion_weight=0.0))
    mw = rssm.Rssm(replace_cfg(SMALL, motion_weight=10.0))
    mw.load_state_dict(m.state_dict())
    torch.manual_seed(1)
    plain = rssm.sequence_loss(m, x, v)[1]["rec"]
    torch.manual_seed(1)
    assert rssm.sequence_loss(mw, x, v)[1]["rec"] > 2 * plain


def test_copy3_composite_copies_the_context_frame_exactly_and_starts_near_it():
    torch.manual_seed(5)
    m = rssm.Rssm(replace_cfg(SMALL, compose="copy3")).eval()
    assert m.decoder.ups[-1].out_channels == 9
    ctx_pm = rssm.premultiply(torch.rand(2, 4, 32, 32))
    ctx = m.encoder.features(ctx_pm)
    feat = torch.randn(2, m.decoder.fc[0].in_features)
    with torch.no_grad():
        # Untrained: mostly the context frame as is (sharp, no resampling blur).
        out = m.decoder(feat, ctx, ctx_pm)
        assert rssm.psnr(out.numpy(), ctx_pm.numpy()) > 20
        # Copy logit dominant: the context frame exactly, whatever the flow.
        m.decoder.ups[-1].bias[4] = 100.0
        m.decoder.ups[-1].bias[7:] = 5.0
        assert torch.allclose(m.decoder(feat, ctx, ctx_pm), ctx_pm, atol=1e-5)
    # The single-mask blend has no unwarped candidate: the same logits warp the frame.
    torch.manual_seed(5)
    b = rssm.Rssm(SMALL).eval()
    with torch.no_grad():
        b.decoder.ups[-1].bias[4] = 100.0
        b.decoder.ups[-1].bias[5:] = 5.0
        assert not torch.allclose(b.decoder(feat, b.encoder.features(ctx_pm), ctx_pm), ctx_pm, atol=1e-2)
    with pytest.raises(DbbError, match="compose"):
        replace_cfg(SMALL, compose="nope").validate()


def test_sharpness_match_costs_a_faded_part_not_a_moved_one():
    # A 4x4 ball on a flat wall: drawn 10 px away it is sharp (no cost here, though squared error
    # counts it twice); the mean of the places it may be (a fade) costs.
    wall = torch.full((1, 4, 32, 32), 0.5)
    def ball(x0):
        f = wall.clone()
        f[:, 0, 14:18, x0:x0 + 4] = 1.0
        return f
    truth = ball(4)
    assert rssm.sharpness_match(ball(14), truth).item() == pytest.approx(0.0, abs=1e-9)
    fade = torch.cat([ball(x0) for x0 in range(4, 24, 2)]).mean(0, keepdim=True)
    assert rssm.sharpness_match(fade, truth).item() > 0.5
    assert ((fade - truth) ** 2).sum() < ((ball(14) - truth) ** 2).sum()   # squared error prefers the fade
    # Descending it sharpens a faded frame.
    pred = fade.clone().requires_grad_()
    rssm.sharpness_match(pred, truth).backward()
    nxt = (pred - 0.05 * pred.grad).detach()
    assert rssm.sharpness_match(nxt, truth) < rssm.sharpness_match(fade, truth)
    # In the loss only when asked for (sequence_loss reports it as "sharp").
    x, v = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 40
    assert "sharp" not in rssm.sequence_loss(rssm.Rssm(SMALL), x, v)[1]
    for compose in ("blend", "accum"):
        loss, parts = rssm.sequence_loss(rssm.Rssm(replace_cfg(SMALL, compose=compose, sharp_scale=2.0)), x, v)
        assert parts["sharp"] > 0 and torch.isfinite(loss)
        loss.backward()
    with pytest.raises(DbbError, match="sharp_scale"):
        replace_cfg(SMALL, sharp_scale=-1.0).validate()


def test_sharpness_match_on_moving_pixels_ignores_the_fixed_texture():
    # A striped wall (fixed texture) and a ball that moves across it: matched over the whole frame a
    # prediction whose wall texture is blurred costs, though it draws the ball sharp; restricted to
    # where the truth moves (sharp_where="moving") only the ball's region counts.
    torch.manual_seed(0)
    wall = torch.full((1, 1, 4, 32, 32), 0.5)
    wall[..., 24:, ::2] = 0.2                           # stripes where nothing moves
    def frame(x0, w=wall):
        f = w.clone()
        f[..., 2:6, x0:x0 + 4] = 1.0
        return f
    truth = torch.cat([frame(4), frame(8), frame(12)], 1)          # (1, 3, 4, 32, 32)
    env = rssm.motion_envelope(truth)
    assert env.shape == (1, 1, 32, 32) and env.max().item() == pytest.approx(1.0)
    assert env[..., 24:, :].abs().max().item() == 0.0 and env[..., 2:6, 4:16].min().item() > 0.5
    flat = wall.clone()
    flat[..., 24:, :] = 0.35                            # the stripes averaged away
    pred = frame(10, flat)[:, 0]                        # the ball sharp (elsewhere), the wall blurred
    t = truth[:, 2]
    assert rssm.sharpness_match(pred, t).item() > 1.0
    assert rssm.sharpness_match(pred, t, env).item() == pytest.approx(0.0, abs=1e-6)
    fade = torch.stack([frame(x0)[:, 0] for x0 in (4, 8, 12)]).mean(0)    # the ball faded: still costs
    assert rssm.sharpness_match(fade, t, env).item() > 0.1
    # In the loss: "moving" gives a different (smaller, here) term than "all"; bad values refused.
    x, v = torch.rand(2, 11, 4, 32, 32) * 0.2, torch.rand(2, 11, 3) * 40
    x[:, :, :, 4:8] = torch.rand(2, 11, 4, 4, 32)        # only these rows change much
    parts = {}
    for where in ("all", "moving"):
        torch.manual_seed(1)
        m = rssm.Rssm(replace_cfg(SMALL, compose="accum", sharp_scale=1.0, sharp_where=where))
        loss, parts[where] = rssm.sequence_loss(m, x, v)
        assert torch.isfinite(loss)
    assert 0 < parts["moving"]["sharp"] < parts["all"]["sharp"]
    with pytest.raises(DbbError, match="sharp_where"):
        replace_cfg(SMALL, sharp_where="edges").validate()


def test_pyramid_err_pulls_a_far_warp_toward_the_truth():
    # A 4x4 ball warped sideways (backward flow) toward a truth 14 px away: at full size the error
    # is flat until the two overlap (no gradient for the flow); blurred at coarser scales it falls
    # all the way, and its gradient points the flow toward the truth.
    S = 64
    ctx = torch.full((1, 4, S, S), 0.5)
    ctx[:, 0, 30:34, 30:34] = 1.0
    truth = torch.full((1, 4, S, S), 0.5)
    truth[:, 0, 30:34, 44:48] = 1.0
    grid = rssm.identity_grid(1, S)
    region = torch.zeros(1, S, S, 1)
    region[:, 20:44, 12:60] = 1.0

    def warped(px):
        flow = region * torch.stack([px * 2.0 / S, torch.zeros(())])
        return torch.nn.functional.grid_sample(ctx, grid + flow, align_corners=False, padding_mode="border")

    shifts = [-0.5 - i for i in range(13)]
    full = [((warped(torch.tensor(p)) - truth) ** 2).sum().item() for p in shifts]
    pyr = [rssm.pyramid_err(warped(torch.tensor(p)), truth, 3).item() for p in shifts]
    assert max(full[:9]) - min(full[:9]) < 1e-4                  # no overlap: flat at full size
    assert all(b < a for a, b in zip(pyr, pyr[1:]))              # coarse: falls at every step
    px = torch.tensor(-3.5, requires_grad=True)
    rssm.pyramid_err(warped(px), truth, 3).backward()
    assert px.grad.item() > 0                                    # descending moves the ball right
    assert rssm.pyramid_err(truth, truth, 3).item() == 0.0
    # In the loss only when asked for, every compose; bad values refused.
    x, v = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 40
    assert "pyramid" not in rssm.sequence_loss(rssm.Rssm(SMALL), x, v)[1]
    for compose in ("blend", "accum"):
        loss, parts = rssm.sequence_loss(rssm.Rssm(replace_cfg(SMALL, compose=compose, pyramid_scale=1.0)), x, v)
        assert parts["pyramid"] > 0 and torch.isfinite(loss)
    with pytest.raises(DbbError, match="pyramid"):
        replace_cfg(SMALL, pyramid_levels=0).validate()


def test_pyramid_on_scores_the_filtering_or_the_open_loop_frames_only(monkeypatch):
    # pyramid_on picks which decoded frames the coarse-scale error sees: "filter" the filtering
    # frames (those of the reconstruction loss), "open_loop" the sampled open loop, "both" both.
    x, v = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 40
    rec_preds, pyr_preds = [], []
    real_rec, real_pyr = rssm._rec_loss, rssm.pyramid_err
    monkeypatch.setattr(rssm, "_rec_loss", lambda pred, *a: rec_preds.append(pred) or real_rec(pred, *a))
    monkeypatch.setattr(rssm, "pyramid_err", lambda pred, *a: pyr_preds.append(pred) or real_pyr(pred, *a))
    for compose in ("blend", "accum"):
        seen = {}
        for on in ("both", "filter", "open_loop"):
            rec_preds.clear(); pyr_preds.clear()
            torch.manual_seed(0)
            m = rssm.Rssm(replace_cfg(SMALL, compose=compose, pyramid_scale=1.0, pyramid_on=on))
            loss, parts = rssm.sequence_loss(m, x, v)
            assert torch.isfinite(loss) and parts["pyramid"] > 0
            filt = [p is rec_preds[0] for p in pyr_preds]
            seen[on] = (filt, parts["pyramid"])
        assert seen["both"][0] == [True, False]
        assert seen["filter"][0] == [True] and seen["open_loop"][0] == [False]
        # Same seed, same frames: the two parts add up to the whole.
        assert seen["filter"][1] + seen["open_loop"][1] == pytest.approx(seen["both"][1], rel=1e-4)
    with pytest.raises(DbbError, match="pyramid_on"):
        replace_cfg(SMALL, pyramid_on="posterior").validate()


def test_open_loop_temperature_scales_the_training_samples_only(monkeypatch):
    # The open loop's prior samples are mean + temperature * std * noise; 0 gives the mean.
    torch.manual_seed(0)
    x, v = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 40
    seen = []
    real = rssm.Rssm.prior_stats
    def spy(self, h):
        m, s = real(self, h)
        seen.append((m, s))
        return m, s
    monkeypatch.setattr(rssm.Rssm, "prior_stats", spy)
    drawn = []
    real_chain = rssm.Rssm.decode_chain
    def chain(self, h, z, *a):
        drawn.append(z.detach())
        return real_chain(self, h, z, *a)
    monkeypatch.setattr(rssm.Rssm, "decode_chain", chain)
    spread = {}
    for temp in (0.0, 1.0, 3.0):
        seen.clear(); drawn.clear()
        torch.manual_seed(2)
        m = rssm.Rssm(replace_cfg(SMALL, compose="accum", open_loop_temperature=temp))
        loss, _ = rssm.sequence_loss(m, x, v)
        assert torch.isfinite(loss)
        # The last chain is the open loop (frames 2..10); its z against the prior means seen last.
        z = drawn[-1]
        means = torch.stack([mm for mm, _ in seen[-(z.shape[1] + 1):-1]], 1)
        stds = torch.stack([ss for _, ss in seen[-(z.shape[1] + 1):-1]], 1)
        spread[temp] = ((z - means) / stds).pow(2).mean().sqrt().item()
    assert spread[0.0] == pytest.approx(0.0, abs=1e-5)
    assert 0.7 < spread[1.0] < 1.3 and 2.2 < spread[3.0] < 3.8
    with pytest.raises(DbbError, match="open_loop_temperature"):
        replace_cfg(SMALL, open_loop_temperature=-1.0).validate()


def test_energy_match_asks_the_open_loop_to_move_as_much_as_the_truth():
    torch.manual_seed(0)
    moving = torch.rand(3, 6, 4, 8, 8)
    still = moving[:, :1].expand(-1, 6, -1, -1, -1)
    assert rssm.energy_match(moving, moving).item() == pytest.approx(0.0, abs=1e-9)
    pred = (still + 0.01 * torch.randn_like(still)).requires_grad_()
    e = rssm.energy_match(pred, moving)
    assert e.item() > 1.0
    e.backward()                                              # descending the term moves the frames apart
    nxt = (pred - 0.01 * pred.grad / pred.grad.abs().max()).detach()
    d = lambda f: (f[:, 1:] - f[:, :-1]).abs().mean().item()
    assert d(nxt) > d(pred.detach())
    # In the loss only when asked for.
    x, v = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 40
    m = rssm.Rssm(replace_cfg(SMALL, energy_scale=1.0))
    assert "energy" in rssm.sequence_loss(m, x, v)[1]
    assert "energy" not in rssm.sequence_loss(rssm.Rssm(SMALL), x, v)[1]


def test_prior_first_decodes_the_run_time_first_step_from_a_prior_sample(monkeypatch):
    torch.manual_seed(0)
    x, v = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 40
    m = rssm.Rssm(replace_cfg(SMALL, prior_first=True, energy_scale=1.0))
    decoded, priors = [], []
    real_dec, real_prior = m.decoder.forward, m.prior_stats
    monkeypatch.setattr(m.decoder, "forward", lambda f, c, p: decoded.append(len(f)) or real_dec(f, c, p))
    monkeypatch.setattr(m, "prior_stats", lambda h: priors.append(h) or real_prior(h))
    _, parts = rssm.sequence_loss(m, x, v)
    assert decoded == [2 * 11, 2 * (1 + 9)]                 # frame 1 from the prior, then the open loop 2..10
    assert "energy" in parts
    # The prior is asked at h_1 of the filtering pass (11 filtering steps, 9 open-loop steps, then frame 1).
    assert len(priors) == 11 + 9 + 1 and torch.equal(priors[20], priors[1])


def test_view_delta_encodes_the_change_of_viewpoint_since_the_context_frame():
    torch.manual_seed(0)
    v1, v0 = torch.rand(5, 3) * 300 - 150, torch.rand(5, 3) * 300 - 150
    pe1, pe0 = rssm.view_encoding(v1, 4), rssm.view_encoding(v0, 4)
    d = rssm.view_delta_encoding(pe1, pe0, 4)
    assert torch.allclose(d, rssm.view_encoding(v1 - v0, 4), atol=1e-5)
    # In the decoder's input (training and the TorchScript stepper agree).
    for mode, n_views in (("both", 3), ("relative", 1)):
        m = rssm.Rssm(replace_cfg(SMALL, decoder_view=mode)).eval()
        assert m.decoder.fc[0].in_features == 16 + 16 + n_views * 16
        first, views = torch.rand(1, 4, 32, 32), torch.rand(1, 4, 3) * 60
        torch.manual_seed(7)
        eager = rssm.rollout(rssm.Stepper(m), first, views)
        torch.manual_seed(7)
        assert torch.allclose(eager, rssm.rollout(rssm.script_stepper(m), first, views), atol=1e-5)
        assert math.isfinite(rssm.sequence_loss(m, torch.rand(1, 11, 4, 32, 32), torch.rand(1, 11, 3))[0].item())
    # Relative: turning the context and the current view together tells the decoder nothing new.
    h, z = torch.randn(5, 16), torch.randn(5, 16)
    feats = [rssm.decoder_features(h, z, rssm.view_encoding(v1 + turn, 4), rssm.view_encoding(v0 + turn, 4),
                                   True, "relative", 4) for turn in (torch.zeros(3), torch.tensor([90.0, 0, 0]))]
    assert torch.allclose(feats[0], feats[1], atol=1e-5)
    with pytest.raises(DbbError, match="decoder_view"):
        replace_cfg(SMALL, decoder_view="nope").validate()
    # Relative is the default; runs written before the setting existed were absolute, and load so.
    assert rssm.RssmConfig().decoder_view == "relative"
    assert rssm.RssmConfig.from_json({"size": 32}).decoder_view == "absolute"
    # Runs written before the eleventh round's defaults keep the settings they were trained with.
    old = rssm.RssmConfig.from_json({"size": 32, "skip": True, "compose": "blend"})
    assert (old.warp_leak, old.motion_weight_of, old.open_loop_scale, old.first_step_scale) == (0.0, "truth", 1.0, 0.0)


def test_best_of_k_scores_each_window_by_its_best_sample():
    # 2 copies x 2 windows x 3 frames of per-pixel errors (4 pixels).
    err = torch.zeros(2, 2, 3, 4)
    err[0, 0] = 1.0             # window 0: copy 0 bad, copy 1 perfect
    err[1, 1] = 2.0             # window 1: copy 1 worse than copy 0
    err[0, 1] = 0.5
    assert rssm.best_of(err.flatten(0, 2), 2, 2).item() == pytest.approx((0.0 + 4 * 0.5) / 2)
    assert rssm.best_of(err[:1].flatten(0, 2), 1, 2).item() == pytest.approx((4 * 1.0 + 4 * 0.5) / 2)
    torch.manual_seed(0)
    x, v = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 40
    m = rssm.Rssm(replace_cfg(SMALL, open_loop_samples=3))
    loss, _ = rssm.sequence_loss(m, x, v)
    assert math.isfinite(loss.item())
    with pytest.raises(DbbError, match="open_loop_samples"):
        replace_cfg(SMALL, open_loop_samples=0).validate()


def test_filter_decode_prior_decodes_the_filtering_frames_from_prior_samples(monkeypatch):
    torch.manual_seed(0)
    x, v = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 40
    zs = {}
    for mode in ("posterior", "prior"):
        m = rssm.Rssm(replace_cfg(SMALL, filter_decode=mode, open_loop_scale=0.0))
        with torch.no_grad():           # prior mean +5, posterior mean -5, both std ~min_std
            for net, mean in ((m.prior, 5.0), (m.post, -5.0)):
                net[-1].weight.zero_()
                net[-1].bias[:16] = mean
                net[-1].bias[16:] = -20.0
        seen = []
        monkeypatch.setattr(m, "decode", lambda h, z, *a, seen=seen, real=m.decode: seen.append(z) or real(h, z, *a))
        rssm.sequence_loss(m, x, v)
        zs[mode] = seen[0]              # the filtering decode comes first
    assert zs["posterior"].mean().item() == pytest.approx(-5.0, abs=0.2)
    assert zs["prior"].mean().item() == pytest.approx(5.0, abs=0.2)
    with pytest.raises(DbbError, match="filter_decode"):
        replace_cfg(SMALL, filter_decode="nope").validate()


def test_augment_mirrors_and_reverses_whole_windows():
    torch.manual_seed(0)
    x, v = torch.rand(64, 5, 4, 8, 8), torch.rand(64, 5, 3) * 50
    y, w = rssm.augment(x, v, "flip", np.random.default_rng(0))
    flipped = (w[:, 0, 0] != v[:, 0, 0])
    assert 10 < int(flipped.sum()) < 54                     # about half the windows
    assert torch.equal(y[flipped], x[flipped].flip(-1)) and torch.equal(w[flipped, :, 0], -v[flipped, :, 0])
    assert torch.equal(y[~flipped], x[~flipped]) and torch.equal(w[:, :, 1:], v[:, :, 1:])
    y, w = rssm.augment(x, v, "reverse", np.random.default_rng(1))
    rev = ~(y == x).flatten(1).all(1)
    assert 10 < int(rev.sum()) < 54
    assert torch.equal(y[rev], x[rev].flip(1)) and torch.equal(w[rev], v[rev].flip(1))
    y, w = rssm.augment(x, v, "none", np.random.default_rng(2))
    assert torch.equal(y, x) and torch.equal(w, v)
    with pytest.raises(DbbError, match="augment"):
        rssm.TrainConfig(augment="flip,spin").validate()


def test_shift_moves_every_frame_of_a_window_alike():
    x = torch.zeros(2, 3, 4, 32, 32)
    x[:, :, :, 10, 20] = 1.0
    y = rssm.shift_windows(x, np.array([[2, -1], [0, 0]]))
    assert torch.nonzero(y[0, :, :, 9, 22]).shape[0] == 3 * 4 and y[0].sum() == 3 * 4   # moved, not smeared
    assert torch.equal(y[1], x[1])
    x = torch.zeros(16, 3, 4, 32, 32)
    x[..., 8:24, 8:24] = torch.rand(16, 3, 4, 16, 16)     # content clear of the edges (max shift 2 px)
    y, w = rssm.augment(x, torch.rand(16, 3, 3), "shift", np.random.default_rng(0))
    assert torch.allclose(y.sum((2, 3, 4)), x.sum((2, 3, 4)))          # moved whole, nothing lost
    assert int((y != x).flatten(1).any(1).sum()) >= 12         # (0, 0) is 1 offset of 25
    rssm.TrainConfig(augment="flip,reverse,shift").validate()


def test_stepper_upsamples_with_phase_convolutions_exactly():
    torch.manual_seed(0)
    for c_in, c_out in ((12, 5), (40, 8)):          # below and above the channels-last width
        up = torch.nn.ConvTranspose2d(c_in, c_out, 4, 2, 1)
        x = torch.randn(2, c_in, 7, 9)
        with torch.no_grad():
            assert torch.allclose(rssm.PhaseUp(up)(x), up(x), atol=1e-5)
    with pytest.raises(ValueError):
        rssm.PhaseUp(torch.nn.ConvTranspose2d(4, 4, 3, 2, 1))
    # The stepper's decoder is the same function as the trained one, with faster layers.
    m = rssm.Rssm(SMALL).eval()
    st = rssm.Stepper(m)
    assert any(isinstance(u, rssm.PhaseUp) for u in st.decoder.ups)
    assert all(isinstance(u, torch.nn.ConvTranspose2d) for u in m.decoder.ups)     # training untouched
    pm = torch.rand(3, 4, 32, 32)
    feat = torch.randn(3, m.decoder.fc[0].in_features)
    with torch.no_grad():
        ctx = m.encoder.features(pm)
        assert torch.allclose(st.decoder(feat, ctx, pm), m.decoder(feat, ctx, pm), atol=1e-5)


def test_fast_default_step_is_the_general_step():
    # The default stepper ("accum", relative views) encodes the view changes from the angles;
    # the general path encodes each view and takes differences (view_delta_encoding), as training.
    m = _moving_model()
    first, views = torch.rand(2, 4, 32, 32), torch.rand(2, 7, 3) * 300 - 150
    fast, general = rssm.Stepper(m), rssm.Stepper(m)
    general.fast_views = False
    assert fast.fast_views
    out = []
    for st in (fast, general, rssm.script_stepper(m)):
        torch.manual_seed(7)
        out.append(rssm.rollout(st, first, views))
    assert torch.allclose(out[0], out[1], atol=1e-5) and torch.allclose(out[0], out[2], atol=1e-5)
    assert float((out[0][:, -1] - out[0][:, 0]).abs().max()) > 0.05     # the frames do move


def test_selection_holds_out_the_training_tail_and_writes_the_best_model(data, tmp_path):
    starts, length = rssm.training_windows(data, None)
    keep, val = rssm.validation_split(data, starts, length, 0.45)
    assert len(keep) > 0 and len(val) > 0
    assert data.times[keep + length - 1].max() < data.times[val].min()    # no training window touches the tail
    assert set(val) <= set(data.starts("train"))
    with pytest.raises(DbbError, match="val_fraction"):
        rssm.validation_split(data, starts, length, 0.01)       # a tail shorter than a window
    with pytest.raises(DbbError, match="val_fraction"):
        rssm.TrainConfig(val_fraction=0.6).validate()
    # A model that moves enough beats a better-scoring one that does not; the kept weights are a copy.
    m = rssm.Rssm(SMALL)
    sel = rssm.Selection()
    sel.offer(10, {"gain": 1.0, "energy_ratio": 0.1}, m, 0.7)
    assert sel.step == 10 and not sel.qualified
    sel.offer(20, {"gain": -1.0, "energy_ratio": 0.9}, m, 0.7)
    sel.offer(30, {"gain": -2.0, "energy_ratio": 0.9}, m, 0.7)
    assert sel.step == 20 and sel.qualified and len(sel.history) == 3
    with torch.no_grad():
        m.prior[0].weight.add_(1.0)
    assert not torch.equal(sel.state_dict["prior.0.weight"], m.prior[0].weight)
    # Scores are those of the run-time open loop, and the random state is left alone.
    torch.manual_seed(5)
    before = torch.rand(1)
    torch.manual_seed(5)
    score = rssm.validate(m, data, val)
    assert torch.equal(torch.rand(1), before)
    assert set(score) == {"gain", "energy_ratio"} and math.isfinite(score["gain"]) and score["energy_ratio"] >= 0
    # A run with selection writes the selected model and says which; the checkpoint keeps the last.
    out = tmp_path / "run"
    meta = rssm.train_run(data.source.parent, out, SMALL, rssm.TrainConfig(steps=4, batch=2, val_fraction=0.45,
                                                                        val_every=2), quiet=True)
    s = meta["selection"]
    assert [v["step"] for v in s["validations"]] == [2, 4] and s["step"] in (2, 4)
    ck = torch.load(out / "checkpoint.pt", weights_only=False)
    assert ck["step"] == 4 and ck["selection"]["step"] == s["step"]
    chosen = rssm.load_model(out).state_dict()
    assert all(torch.equal(chosen[k], ck["selection"]["state_dict"][k]) for k in chosen)


def test_accumulated_warp_moves_parts_far_and_resamples_the_image_once():
    S = 32
    base = rssm.identity_grid(1, S)
    assert torch.allclose(rssm.accumulated_warp(base, torch.zeros(1, 2, S, S), base), base, atol=1e-6)
    # A bright square moved right by four steps of half a pixel: the composed coordinates
    # resample the context frame once, 2 px over; four resamplings of the image smear it.
    img = torch.zeros(1, 4, S, S)
    img[:, :, 12:18, 8:14] = 1.0
    half = torch.zeros(1, 2, S, S)
    half[:, 0] = -0.5 * 2.0 / S                         # backward flow: from half a pixel to the left
    grid, resampled = base, img
    for _ in range(4):
        grid = rssm.accumulated_warp(grid, half, base)
        resampled = torch.nn.functional.grid_sample(resampled, base + half.permute(0, 2, 3, 1),
                                                    align_corners=False)
    once = torch.nn.functional.grid_sample(img, grid, align_corners=False)
    shifted = torch.roll(img, 2, -1)
    assert torch.allclose(once, shifted, atol=1e-4)
    assert (resampled - shifted).abs().max() > 0.2
    # Far travel: 40 steps of 1 px take the square 40 px from where a single flow could reach.
    one = torch.zeros(1, 2, 64, 64)
    one[:, 0] = -2.0 / 64
    b64, big = rssm.identity_grid(1, 64), torch.zeros(1, 4, 64, 64)
    big[:, :, 30:34, 2:6] = 1.0
    g = b64
    for _ in range(40):
        g = rssm.accumulated_warp(g, one, b64)
    out = torch.nn.functional.grid_sample(big, g, align_corners=False)
    assert torch.allclose(out[:, :, 30:34, 42:46], torch.ones(1, 4, 4, 4), atol=1e-4) and out[..., :40].abs().max() < 1e-4
    # A leak shrinks the displacement toward the context layout each step; still parts stay put.
    held = rssm.accumulated_warp(g, torch.zeros(1, 2, 64, 64), b64, leak=0.25)
    assert torch.allclose(held - b64, 0.75 * (g - b64), atol=1e-5)
    assert torch.equal(rssm.accumulated_warp(b64, torch.zeros(1, 2, 64, 64), b64, leak=0.25), b64)
    with pytest.raises(DbbError, match="warp_leak"):
        replace_cfg(SMALL, compose="accum", warp_leak=1.0).validate()


def test_warp_leak_per_second_is_rescaled_to_the_footage_frame_rate(crops, tmp_path):
    # 0.1 a frame at 10 frames/s leaves 0.9 ** 10 of a displacement after one second; at 30 frames/s
    # the same second takes 30 frames, so the leak per frame is 1 - 0.9 ** (1 / 3) ~ 0.0345.
    cfg = replace_cfg(SMALL, compose="accum", warp_leak=0.1, warp_leak_fps=10.0)
    at30 = rssm.leak_at_frame_rate(cfg, 30.0)
    assert at30.warp_leak == pytest.approx(1.0 - 0.9 ** (1.0 / 3.0)) and at30.warp_leak_fps == 30.0
    assert (1.0 - at30.warp_leak) ** 30 == pytest.approx(0.9 ** 10)
    assert rssm.leak_at_frame_rate(at30, 30.0) == at30                 # applying it again changes nothing
    assert rssm.leak_at_frame_rate(cfg, 10.0).warp_leak == pytest.approx(0.1)
    plain = replace_cfg(SMALL, compose="accum", warp_leak=0.1)          # the default: a leak per frame
    assert rssm.leak_at_frame_rate(plain, 30.0) == plain and rssm.leak_at_frame_rate(cfg, None) == cfg
    with pytest.raises(DbbError, match="warp_leak_fps"):
        replace_cfg(SMALL, warp_leak_fps=-1.0).validate()
    # Training builds the model at the dataset's rate: 0.1 a frame at 5 frames/s is 1 - 0.9 ** 0.5 a
    # frame of the 10-fps fixture.
    out = tmp_path / "run"
    rssm.train_run(crops.root, out, replace_cfg(cfg, warp_leak_fps=5.0),
                   rssm.TrainConfig(steps=1, batch=2, augment="none"), quiet=True)
    saved = json.loads((out / "run.json").read_text())["model"]["config"]
    assert saved["warp_leak"] == pytest.approx(1.0 - 0.9 ** 0.5) and saved["warp_leak_fps"] == 10.0
    assert rssm.load_model(out).decoder.warp_leak == pytest.approx(1.0 - 0.9 ** 0.5)


def test_accum_composite_starts_as_the_context_frame_and_steps_from_its_own_warp(tmp_path):
    torch.manual_seed(6)
    cfg = replace_cfg(SMALL, compose="accum")
    m = rssm.Rssm(cfg).eval()
    first = torch.rand(2, 4, 32, 32)
    views = torch.rand(2, 8, 3) * 40
    with torch.no_grad():
        out = rssm.rollout(rssm.Stepper(m), first, views)
        ctx_pm = rssm.premultiply(first)
        # Untrained: zero flow, ~95 % the context frame at every step (not drifting away).
        for t in range(out.shape[1]):
            assert rssm.psnr(rssm.premultiply(out[:, t]).numpy(), ctx_pm.numpy()) > 25
        m.decoder.ups[-1].bias[4] = 100.0                  # warp share 1: the context frame exactly
        out = rssm.rollout(rssm.Stepper(m), first, views)
        assert torch.allclose(rssm.premultiply(out), ctx_pm[:, None].expand_as(out), atol=1e-4)
        # A constant step flow: frame t is the context frame moved t steps (composed, not clamped).
        m.decoder.ups[-1].bias[5] = 0.5                    # tanh(0.5) * 0.25 half-widths = 1.85 px per step
        st = rssm.Stepper(m)
        h, z = st.start(first, views[:, 0])
        for _ in range(3):
            h, z, x = st.step(h, z, views[:, 1])
        shift = 3 * math.tanh(0.5) * 0.25
        inside = slice(0, 20)                              # columns whose source is still in the frame
        assert torch.allclose(st.warp[..., inside, 0], rssm.identity_grid(1, 32)[..., inside, 0] + shift, atol=1e-4)
    # The scripted stepper runs the same chain.
    torch.manual_seed(8)
    m = rssm.Rssm(cfg).eval()
    path = tmp_path / "stepper.ts"
    rssm.script_stepper(m).save(str(path))
    torch.manual_seed(7)
    eager = rssm.rollout(rssm.Stepper(m), first, views)
    torch.manual_seed(7)
    assert torch.allclose(eager, rssm.rollout(torch.jit.load(str(path)), first, views), atol=1e-5)
    with pytest.raises(DbbError, match="skip"):
        replace_cfg(cfg, skip=False).validate()


def test_accum_training_decodes_frames_in_order_and_the_open_loop_from_the_filtering_warp(monkeypatch):
    torch.manual_seed(9)
    m = rssm.Rssm(replace_cfg(SMALL, compose="accum", open_loop_samples=2))
    calls = []
    real = m.decode_chain

    def spy(h, z, pe, prev_pe, ctx, ctx_pm, ctx_pe, grid, kp=None):
        calls.append((h.shape[0], h.shape[1], grid.clone()))
        return real(h, z, pe, prev_pe, ctx, ctx_pm, ctx_pe, grid, kp)

    monkeypatch.setattr(m, "decode_chain", spy)
    x, v = torch.rand(3, 11, 4, 32, 32), torch.rand(3, 11, 3) * 40
    loss, parts = rssm.sequence_loss(m, x, v)
    # Filtering frame 1, filtering frames 2..10 from its warp, the prior's first step (2 copies)
    # from the identity, the open loop 2..10 (2 copies) from filtering frame 1's warp.
    assert [(n, t) for n, t, _ in calls] == [(3, 1), (3, 9), (6, 1), (6, 9)]
    ident = m.decoder.grid.expand(3, -1, -1, -1)
    assert torch.equal(calls[0][2], ident) and torch.equal(calls[2][2], ident.repeat(2, 1, 1, 1))
    assert torch.equal(calls[3][2], calls[1][2].repeat(2, 1, 1, 1))
    loss.backward()
    assert math.isfinite(loss.item())
    assert m.decoder.ups[-1].weight.grad[:, 5:7].abs().sum() > 0       # the step flow learns


def test_motion_weights_of_both_weigh_change_predicted_where_none_comes():
    x = torch.zeros(1, 3, 4, 8, 8)
    x[:, 2, :, 2:4, 2:4] = 1.0                               # the truth changes in one corner at frame 2
    w = rssm.motion_weights(x, 10.0)[:, 1:].flatten(0, 1)    # weights of frames 1 and 2
    pred = torch.zeros(2, 4, 8, 8)
    pred[:, :, 5:7, 5:7] = 1.0                               # the prediction changes elsewhere
    prev = x[:, :2].flatten(0, 1)
    assert torch.equal(rssm.with_predicted_change(w, pred, prev, 10.0, "truth"), w)
    both = rssm.with_predicted_change(w, pred, prev, 10.0, "both")
    assert torch.all(both[:, :, 5:7, 5:7] == 11.0) and torch.all(both[1, :, 2:4, 2:4] == 11.0)
    assert both[:, :, 0, 0].eq(1.0).all() and torch.all(both >= w)
    # The loss runs with it in both composites, and the weight carries no gradient.
    for compose in ("blend", "accum"):
        m = rssm.Rssm(replace_cfg(SMALL, compose=compose, motion_weight_of="both"))
        loss, _ = rssm.sequence_loss(m, torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 30)
        loss.backward()
        assert math.isfinite(loss.item())
    with pytest.raises(DbbError, match="motion_weight_of"):
        replace_cfg(SMALL, motion_weight_of="pred").validate()


def test_snapped_flow_and_mask_copy_still_pixels_exactly_and_still_learn():
    ctx_pm = rssm.premultiply(torch.rand(2, 4, 32, 32))
    base = rssm.identity_grid(2, 32)
    flow = torch.full((2, 2, 32, 32), 0.3 * 2 / 32, requires_grad=True)   # 0.3 px everywhere
    with torch.no_grad():
        flow[:, 0, :4] = 2.0 * 2 / 32                                      # 2 px in the top rows
    snapped = rssm.snap_flow(flow, 0.5 * 2 / 32)
    warp = lambda f: torch.nn.functional.grid_sample(ctx_pm, base + f.permute(0, 2, 3, 1), mode="bilinear",
                                                     padding_mode="zeros", align_corners=False)
    # A 0.3 px flow resamples (softens) the frame; snapped, the still rows are the frame exactly.
    assert not torch.allclose(warp(flow.detach())[..., 8:, :], ctx_pm[..., 8:, :], atol=1e-3)
    assert torch.allclose(warp(snapped.detach())[..., 8:, :], ctx_pm[..., 8:, :], atol=1e-6)
    assert torch.equal(snapped[:, :, :4], flow[:, :, :4])                  # long flows are kept
    snapped.sum().backward()                                                # straight-through gradient
    assert torch.equal(flow.grad, torch.ones_like(flow))
    m = torch.tensor([0.2, 0.93, 0.97], requires_grad=True)
    s = rssm.snap_mask(m, 0.05)
    assert torch.allclose(s, torch.tensor([0.2, 0.93, 1.0]))
    s.sum().backward()
    assert torch.equal(m.grad, torch.ones(3))
    assert rssm.snap_flow(flow, 0.0) is flow and rssm.snap_mask(m, 0.0) is m
    # In the composites: untrained blend (small flow) with a snap and the mask at ~1 copies exactly;
    # the scripted stepper runs the same.
    for compose in ("blend", "accum"):
        torch.manual_seed(3)
        mod = rssm.Rssm(replace_cfg(SMALL, compose=compose, flow_snap=1.0, mask_snap=0.05)).eval()
        first = torch.rand(2, 4, 32, 32)
        with torch.no_grad():
            mod.decoder.ups[-1].bias[4] = 10.0                 # warp share 0.99995: snapped to 1
            mod.decoder.ups[-1].weight[:, 5:7] = 0.0
            mod.decoder.ups[-1].bias[5:7] = 0.05               # a 0.2-0.4 px flow everywhere: snapped to 0
            out = rssm.rollout(rssm.Stepper(mod), first, torch.rand(2, 4, 3) * 30)
            assert torch.allclose(rssm.premultiply(out), rssm.premultiply(first)[:, None].expand_as(out), atol=1e-5)
            feat = torch.randn(2, mod.decoder.fc[0].in_features)
            assert torch.allclose(mod.decoder(feat, mod.encoder.features(ctx_pm), ctx_pm), ctx_pm, atol=1e-6)
            mod.decoder.flow_snap = 0.0                        # unsnapped, the same flow resamples
            assert not torch.allclose(mod.decoder(feat, mod.encoder.features(ctx_pm), ctx_pm), ctx_pm, atol=1e-3)
        loss, _ = rssm.sequence_loss(rssm.Rssm(replace_cfg(SMALL, compose=compose, flow_snap=1.0, mask_snap=0.05)),
                                     torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 30)
        loss.backward()
        assert math.isfinite(loss.item())
    ts = rssm.script_stepper(rssm.Rssm(replace_cfg(SMALL, flow_snap=1.0, mask_snap=0.05)).eval())
    assert ts.start(torch.rand(1, 4, 32, 32), torch.zeros(1, 3))[0].shape == (1, SMALL.deter)
    with pytest.raises(DbbError, match="flow_snap"):
        replace_cfg(SMALL, mask_snap=1.0).validate()


def test_learning_rate_falls_over_the_budget(crops, tmp_path):
    tcfg = rssm.TrainConfig(steps=6, batch=2, lr=2e-3, lr_end=0.25)
    assert rssm.lr_at(tcfg, 0.0) == pytest.approx(2e-3) and rssm.lr_at(tcfg, 1.0) == pytest.approx(5e-4)
    assert rssm.lr_at(tcfg, 0.5) == pytest.approx(1.25e-3)
    rssm.train_run(crops.root, tmp_path / "run", SMALL, tcfg, quiet=True)
    ck = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    lr = ck["opt"]["param_groups"][0]["lr"]
    assert 5e-4 <= lr < 0.8e-3                          # the last step's rate, near the end of the fall
    with pytest.raises(DbbError, match="lr_end"):
        rssm.TrainConfig(lr_end=0.0).validate()


def test_weight_decay_shrinks_the_weights_it_does_not_need():
    # AdamW's decoupled decay: with a zero loss, every step multiplies the weights by 1 - lr x decay.
    m = rssm.Rssm(SMALL)
    w0 = m.prior[0].weight.detach().clone()
    for decay, factor in ((0.0, 1.0), (0.5, (1 - 1e-3 * 0.5) ** 3)):
        m.prior[0].weight.data.copy_(w0)
        opt = rssm._optimizer(m, rssm.TrainConfig(lr=1e-3, weight_decay=decay))
        for _ in range(3):
            opt.zero_grad()
            (0.0 * sum(p.sum() for p in m.parameters())).backward()
            opt.step()
        assert torch.allclose(m.prior[0].weight, w0 * factor, atol=1e-7)
    with pytest.raises(DbbError, match="weight_decay"):
        rssm.TrainConfig(weight_decay=-1.0).validate()


def test_moving_average_of_the_weights_is_the_written_model(crops, tmp_path):
    m = rssm.Rssm(SMALL)
    st = rssm.TrainState(m, rssm._optimizer(m, rssm.TrainConfig()))
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
    # A run with the average writes it, and a resumed run continues it from the checkpoint.
    tcfg = rssm.TrainConfig(steps=3, batch=2, ema=0.5)
    meta = rssm.train_run(crops.root, tmp_path / "run", SMALL, tcfg, quiet=True)
    assert meta["training"]["weights"] == "moving average"
    ck = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    written = torch.load(tmp_path / "run" / "model.pt", weights_only=False)["state_dict"]
    assert torch.equal(written["prior.0.weight"], ck["ema"]["prior.0.weight"])
    assert not torch.equal(written["prior.0.weight"], ck["model"]["prior.0.weight"])
    with pytest.raises(DbbError, match="ema"):
        rssm.TrainConfig(ema=1.0).validate()
    # The defaults since the twelfth round: both seeds of the sample met the bars with them.
    assert (rssm.TrainConfig().weight_decay, rssm.TrainConfig().ema) == (0.25, 0.995)


def test_keypoints_follow_a_small_part_the_flattened_embedding_hardly_sees(tmp_path):
    """A 2x2-px spot on a plain 32x32 frame: the keypoints move with it by a large fraction of the
    frame, the flattened conv embedding by orders of magnitude less; the stepper scripts and
    matches the model with them, and runs without keypoints keep their weights' names."""
    torch.manual_seed(0)
    cfg = replace(DEFAULTS, keypoints=8)
    m = rssm.Rssm(cfg).eval()
    frames = torch.full((6, 4, 32, 32), 0.6)
    frames[:, 3] = 1.0
    for i in range(6):                       # the spot travels left to right along a row
        frames[i, :3, 15:17, 3 + 5 * i:5 + 5 * i] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    with torch.no_grad():
        e = m.encoder(frames)
    assert e.shape == (6, cfg.embed + 2 * cfg.keypoints)
    emb_spread = e[:, :cfg.embed].std(0).mean()
    kp_spread = e[:, cfg.embed:].std(0).mean()
    assert kp_spread > 0.05 and kp_spread > 100 * emb_spread
    # A keypoint that picks the spot's channel lands on it: x grows with the spot's column.
    sm = rssm.SpatialSoftmax(1, 1, 16)
    with torch.no_grad():
        sm.conv.weight.fill_(1.0)
        sm.conv.bias.zero_()
        sm.log_beta.fill_(math.log(50.0))
        f = torch.zeros(1, 1, 16, 16)
        f[0, 0, 4, 12] = 1.0
        kx, ky = sm(f)[0]
    assert abs(kx.item() - (12.5 / 8 - 1)) < 1e-3 and abs(ky.item() - (4.5 / 8 - 1)) < 1e-3
    # TorchScript stepper = eager model, with keypoints.
    path = tmp_path / "stepper.ts"
    rssm.script_stepper(m).save(str(path))
    first, views = frames[:1], torch.rand(1, 4, 3) * 30
    torch.manual_seed(3)
    eager = rssm.rollout(rssm.Stepper(m), first, views)
    torch.manual_seed(3)
    assert torch.allclose(eager, rssm.rollout(torch.jit.load(str(path)), first, views), atol=1e-5)
    assert not any("keypoints" in k for k in rssm.Rssm(DEFAULTS).state_dict())
    with pytest.raises(DbbError, match="keypoints"):
        replace(DEFAULTS, keypoints=-1).validate()


def test_keypoint_loss_makes_the_state_say_where_the_spot_is():
    """keypoint_scale: the state (h, z) is trained to give its frame's keypoints, the posterior's at
    each filtering step and the prior samples' along the open loop; a frozen keypoint layer takes
    no gradient, and a few steps on spot sequences bring that error down."""
    torch.manual_seed(0)
    cfg = replace(DEFAULTS, keypoints=4, keypoint_scale=10.0, keypoints_frozen=True)
    m = rssm.Rssm(cfg)
    x = torch.full((4, 11, 4, 32, 32), 0.6)
    x[:, :, 3] = 1.0
    for b in range(4):                       # a spot that travels, from a different column per sequence
        for t in range(11):
            c = (3 * b + 2 * t) % 28
            x[b, t, :3, 14:18, c:c + 4] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    x = rssm.premultiply(x)
    v = torch.zeros(4, 11, 3)
    loss, parts = rssm.sequence_loss(m, x, v)
    loss.backward()
    assert "keypoints" in parts and parts["keypoints"] > 0
    assert all(p.grad is None for p in m.encoder.keypoints.parameters())
    for part in (m.kp_head, m.post, m.prior, m.gru):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in part.parameters())
    opt = torch.optim.Adam([p for p in m.parameters() if p.requires_grad], 3e-3)
    for _ in range(70):
        opt.zero_grad()
        loss, parts = rssm.sequence_loss(m, x, v)
        loss.backward()
        opt.step()
    # Below what a state that knows nothing scores (the targets' variance, filtering + open loop).
    with torch.no_grad():
        kp = m.encoder(x.flatten(0, 1))[:, cfg.embed:]
    assert parts["keypoints"] < 0.5 * 2 * kp.var(0).sum().item()
    assert "kp_head" not in "".join(rssm.Rssm(replace(DEFAULTS, keypoints=4)).state_dict())
    with pytest.raises(DbbError, match="keypoint_scale"):
        replace(DEFAULTS, keypoint_scale=1.0).validate()


def test_keypoint_error_reads_the_open_loop_and_the_forecasts_only_when_asked():
    """keypoint_open_loop=False: the keypoint error is the filtering states' alone, so no gradient
    reaches the open loop through it; True (the default) also scores the open loop's states.
    keypoint_prior=True also scores each filtering step's prior mean (frame 0's excepted)."""
    cfg = replace(DEFAULTS, keypoints=4, keypoint_scale=1.0)
    for open_loop, forecast in ((True, False), (False, False), (False, True)):
        m = rssm.Rssm(replace(cfg, keypoint_open_loop=open_loop, keypoint_prior=forecast))
        emb = torch.randn(2, 11, cfg.embed + 8)
        hs = [torch.randn(2, cfg.deter, requires_grad=True) for _ in range(11)]
        zs = [torch.randn(2, cfg.stoch, requires_grad=True) for _ in range(11)]
        pms = [torch.randn(2, cfg.stoch, requires_grad=True) for _ in range(11)]
        ol = [torch.randn(2, n, requires_grad=True) for n in (cfg.deter, cfg.stoch) for _ in range(9)]
        rssm._keypoint_err(m, emb, hs, zs, ol[:9], ol[9:], 1, pms).backward()
        assert all(t.grad is not None for t in hs + zs)
        assert all((t.grad is not None) == open_loop for t in ol)
        assert pms[0].grad is None and all((t.grad is not None) == forecast for t in pms[1:])


def test_keypoint_energy_scores_a_settled_open_loop():
    """keypoint_energy: an open loop whose keypoints stand still scores more than one that moves as
    the frames' keypoints do, by the weight times the squared mean step length the frames take."""
    cfg = replace(DEFAULTS, keypoints=1, keypoint_scale=1.0, keypoint_energy=2.0)
    m = rssm.Rssm(cfg)

    class FirstTwoOfZ(torch.nn.Module):           # a head that reads its keypoint off z's first two numbers
        def forward(self, s):
            return s[..., cfg.deter:cfg.deter + 2]

    m.kp_head = FirstTwoOfZ()
    track = torch.stack([torch.linspace(-0.5, 0.5, 11), torch.zeros(11)], -1)       # (11, 2): x moves 0.1 a frame
    emb = torch.cat([torch.zeros(1, 11, cfg.embed), track[None]], -1)
    state = lambda points: [torch.cat([torch.zeros(1, cfg.deter), q[None], torch.zeros(1, cfg.stoch - 2)], -1)
                            for q in points]
    hs, zs = [s[:, :cfg.deter] for s in state(track)], [s[:, cfg.deter:] for s in state(track)]
    moving = state(track[2:])
    still = state(track[2:].mean(0).expand(9, 2))
    err = {name: rssm._keypoint_err(m, emb, hs, zs, [s[:, :cfg.deter] for s in ol], [s[:, cfg.deter:] for s in ol], 1)
           for name, ol in (("moving", moving), ("still", still))}
    regression = ((track[2:] - track[2:].mean(0)) ** 2).sum(-1).mean()
    assert err["moving"].item() == pytest.approx(0.0, abs=1e-6)
    assert err["still"].item() == pytest.approx(regression.item() + 2.0 * 0.1 ** 2, rel=1e-4)


def test_dynamics_steps_train_the_transition_and_prior_alone(data):
    """latent_loss trains only the transition, the prior (and the keypoint head): after one step
    with dynamics_steps the encoder, posterior and decoder are those of a run without them, the
    dynamics are not."""
    x = torch.rand(2, 11, 4, 32, 32)
    v = torch.rand(2, 11, 3) * 40
    m = rssm.Rssm(replace(SMALL, keypoints=4, keypoint_scale=1.0))
    loss, parts = rssm.latent_loss(m, x, v)
    loss.backward()
    assert set(parts) == {"kl_dyn", "overshoot", "keypoints"} and math.isfinite(loss.item())
    trained = {n.split(".")[0] for n, p in m.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert trained == {"z_in", "gru", "prior", "kp_head"}
    runs = {}
    for extra in (0, 3):
        torch.manual_seed(0)
        m = rssm.Rssm(SMALL)
        tc = rssm.TrainConfig(steps=1, batch=2, dynamics_steps=extra, ema=0.0)
        runs[extra] = rssm.train(rssm.TrainState(m, rssm._optimizer(m, tc)), data, tc).model.state_dict()
    for name, w in runs[0].items():
        same = torch.equal(w, runs[3][name])
        assert same == (name.split(".")[0] not in ("z_in", "gru", "prior")), name


def test_dynamics_horizon_gives_the_latent_steps_longer_windows(data, monkeypatch):
    """The latent-only steps read windows of 1 + dynamics_horizon frames (cut from consecutive
    training frames), the full steps keep the dataset's; a horizon below 1 is refused."""
    seen = {"full": [], "latent": []}
    full, latent = rssm.sequence_loss, rssm.latent_loss
    monkeypatch.setattr(rssm, "sequence_loss", lambda m, x, v: seen["full"].append(x.shape[1]) or full(m, x, v))
    monkeypatch.setattr(rssm, "latent_loss", lambda m, x, v: seen["latent"].append(x.shape[1]) or latent(m, x, v))
    long_starts, long_len = rssm.training_windows(data, 12)
    assert long_len > data.length and len(long_starts) > 0
    tc = rssm.TrainConfig(steps=2, batch=2, dynamics_steps=2, dynamics_horizon=12, ema=0.0)
    m = rssm.Rssm(SMALL)
    rssm.train(rssm.TrainState(m, rssm._optimizer(m, tc)), data, tc)
    assert seen == {"full": [data.length] * 2, "latent": [long_len] * 4}
    with pytest.raises(rssm.DbbError, match="dynamics_horizon"):
        rssm.TrainConfig(dynamics_horizon=0).validate()


def _moving_model(seed: int = 4) -> rssm.Rssm:
    torch.manual_seed(seed)
    m = rssm.Rssm(DEFAULTS).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.05 * torch.randn_like(p))      # moving, not the initial zero flow
    return m


def test_observe_and_decode_follow_the_footage_in_torchscript_as_eager(data):
    m = _moving_model()
    x = torch.from_numpy(data.rgba[:4]).permute(0, 3, 1, 2).float()[None] / 255.0     # (1, 4, 4, S, S)
    v = torch.from_numpy(data.views[:4])[None]
    outs = []
    for st in (rssm.Stepper(m, 0.0), rssm.script_stepper(m, 0.0)):
        h, z = st.start(x[:, 0], v[:, 0])
        frames = []
        for t in range(1, 4):
            h, z = st.observe(h, z, x[:, t], v[:, t])
            frames.append(st.decode(h, z, v[:, 0]))
        outs.append(torch.stack(frames))
    assert torch.allclose(outs[0], outs[1], atol=1e-5)
    # The posterior reads the frames: other footage, other states.
    st = rssm.Stepper(m, 0.0)
    h, z = st.start(x[:, 0], v[:, 0])
    assert not torch.allclose(st.observe(h, z, x[:, 1], v[:, 1])[1], st.observe(h, z, 1 - x[:, 1], v[:, 1])[1])


def test_calibrated_temperature_moves_the_still_view_as_much_as_the_footage(data, monkeypatch):
    m = _moving_model()
    cal = rssm.calibrate_temperature(m, data, steps=20, count=2)
    assert cal.steps >= data.length - 1 and len(cal.starts) >= 1
    assert all(data.splits[s:s + cal.steps + 1].tolist() == ["train"] * (cal.steps + 1) for s in cal.starts)
    starts, n = np.array(cal.starts), cal.steps + 1
    assert cal.target == pytest.approx(rssm.still_view_target(m, data, starts, n))
    es = [cal.energy[t] for t in sorted(cal.energy)]
    assert es[-1] > 1.2 * es[0]                     # sampling moves it
    # Footage between what the temperatures tried give: the fitted one meets it.
    mid = 0.5 * (cal.energy[0.5] + cal.energy[2.0])
    monkeypatch.setattr(rssm, "still_view_target", lambda *a: mid)
    fit = rssm.calibrate_temperature(m, data, steps=20, count=2)
    assert 0.5 < fit.temperature < 2.0 and fit.note is None
    assert rssm.still_view_energy(m, data, starts, n, fit.temperature) == pytest.approx(mid, rel=0.25)
    # Beyond them: the nearest one, said so.
    monkeypatch.setattr(rssm, "still_view_target", lambda *a: 2 * es[-1])
    hot = rssm.calibrate_temperature(m, data, steps=20, count=2)
    monkeypatch.setattr(rssm, "still_view_target", lambda *a: 0.0)
    cold = rssm.calibrate_temperature(m, data, steps=20, count=2)
    assert hot.temperature == max(rssm.CALIBRATION_TEMPERATURES) and "less than the footage" in hot.note
    assert cold.temperature == min(rssm.CALIBRATION_TEMPERATURES) and "more than the footage" in cold.note
    # No run of consecutive training frames: the fixed default, said so.
    alternate = replace(data, splits=np.where(np.arange(len(data.splits)) % 2 == 0, "train", "test"))
    none = rssm.calibrate_temperature(m, alternate)
    assert none.temperature == rssm.RUN_TEMPERATURE and none.target is None and "consecutive" in none.note


def test_a_fixed_camera_fits_the_temperature_to_the_footage_itself(data):
    """Its footage is seen from a still viewpoint: its own change is the target."""
    m = _moving_model()
    starts, n = rssm.long_training_runs(data, 20, 2)
    fixed = replace(data, views=np.repeat(data.views[:1], len(data.views), 0))
    assert rssm.fixed_camera(fixed) and not rssm.fixed_camera(data)
    frames = fixed.rgba[starts[:, None] + np.arange(1, n)[None]].astype(np.float32) / 255.0      # (B, L-1, S, S, 4)
    pm = np.concatenate([frames[..., :3] * frames[..., 3:], frames[..., 3:]], -1)
    assert rssm.still_view_target(m, fixed, starts, n) == pytest.approx(np.abs(np.diff(pm, axis=1)).mean(), rel=1e-4)


def test_oscillator_modes_ring_after_the_input_stops_and_script_as_eager(tmp_path):
    cfg = replace(DEFAULTS, deter=24, osc=4)
    m = rssm.Rssm(cfg).eval()
    cell = m.gru
    assert isinstance(cell, rssm.OscCell) and cell.cell.hidden_size == 16
    # One kick, then no input: the modes keep turning (a GRU's state settles to a fixed point).
    with torch.no_grad():
        h = cell(torch.randn(1, cfg.hidden), torch.zeros(1, cfg.deter))
        zero = torch.zeros(1, cfg.hidden)
        modes = []
        for _ in range(60):
            h = cell(zero, h)
            modes.append(h[0, 16:].clone())
        modes = torch.stack(modes)
    keep = cell.kept().detach()
    re, im = modes[:, :4], modes[:, 4:]
    amp = torch.sqrt(re ** 2 + im ** 2)
    assert torch.allclose(amp[-1], amp[0] * keep ** 59, rtol=1e-4)            # damped only by keep
    assert (modes[1:] - modes[:-1]).abs().sum(1).min() > 1e-3 * modes.abs().sum(1).max()   # still turning
    # The stepper carries the modes in h: TorchScript as eager.
    assert torch.allclose(*_eager_and_scripted_rollouts(m, tmp_path, 1), atol=1e-5)
    with pytest.raises(rssm.DbbError, match="osc"):
        replace(DEFAULTS, deter=16, osc=8).validate()
    # A floor on the kept length holds whatever the trained rate says.
    floored = rssm.Rssm(replace(cfg, osc_keep_min=0.999)).gru
    with torch.no_grad():
        floored.nu.fill_(5.0)                                  # exp(-exp(5)): nothing kept
        h = floored(torch.zeros(1, cfg.hidden), torch.cat([torch.zeros(1, 16), torch.ones(1, 8)], 1))
    assert torch.allclose(torch.sqrt(h[0, 16:20] ** 2 + h[0, 20:] ** 2), torch.full((4,), 0.999 * 2 ** 0.5))


def test_keypoint_maps_peak_at_the_keypoint_at_every_scale():
    kp = torch.tensor([[-0.45, 0.3, 0.7, -0.1]])                 # K = 2: x = (-0.45, 0.3), y = (0.7, -0.1)
    for r in (4, 8, 32):
        maps = rssm.keypoint_maps(kp, r, 0.08)
        assert maps.shape == (1, 2, r, r) and float(maps.max()) <= 1.0
        for k, (x, y) in enumerate([(-0.45, 0.7), (0.3, -0.1)]):
            row, col = divmod(int(maps[0, k].argmax()), r)
            assert (row, col) == (int((y + 1) / 2 * r), int((x + 1) / 2 * r))
    # At least half a cell wide: a point between coarse pixel centres still reaches them.
    assert float(rssm.keypoint_maps(torch.tensor([[0.0, 0.0]]), 4, 0.01).max()) > 0.3     # exp(-1): not ~0


def test_keypoint_maps_decoder_draws_from_the_states_keypoints():
    with pytest.raises(rssm.DbbError, match="keypoint_maps"):
        replace_cfg(DEFAULTS, keypoints=4, keypoint_maps=True).validate()
    m = rssm.Rssm(replace_cfg(DEFAULTS, keypoints=4, keypoint_scale=1.0, keypoint_maps=True)).eval()
    assert m.kp_head is m.decoder.kp_net          # one head: trained on the keypoints, drawn where it says
    torch.manual_seed(0)
    first, views = torch.rand(1, 4, 32, 32), torch.rand(1, 4, 3) * 60
    ctx_pm = rssm.premultiply(first)
    ctx = m.encoder.context(ctx_pm)
    assert [c.shape[1] for c in ctx] == [c.shape[1] + 4 for c in m.encoder.features(ctx_pm)]
    h, z, pe = torch.randn(1, 16), torch.randn(1, 16), rssm.view_encoding(views[:, 1], m.cfg.view_freqs)
    ctx_pe = rssm.view_encoding(views[:, 0], m.cfg.view_freqs)
    with torch.no_grad():
        m.decoder.ups[-1].weight[:, 5:7] = 0.01 * torch.randn_like(m.decoder.ups[-1].weight[:, 5:7])
    out = m.decode(h, z, pe, ctx, ctx_pm, ctx_pe)
    out.square().sum().backward()                 # the pixels pull on the keypoints' head
    assert float(m.decoder.kp_net[-1].weight.grad.abs().sum()) > 0
    with torch.no_grad():
        m.decoder.kp_net[-1].bias.add_(0.5)       # the state's keypoints elsewhere: another frame
        assert not torch.allclose(m.decode(h, z, pe, ctx, ctx_pm, ctx_pe), out, atol=1e-5)
    torch.manual_seed(7)
    eager = rssm.rollout(rssm.Stepper(m), first, views)
    torch.manual_seed(7)
    assert torch.allclose(eager, rssm.rollout(rssm.script_stepper(m), first, views), atol=1e-5)
    assert math.isfinite(rssm.sequence_loss(m, torch.rand(1, 11, 4, 32, 32), torch.rand(1, 11, 3))[0].item())


def test_keypoint_teacher_decodes_training_frames_from_their_own_keypoints():
    with pytest.raises(rssm.DbbError, match="keypoint_teacher"):
        replace_cfg(DEFAULTS, keypoints=4, keypoint_scale=1.0, keypoint_teacher=True).validate()
    torch.manual_seed(0)
    x, views = torch.rand(2, 11, 4, 32, 32), torch.rand(2, 11, 3) * 60

    def parts(teacher: bool, shift: float) -> dict:
        m = rssm.Rssm(replace_cfg(DEFAULTS, keypoints=4, keypoint_scale=1.0, keypoint_maps=True,
                                  keypoint_teacher=teacher, energy_scale=1.0))
        with torch.no_grad():
            m.decoder.kp_net[-1].bias.add_(shift)     # the state's keypoints elsewhere
        torch.manual_seed(3)
        return rssm.sequence_loss(m, x, views)[1]

    for teacher in (False, True):
        torch.manual_seed(1)
        a = parts(teacher, 0.0)
        torch.manual_seed(1)
        b = parts(teacher, 0.5)
        assert b["keypoints"] != pytest.approx(a["keypoints"])             # the head is still trained
        moved = [k for k in ("rec", "energy") if b[k] != pytest.approx(a[k], rel=1e-6)]
        # Teacher: no pixel term reads the state's keypoints; without it every one does.
        assert moved == ([] if teacher else ["rec", "energy"])
