"""Field settings compared at a fixed number of steps on NeRF-synthetic lego (figures of each
lever in docs/decisions.md). Steps, not minutes, so the machine's load does not change the outcome:

    python bench/bench_field_ablation.py NAME '{"tv_density": 1e-5, "tv_sh": 1e-5}' --steps 800
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from common import emit  # bench/ is the script folder: on sys.path

from dbb_capture.static.field import FieldConfig
from dbb_capture.static.run import RunConfig, train_run

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "nerf_lego"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("name")
    ap.add_argument("settings", help="JSON object of FieldConfig fields to change")
    ap.add_argument("--steps", type=int, default=800)
    ap.add_argument("--res-max", type=int, default=128)
    ap.add_argument("--work", type=Path, default=Path("out/bench/ablation"))
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    kw = json.loads(a.settings)
    fc = FieldConfig(res_max=a.res_max, res_start=min(32, a.res_max), max_points=4_000_000, **kw)
    t = time.time()
    run = train_run(DATA, a.work / a.name, RunConfig(steps=a.steps, downscale=4, max_report_views=13), fc,
                    overwrite=True, quiet=True)
    rec = run.record
    return emit({"name": a.name, "settings": kw, "steps": rec.training.steps,
                 "train_seconds": rec.training.seconds, "wall_seconds": round(time.time() - t),
                 "psnr_tree_white": rec.metrics["mean_psnr_tree_white"],
                 "psnr_field_white": rec.metrics["mean_psnr_field_white"]}, None)


if __name__ == "__main__":
    sys.exit(main())
