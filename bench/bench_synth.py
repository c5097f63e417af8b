"""Speed of the synthetic capture renderer: seconds per frame at a given resolution.

Measures (a) the renderer alone in this process (ray casting, shading, anti-aliasing; with the
share of pixels the adaptive renderer supersampled) and
(b) a whole `write_capture` (render in worker processes + sensor noise + H.264 encoding +
masks; worker start-up included), per frame, and prints a Markdown table row for
docs/results.md.

    .venv/bin/python bench/bench_synth.py --resolution 640x480 --frames 30
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from dbb_capture.synth.capture import write_capture
from dbb_capture.synth.path import camera_path
from dbb_capture.synth.render import Renderer
from dbb_capture.synth.scene import SynthConfig, make_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", default="640x480")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--samples", type=int, default=2)
    ap.add_argument("--kind", default="dynamic")
    ap.add_argument("--workers", type=int, default=0, help="render processes (0: write_capture's default)")
    a = ap.parse_args()
    w, h = (int(v) for v in a.resolution.split("x"))
    cfg = SynthConfig(kind=a.kind, width=w, height=h, samples=a.samples, seconds=a.frames / 10,
                      background_seconds=None, workers=a.workers)
    scene = make_scene(cfg, np.random.default_rng(0))
    r = Renderer(cfg.intrinsics(), cfg.samples)
    times = np.arange(a.frames) / cfg.fps
    poses = camera_path(cfg, scene, times, np.random.default_rng(1))
    r.render(scene, poses[0], 0.0)  # warm-up
    per, refined = [], []
    for i in range(a.frames):
        t0 = time.perf_counter()
        r.render(scene, poses[i], float(times[i]))
        per.append(time.perf_counter() - t0)
        refined.append(r.refined)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        res = write_capture(cfg, Path(d) / "cap")
        total = time.perf_counter() - t0
    load = os.getloadavg()[0]
    print(f"| {w}x{h}, {a.samples}x{a.samples} samples, {a.kind}, {a.frames} frames "
          f"| {statistics.median(per) * 1000:.0f} ms | {100 * statistics.mean(refined):.0f} % "
          f"| {res.seconds_per_frame * 1000:.0f} ms "
          f"| {total:.1f} s | {torch.get_num_threads()} threads / {a.workers or 'default'} workers, "
          f"{os.cpu_count()} cores, load {load:.1f} |")


if __name__ == "__main__":
    main()
