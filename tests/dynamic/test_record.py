"""run.json: the typed record reads what it writes and refuses other formats and older versions."""

from __future__ import annotations

import json

import pytest

from dbb_capture.core.errors import DbbError
from dbb_capture.dynamic.record import (
    RUN_FORMAT,
    RUN_VERSION,
    RunRecord,
    StepperRecord,
    TrainingRecord,
)

from .conftest import scaled


def _record() -> RunRecord:
    return RunRecord("/data/ds", "crops.json", {"center": [0.0, 0.1, 0.2], "radius": 0.1}, [0.0, 0.0, -1.0],
                     {"size": 64, "fill": 0.9}, scaled(energy=2.0), StepperRecord(32, 10.0, 0.5, None, 10),
                     TrainingRecord(3, 1.5, 0.5, 2.0, None, 3, 2, 1e-3, "moving average", 0, 12, 0, {"step": 3}),
                     {"split": "train"})


def test_run_json_round_trip(tmp_path):
    rec = _record()
    rec.write(tmp_path)
    doc = json.loads((tmp_path / "run.json").read_text())
    assert (doc["format"], doc["version"], doc["kind"]) == (RUN_FORMAT, RUN_VERSION, "dynamic")
    assert doc["model"] == {"file": "model.pt", "type": "rssm", "config": doc["model"]["config"]}
    assert doc["model"]["config"]["loss_scales"]["energy"] == 2.0 and "selection" not in doc
    assert set(doc["stepper"]) == {"file", "format", "api", "view", "frame_size", "fps", "temperature",
                                   "temperature_warmup_steps", "temperature_calibration"}
    assert RunRecord.read(tmp_path) == rec
    # A run written before the warm-up samples at its temperature from the first step.
    del doc["stepper"]["temperature_warmup_steps"]
    assert StepperRecord.from_json(doc["stepper"]).warmup == 0


def test_older_runs_and_other_formats_are_refused_in_one_line(tmp_path):
    doc = _record().to_json()
    for bad, what in (({**doc, "version": 1}, "version 1 .*train it again"), ({**doc, "format": "dbb-tree"}, "not an RSSM run"),
                      ({k: v for k, v in doc.items() if k != "training"}, "incomplete")):
        (tmp_path / "run.json").write_text(json.dumps(bad))
        with pytest.raises(DbbError, match=what) as e:
            RunRecord.read(tmp_path)
        assert "\n" not in str(e.value) and "--" not in str(e.value)      # one line, no command-line flags
