"""Splits by time and the windows of consecutive frames."""

from __future__ import annotations

import numpy as np

from dbb_capture.crops.sequences import (
    follows_previous,
    sequence_windows,
    split_by_time,
)


def test_split_and_windows_respect_time_gaps_and_splits():
    t = np.arange(40) * 0.1
    t = np.delete(t, [15])                      # a dropped frame breaks sequences through it
    split = split_by_time(t, 0.2)
    assert (split == "test").sum() == 8 and split[-1] == "test" and split[0] == "train"
    wins = sequence_windows(t, split, length=11)
    starts = [s for s, _ in wins]
    for s, sp in wins:
        assert np.allclose(np.diff(t[s:s + 11]), 0.1) and len(set(split[s:s + 11])) == 1
    assert 0 in starts and 4 in starts and 5 not in starts    # 4..14 fits before the gap
    assert 15 in starts                                       # starts right after the gap


def test_follows_previous_breaks_at_gaps():
    """The matte's temporal vote links a crop only to frames right next to it in time."""
    t = np.array([0.0, 0.1, 0.2, 0.5, 0.6, 0.7])        # frames 0.3 and 0.4 dropped
    assert follows_previous(t).tolist() == [False, True, True, False, True, True]
    assert follows_previous(np.array([1.0])).tolist() == [False]
