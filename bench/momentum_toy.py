"""Does a training objective leave a forecaster its momentum? A toy beside the RSSM.

The pendulum's ball, reduced to one point per frame (the centroid of each frame's difference from
the footage's per-pixel median, :func:`bench_rssm.centroids`), is forecast by a small GRU trained
on windows of the training frames the way the RSSM's prior is: teacher forced (every input a true
frame), or open loop after ``--context`` true frames (its own forecasts fed back), with an optional
match of the forecast's mean step length to the truth's (the RSSM's ``energy_scale``, on points).
It is then rolled out open loop from the first two frames for 150 steps and scored like the RSSM:
mean |step| of the forecast over the truth's, and how far it travels. Nothing of the RSSM is used,
so what it shows is the objective's doing, not the model's.

    python bench/momentum_toy.py /tmp/h6/pend_ds --window 11 --context 11     # teacher forced
    python bench/momentum_toy.py /tmp/h6/pend_ds --window 11 --context 2      # open loop, 10 steps
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from torch import nn

from bench_rssm import centroids, spread
from dbb_capture.dynamic import rssm as rssm


def forecast(cell: nn.GRUCell, head: nn.Linear, seq: torch.Tensor, context: int) -> torch.Tensor:
    """Points 1..L-1 of ``seq`` (B, L, 2) forecast one step at a time; inputs are the true points
    for the first ``context`` steps and the forecasts after. Returns (B, L - 1, 2)."""
    h = seq.new_zeros(seq.shape[0], cell.hidden_size)
    inp, out = seq[:, 0], []
    for t in range(1, seq.shape[1]):
        h = cell(inp, h)
        out.append(head(h))
        inp = seq[:, t] if t < context else out[-1]
    return torch.stack(out, 1)


def run(points: np.ndarray, n_train: int, window: int, context: int, energy: float, steps: int,
        seed: int, horizon: int = 150) -> dict:
    """Train on windows of the first ``n_train`` of ``points`` (T, 2), then roll out from points
    0-1 for ``horizon`` steps; the energy ratio and travel (px) of the rollout against the truth's."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    mean, std = points[:n_train].mean(0), points[:n_train].std(0)
    p = torch.tensor((points - mean) / std, dtype=torch.float32)
    cell, head = nn.GRUCell(2, 64), nn.Linear(64, 2)
    opt = torch.optim.Adam([*cell.parameters(), *head.parameters()], 1e-3)
    starts = np.arange(0, n_train - window + 1)
    for _ in range(steps):
        seq = torch.stack([p[s:s + window] for s in rng.choice(starts, 16)])
        pred = forecast(cell, head, seq, context)
        loss = ((pred - seq[:, 1:]) ** 2).mean()
        if energy > 0:
            loss = loss + energy * ((rssm.mean_step(pred) - rssm.mean_step(seq[:, 1:])) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        roll = forecast(cell, head, p[None, :horizon + 1], 2)[0].numpy() * std + mean
    truth = points[1:horizon + 1]
    energy_of = lambda a: np.abs(np.diff(a, axis=0)).mean()
    return {"ratio": round(float(energy_of(roll) / energy_of(truth)), 3),
            "travel_px": round(spread(roll[1:]), 2), "truth_travel_px": round(spread(truth[1:]), 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path, help="a preprocess dataset of a fixed camera (crops.json)")
    ap.add_argument("--window", type=int, default=11, help="frames per training window (1 + forecast steps)")
    ap.add_argument("--context", type=int, default=2,
                    help="true inputs per window before the forecasts are fed back (= --window: teacher forced)")
    ap.add_argument("--energy", type=float, default=0.0, help="weight of the step-length match")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--seed", type=int, nargs="+", default=[0])
    args = ap.parse_args()
    torch.set_num_threads(1)
    data = rssm.load_sequences(args.dataset)
    rgb = data.rgba[..., :3]
    points = centroids(rgb, np.median(rgb, axis=0))
    n_train = int((data.splits == "train").sum())
    rows = [run(points, n_train, args.window, args.context, args.energy, args.steps, s) | {"seed": s}
            for s in args.seed]
    print(json.dumps({"window": args.window, "context": args.context, "energy": args.energy, "runs": rows}))


if __name__ == "__main__":
    main()
