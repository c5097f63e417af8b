"""RSSM benchmarks (issue 6): run-time stepping speed, and quality on a synthetic dynamic capture.

    speed:   one step + decode, batch 1, TorchScript stepper, at 64x64 and 256x256
             .venv/bin/python bench/bench_rssm.py speed --threads 2
    quality: render a synthetic dynamic toy's crops (crops.json, perfect mattes), train for
             --minutes, then 10-step open-loop PSNR vs copy-first and "near", and the
             motion-energy ratio of a 150-step rollout at a still viewpoint against the toy
             rendered at that same still viewpoint
             .venv/bin/python bench/bench_rssm.py quality --minutes 15 --work /tmp/dbb-bench-rssm

Take timing figures under ``flock /tmp/dbb-bench.lock`` on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

from dbb_capture import rssm


def speed(size: int, steps: int = 300) -> dict:
    model = rssm.Rssm(rssm.RssmConfig(size=size)).eval()
    ts = rssm.script_stepper(model)
    with torch.no_grad():
        h, z = ts.start(torch.rand(1, 4, size, size), torch.tensor([[30.0, 40.0, 0.7]]))
        view = torch.tensor([[30.0, 40.0, 0.7]])
        for _ in range(30):                      # warm-up (TorchScript profiling runs)
            h, z, _ = ts.step(h, z, view)
        t, c = time.perf_counter(), time.process_time()
        for i in range(steps):
            view = torch.tensor([[30.0 + 0.1 * i, 40.0, 0.7]])
            h, z, _x = ts.step(h, z, view)
        dt, dc = time.perf_counter() - t, time.process_time() - c
    # CPU seconds say what the step costs when the machine is shared (wall time then also
    # counts the time other processes hold the cores).
    return {"size": size, "steps": steps, "frames_per_s": round(steps / dt, 1), "ms_per_frame": round(1e3 * dt / steps, 3),
            "frames_per_cpu_s": round(steps / dc, 1), "load_average_1min": round(os.getloadavg()[0], 2),
            "threads": torch.get_num_threads(), "parameters": sum(p.numel() for p in model.parameters())}


def quality(work: Path, minutes: float, seconds: float, size: int, batch: int, steps: int | None,
            lr: float, run_name: str = "run") -> dict:
    work.mkdir(parents=True, exist_ok=True)
    ds = work / "dataset"
    t = time.perf_counter()
    if not (ds / "crops.json").is_file() or not (work / "still.pt").is_file():
        sc = rssm.synthetic_crops(ds, seconds=seconds, fps=10, size=size, still_steps=150)
        torch.save({"first": sc.still_first, "view": sc.still_view, "truth": sc.still_truth}, work / "still.pt")
    still = torch.load(work / "still.pt", weights_only=False)
    render_s = time.perf_counter() - t
    run = work / run_name
    t = time.perf_counter()
    meta = rssm.train_run(ds, run, rssm.RssmConfig(size=size), rssm.TrainConfig(minutes, steps, batch=batch, lr=lr),
                          overwrite=True)
    train_s = time.perf_counter() - t
    # Re-evaluate with the motion truth rendered at the still viewpoint (the run's own eval has
    # only the moving-camera dataset to compare with).
    model = rssm.load_model(run)
    data = rssm.load_sequences(ds, size)
    rep = rssm.run_eval(model, data, run / "report-still",
                        torch.load(run / "checkpoint.pt", weights_only=False)["history"], still_truth=still["truth"],
                        still_start=(still["first"], still["view"]))
    ev = rep.to_json()
    return {"dataset_frames": len(data.rgba), "train_sequences": len(data.starts("train")),
            "test_sequences": len(data.starts("test")), "render_seconds": round(render_s, 1),
            "train_steps": meta["training"]["steps"], "train_minutes": round(meta["training"]["seconds"] / 60, 2),
            "wall_minutes_train_and_eval": round(train_s / 60, 2), "threads": torch.get_num_threads(),
            "mean_psnr_db": ev["mean_psnr_db"], "psnr_gain_db": ev["psnr_gain_db"], "mean_ssim": ev["mean_ssim"],
            "psnr_per_step": ev["psnr_db"], "motion_still_truth": ev["motion"],
            "motion_dataset_truth": meta["eval"]["motion"], "run": str(run)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("speed")
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--sizes", default="64,256")
    q = sub.add_parser("quality")
    q.add_argument("--work", type=Path, default=Path("/tmp/dbb-bench-rssm"))
    q.add_argument("--minutes", type=float, default=15.0)
    q.add_argument("--steps", type=int, default=None)
    q.add_argument("--seconds", type=float, default=60.0, help="length of the synthetic capture")
    q.add_argument("--size", type=int, default=64)
    q.add_argument("--batch", type=int, default=8)
    q.add_argument("--threads", type=int, default=1)
    q.add_argument("--lr", type=float, default=rssm.TrainConfig.lr)
    q.add_argument("--run-name", default="run")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.cmd == "speed":
        out = [speed(int(s)) for s in a.sizes.split(",")]
    else:
        out = quality(a.work, a.minutes, a.seconds, a.size, a.batch, a.steps, a.lr, a.run_name)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
