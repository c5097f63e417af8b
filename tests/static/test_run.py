"""The run folder: dbb-train plenoctree writes a self-describing run, its typed record reads it
back, and runs of another version are refused."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import synthetic_object_frames
from dbb_capture.cli.train import main

from dbb_capture.core.errors import DbbError
from dbb_capture.core.images import LABEL_PX
from dbb_capture.datasets.transforms import missing_crops, write_transforms
from dbb_capture.static.field import FieldConfig
from dbb_capture.datasets.records import Frame, PosedDataset
from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.static.run import (
    REPORT_VIEW_PX,
    RUN_VERSION,
    RunConfig,
    RunRecord,
    for_tree_depth,
    load_run,
    split_frames,
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("run_dataset")
    frames, vol = synthetic_object_frames(folder, n=12, size=24, seed=2)
    write_transforms(folder / "transforms.json", frames, vol)
    return folder, vol


def test_cli_writes_a_self_describing_run_and_rejects_bad_input(dataset, tmp_path):
    data, vol = dataset
    run = tmp_path / "run"
    args = ["plenoctree", str(data), "-o", str(run), "--steps", "8", "--res-max", "16", "--batch-rays", "256"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    meta = json.loads((run / "run.json").read_text())
    assert (meta["format"], meta["version"]) == ("dbb-plenoctree-run", RUN_VERSION)
    assert meta["mode"] == "object" and meta["tree"]["colour_activation"] == "sigmoid"
    # A transforms dataset's alpha is the truth: no carving or robust training unless asked for.
    assert meta["field"]["carve_share"] == 0.0 and meta["field"]["robust_from"] == 1.0
    assert meta["object"]["radius"] == pytest.approx(vol.radius)
    loaded = load_run(run)
    rec = loaded.record
    assert RunRecord.from_json(meta, run) == rec and json.loads(json.dumps(rec.to_json())) == meta
    assert rec.field.res_max == 16 and rec.final_res == 16 and rec.training.steps == 8
    assert rec.tree.leaf_resolution == 1 << (rec.tree.depth_limit + 1)
    assert loaded.tree().data_format == rec.tree.data_format == "SH9"
    for name in ("tree.npz", "density_grid.npz", "checkpoint.pt", "report/curve.png", "report/metrics.json"):
        assert (run / name).is_file(), name
    # Its own test views, named for what they are.
    assert "on 2 test held-out views (the dataset's test views): renders differ from the photos by " in res.output, \
        res.output
    assert set(meta["metrics"]["sets"]) == {"test"} and meta["metrics"]["headline"] == "test"
    # Held-out views large enough to judge: truth | render, each at least 256 px, named on a band.
    views = sorted((run / "report").glob("heldout_*.png"))
    img = cv2.imread(str(views[0]))
    assert img.shape[0] - LABEL_PX >= REPORT_VIEW_PX and img.shape[1] >= 2 * REPORT_VIEW_PX
    half = img.shape[1] // 2
    assert (img[:LABEL_PX, :half] > 200).any() and (img[:LABEL_PX, half:] > 200).any()
    assert loaded.density_grid_path.is_file() and loaded.checkpoint_path.is_file()
    g = np.load(run / "density_grid.npz")
    assert g["sigma"].shape == (16, 16, 16)
    assert CliRunner().invoke(main, args).exit_code == 2                     # exists, no --overwrite
    res = CliRunner().invoke(main, args + ["--resume", "--steps", "10"])      # continue the same run
    assert res.exit_code == 0, res.output
    assert "resumed from step 8 of 10, " in res.output and "(checkpoint of the finished run: " in res.output
    assert load_run(run).record.training.steps == 10
    assert CliRunner().invoke(main, ["plenoctree", str(data / "nope"), "-o", str(tmp_path / "r2")]).exit_code == 2
    assert CliRunner().invoke(main, args[:3] + [str(tmp_path / "r5"), "--downscale", "0.5"]).exit_code == 2
    # Carving and robust training from the command line, recorded with the field's settings.
    more = ["--carve", "0.2", "--robust-from", "0.5"]
    res = CliRunner().invoke(main, args[:3] + [str(tmp_path / "r3")] + args[4:] + more)
    assert res.exit_code == 0, res.output
    assert (load_run(tmp_path / "r3").record.field.carve_share, load_run(tmp_path / "r3").record.field.robust_from) \
        == (0.2, 0.5)
    assert CliRunner().invoke(main, args[:3] + [str(tmp_path / "r4"), "--carve", "2"]).exit_code == 2
    # A spent budget, another field or --overwrite with --resume: one line each, the run kept as it is.
    for extra, words in ((["--steps", "10"], "is finished (10 steps, "), (["--sh-degree", "3"], "--sh-degree 3 (the run's 2)"),
                         (["--overwrite"], "--resume continues RUN and --overwrite replaces it")):
        res = CliRunner().invoke(main, args + ["--resume", "--steps", "12"] + extra)
        assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1 and words in res.output, res.output
    assert load_run(run).record.training.steps == 10 and load_run(run).record.training.budget_steps == 10


def test_a_preprocess_dataset_without_crops_is_refused(dataset, tmp_path):
    """``preprocess --stop-after poses`` leaves the full frames only: the plain folder would train
    the whole room, so it is refused with how to make the crops; its transforms.json given by
    name is still a dataset (the room, deliberately)."""
    import shutil

    data, _ = dataset
    poses_only = tmp_path / "ds"
    shutil.copytree(data, poses_only)
    (poses_only / "preprocess.json").write_text(json.dumps({"stages_run": ["poses"], "stop_after": "poses"}))
    res = CliRunner().invoke(main, ["plenoctree", str(poses_only), "-o", str(tmp_path / "run"), "--steps", "2"])
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1, res.output
    assert "has no object crops (crops.json): preprocess ran only poses" in res.output
    assert "without --stop-after" in res.output and not (tmp_path / "run").exists()
    assert missing_crops(poses_only / "transforms.json") is None and missing_crops(data) is None


def test_runs_of_another_version_or_damaged_records_are_refused(dataset, tmp_path):
    """A run of format version 1 (before this one) is refused with one line saying to train it
    again, by the record, by --resume and by dbb-export bundle; a damaged record is named."""
    from dbb_capture.cli.export import main as export_main

    data, _ = dataset
    run = tmp_path / "run"
    args = ["plenoctree", str(data), "-o", str(run), "--steps", "4", "--res-max", "16", "--batch-rays", "256"]
    assert CliRunner().invoke(main, args).exit_code == 0
    meta = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps(meta | {"version": 1}))
    with pytest.raises(DbbError, match="train it again"):
        load_run(run)
    res = CliRunner().invoke(export_main, ["bundle", str(run), "-o", str(tmp_path / "b")])
    assert res.exit_code == 2 and "train it again" in res.output and len(res.output.strip().splitlines()) == 1
    del meta["tree"]["nodes"]
    (run / "run.json").write_text(json.dumps(meta))
    with pytest.raises(DbbError, match="lacks tree.nodes"):
        load_run(run)
    (run / "run.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(DbbError, match="not a PlenOctree run"):
        load_run(run)


def test_a_tree_finer_than_the_lattice_skips_the_nearest_lookup_phase():
    cfg = FieldConfig(res_max=128)
    assert for_tree_depth(cfg, 7).nearest_from == 1.0           # 256^3 leaves sample the trilinear field
    assert for_tree_depth(cfg, 6).nearest_from == cfg.nearest_from   # 128^3 leaves: the lattice's own cells
    assert for_tree_depth(cfg, None) == cfg


def _frames(n: int, later: int) -> list[Frame]:
    """``n`` frames along a path in time, the last ``later`` of them the dataset's test split."""
    intr = Intrinsics(8, 8, 8.0, 8.0, 3.5, 3.5)
    return [Frame(f"{i:03d}", Path(f"{i:03d}.png"), np.eye(4), intr, "test" if i >= n - later else "train",
                  time=0.1 * i) for i in range(n)]


def test_a_capture_is_scored_between_its_views_all_along_its_path():
    # A capture's time split (its last stretch, for the RSSM) is trained on: every 8th view is held out.
    frames = _frames(50, 10)
    sp = split_frames(PosedDataset(Path("crops.json"), "crops", frames, True), RunConfig(holdout_every=8))
    assert [h.name for h in sp.heldout] == ["interleaved"]
    assert [f.name for f in sp.test] == ["000", "008", "016", "024", "032", "040", "048"]
    assert len(sp.train) == 43 and not {f.name for f in sp.train} & {f.name for f in sp.test}
    # Without a split the same; a dataset's own test views: those only; named frames if asked.
    sp = split_frames(PosedDataset(Path("t.json"), "transforms", _frames(16, 0), True), RunConfig(holdout_every=8))
    assert [h.name for h in sp.heldout] == ["interleaved"] and len(sp.train) == 14
    sp = split_frames(PosedDataset(Path("t.json"), "blender", _frames(16, 4), True), RunConfig(holdout_every=8))
    assert [(h.name, len(h.frames)) for h in sp.heldout] == [("test", 4)] and len(sp.train) == 12
    sp = split_frames(PosedDataset(Path("t.json"), "crops", _frames(16, 4), True), RunConfig(holdout_names=("003",)))
    assert [(h.name, [f.name for f in h.frames]) for h in sp.heldout] == [("named", ["003"])]
