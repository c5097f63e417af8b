"""Typed results of a batch: one :class:`StageRecord` per stage run, one :class:`CaptureRecord`
per capture, and the :class:`BatchSummary` written to ``OUT/summary.json``."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..core.outputs import write_json

SUMMARY_FORMAT = "dbb-batch-summary"
SUMMARY_VERSION = 1
SUMMARY_FILE = "summary.json"

# Capture statuses: waiting for its first stage, a stage submitted, finished, or cut off.
PENDING, RUNNING, OK, SKIPPED, FAILED, INTERRUPTED = "pending", "running", "ok", "skipped", "failed", "interrupted"


@dataclass
class CaptureMetrics:
    """What a capture's outputs say about its quality (None: not known, e.g. the stage did not run)."""

    frames_posed: int | None = None
    heldout_psnr_db: float | None = None     # static: the tree's mean PSNR on white (dB) ...
    psnr_views: str | None = None            # ... over these views ("held-out", or the training views)
    rssm_gain_db: float | None = None        # dynamic: 10-step open-loop PSNR minus copy-first (dB)

    def merged(self, other: CaptureMetrics) -> CaptureMetrics:
        """These metrics with every entry ``other`` knows replaced by its value."""
        mine, theirs = asdict(self), asdict(other)
        return CaptureMetrics(**{k: theirs[k] if theirs[k] is not None else mine[k] for k in mine})


@dataclass
class StageRecord:
    """One stage of one capture as its worker ran it. ``status``: "ran", "skipped" (its output was
    there and complete) or "failed" (``error`` says why, in one line)."""

    stage: str                    # check, preprocess, train, bundle, verify
    status: str
    seconds: float                # the stage's own work, measured in the worker (s)
    node_id: str | None = None
    node_ip: str | None = None
    started_at: float = 0.0       # worker clock (epoch s) when the stage began
    note: str = ""                # e.g. why it was skipped, the verification's last line
    error: str | None = None
    verified: bool = False        # check and verify: the bundle verified
    metrics: CaptureMetrics = field(default_factory=CaptureMetrics)
    wall_seconds: float | None = None   # submission to result, seen by the driver (s): queueing included

    def to_json(self) -> dict:
        d = asdict(self)
        d.pop("metrics")
        return d


@dataclass
class CaptureRecord:
    """One capture's course through the batch."""

    name: str
    kind: str | None
    kind_source: str
    status: str = PENDING
    stage: str | None = None                 # the stage running now (or the one that failed)
    stage_since: float | None = None         # driver's monotonic clock at that stage's submission
    began: float | None = None               # ... at the first stage's submission
    seconds: float | None = None             # wall time from the first submission to the end (s)
    stages: list[StageRecord] = field(default_factory=list)
    metrics: CaptureMetrics = field(default_factory=CaptureMetrics)
    bundle: str | None = None
    error: str | None = None                 # one line: "<stage>: <message>"

    @property
    def done(self) -> bool:
        return self.status in (OK, SKIPPED, FAILED, INTERRUPTED)

    def stage_seconds(self) -> dict[str, float]:
        """Seconds of each stage's own work (the last attempt of each)."""
        return {s.stage: round(s.seconds, 1) for s in self.stages}

    def to_json(self) -> dict:
        return {"name": self.name, "kind": self.kind, "kind_source": self.kind_source, "status": self.status,
                **asdict(self.metrics), "stage_seconds": self.stage_seconds(),
                "seconds": None if self.seconds is None else round(self.seconds, 1),
                "bundle": self.bundle, "error": self.error, "failed_stage": self.stage if self.status == FAILED else None,
                "stages": [s.to_json() for s in self.stages]}


@dataclass
class ClusterInfo:
    """The Ray cluster a batch ran on, as it was at the start."""

    address: str                  # "local" (started by the batch) or the address joined
    nodes: int
    cpus: float
    gpus: float
    max_node_cpus: float          # the largest node's CPUs (a task asking for more could never run)
    connected_here: bool          # the batch called ray.init (and leaves at the end; a local Ray stops)

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class BatchSummary:
    """``OUT/summary.json``: every capture's result, the cluster and the settings."""

    captures_dir: Path
    out: Path
    cluster: ClusterInfo
    settings: dict
    captures: list[CaptureRecord]
    not_captures: list[str] = field(default_factory=list)
    started_utc: str = field(default_factory=lambda: time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    wall_seconds: float = 0.0
    interrupted: bool = False

    @property
    def failed(self) -> list[CaptureRecord]:
        return [c for c in self.captures if c.status in (FAILED, INTERRUPTED)]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for c in self.captures:
            out[c.status] = out.get(c.status, 0) + 1
        return out

    def to_json(self) -> dict:
        return {"format": SUMMARY_FORMAT, "version": SUMMARY_VERSION,
                "captures_dir": str(Path(self.captures_dir).resolve()), "out": str(Path(self.out).resolve()),
                "started_utc": self.started_utc, "wall_seconds": round(self.wall_seconds, 1),
                "interrupted": self.interrupted, "counts": self.counts(), "cluster": self.cluster.to_json(),
                "settings": self.settings, "not_captures": self.not_captures,
                "captures": [c.to_json() for c in self.captures]}

    def write(self) -> Path:
        """Write ``OUT/summary.json`` (atomically) and return its path."""
        path = Path(self.out) / SUMMARY_FILE
        write_json(path, self.to_json())
        return path
