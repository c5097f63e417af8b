"""Metrics the benchmarks report (bench/), checked on frames whose answer is known."""
import importlib.util
from pathlib import Path

import numpy as np

_spec = importlib.util.spec_from_file_location("bench_rssm", Path(__file__).parents[1] / "bench" / "bench_rssm.py")
bench_rssm = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_rssm)


def test_travel_scores_a_swing_not_flicker():
    """A 4-px spot swinging 20 px to either side travels its swing's RMS (~14 px); the same spot
    still under frame-wide flicker of about its energy travels under a pixel."""
    rng = np.random.default_rng(0)
    bg = np.full((64, 64, 3), 0.5)
    t = np.arange(60)
    swing, still = np.repeat(bg[None], 60, 0), np.repeat(bg[None], 60, 0)
    for i, x in enumerate(30 + np.round(20 * np.sin(2 * np.pi * t / 30)).astype(int)):
        swing[i, 30:34, x:x + 4] = 1.0
        still[i, 30:34, 30:34] = 1.0
    still += rng.normal(0, 0.03, still.shape)          # flicker: about the spot's squared difference
    assert abs(bench_rssm.travel(swing, bg) - 20 / np.sqrt(2)) < 1.5
    assert bench_rssm.travel(still, bg) < 1.0
