"""Metrics the benchmarks report (bench/), checked on frames whose answer is known."""
import importlib.util
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).parents[1] / "bench"
sys.path.insert(0, str(BENCH))      # the bench scripts import their neighbour `common`


def _bench(name: str):
    """A bench script loaded as a module (bench/ is not a package)."""
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


bench_rssm = _bench("bench_rssm")
bench_plenoctree = _bench("bench_plenoctree")


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


def test_path_distance_finds_a_part_that_moves_elsewhere_whatever_the_phase():
    """A swing along the truth's row at another phase misses nothing; a spot that slides up from
    the swing's start instead misses the row's far places, and strays from the row as it climbs."""
    t = np.arange(60)
    truth = np.stack([np.full(60, 32.0), 30 + 20 * np.sin(2 * np.pi * t / 30)], 1)      # (y, x)
    late = np.stack([np.full(60, 32.0), 30 + 20 * np.sin(2 * np.pi * (t + 7) / 30)], 1)
    climb = np.stack([32.0 - t / 6, np.full(60, 30.0)], 1)
    assert bench_rssm.path_distance(truth, late) < 0.5 and bench_rssm.path_distance(late, truth) < 0.5
    assert bench_rssm.path_distance(truth, climb) > 8.0          # the swing's ends are never reached
    assert bench_rssm.path_distance(climb, truth) > 4.0          # and the climb leaves the row


def test_error_parts_put_an_outline_one_pixel_off_in_its_edge_bands():
    """A grey disc drawn one pixel to the right of the truth's: the error lies in the room and
    core pixels next to the outline and the rim, none deeper in either."""
    yy, xx = np.mgrid[:64, :64]
    def disc(cx):
        a = np.clip(12.5 - np.hypot(yy - 32, xx - cx), 0, 1)      # antialiased edge, radius 12
        return np.dstack([np.full((64, 64, 3), 0.3), a])
    gt, img = disc(32.0), disc(33.0)
    p = bench_plenoctree.summarize_parts([bench_plenoctree.error_parts(img, gt)])
    whole = p["mse_white_room"] + p["mse_white_core"] + p["mse_white_rim"]
    assert whole > 0
    assert p["mse_white_room"] > 0 and np.isclose(p["mse_white_room_edge"], p["mse_white_room"])
    assert p["mse_white_core"] > 0 and np.isclose(p["mse_white_core_edge"], p["mse_white_core"])
    same = bench_plenoctree.summarize_parts([bench_plenoctree.error_parts(gt, gt)])
    assert same["mse_white_room_edge"] == same["mse_white_core_edge"] == 0


def test_swing_period_finds_a_drifting_swing_and_not_jitter():
    """A 21-frame swing of 10 px riding on a slow drift, with a little noise, reads period 21 and
    amplitude 10 with most of its power there; a jittering point has no rhythm to speak of."""
    rng = np.random.default_rng(0)
    t = np.arange(150)
    swing = np.stack([40 + 0.1 * t, 30 + 10 * np.sin(2 * np.pi * t / 21) + 0.1 * t], 1) + rng.normal(0, 0.5, (150, 2))
    s = bench_rssm.swing_period(swing)
    assert abs(s["period"] - 21) < 1.0 and abs(s["amp_px"] - 10) < 1.5 and s["share"] > 0.7
    jitter = 32 + rng.normal(0, 3, (150, 2))
    assert bench_rssm.swing_period(jitter)["share"] < 0.35
