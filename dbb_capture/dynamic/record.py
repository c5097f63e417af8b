"""``run.json`` of an RSSM run folder: :class:`RunRecord` reads and writes it.

A run folder (``dbb-train rssm DATASET -o RUN``) holds ``run.json``, ``model.pt`` (``{"config":
RssmConfig fields, "state_dict": ...}``, a plain torch save), ``stepper.ts`` (the TorchScript
:class:`dbb_capture.dynamic.stepper.Stepper`), ``checkpoint.pt`` (model, optimiser, step and history,
to continue training) and ``report/`` (``eval.json``, ``plots.png``, ``strip.png``, ``rollout.png``).
Checkpoints during training go to ``.<RUN>.work/`` beside RUN. Imports no torch: readers of a run
(the bundle builder) need not load the trainer.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from ..core.errors import DbbError
from ..core.outputs import read_json, write_json
from .config import RssmConfig

RUN_FORMAT = "dbb-rssm-run"
RUN_VERSION = 3          # 3: the view anchor (anchor/, model.pt "anchor", training.anchor_seconds)

STEPPER_API = {"start": "(rgba (B,4,S,S) straight RGBA 0..1, view (B,3)) -> (h, z)",
               "step": "(h, z, view (B,3)) -> (h, z, rgba (B,4,S,S) straight RGBA 0..1)"}
STEPPER_VIEW = ("[azimuth_deg, elevation_deg, distance_m] of the camera from the object centre "
                "(crops.json viewpoint)")


@dataclass
class StepperRecord:
    """``run.json: stepper``: the TorchScript stepper and how it samples."""

    frame_size: int                       # S of its (B, 4, S, S) frames
    fps: float | None                     # the footage's frame rate (one step a frame)
    temperature: float                    # run-time sampling temperature of the stochastic state
    temperature_calibration: dict | None  # how it was fitted (Calibration.to_json), None if set by hand
    warmup: int = 0                       # steps over which the temperature rises to it (Stepper.step_temperature)
    file: str = "stepper.ts"

    def to_json(self) -> dict:
        return {"file": self.file, "format": "TorchScript", "api": dict(STEPPER_API), "view": STEPPER_VIEW,
                "frame_size": self.frame_size, "fps": self.fps, "temperature": self.temperature,
                "temperature_warmup_steps": self.warmup, "temperature_calibration": self.temperature_calibration}

    @classmethod
    def from_json(cls, d: dict) -> StepperRecord:
        return cls(int(d["frame_size"]), d["fps"], float(d["temperature"]), d["temperature_calibration"],
                   int(d.get("temperature_warmup_steps", 0)), d["file"])


@dataclass
class TrainingRecord:
    """``run.json: training``: how the run was trained."""

    steps: int
    seconds: float                        # time in training steps, over all resumptions (the anchor's included)
    anchor_seconds: float                 # of which fitting the view anchor's PlenOctree
    last_wall_seconds: float      # wall clock of the last command, evaluation included
    budget_minutes: float | None
    budget_steps: int | None
    batch: int
    lr: float
    weights: str                          # "moving average" (TrainConfig.ema) or "last"
    non_finite_steps_skipped: int
    train_sequences: int
    test_sequences: int
    final: dict | None                    # the last history entry (step, seconds, loss parts)


@dataclass
class RunRecord:
    """``run.json`` of an RSSM run (format :data:`RUN_FORMAT`, version :data:`RUN_VERSION`)."""

    dataset: str                          # the dataset folder it was trained on (absolute)
    dataset_file: str                     # "crops.json"
    object: dict | None                   # the dataset's object sphere {center, radius} (board frame)
    up: list | None                       # the dataset's up direction (board frame)
    crop: dict                            # {size, fill} of the dataset's crops
    config: RssmConfig                    # model.config
    stepper: StepperRecord
    training: TrainingRecord
    eval: dict                            # EvalReport.to_json() (also report/eval.json)
    model_file: str = "model.pt"
    checkpoint: str = "checkpoint.pt"
    report: str = "report/"

    def to_json(self) -> dict:
        return {"format": RUN_FORMAT, "version": RUN_VERSION, "kind": "dynamic",
                "dataset": self.dataset, "dataset_file": self.dataset_file, "object": self.object,
                "up": self.up, "crop": self.crop,
                "model": {"file": self.model_file, "type": "rssm", "config": asdict(self.config)},
                "stepper": self.stepper.to_json(), "checkpoint": self.checkpoint,
                "training": asdict(self.training), "eval": self.eval, "report": self.report}

    @classmethod
    def from_json(cls, d: dict, where: Path | str = "run.json") -> RunRecord:
        """The record of a parsed run.json; another format, or an older version of this one, is refused."""
        if not isinstance(d, dict) or d.get("format") != RUN_FORMAT:
            raise DbbError(f"{where} is not an RSSM run (run.json format "
                           f"{d.get('format') if isinstance(d, dict) else None!r})")
        if d.get("version") != RUN_VERSION:
            raise DbbError(f"{where} is an RSSM run of version {d.get('version')} (this version reads "
                           f"{RUN_VERSION}): train it again")
        try:
            return cls(d["dataset"], d["dataset_file"], d["object"], d["up"], d["crop"],
                       RssmConfig.from_json(d["model"]["config"]), StepperRecord.from_json(d["stepper"]),
                       TrainingRecord(**d["training"]), d["eval"], d["model"]["file"], d["checkpoint"], d["report"])
        except (KeyError, TypeError) as e:
            raise DbbError(f"{where}/run.json is incomplete ({e}): is it a finished training run?") from None

    @classmethod
    def read(cls, run: Path) -> RunRecord:
        """The record of the run folder ``run``."""
        return cls.from_json(read_json(Path(run) / "run.json", "run description"), run)

    def write(self, run: Path) -> None:
        """``run/run.json``, written aside and renamed into place."""
        write_json(Path(run) / "run.json", self.to_json())
