"""Stage decisions without Ray: what counts as a complete output, what a killed worker leaves,
and each stage's resource request."""

from __future__ import annotations

import json

import pytest

from dbb_capture.batch.cluster import resources
from dbb_capture.batch.config import BatchConfig
from dbb_capture.batch.records import CaptureMetrics, ClusterInfo
from dbb_capture.batch.stages import clear_scratch, dataset_complete
from dbb_capture.core.errors import DbbError


def test_dataset_complete_needs_every_preprocess_stage(tmp_path):
    ds = tmp_path / "dataset"
    ds.mkdir()
    assert not dataset_complete(ds)
    (ds / "crops.json").write_text("{}")
    (ds / "dataset.json").write_text("{}")
    (ds / "preprocess.json").write_text(json.dumps({"stages_run": ["poses", "background"]}))
    assert not dataset_complete(ds)
    (ds / "preprocess.json").write_text(json.dumps({"stages_run": ["poses", "background", "crops"]}))
    assert dataset_complete(ds)


def test_clear_scratch_removes_only_leftovers(tmp_path):
    (tmp_path / ".run.partial-123-abc-x").mkdir()
    (tmp_path / ".run.old-9").mkdir()
    (tmp_path / ".run.work").mkdir()                   # an interrupted run's checkpoint: kept
    (tmp_path / ".dataset.partial-1").mkdir()
    clear_scratch(tmp_path / "run")
    assert sorted(p.name for p in tmp_path.iterdir()) == [".dataset.partial-1", ".run.work"]


def _cluster(cpus, gpus):
    return ClusterInfo("local", 1, cpus, gpus, cpus, True)


def test_resources_follow_the_cluster():
    r = resources(BatchConfig(), _cluster(2, 0))
    assert (r.cpus("preprocess"), r.cpus("train"), r.gpus("train"), r.cpus("verify")) == (2, 1, 0, 1)
    assert resources(BatchConfig(), _cluster(8, 2)).gpus("train") == 1
    assert resources(BatchConfig(gpus_per_train=0.5), _cluster(8, 2)).gpus("train") == 0.5
    assert resources(BatchConfig(preprocess_cpus=4), _cluster(1, 0)).preprocess_cpus == 1
    with pytest.raises(DbbError, match="no GPU"):
        resources(BatchConfig(gpus_per_train=1), _cluster(2, 0))


def test_metrics_merge_keeps_what_is_known():
    m = CaptureMetrics(frames_posed=12).merged(CaptureMetrics(heldout_psnr_db=25.0))
    assert (m.frames_posed, m.heldout_psnr_db, m.rssm_gain_db) == (12, 25.0, None)
