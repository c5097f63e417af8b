"""An RSSM run folder end to end: train on a dataset and write the folder (:func:`train_run`),
evaluate a finished one again (:func:`eval_run`), read its model (:func:`load_model`). The folder's
files: :mod:`dbb_capture.dynamic.record`."""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, replace
from pathlib import Path

import torch

from ..core.device import pick_device
from ..core.errors import DbbError
from ..core.outputs import (
    atomic_dir,
    check_run_output,
    refuse_spent_budget,
    resume_checkpoint,
    run_work_dir,
    training_minutes,
    write_json,
)
from ..core.progress import console, progress, resumed_line
from .config import RssmConfig, TrainConfig, leak_at_frame_rate
from .anchor import ViewAtlas, build_atlas
from .data import SequenceData, load_sequences, with_anchor
from .evaluate import RUN_TEMPERATURE, EvalReport, calibrate_temperature, evaluate, fit_amp_limit
from .networks import OscCell
from .figures import write_figures
from .model import Rssm
from .record import RunRecord, StepperRecord, TrainingRecord
from .stepper import Stepper, script_stepper
from .train import TrainState, budget_fraction, read_checkpoint, train

ANCHOR_DIR = "anchor"        # the view anchor's PlenOctree run folder, inside the run folder


def resume_configs(out: Path) -> tuple[RssmConfig, TrainConfig]:
    """The model and training settings of the run ``out``'s last checkpoint, as the base that a
    resumed run's own settings go over (so resuming keeps the preset and settings given at the start)."""
    ck = read_checkpoint(resume_checkpoint(Path(out)))
    return ck.config, ck.train_config


def train_run(dataset: Path, out: Path, cfg: RssmConfig, tcfg: TrainConfig, resume: bool = False,
              overwrite: bool = False, quiet: bool = False, temperature: float | None = None) -> RunRecord:
    """Train on ``dataset`` and write the run folder ``out`` atomically; returns its record.

    ``temperature``: the stepper's sampling temperature (scales the prior's std at run time;
    None: fitted to the footage, :func:`calibrate_temperature`).
    """
    out = Path(out)
    check_run_output(out, overwrite, resume)
    tcfg = replace(tcfg, minutes=training_minutes(tcfg.minutes, tcfg.steps, default=15.0))
    if resume:
        refuse_spent_budget(out, tcfg.steps, tcfg.minutes)
    device = pick_device()
    work = run_work_dir(out)
    ckpt = work / "checkpoint.pt"
    state = None
    if resume:
        src = resume_checkpoint(out)
        state = TrainState.load(src, tcfg, device)
        cfg = state.model.cfg
        if not quiet:
            console.print(resumed_line(state.step, state.seconds, tcfg.steps, tcfg.minutes, src,
                                       src.parent == work), markup=False)
    cfg.validate()
    tcfg.validate()
    data = load_sequences(dataset, cfg.size)
    if state is None and cfg.anchor and data.fixed_camera():
        cfg = replace(cfg, anchor=False)        # one view: nothing for a 3D model of it to carry
        if not quiet:
            console.print("a fixed camera: no view anchor (every frame is seen from the same view)", markup=False)
    torch.manual_seed(tcfg.seed)
    if state is None:
        state = TrainState.new(Rssm(leak_at_frame_rate(cfg, data.fps())).to(device), tcfg)
    work.mkdir(parents=True, exist_ok=True)
    if not ckpt.is_file():              # resumable from here on, the anchor's fit included
        state.train_config = asdict(tcfg)
        state.save(ckpt)
    t0 = time.perf_counter()
    anchor_seconds = 0.0
    if cfg.anchor:
        anchor_seconds = fit_anchor(dataset, work / ANCHOR_DIR, out / ANCHOR_DIR, tcfg, quiet)
        data = with_anchor(data, build_atlas(work / ANCHOR_DIR / "tree.npz", data.views, data.meta, cfg.size, quiet))
    rssm_tcfg = tcfg if tcfg.minutes is None else replace(tcfg, minutes=tcfg.minutes - anchor_seconds / 60)
    with progress(disable=quiet) as prog:
        task = prog.add_task("train rssm", total=100, info="")

        def on_step(st: TrainState, parts: dict | None) -> None:
            if quiet:
                return
            info = ("non-finite step skipped" if parts is None else
                    f"step {st.step}  rec {parts['rec']:.1f}  kl {parts['kl_dyn']:.2f}  over {parts['overshoot']:.2f}")
            prog.update(task, completed=100 * budget_fraction(st, rssm_tcfg), info=info)

        state = train(state, data, rssm_tcfg, ckpt, on_step)
        prog.update(task, completed=100)
    record = write_run(out, state, data, dataset, tcfg, ckpt, wall=time.perf_counter() - t0, temperature=temperature,
                       anchor=work / ANCHOR_DIR if cfg.anchor else None, anchor_seconds=anchor_seconds)
    shutil.rmtree(work, ignore_errors=True)
    return record


# The anchor is the object's mean over time: its moving parts are what it should average, not
# outliers for robust training to outvote or for carving to cut where some views see through them
# (docs/decisions.md, "anchor field").
ANCHOR_FIELD_SETTINGS = {"robust_from": 1.0, "carve_share": 0.0}


def fit_anchor(dataset: Path, folder: Path, finished: Path, tcfg: TrainConfig, quiet: bool = False) -> float:
    """Fit the view anchor, a PlenOctree of the dataset's crops (:mod:`dbb_capture.dynamic.anchor`),
    into the PlenOctree run folder ``folder`` unless it is there (an interrupted fit resumes; a
    resumed run takes its finished one from ``finished``); ``anchor_share`` of a minutes budget, as
    many steps as the RSSM's with a steps budget. It trains on the RSSM's training frames only
    (the test windows' frames are its held-out views). Returns its training seconds."""
    from ..datasets.transforms import load_dataset
    from ..static.field import FieldConfig
    from ..static.run import RunConfig, load_run, train_run as train_tree
    from ..core.outputs import run_work_dir as work_of

    if not (folder / "tree.npz").is_file() and (finished / "tree.npz").is_file():
        shutil.copytree(finished, folder, dirs_exist_ok=True)
    if not (folder / "tree.npz").is_file():
        if not quiet:
            console.print("fitting the view anchor (a PlenOctree of the crops)", markup=False)
        minutes = None if tcfg.minutes is None else tcfg.anchor_share * tcfg.minutes
        test = tuple(f.name for f in load_dataset(Path(dataset)).frames if f.split == "test")
        train_tree(Path(dataset), folder, RunConfig(minutes=minutes, steps=tcfg.steps, holdout_names=test),
                   FieldConfig(**ANCHOR_FIELD_SETTINGS), resume=(work_of(folder) / "checkpoint.pt").is_file(),
                   overwrite=True, quiet=quiet)
    return float(load_run(folder).record.training.seconds)


def write_run(out: Path, state: TrainState, data: SequenceData, dataset: Path, tcfg: TrainConfig,
              ckpt: Path, wall: float, temperature: float | None = None, anchor: Path | None = None,
              anchor_seconds: float = 0.0) -> RunRecord:
    """The run folder of a trained state; ``temperature`` None: calibrated (run.json says how);
    ``anchor`` the view anchor's PlenOctree run folder (its tree, record and report are kept)."""
    model = state.run_model()           # checkpoint.pt keeps the last weights (to continue training)
    fit_amp_limit(model, data)
    cal = calibrate_temperature(model, data) if temperature is None else None
    temperature = cal.temperature if cal is not None else float(temperature)
    with atomic_dir(out, overwrite=True) as tmp:
        shutil.copyfile(ckpt, tmp / "checkpoint.pt")
        save_model(model, data.atlas, tmp / "model.pt")
        if anchor is not None:
            shutil.copytree(anchor, tmp / ANCHOR_DIR, ignore=shutil.ignore_patterns("checkpoint.pt", ".*"))
        script_stepper(model, temperature, data.atlas, data.horizon()).save(str(tmp / "stepper.ts"))
        report = run_eval(model, data, tmp / "report", state.history, temperature, data.horizon())
        record = RunRecord(
            dataset=str(Path(dataset).resolve()), dataset_file=data.source.name,
            object=data.meta.get("object"), up=data.meta.get("up"),
            crop={"size": data.meta.get("crop_size"), "fill": data.meta.get("crop_fill")}, config=model.cfg,
            stepper=StepperRecord(model.cfg.size, data.fps(), temperature, None if cal is None else cal.to_json(),
                                  data.horizon()),
            training=TrainingRecord(
                steps=state.step, seconds=round(state.seconds + anchor_seconds, 1),
                anchor_seconds=round(anchor_seconds, 1), last_wall_seconds=round(wall, 1),
                budget_minutes=tcfg.minutes, budget_steps=tcfg.steps, batch=tcfg.batch, lr=tcfg.lr,
                weights="moving average" if state.ema is not None else "last",
                non_finite_steps_skipped=state.bad_steps, train_sequences=len(data.starts("train")),
                test_sequences=len(data.starts("test")), final=state.history[-1] if state.history else None),
            eval=report.to_json())
        record.write(tmp)
    return record


def run_eval(model: Rssm, data: SequenceData, folder: Path, history: list[dict],
             temperature: float = RUN_TEMPERATURE, warmup: int = 0, **kw) -> EvalReport:
    """Evaluate ``model`` (sampling at ``temperature``, reached after ``warmup`` steps: :class:`Stepper`)
    on ``data``; ``eval.json`` and figures into ``folder``; ``kw`` as
    :func:`dbb_capture.dynamic.evaluate.evaluate`'s."""
    report, figs = evaluate(Stepper(model.cpu().eval(), temperature, data.atlas, warmup), data, **kw)
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "eval.json", report.to_json())
    write_figures(report, figs, history, folder)
    return report


def save_model(model: Rssm, atlas: ViewAtlas | None, path: Path) -> None:
    """A run's ``model.pt``: config, weights, the view anchor's atlas and the oscillator's bound
    (a run-time fit, :func:`fit_amp_limit`; None without oscillator modes)."""
    amp = model.gru.amp_limit.tolist() if isinstance(model.gru, OscCell) else None
    torch.save({"config": asdict(model.cfg), "state_dict": model.state_dict(),
                "anchor": None if atlas is None else atlas.state(), "amp_limit": amp}, path)


def load_model(run: Path) -> Rssm:
    """The trained model of a run folder (``model.pt``), in eval mode."""
    return _read_model(run)[0]


def load_atlas(run: Path) -> ViewAtlas | None:
    """The view anchor's atlas of a run folder (``model.pt``), None for a model without one."""
    return _read_model(run)[1]


def load_run_data(run: Path, dataset: Path | None = None) -> tuple[Rssm, SequenceData]:
    """A run's model and a dataset (default: the run's own) at its frame size, with the run's view anchor."""
    record = RunRecord.read(run)
    model, atlas = _read_model(run)
    data = load_sequences(Path(dataset) if dataset is not None else Path(record.dataset), model.cfg.size)
    return model, with_anchor(data, atlas)


def _read_model(run: Path) -> tuple[Rssm, ViewAtlas | None]:
    record = RunRecord.read(run)
    try:
        ck = torch.load(Path(run) / record.model_file, map_location="cpu", weights_only=False)
        model = Rssm(RssmConfig.from_json(ck["config"]))
        model.load_state_dict(ck["state_dict"])
        atlas = None if ck.get("anchor") is None else ViewAtlas.from_state(ck["anchor"])
        if ck.get("amp_limit") is not None and isinstance(model.gru, OscCell):
            model.gru.amp_limit.copy_(torch.as_tensor(ck["amp_limit"], dtype=torch.float32))
    except (OSError, KeyError, RuntimeError, TypeError, ValueError) as e:
        raise DbbError(f"cannot read the RSSM model of {run}: {e}") from None
    if model.cfg.anchor and atlas is None:
        raise DbbError(f"cannot read the RSSM model of {run}: its view anchor's atlas is missing from model.pt")
    return model.eval(), atlas


def eval_run(run: Path, dataset: Path | None = None, temperature: float | None = None,
             calibrate: bool = False) -> EvalReport:
    """Evaluate a run folder again (on its own dataset unless ``dataset`` is given).

    Replaces ``report/`` and the ``eval`` entry of ``run.json``; a new ``temperature`` (or
    ``calibrate``: fit it again, :func:`calibrate_temperature`, and the warm-up to the dataset's
    horizon) also replaces ``stepper.ts`` and the stepper's temperature in ``run.json``;
    ``calibrate`` fits the oscillator's bound again too (:func:`fit_amp_limit`, ``model.pt``).
    Each file is written aside and renamed into place, run.json last.
    """
    run = Path(run)
    record = RunRecord.read(run)
    model, data = load_run_data(run, dataset)
    ck = run / record.checkpoint
    history = read_checkpoint(ck).history if ck.is_file() else []
    stepper = record.stepper
    warmup = stepper.warmup
    refit = calibrate and isinstance(model.gru, OscCell)
    if refit:
        fit_amp_limit(model, data)
        save_model(model, data.atlas, run / f".{record.model_file}.partial")
    if calibrate:
        cal = calibrate_temperature(model, data)
        temperature, stepper.temperature_calibration, warmup = cal.temperature, cal.to_json(), data.horizon()
    elif temperature is None:
        temperature = stepper.temperature
    elif temperature != stepper.temperature:
        stepper.temperature_calibration = None          # set by hand
    with atomic_dir(run / "report", overwrite=True) as tmp:
        report = run_eval(model, data, tmp, history, temperature, warmup)
    if refit:
        (run / f".{record.model_file}.partial").replace(run / record.model_file)
    if refit or (temperature, warmup) != (stepper.temperature, stepper.warmup):
        ts = run / f".{stepper.file}.partial"
        script_stepper(model, temperature, data.atlas, warmup).save(str(ts))
        ts.replace(run / stepper.file)
        stepper.temperature, stepper.warmup = temperature, warmup
    record.eval = report.to_json()
    record.write(run)
    return report
