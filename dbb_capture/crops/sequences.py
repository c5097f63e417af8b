"""Train/test splits by time and the windows of consecutive frames the RSSM trains on."""

from __future__ import annotations

import numpy as np


def split_by_time(times: np.ndarray, test_fraction: float = 0.2) -> np.ndarray:
    """Split labels (N,) of str: the last ``test_fraction`` of the capture's duration is ``test``."""
    times = np.asarray(times, float)
    if len(times) == 0:
        return np.array([], dtype=object)
    t_cut = times.min() + (1 - test_fraction) * (times.max() - times.min())
    return np.where(times > t_cut if test_fraction > 0 else np.zeros(len(times), bool), "test", "train")


def follows_previous(times: np.ndarray, max_gap_factor: float = 1.5) -> np.ndarray:
    """(N,) bool: frame i directly follows frame i-1 (a time step at most ``max_gap_factor`` times
    the median step; a frame skipped for blur or for no board is a gap). Frame 0 follows nothing."""
    times = np.asarray(times, float)
    out = np.zeros(len(times), bool)
    if len(times) > 1:
        step = np.diff(times)
        out[1:] = step <= max_gap_factor * float(np.median(step))
    return out


def sequence_windows(times: np.ndarray, splits: np.ndarray, length: int = 11,
                     max_gap_factor: float = 1.5, stride: int = 1) -> list[tuple[int, str]]:
    """Start indices of windows of ``length`` consecutive frames (1 context + length-1 predicted).

    A window never crosses a split boundary or a gap (a frame skipped for blur or for no board,
    seen as a time step over ``max_gap_factor`` times the median step). Returns [(start, split)].
    """
    times = np.asarray(times, float)
    n = len(times)
    if n < length:
        return []
    step = float(np.median(np.diff(times))) if n > 1 else 1.0
    broken = np.zeros(n, bool)  # broken[i]: frame i does not follow frame i-1
    broken[1:] = (np.diff(times) > max_gap_factor * step) | (splits[1:] != splits[:-1])
    out = []
    for s in range(0, n - length + 1, stride):
        if not broken[s + 1:s + length].any():
            out.append((s, str(splits[s])))
    return out
