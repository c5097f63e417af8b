"""The settings of a batch: what each kind of capture is preprocessed and trained with, and what
each stage asks of the cluster."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..capture.object_spec import OBJECT_KINDS
from ..core.errors import DbbError
from ..dynamic.config import RssmConfig, TrainConfig
from ..preprocess.inputs import DYNAMIC_CROP_SIZE, PreprocessConfig
from ..static.field import FieldConfig
from ..static.run import RunConfig

@dataclass(frozen=True)
class StaticSettings:
    """A static capture: preprocess, then ``dbb-train plenoctree`` (default budget 10 minutes)."""

    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)     # crops as fine as the footage
    run: RunConfig = field(default_factory=lambda: RunConfig(minutes=10.0))
    field: FieldConfig | None = None          # None: the trainer's defaults (as dbb-train plenoctree)


@dataclass(frozen=True)
class DynamicSettings:
    """A dynamic capture: preprocess, then ``dbb-train rssm`` (default budget 15 minutes)."""

    # A capture is dynamic here by the batch's choice too (default_kind), not only by its object.json.
    preprocess: PreprocessConfig = field(default_factory=lambda: PreprocessConfig(crop_size=DYNAMIC_CROP_SIZE))
    model: RssmConfig = field(default_factory=RssmConfig)
    train: TrainConfig = field(default_factory=lambda: TrainConfig(minutes=15.0))


@dataclass(frozen=True)
class Resources:
    """What one task of each stage asks Ray for (CPUs, GPUs; Ray's logical units)."""

    preprocess_cpus: float = 2.0      # also the preprocess's decoding processes (workers)
    train_cpus: float = 1.0           # also torch's and numba's threads
    train_gpus: float = 0.0           # 0: train on CPUs
    other_cpus: float = 1.0           # check, bundle and verify

    def cpus(self, stage: str) -> float:
        return {"preprocess": self.preprocess_cpus, "train": self.train_cpus}.get(stage, self.other_cpus)

    def gpus(self, stage: str) -> float:
        return self.train_gpus if stage == "train" else 0.0


@dataclass(frozen=True)
class BatchConfig:
    """Everything a batch decides. ``gpus_per_train`` None: 1 where the cluster has GPUs, else 0.
    ``retries``: times a stage is run again after its worker or node was lost."""

    static: StaticSettings = field(default_factory=StaticSettings)
    dynamic: DynamicSettings = field(default_factory=DynamicSettings)
    default_kind: str = "static"        # for captures whose object.json says no kind
    retries: int = 2
    gpus_per_train: float | None = None
    preprocess_cpus: float = 2.0
    force: bool = False                 # redo every stage of every capture

    def validate(self) -> None:
        if self.default_kind not in OBJECT_KINDS:
            raise DbbError(f"{{=default_kind}} {self.default_kind!r}: expected static or dynamic")
        if self.retries < 0:
            raise DbbError(f"{{=retries}} {self.retries}: expected 0 or more")
        if self.gpus_per_train is not None and self.gpus_per_train < 0:
            raise DbbError(f"{{=gpus_per_train}} {self.gpus_per_train}: expected 0 or more")
        if self.preprocess_cpus < 1:
            raise DbbError(f"{{=preprocess_cpus}} {self.preprocess_cpus}: expected at least 1")
        for name, minutes in (("static_minutes", self.static.run.minutes),
                              ("dynamic_minutes", self.dynamic.train.minutes)):
            if minutes is not None and minutes <= 0:
                raise DbbError(f"{{={name}}} {minutes}: expected a positive number of minutes")
        self.static.preprocess.validate()
        self.dynamic.preprocess.validate()
        self.dynamic.model.validate()
        self.dynamic.train.validate()
