"""The run folder end to end: the command line, continuing a run, evaluating it again, older runs."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch
from click.testing import CliRunner

from dbb_capture.core.errors import DbbError
from dbb_capture.dynamic.config import TrainConfig
from dbb_capture.dynamic.record import RunRecord
from dbb_capture.dynamic.run import load_model, resume_configs, train_run

from .conftest import SMALL


def _lines(r) -> list[str]:
    return [ln for ln in r.output.splitlines() if ln.strip()]


def test_run_folder_cli_resume_and_eval(crops, tmp_path):
    from dbb_capture.cli import train as cli

    out = tmp_path / "run"
    r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(out), "--size", "32", "--steps", "3",
                                      "--batch", "2", "--threads", "1"])
    assert r.exit_code == 0, r.output
    assert "open-loop PSNR" in r.output and "run-time temperature" in r.output
    assert "dB against copying the first frame and " in r.output and "(1 is right, 0 frozen)" in r.output
    for f in ("run.json", "model.pt", "stepper.ts", "checkpoint.pt", "report/eval.json", "report/plots.png",
              "report/strip.png", "report/rollout.png"):
        assert (out / f).is_file(), f
    rec = RunRecord.read(out)
    assert rec.training.steps == 3 and rec.config.size == 32 and rec.training.weights == "moving average"
    # The view anchor by default: its PlenOctree run beside the model, its atlas in model.pt.
    assert rec.config.anchor and (out / "anchor" / "tree.npz").is_file() and (out / "anchor" / "run.json").is_file()
    assert 0 < rec.training.anchor_seconds < rec.training.seconds
    assert torch.load(out / "model.pt", weights_only=False)["anchor"]["images"].shape[2:] == (4, 32, 32)
    cal = rec.stepper.temperature_calibration       # fitted to the footage by default
    assert cal["steps"] >= 10 and cal["temperature"] == rec.stepper.temperature
    # The temperature is reached over the open-loop steps a training window covers.
    assert rec.stepper.warmup == len(rec.eval["psnr_db"]["model"]) == 10
    assert torch.jit.load(str(out / "stepper.ts")).warmup == 10
    assert rec.eval["split"] == "train" and len(rec.eval["psnr_db"]["model"]) == 10
    # The written model is the weights' average; the checkpoint keeps the last weights.
    ck = torch.load(out / "checkpoint.pt", weights_only=False)
    written = torch.load(out / "model.pt", weights_only=False)["state_dict"]
    assert torch.equal(written["prior.0.weight"], ck["ema"]["prior.0.weight"])
    assert not torch.equal(written["prior.0.weight"], ck["model"]["prior.0.weight"])
    with pytest.raises(DbbError, match="already exists"):
        train_run(crops.root, out, SMALL, TrainConfig(steps=3, batch=2), quiet=True)
    rec2 = train_run(crops.root, out, SMALL, TrainConfig(steps=5, batch=2), resume=True, quiet=True)
    assert rec2.training.steps == 5 and rec2.training.final["step"] == 5
    assert rec2.config == rec.config                     # resumed, not restarted with SMALL's sizes
    assert rec2.training.anchor_seconds == rec.training.anchor_seconds     # the anchor is not fitted again
    ts = torch.jit.load(str(out / "stepper.ts"))
    h, z = ts.start(torch.rand(1, 4, 32, 32), torch.zeros(1, 3))
    assert ts.step(h, z, torch.zeros(1, 3))[2].shape == (1, 4, 32, 32)
    # Evaluated again at another temperature: stepper.ts and run.json follow; nothing is left aside.
    r = CliRunner().invoke(cli.main, ["rssm-eval", str(out), "--temperature", "0.5"])
    assert r.exit_code == 0, r.output
    st = RunRecord.read(out).stepper
    assert st.temperature == 0.5 and st.temperature_calibration is None and st.warmup == 10    # set by hand
    assert torch.jit.load(str(out / "stepper.ts")).temperature == 0.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"] and not list(out.glob(".*"))
    r = CliRunner().invoke(cli.main, ["rssm-eval", str(out), "--calibrate"])
    assert r.exit_code == 0, r.output
    st = RunRecord.read(out).stepper
    assert st.temperature_calibration["temperature"] == st.temperature
    assert torch.jit.load(str(out / "stepper.ts")).temperature == st.temperature
    r = CliRunner().invoke(cli.main, ["rssm-eval", str(out), "--calibrate", "--temperature", "1"])
    assert r.exit_code == 2 and "not both" in r.output


def test_settings_presets_and_resumed_settings_on_the_command_line(crops, tmp_path):
    from dbb_capture.cli import train as cli

    acc = tmp_path / "acc"
    r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(acc), "--size", "32", "--steps", "2",
                                      "--batch", "2", "--threads", "1", "--set", "warp_leak=0.05",
                                      "--set", "loss_scales.first_step=0.5", "--set", "augment=none"])
    assert r.exit_code == 0, r.output
    cfg = RunRecord.read(acc).config
    assert cfg.warp_leak == 0.05 and cfg.scale("first_step") == 0.5 and cfg.size == 32
    # Resuming keeps the run's training settings (augment=none) unless told otherwise (--batch here).
    r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(acc), "--steps", "3",
                                      "--batch", "3", "--threads", "1", "--resume"])
    assert r.exit_code == 0, r.output
    assert "resumed from step 2 of 3, " in r.output and "(checkpoint of the finished run: " in r.output, r.output
    _cfg, tcfg = resume_configs(acc)
    assert tcfg.augment == "none" and tcfg.batch == 3 and tcfg.steps == 3
    assert RunRecord.read(acc).training.steps == 3
    # A spent budget, another model or --overwrite with --resume: one line each, the run kept as it is.
    for extra, words in ((["--steps", "3"], "is finished (3 steps, "), (["--size", "64"], "size 64 (the run's 32)"),
                         (["--set", "warp_leak=0.2"], "warp_leak 0.2 (the run's 0.05)"),
                         (["--overwrite"], "--resume continues RUN and --overwrite replaces it")):
        r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(acc), "--resume", "--steps", "4",
                                          "--threads", "1"] + extra)
        assert r.exit_code == 2 and len(_lines(r)) == 1 and words in _lines(r)[0], r.output
    assert RunRecord.read(acc).training.steps == 3 and RunRecord.read(acc).training.budget_steps == 3
    for bad in ("warp_leek=0.1", "warp_leak=lots", "warp_leak", "compose=accum"):
        r = CliRunner().invoke(cli.main, ["rssm", str(crops.root), "-o", str(tmp_path / "y"), "--set", bad])
        assert r.exit_code == 2 and len(_lines(r)) == 1 and "--set" in _lines(r)[0], r.output
    assert not (tmp_path / "y").exists()
    r = CliRunner().invoke(cli.main, ["rssm", str(tmp_path / "missing"), "-o", str(tmp_path / "x")])
    assert r.exit_code == 2 and len(_lines(r)) == 1 and _lines(r)[0].startswith("error:"), r.output
    assert not (tmp_path / "x").exists()
    with pytest.raises(DbbError, match="nothing to resume"):
        train_run(crops.root, tmp_path / "none", SMALL, TrainConfig(steps=1), resume=True)
    help_lines = CliRunner().invoke(cli.main, ["rssm", "--help"]).output.splitlines()
    assert len(help_lines) <= 50


def test_a_new_run_never_takes_an_interrupted_runs_view_anchor(crops, tmp_path):
    from dbb_capture.core.outputs import run_work_dir

    out = tmp_path / "run"
    stale = run_work_dir(out) / "anchor"              # an interrupted run's fitted anchor, of other crops
    stale.mkdir(parents=True)
    (stale / "tree.npz").write_bytes(b"not this dataset's tree")
    cfg, tcfg = replace(SMALL, anchor=True), TrainConfig(steps=1, batch=2)
    with pytest.raises(DbbError, match="an interrupted run"):
        train_run(crops.root, out, cfg, tcfg, quiet=True)
    rec = train_run(crops.root, out, cfg, tcfg, overwrite=True, quiet=True)
    assert rec.config.anchor and (out / "anchor" / "tree.npz").stat().st_size > 100     # fitted afresh
    assert not run_work_dir(out).exists()


def test_training_rescales_the_warp_leak_to_the_footage_frame_rate(crops, tmp_path):
    # 0.1 a frame at 5 frames/s is 1 - 0.9 ** 0.5 a frame of the 10-fps fixture.
    out = tmp_path / "run"
    train_run(crops.root, out, replace(SMALL, warp_leak=0.1, warp_leak_fps=5.0),
              TrainConfig(steps=1, batch=2, augment="none"), quiet=True)
    saved = RunRecord.read(out).config
    assert saved.warp_leak == pytest.approx(1.0 - 0.9 ** 0.5) and saved.warp_leak_fps == 10.0
    assert load_model(out).decoder.warp_leak == pytest.approx(1.0 - 0.9 ** 0.5)


def test_an_older_run_is_refused_with_one_line_saying_to_train_again(crops, tmp_path):
    from dbb_capture.cli import export as export_cli
    from dbb_capture.cli import train as cli

    out = tmp_path / "run"
    train_run(crops.root, out, SMALL, TrainConfig(steps=1, batch=2), quiet=True)
    doc = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**doc, "version": 1}))
    ck = torch.load(out / "checkpoint.pt", weights_only=False)
    torch.save({k: v for k, v in ck.items() if k not in ("format", "version")}, out / "checkpoint.pt")
    for runner, args in ((cli.main, ["rssm-eval", str(out)]),
                         (cli.main, ["rssm", str(crops.root), "-o", str(out), "--steps", "2", "--resume"]),
                         (export_cli.main, ["bundle", str(out), "-o", str(tmp_path / "bundle")])):
        r = CliRunner().invoke(runner, args)
        assert r.exit_code == 2 and len(_lines(r)) == 1 and "train" in _lines(r)[0] and "again" in _lines(r)[0], r.output


def test_an_oscillator_runs_bound_is_fitted_saved_and_fitted_again(crops, tmp_path):
    from dbb_capture.cli import train as cli

    out = tmp_path / "run"
    train_run(crops.root, out, replace(SMALL, deter=24, osc=4), TrainConfig(steps=1, batch=2), quiet=True)
    saved = torch.load(out / "model.pt", weights_only=False)
    limit = torch.tensor(saved["amp_limit"])
    assert limit.shape == (4,) and bool((limit > 0).all())
    assert torch.equal(load_model(out).gru.amp_limit, limit)
    assert torch.equal(torch.jit.load(str(out / "stepper.ts")).gru.amp_limit, limit)   # the stepper bounds too
    # A model saved before the bound existed loads unbounded; fitting its run again fits it.
    torch.save({k: v for k, v in saved.items() if k != "amp_limit"}, out / "model.pt")
    assert load_model(out).gru.amp_limit.eq(0).all()
    r = CliRunner().invoke(cli.main, ["rssm-eval", str(out), "--calibrate"])
    assert r.exit_code == 0, r.output
    assert torch.allclose(load_model(out).gru.amp_limit, limit)
    assert torch.allclose(torch.jit.load(str(out / "stepper.ts")).gru.amp_limit, limit)
    assert not list(out.glob(".*"))
    # Without oscillator modes there is nothing to bound.
    plain = tmp_path / "plain"
    train_run(crops.root, plain, SMALL, TrainConfig(steps=1, batch=2), quiet=True)
    assert torch.load(plain / "model.pt", weights_only=False)["amp_limit"] is None
