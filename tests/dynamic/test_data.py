"""The dataset in memory, its windows, batches and their augmentation."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from dbb_capture.core.errors import DbbError
from dbb_capture.dynamic.data import (
    SequenceData,
    augment,
    batch,
    load_sequences,
    long_training_runs,
    shift_windows,
    training_windows,
)


def test_dataset_reads_crops_json_windows_and_viewpoints(crops, data):
    doc = json.loads((crops.root / "crops.json").read_text())
    assert data.rgba.shape == (len(doc["frames"]), 32, 32, 4)
    assert data.length == 11
    assert [s for s, _ in data.windows] == [s["start"] for s in doc["sequences"]]
    assert len(data.starts("train")) > 0 and len(data.starts("test")) == 0  # test split is < 11 frames here
    assert np.allclose(data.views[5], [doc["frames"][5]["viewpoint"][k]
                                       for k in ("azimuth_deg", "elevation_deg", "distance_m")], atol=1e-3)
    assert data.rgba[..., 3].max() == 255 and data.rgba[..., 3].min() == 0    # object with a matte
    assert data.fps() == pytest.approx(10.0) and not data.fixed_camera()
    assert replace(data, views=np.repeat(data.views[:1], len(data.views), 0)).fixed_camera()
    x, v = batch(data, data.starts("train")[:2], torch.device("cpu"))
    assert x.shape == (2, 11, 4, 32, 32) and v.shape == (2, 11, 3)
    assert torch.allclose(x[..., :3, :, :], x[..., :3, :, :].clamp(max=x[..., 3:, :, :]))   # premultiplied


def test_only_preprocess_datasets(tmp_path):
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": [{"file_path": "a.png"}]}))
    with pytest.raises(DbbError, match="crops.json"):
        load_sequences(tmp_path)
    (tmp_path / "preprocess.json").write_text(json.dumps({"stages_run": ["poses", "background"]}))
    with pytest.raises(DbbError, match="preprocess ran only poses, background; run `dbb-capture preprocess` without"):
        load_sequences(tmp_path)


def test_long_windows_are_runs_of_consecutive_training_frames(data):
    starts, length = training_windows(data, 30)
    # 24 training frames here: the longest windows that still give >= 12 starts.
    n_train = int((data.splits == "train").sum())
    assert data.length < length <= n_train and len(starts) >= n_train // 2
    idx = starts[:, None] + np.arange(length)[None]
    assert (data.splits[idx] == "train").all()
    assert np.allclose(np.diff(data.times[idx], axis=1), 0.1)
    assert training_windows(data, None) == (pytest.approx(data.starts("train")), data.length)
    # A gap in time (a dropped frame) splits the runs: no window crosses it.
    n = 60
    times = np.arange(n) / 10.0 + np.where(np.arange(n) >= 20, 1.0, 0.0)
    gapped = SequenceData(data.source, data.rgba[np.arange(n) % len(data.rgba)], np.zeros((n, 3), np.float32),
                          np.array(["train"] * n), times, [(0, "train")], 11)
    starts, length = training_windows(gapped, 30)
    assert length > 11 and len(starts) >= 30
    assert all(s + length <= 20 or s >= 20 for s in starts)
    # Calibration runs: four starts a window (11) apart, so as long as that allows (18 frames).
    starts, length = long_training_runs(gapped, 150, 4)
    assert length == 18 and list(starts) == [0, 20, 31, 42]
    starts, length = long_training_runs(gapped, 150, 1)
    assert length == 40 and list(starts) == [20]             # one: the longest run, frames 20-59


def test_augment_mirrors_and_reverses_whole_windows():
    torch.manual_seed(0)
    x, v = torch.rand(64, 5, 4, 8, 8), torch.rand(64, 5, 3) * 50
    y, w, _ = augment(x, v, "flip", np.random.default_rng(0))
    flipped = (w[:, 0, 0] != v[:, 0, 0])
    assert 10 < int(flipped.sum()) < 54                     # about half the windows
    assert torch.equal(y[flipped], x[flipped].flip(-1)) and torch.equal(w[flipped, :, 0], -v[flipped, :, 0])
    assert torch.equal(y[~flipped], x[~flipped]) and torch.equal(w[:, :, 1:], v[:, :, 1:])
    y, w, _ = augment(x, v, "reverse", np.random.default_rng(1))
    rev = ~(y == x).flatten(1).all(1)
    assert 10 < int(rev.sum()) < 54
    assert torch.equal(y[rev], x[rev].flip(1)) and torch.equal(w[rev], v[rev].flip(1))
    y, w, _ = augment(x, v, "none", np.random.default_rng(2))
    assert torch.equal(y, x) and torch.equal(w, v)


def test_shift_moves_every_frame_of_a_window_alike():
    x = torch.zeros(2, 3, 4, 32, 32)
    x[:, :, :, 10, 20] = 1.0
    y = shift_windows(x, np.array([[2, -1], [0, 0]]))
    assert torch.nonzero(y[0, :, :, 9, 22]).shape[0] == 3 * 4 and y[0].sum() == 3 * 4   # moved, not smeared
    assert torch.equal(y[1], x[1])
    x = torch.zeros(16, 3, 4, 32, 32)
    x[..., 8:24, 8:24] = torch.rand(16, 3, 4, 16, 16)     # content clear of the edges (max shift 2 px)
    y, w, _ = augment(x, torch.rand(16, 3, 3), "shift", np.random.default_rng(0))
    assert torch.allclose(y.sum((2, 3, 4)), x.sum((2, 3, 4)))          # moved whole, nothing lost
    assert int((y != x).flatten(1).any(1).sum()) >= 12         # (0, 0) is 1 offset of 25
