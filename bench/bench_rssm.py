"""RSSM benchmarks: run-time stepping speed, and quality on a synthetic dynamic capture.

    speed:   one step + decode, batch 1, TorchScript stepper, at 64x64 and 256x256
             .venv/bin/python bench/bench_rssm.py speed --threads 2
    quality: train on a `dbb-capture preprocess` dataset for --minutes, then 10-step open-loop
             PSNR vs copy-first and "near", and the motion-energy ratio of a 150-step rollout at
             a still viewpoint; with --capture (the synthetic capture behind the dataset) the
             truth of that ratio is the ground-truth object rendered at the still viewpoint
             .venv/bin/dbb-capture preprocess sample_data/dynamic -o dyn_ds --background-minutes 1
             .venv/bin/python bench/bench_rssm.py quality dyn_ds --capture sample_data/dynamic \
                 --run rssm_run --minutes 15
    protocols: the gain over copy-first of one sampled rollout (the run-time protocol, the bar's),
             of the mean of 8 and of the best of 8 (extra, labelled: no run-time stepper draws those)
             .venv/bin/python bench/bench_rssm.py protocols rssm_run dyn_ds
    subset:  the same dataset trained on less footage (the first --seconds; same test split)
             .venv/bin/python bench/bench_rssm.py subset long_ds --seconds 24 -o long_24s
    first-step: what the run-time first step loses against copying (its candidates, mask, flow)
             .venv/bin/python bench/bench_rssm.py first-step rssm_run dyn_ds
    motion:  where the still-view motion goes: the energy ratio per block of steps at temperatures
             0 / 1 / 2 (0 = the prior mean: motion the deterministic path carries) and per
             open-loop step on the test windows
             .venv/bin/python bench/bench_rssm.py motion rssm_run dyn_ds --capture sample_data/dynamic
    new-path: 10-step rollouts along viewpoint paths the footage never followed, from the
             synthetic capture's truth: the footage's viewpoints a quarter, half and three
             quarters of the capture later (--shift), at the test windows' times, pooled and
             each; the camera turning back from each window's first view; the footage's own
             path rendered from the truth and the run's test windows; step-1 PSNR against the
             given first frame
             .venv/bin/python bench/bench_rssm.py new-path rssm_run dyn_ds --capture sample_data/dynamic
    blurred-copy: what copy-first blurred more at each step (a hedge that never moves) scores
             .venv/bin/python bench/bench_rssm.py blurred-copy dyn_ds --sigma 0.5 --sigma 1

Take timing figures with the machine to itself.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from dbb_capture.core.errors import DbbError
from dbb_capture.core.metrics import psnr
from dbb_capture.dynamic.config import (
    RssmConfig,
    TrainConfig,
    apply_preset,
    configs_from_settings,
)
from dbb_capture.dynamic.anchor import ViewAtlas, atlas_grid
from dbb_capture.dynamic.data import batch as window_batch
from dbb_capture.dynamic.data import SequenceData, anchor_batch, load_sequences
from dbb_capture.dynamic.evaluate import evaluate as evaluate_stepper
from dbb_capture.dynamic.evaluate import motion_coherence, score_rollouts
from dbb_capture.dynamic.model import Rssm, decoder_input, sample
from dbb_capture.dynamic.networks import image_pyramid, warp_maps
from dbb_capture.dynamic.record import RunRecord
from dbb_capture.dynamic.rgba import premultiplied, premultiply
from dbb_capture.dynamic.run import (
    eval_run,
    load_model,
    load_run_data,
    resume_configs,
    run_eval,
    train_run,
)
from dbb_capture.dynamic.stepper import Stepper, rollout, script_stepper
from dbb_capture.dynamic.views import view_delta_encoding


def speed(size: int, steps: int = 300, settings: list[str] = (), repeat: int = 1, preset: str | None = None) -> dict:
    """Frames per second of the TorchScript stepper (batch 1) over ``steps`` steps, ``repeat`` times:
    the median, and every repetition (a shared machine's timings vary by tens of per cent)."""
    model = Rssm(replace(overrides(list(settings), preset=preset)[0], size=size)).eval()
    atlas = None
    if model.cfg.anchor:        # an atlas of the size footage seen from 0-60 deg elevation gets
        grid = atlas_grid(np.array([[0.0, 0.0, 0.7], [0.0, 60.0, 0.7]]), size)
        atlas = ViewAtlas(torch.randint(0, 256, (grid.n_el, grid.n_az, 4, size, size), dtype=torch.uint8), grid)
    ts = script_stepper(model, atlas=atlas)
    with torch.no_grad():
        h, z = ts.start(torch.rand(1, 4, size, size), torch.tensor([[30.0, 40.0, 0.7]]))
        view = torch.tensor([[30.0, 40.0, 0.7]])
        for _ in range(30):                      # warm-up (TorchScript profiling runs)
            h, z, _ = ts.step(h, z, view)
        runs = []
        for _ in range(repeat):
            t, c = time.perf_counter(), time.process_time()
            for i in range(steps):
                view = torch.tensor([[30.0 + 0.1 * i, 40.0, 0.7]])
                h, z, _x = ts.step(h, z, view)
            runs.append((time.perf_counter() - t, time.process_time() - c))
    dt, dc = float(np.median([r[0] for r in runs])), float(np.median([r[1] for r in runs]))
    # CPU seconds say what the step costs when the machine is shared (wall time then also
    # counts the time other processes hold the cores).
    return {"size": size, "steps": steps, "frames_per_s": round(steps / dt, 1), "ms_per_frame": round(1e3 * dt / steps, 3),
            "frames_per_s_each": [round(steps / r[0], 1) for r in runs],
            "frames_per_cpu_s": round(steps / dc, 1), "load_average_1min": round(os.getloadavg()[0], 2),
            "threads": torch.get_num_threads(), "parameters": sum(p.numel() for p in model.parameters())}


def still_truth(dataset: Path, capture: Path, steps: int = 150, samples: int = 2) -> dict:
    """Motion truth at a still viewpoint for a preprocess dataset of a synthetic capture.

    The first test crop (its image as preprocess cut it, its viewpoint) starts the rollout;
    the truth is the capture's ground-truth object rendered through that frame's crop camera
    (preprocess poses are in the board frame, as the synthetic world) for ``steps`` more frames.
    """
    from dbb_capture.datasets.transforms import load_dataset
    from dbb_capture.synth.capture import load_ground_truth
    from dbb_capture.synth.render import render_object_rgba

    doc = json.loads((Path(dataset) / "crops.json").read_text())
    frames = doc["frames"]
    k = next((i for i, f in enumerate(frames) if f["split"] == "test"), 0)
    f = frames[k]
    cam = load_dataset(dataset).frames[k]          # the crop camera in the toolkit's conventions
    intr, c2w = cam.intr, cam.c2w
    fps = 1.0 / float(np.median(np.diff([fr["time"] for fr in frames])))
    _, _, obj = load_ground_truth(capture)
    truth = np.stack([render_object_rgba(obj, intr, c2w, f["time"] + j / fps, samples) for j in range(1, steps + 1)])
    data = load_sequences(dataset, int(f["w"]))
    vp = f["viewpoint"]
    return {"first": data.rgba[k], "view": np.array([vp["azimuth_deg"], vp["elevation_deg"], vp["distance_m"]],
                                                      np.float32), "truth": truth, "frame": k}


def crop_cameras(dataset: Path, views: np.ndarray) -> list[tuple[np.ndarray, object]]:
    """The crop camera (OpenCV c2w (4, 4), intrinsics) that preprocess would cut at each of
    ``views`` (..., 3) of the dataset's object sphere (board frame), flattened."""
    from dbb_capture.crops.camera import facing_camera
    from dbb_capture.geometry.viewpoint import Viewpoint, eye_at

    doc = json.loads((Path(dataset) / "crops.json").read_text())
    center, radius = np.asarray(doc["object"]["center"]), float(doc["object"]["radius"])
    up, size, fill = np.asarray(doc["up"], float), int(doc["crop_size"]), float(doc["crop_fill"])
    return [facing_camera(eye_at(Viewpoint(*map(float, v)), center, up), center, radius, up, size, fill)
            for v in views.reshape(-1, 3)]


def path_truth(dataset: Path, capture: Path, times: np.ndarray, views: np.ndarray, samples: int = 2) -> np.ndarray:
    """The synthetic capture's object rendered through the crop camera of each of ``views``
    (..., 3) at ``times`` (...) s: straight RGBA uint8 (..., S, S, 4)."""
    from dbb_capture.synth.capture import load_ground_truth
    from dbb_capture.synth.render import render_object_rgba

    _, _, obj = load_ground_truth(capture)
    out = [render_object_rgba(obj, intr, c2w, float(t), samples)
           for t, (c2w, intr) in zip(times.reshape(-1), crop_cameras(dataset, views))]
    return np.stack(out).reshape(*times.shape, *out[0].shape)


def tree_renders(renderer, dataset: Path, views: np.ndarray) -> np.ndarray:
    """A PlenOctree's renders (``renderer``: its :class:`~dbb_capture.octree.render.TreeRenderer`)
    through the crop camera of each of ``views`` (..., 3): straight RGBA uint8 (..., S, S, 4)."""
    out = [np.clip(np.round(renderer.render(c2w, intr) * 255), 0, 255).astype(np.uint8)
           for c2w, intr in crop_cameras(dataset, views)]
    return np.stack(out).reshape(*views.shape[:-1], *out[0].shape)


NEW_PATH_SHIFTS = (0.25, 0.5, 0.75)


def new_path(run: Path, dataset: Path, capture: Path, shifts: tuple[float, ...] = NEW_PATH_SHIFTS, windows: int = 32,
             seed: int = 0, anchor: Path | None = None, temperature: float | None = None) -> dict:
    """Rollouts from the run's stepper (``temperature``, by default its run-time one) on sets of windows at the
    test windows' times: ``own_crops`` (the test windows as preprocess cut them), ``own_path_truth``
    (the same viewpoints rendered from the truth), ``new_path_truth`` (the viewpoints of the
    stretch a shift of the capture later, wrapped, rendered from the truth at the same times: each
    of ``shifts`` in ``new_path_by_shift``, pooled in ``new_path_truth``) and ``reversed_path_truth``
    (from each window's first view, the camera turning the opposite way).
    Each set: mean PSNR of the model, copy-first and near over the steps, the gains, and the
    model's step 1 against the given first frame; with ``anchor`` (a PlenOctree run trained on the
    same dataset) also that tree's render at each predicted step's view ("anchor").

    Several shifts: "near" along a new path is the footage at the very view but another moment,
    so it scores well where that moment happens to show the swinging parts in the same phase; one
    shift is one draw of that coincidence (on three captures near varied by 1.1-2.2 dB between
    shifts 0.25, 0.5 and 0.75)."""
    from dbb_capture.dynamic.evaluate import view_angle_deg
    from dbb_capture.octree.render import TreeRenderer
    from dbb_capture.octree.tree import PlenOctree

    tree = None if anchor is None else TreeRenderer(PlenOctree.load(Path(anchor) / "tree.npz"))
    model, data = run_data(run, dataset)
    if temperature is None:
        temperature = RunRecord.read(run).stepper.temperature
    stepper = run_stepper(run, model, data, temperature)
    starts = data.starts("test")
    if len(starts) > windows:
        starts = starts[np.linspace(0, len(starts) - 1, windows).round().astype(int)]
    n, L = len(data.rgba), data.length
    idx = starts[:, None] + np.arange(L)[None]
    times, own_views = data.times[idx], data.views[idx]
    back = own_views.copy()                        # from the same first view, the camera turning the other way
    back[..., :2] = 2 * own_views[:, :1, :2] - own_views[..., :2]
    back[..., 1] = np.clip(back[..., 1], -85.0, 85.0)
    sets = {"own_crops": (data.rgba[idx], own_views),
            "own_path_truth": (path_truth(dataset, capture, times, own_views), own_views),
            "reversed_path_truth": (path_truth(dataset, capture, times, back), back)}
    shifted = {}
    for shift in shifts:
        moved = (starts[:, None] + int(round(shift * n))) % (n - L + 1) + np.arange(L)[None]
        new_views = data.views[moved].copy()
        new_views[..., 2] = own_views[..., 2]      # the same distance: only the direction is new
        shifted[f"{shift:g}"] = (path_truth(dataset, capture, times, new_views), new_views)

    def scored(truth: np.ndarray, views: np.ndarray) -> dict:
        ps, _, figs = score_rollouts(stepper, data, truth, views, seed)
        m = {k: round(float(np.mean(v)), 3) for k, v in ps.items()}
        if tree is not None:
            a = premultiplied(tree_renders(tree, dataset, views[:, 1:]))
            m["anchor"] = round(float(np.mean([psnr(a[w, t], figs["truth"][w, t + 1])
                                               for w in range(len(starts)) for t in range(L - 1)])), 3)
        step1 = float(np.mean([psnr(figs["methods"]["model"][w, 0], figs["truth"][w, 0]) for w in range(len(starts))]))
        return _path_figures(m, step1, figs["near_gap_deg"])

    turns = [view_angle_deg(views, own_views) for _, views in shifted.values()]
    out = {"run": str(run), "temperature": temperature, "windows": len(starts), "steps": L - 1,
           "shifts": list(shifts), "new_path_turn_deg": round(float(np.median(turns)), 2)}
    out.update({name: scored(truth, views) for name, (truth, views) in sets.items()})
    by_shift = {name: scored(truth, views) for name, (truth, views) in shifted.items()}
    # Every shift scores as many windows: the pooled means are the means of theirs.
    pooled = {k: round(float(np.mean([b["mean_psnr_db"][k] for b in by_shift.values()])), 3)
              for k in next(iter(by_shift.values()))["mean_psnr_db"]}
    out["new_path_truth"] = _path_figures(pooled, float(np.mean([b["step1_vs_first_frame_db"] for b in by_shift.values()])),
                                          float(np.median([b["near_gap_deg"] for b in by_shift.values()])))
    out["new_path_by_shift"] = by_shift
    return out


def _path_figures(m: dict, step1: float, near_gap: float) -> dict:
    """One path set's entry of :func:`new_path`."""
    return {"mean_psnr_db": m, "gain_vs_copy_first_db": round(m["model"] - m["copy_first"], 3),
            "gain_vs_near_db": round(m["model"] - m["near"], 3), "step1_vs_first_frame_db": round(step1, 3),
            "near_gap_deg": round(near_gap, 2)}


def run_data(run: Path, dataset: Path, model: Rssm | None = None) -> tuple[Rssm, SequenceData]:
    """The run's model (or ``model``, e.g. :func:`with_settings` of it) and ``dataset`` with the run's view anchor."""
    own, data = load_run_data(run, dataset)
    return (own if model is None else model).eval(), data


def run_stepper(run: Path, model: Rssm, data: SequenceData, temperature: float) -> Stepper:
    """The eager stepper of ``model`` as the run samples at run time, at ``temperature`` (the run's
    temperature warm-up, its view anchor)."""
    return Stepper(model, temperature, data.atlas, RunRecord.read(run).stepper.warmup)


def with_settings(model: Rssm, settings: list[str]) -> Rssm:
    """``model`` rebuilt with other settings (``NAME=VALUE``) and the same weights: for settings
    that leave the weights' shapes alone, e.g. ``warp_leak`` tried on a model trained with another."""
    if not settings:
        return model
    cfg, _ = configs_from_settings(list(settings), model.cfg)
    out = Rssm(cfg)
    out.load_state_dict(model.state_dict())
    return out.eval()


def evaluate(run: Path, dataset: Path, still: dict | None, temperature: float, name: str,
             model: Rssm | None = None) -> dict:
    """Evaluate a run folder (again; its model.pt unless ``model``) at ``temperature``, into
    ``run/name``; the report's figures."""
    model, data = run_data(run, dataset, model)
    ck = run / "checkpoint.pt"
    history = torch.load(ck, weights_only=False)["history"] if ck.is_file() else []
    kw = {} if still is None else {"still_truth": still["truth"], "still_start": (still["first"], still["view"])}
    ev = run_eval(model, data, run / name, history, temperature, RunRecord.read(run).stepper.warmup, **kw).to_json()
    return {"temperature": temperature, "mean_psnr_db": ev["mean_psnr_db"], "psnr_gain_db": ev["psnr_gain_db"],
            "mean_ssim": ev["mean_ssim"], "psnr_per_step": ev["psnr_db"], "motion": ev["motion"],
            "report": str(run / name)}


def train_test_gap(run: Path, dataset: Path, temperature: float, windows: int = 40,
                   model: Rssm | None = None) -> dict:
    """Mean open-loop PSNR gain over copy-first on training windows and on held-out ones (dB).

    A model that fits its training windows far better than held-out ones has learned which pose
    goes with which training view and window, not how the toy moves.
    """
    model, data = run_data(run, dataset, model)
    out = {}
    for split in ("train", "test"):
        sub = replace(data, windows=[(s, "test") for s, sp in data.windows if sp == split])
        rep, _ = evaluate_stepper(run_stepper(run, model, data, temperature), sub, max_windows=windows, rollout_steps=3)
        out[split] = round(rep.mean("psnr", "model") - rep.mean("psnr", "copy_first"), 3)
    return out


def blurred_copy(dataset: Path, sigma: float, size: int = 64) -> dict:
    """Copy-first blurred by a Gaussian of ``sigma`` x sqrt(step) pixels, on the test windows: PSNR
    gain (dB) over plain copy-first per step and on average. What a prediction that only hedges
    (grows less sure, never moves) scores against the bar."""
    import cv2

    data = load_sequences(dataset, size)
    starts = data.starts("test")
    idx = starts[:, None] + np.arange(data.length)[None]
    truth = premultiplied(data.rgba[idx])                                   # (W, L, S, S, 4)
    gains = []
    for t in range(1, data.length):
        s = sigma * np.sqrt(t)
        blur = [cv2.GaussianBlur(truth[w, 0], (0, 0), s) if s > 0 else truth[w, 0] for w in range(len(starts))]
        gains.append(np.mean([psnr(b, truth[w, t]) for w, b in enumerate(blur)])
                     - np.mean([psnr(truth[w, 0], truth[w, t]) for w in range(len(starts))]))
    return {"sigma_px_times_sqrt_step": sigma, "windows": len(starts), "gain_per_step_db": [round(g, 3) for g in gains],
            "gain_db": round(float(np.mean(gains)), 3)}


@torch.no_grad()
def first_step(run: Path, dataset: Path, split: str = "test", temperature: float = 1.0, seed: int = 0,
               model: Rssm | None = None) -> dict:
    """What the run-time first step does on the windows of ``split`` (one sampled z_1 per window, as
    ``dbb-export render``): PSNR (dB) of the frame, of copy-first, and of the decoder's candidates
    alone (the warped context frame with warp share 1, the generated content with share 0), the mean
    warp share on the object (truth or context alpha > 0.5) and the step flow's mean and
    95th-percentile length in pixels there."""
    model, data = run_data(run, dataset, model)
    cfg = model.cfg
    starts = data.starts(split)
    x, views = window_batch(data, starts, torch.device("cpu"))          # premultiplied (W, L, 4, S, S)
    torch.manual_seed(seed)
    pe = model.encode_view(views)
    h0 = x.new_zeros(len(starts), cfg.deter)
    z0 = sample(*model.post_stats(h0, model.encoder(x[:, 0]), pe[:, 0]), temperature)
    h1 = model.transition(h0, z0)
    z1 = sample(*model.prior_stats(h1), temperature)
    ctx, ctx_pm, dec = model.encoder.context(x[:, 0]), x[:, 0], model.decoder
    change = view_delta_encoding(pe[:, 1], pe[:, 0])             # since the context frame, which is the last
    feat = decoder_input(h1, z1, change, change)
    ident = dec.grid.expand(len(starts), -1, -1, -1)
    a = anchor_batch(data, starts, torch.device("cpu"))
    anchor, ctx_anchor = (None, None) if a is None else (a[:, 1], image_pyramid(a[:, 0], len(dec.ups)))
    frame, grid = dec(feat, ctx, ctx_pm, ident, None, anchor, ctx_anchor)
    xh = dec.heads(feat, warp_maps(ctx, ident), dec.state_keypoints(feat),
                   [] if anchor is None else dec.anchor_maps(anchor, ctx_anchor))
    flow = torch.tanh(xh[:, 5:7]) * dec.max_step_flow
    warped = torch.nn.functional.grid_sample(ctx_pm, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    gen = torch.sigmoid(xh[:, :4])
    gen = torch.cat([gen[:, :3] * gen[:, 3:4], gen[:, 3:4]], 1)
    share = torch.sigmoid(xh[:, 4])
    truth = x[:, 1].numpy()
    ps_ = lambda a: float(np.mean([psnr(p, t) for p, t in zip(np.asarray(a), truth)]))
    obj = ((x[:, 1, 3] > 0.5) | (x[:, 0, 3] > 0.5)).numpy()
    px = flow.norm(dim=1).numpy() * cfg.size / 2
    out = {"windows": len(starts), "split": split, "psnr_db": ps_(frame), "copy_first_db": ps_(ctx_pm),
           "warped_only_db": ps_(warped), "generated_only_db": ps_(gen),
           "warp_share_on_object": round(float(share.numpy()[obj].mean()), 3),
           "flow_px_mean_on_object": round(float(px[obj].mean()), 3),
           "flow_px_p95_on_object": round(float(np.percentile(px[obj], 95)), 3),
           "still_share_on_object": round(float((px[obj] == 0).mean()), 3)}
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}


@torch.no_grad()
def protocols(run: Path, dataset: Path, samples: int = 8, temperature: float = 1.0, max_windows: int = 64,
              model: Rssm | None = None) -> dict:
    """Open-loop gain over copy-first (dB, test windows) under three protocols: ``one_sample`` (one
    sampled rollout per window: the run-time protocol, what the bar is claimed on), ``mean_of_samples``
    (the mean frame of ``samples`` rollouts: a hedge no run-time stepper draws) and ``best_of_samples``
    (each window's best rollout by its 10-step PSNR, chosen with the truth: SVG/SAVP's oracle)."""
    model, data = run_data(run, dataset, model)
    starts = data.starts("test")
    if len(starts) > max_windows:
        starts = starts[np.linspace(0, len(starts) - 1, max_windows).round().astype(int)]
    x, views = window_batch(data, starts, torch.device("cpu"))
    first = torch.from_numpy(data.rgba[starts]).permute(0, 3, 1, 2).float() / 255.0
    truth = x[:, 1:].numpy()
    runs = []
    for i in range(samples):
        torch.manual_seed(i)
        runs.append(premultiply(rollout(run_stepper(run, model, data, temperature), first, views)).numpy())
    runs = np.stack(runs)                                                   # (N, W, T, 4, S, S)

    def window_psnr(pred: np.ndarray) -> np.ndarray:                        # (W, T, ...) -> (W,) mean over steps
        return np.array([[psnr(pred[w, t], truth[w, t]) for t in range(truth.shape[1])]
                         for w in range(len(starts))]).mean(1)

    copy = window_psnr(np.broadcast_to(x[:, :1].numpy(), truth.shape)).mean()
    per = np.stack([window_psnr(r) for r in runs])                          # (N, W)
    return {"windows": len(starts), "samples": samples, "temperature": temperature,
            "gain_vs_copy_first_db": {"one_sample": round(float(per[0].mean() - copy), 3),
                                      "one_sample_mean_over_seeds": round(float(per.mean() - copy), 3),
                                      "mean_of_samples": round(float(window_psnr(runs.mean(0)).mean() - copy), 3),
                                      "best_of_samples": round(float(per.max(0).mean() - copy), 3)}}


def centroids(frames: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Where each of ``frames`` (T, S, S, C) differs from a still ``background`` (S, S, C): the
    centroid of its squared difference, (T, 2) as (y, x) in pixels (pixel centres at +0.5)."""
    d = ((frames.astype(np.float64) - background.astype(np.float64)) ** 2).sum(-1)        # (T, S, S)
    w = d / np.maximum(d.sum(axis=(1, 2), keepdims=True), 1e-12)
    c = np.arange(frames.shape[1]) + 0.5
    return np.stack([(w.sum(2) * c).sum(1), (w.sum(1) * c).sum(1)], 1)


def travel(frames: np.ndarray, background: np.ndarray) -> float:
    """How far what moves travels, in pixels: ``frames`` (T, S, S, C) against a still ``background``
    (S, S, C), the RMS distance of the frames' :func:`centroids` from their mean. A part that swings
    across the frame scores its swing; flicker spread over the frame, or a part that shakes in
    place, scores little (unlike the energy ratio, which counts both as motion)."""
    return spread(centroids(frames, background))


def path_distance(points: np.ndarray, path: np.ndarray) -> float:
    """Mean distance from each of ``points`` (T, 2) to the nearest of ``path`` (U, 2), in their units.

    With the truth's :func:`centroids` as ``points`` and a rollout's as ``path`` it says how far
    the places the truth's moving part visits lie from anywhere the rollout takes it (its "miss");
    the other way round, how far the rollout strays from the truth's path. Both ignore timing, so
    a swing along the truth's arc at another phase scores ~0; a part that shakes where it started,
    or slides another way, misses the places the truth reaches by their distance."""
    d = np.sqrt(((points[:, None, :] - path[None, :, :]) ** 2).sum(-1))
    return float(d.min(1).mean())


def swing_period(points: np.ndarray, shortest: float = 4.0, longest: float = 60.0) -> dict:
    """The rhythm of a path ``points`` (T, 2), e.g. :func:`centroids`: the dominant period in
    frames (between ``shortest`` and ``longest``) of its motion along its main axis, once its drift
    (a moving mean over ``longest`` frames, the path odd-reflected at its ends so the mean follows
    a trend there) is taken out; ``share``, the part of that motion's power
    at that period, within the path's resolution (+-2 / T cycles a frame; a clean swing near 1,
    white jitter ~0.2-0.35); ``amp_px``, the motion's amplitude (sqrt 2 times its RMS, a sine's peak).

    The autocorrelation's largest value past a few lags does not give the period: a smooth path
    correlates best with itself at the smallest lag looked at, whatever its rhythm."""
    k = int(longest) | 1
    pad = np.pad(points.astype(np.float64), ((k // 2, k // 2), (0, 0)), mode="reflect", reflect_type="odd")
    drift = np.stack([np.convolve(pad[:, i], np.ones(k) / k, "valid") for i in range(2)], 1)
    d = points - drift
    d -= d.mean(0)
    s = d @ np.linalg.svd(d, full_matrices=False)[2][0]      # along the main axis
    n = max(1024, 4 * len(s))
    power = np.abs(np.fft.rfft(s * np.hanning(len(s)), n)) ** 2
    f = np.fft.rfftfreq(n)
    band = (f >= 1.0 / longest) & (f <= 1.0 / shortest)
    if not band.any() or power[band].sum() <= 0:
        return {"period": None, "share": 0.0, "amp_px": 0.0}
    f0 = f[band][np.argmax(power[band])]
    near = band & (np.abs(f - f0) <= 2.0 / len(s))        # the Hann window's main lobe
    return {"period": round(float(1.0 / f0), 1), "share": round(float(power[near].sum() / power[band].sum()), 2),
            "amp_px": round(float(np.sqrt(2.0) * s.std()), 2)}


def spread(points: np.ndarray) -> float:
    """RMS distance of ``points`` (T, 2) from their mean, in their units."""
    return float(np.sqrt(((points - points.mean(0)) ** 2).sum(1).mean()))


@torch.no_grad()
def motion(run: Path, dataset: Path, still: dict, temperatures: list[float] = (0.0, 1.0, 2.0), samples: int = 3,
           model: Rssm | None = None) -> dict:
    """Where the still-view motion goes. ``still`` as :func:`still_truth` (``first`` (S, S, 4) uint8,
    ``view`` (3,), ``truth`` (T, S, S, 4) uint8). For each temperature (0 = the prior mean) and
    ``samples`` seeds: the motion-energy ratio (mean |frame change| of the rollout over the
    truth's) in blocks of steps 1-10 (the trained open loop), 11-30, 31-75, 76-150 and over all,
    and the coherence (:func:`motion_coherence`). Also, on the test windows (moving camera,
    temperature 1, seed 0), the ratio per open-loop step 1..10 (step 1 from the context frame).

    A rollout whose motion comes from the deterministic path moves at temperature 0; one whose
    motion is only the prior's noise freezes there and moves in proportion to the temperature.
    ``travel_px`` per rollout (:func:`travel`, against the truth's per-pixel median): whether the
    motion carries a part across the frame, beside the truth's; ``miss_px`` and ``stray_px``
    (:func:`path_distance` between the rollout's and the truth's centroids): whether it carries it
    where the truth's goes (travel alone counts a part sliding the wrong way as a swing); ``swing``
    (:func:`swing_period` of the rollout's centroids, the truth's beside it): at what rhythm."""
    model, data = run_data(run, dataset, model)
    truth = premultiplied(still["truth"])
    n = len(truth)
    t_e = np.abs(np.diff(truth.astype(np.float64), axis=0)).mean(axis=(1, 2, 3))       # (n - 1,)
    background = np.median(truth, axis=0)
    truth_path = centroids(truth, background)
    blocks = [(a, b) for a, b in ((0, 9), (9, 29), (29, 74), (74, n - 1)) if b <= n - 1 and a < b]
    f0 = torch.from_numpy(still["first"][None]).permute(0, 3, 1, 2).float() / 255.0
    views = torch.from_numpy(np.asarray(still["view"], np.float32)[None, None]).expand(-1, n + 1, -1).contiguous()
    out: dict = {"blocks": [f"{a + 1}-{b + 1}" for a, b in blocks] + ["all"], "per_temperature": {}}
    for temp in temperatures:
        rows = []
        for s in range(samples if temp > 0 else 1):
            torch.manual_seed(s + 1)
            long = premultiplied(rollout(run_stepper(run, model, data, temp), f0, views)[0].permute(0, 2, 3, 1).numpy())
            p_e = np.abs(np.diff(long.astype(np.float64), axis=0)).mean(axis=(1, 2, 3))
            coh = motion_coherence(long)
            path = centroids(long, background)
            rows.append({"ratio": [round(float(p_e[a:b].mean() / t_e[a:b].mean()), 3) for a, b in blocks]
                         + [round(float(p_e.mean() / t_e.mean()), 3)],
                         "coherence": None if coh is None else round(coh, 3),
                         "travel_px": round(spread(path), 2),
                         "miss_px": round(path_distance(truth_path, path), 2),
                         "stray_px": round(path_distance(path, truth_path), 2),
                         "swing": swing_period(path)})
        out["per_temperature"][f"{temp:g}"] = rows
    out["truth_coherence"] = round(motion_coherence(truth), 3)
    out["truth_travel_px"] = round(spread(truth_path), 2)
    out["truth_swing"] = swing_period(truth_path)
    starts = data.starts("test")[:64]
    x, v = window_batch(data, starts, torch.device("cpu"))                              # premultiplied
    torch.manual_seed(0)
    first = torch.from_numpy(data.rgba[starts]).permute(0, 3, 1, 2).float() / 255.0
    pred = premultiply(rollout(run_stepper(run, model, data, 1.0), first, v))
    seq = torch.cat([x[:, :1], pred], 1).numpy()
    e = lambda a: np.abs(np.diff(a.astype(np.float64), axis=1)).mean(axis=(0, 2, 3, 4))
    out["test_windows_ratio_per_step"] = [round(float(a / b), 3) for a, b in zip(e(seq), e(x.numpy()))]
    return out


def subset(dataset: Path, out: Path, seconds: float) -> dict:
    """A copy of a preprocess dataset's crops.json that trains on less footage: the training frames
    of the first ``seconds`` of the capture and the same test frames and windows (images linked,
    frame indices renumbered; later training frames dropped, so "near" sees only the kept ones)."""
    doc = json.loads((Path(dataset) / "crops.json").read_text())
    frames = doc["frames"]
    t0 = min(f["time"] for f in frames)
    keep = [i for i, f in enumerate(frames) if f["split"] == "test" or f["time"] - t0 < seconds]
    new = {old: i for i, old in enumerate(keep)}
    length = int(doc.get("sequence_length", 11))
    seqs = [{**q, "start": new[q["start"]]} for q in doc["sequences"]
            if all(q["start"] + j in new for j in range(length))
            and new[q["start"] + length - 1] - new[q["start"]] == length - 1]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name in {Path(f["file_path"]).parts[0] for f in frames}:
        link = out / name
        if not link.exists():
            link.symlink_to((Path(dataset) / name).resolve())
    (out / "crops.json").write_text(json.dumps({**doc, "frames": [frames[i] for i in keep], "sequences": seqs}))
    count = lambda sp: sum(q["split"] == sp for q in seqs)
    return {"seconds": seconds, "frames": len(keep), "train_windows": count("train"), "test_windows": count("test")}


def overrides(pairs: list[str], resume_from: Path | None = None,
              preset: str | None = None) -> tuple[RssmConfig, TrainConfig]:
    """Model and training settings from a preset and ``name=value`` pairs (``dbb-train rssm --set``
    names), over the defaults or the settings of the run ``resume_from`` (as ``dbb-train rssm --resume``)."""
    try:
        cfg, tcfg = resume_configs(resume_from) if resume_from else (RssmConfig(), TrainConfig())
        if preset:
            cfg, tcfg = apply_preset(preset, cfg, tcfg)
        return configs_from_settings(pairs, cfg, tcfg)
    except DbbError as e:
        raise SystemExit(str(e)) from None


def quality(dataset: Path, run: Path, capture: Path | None, minutes: float, steps: int | None, batch: int,
            lr: float, temperature: float | None, train: bool, settings: list[str] = (),
            start_frame: int | None = None, resume: bool = False, preset: str | None = None) -> dict:
    """Train on a preprocess dataset (unless ``train`` is off), then evaluate with the still-view truth.

    ``temperature`` None: the run's own, fitted to the footage (``dbb_capture.dynamic.evaluate.calibrate_temperature``;
    with ``train`` off it is fitted again and the run's report rewritten)."""
    still = None
    if capture is not None:
        cache = run.parent / f".{run.name}.still.pt"
        if not cache.is_file():
            torch.save(still_truth(dataset, capture), cache)
        still = torch.load(cache, weights_only=False)
    out: dict = {"dataset": str(dataset), "threads": torch.get_num_threads(),
                 "load_average_1min_before": round(os.getloadavg()[0], 2)}
    if train:
        t = time.perf_counter()
        cfg, tcfg = overrides(list(settings), run if resume else None, preset)
        tcfg = replace(tcfg, minutes=minutes, steps=steps, batch=batch, lr=lr)
        record = train_run(dataset, run, cfg, tcfg, overwrite=not resume, resume=resume, temperature=temperature)
        out["settings"] = ([f"preset={preset}"] if preset else []) + list(settings)
        out.update({"train_steps": record.training.steps,
                    "train_minutes": round(record.training.seconds / 60, 2),
                    "wall_minutes_train_and_eval": round((time.perf_counter() - t) / 60, 2),
                    "train_sequences": record.training.train_sequences,
                    "test_sequences": record.training.test_sequences,
                    "run_eval_motion_dataset_truth": record.eval["motion"]})
    else:
        if temperature is None:
            eval_run(run, dataset, calibrate=True)
        record = RunRecord.read(run)
        out["eval_settings"] = list(settings)       # tried on the trained weights (with_settings)
        out.update({"train_steps": record.training.steps,
                    "train_minutes": round(record.training.seconds / 60, 2)})
    out["load_average_1min_after"] = round(os.getloadavg()[0], 2)
    if temperature is None:
        temperature = record.stepper.temperature
        out["temperature_calibration"] = record.stepper.temperature_calibration
    if still is None and start_frame is not None:
        # Fixed-camera footage is its own still-view truth, from any start frame.
        data = load_sequences(dataset, load_model(run).cfg.size)
        k = start_frame
        still = {"first": data.rgba[k], "view": data.views[k], "truth": data.rgba[k + 1:k + 151], "frame": k}
    if still is not None:
        name = f"report-still-t{temperature:g}" + ("" if start_frame is None else f"-from{start_frame}")
        model = None
        if not train and settings:
            model = with_settings(load_model(run), list(settings))
            name += "-" + "-".join(s.replace("=", "") for s in settings)
        out["still_view_eval"] = evaluate(run, dataset, still, temperature, name, model=model)
        out["gain_vs_copy_first_train_test"] = train_test_gap(run, dataset, temperature, model=model)
        if capture is None:
            k = still["frame"]
            out["still_view_eval"]["motion"]["truth_source"] = f"the footage itself, frames {k + 1}-{k + 150}"
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("speed")
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--sizes", default="64,256")
    s.add_argument("--steps", type=int, default=300, help="steps per timing")
    s.add_argument("--repeat", type=int, default=1, help="timings per size (the median is reported)")
    s.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a model setting other than its default (dbb-train rssm --set; repeatable)")
    s.add_argument("--preset", default=None, help="a preset (dbb-train rssm --preset), applied before --set")
    q = sub.add_parser("quality")
    q.add_argument("dataset", type=Path, help="a dbb-capture preprocess output (crops.json)")
    q.add_argument("--run", type=Path, required=True, help="run folder to write (or read with --no-train)")
    q.add_argument("--capture", type=Path, default=None,
                   help="the synthetic capture the dataset came from: its ground truth gives the still-view motion")
    q.add_argument("--minutes", type=float, default=15.0)
    q.add_argument("--steps", type=int, default=None)
    q.add_argument("--batch", type=int, default=TrainConfig.batch)
    q.add_argument("--threads", type=int, default=1)
    q.add_argument("--lr", type=float, default=TrainConfig.lr)
    q.add_argument("--temperature", type=float, default=None,
                   help="run-time sampling temperature (default: fitted to the footage, as dbb-train rssm does)")
    q.add_argument("--no-train", action="store_true", help="only evaluate an existing run")
    q.add_argument("--resume", action="store_true", help="train an existing run further (to --minutes in all)")
    q.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a setting other than its default (dbb-train rssm --set; repeatable)")
    q.add_argument("--preset", default=None, help="a preset (dbb-train rssm --preset), applied before --set")
    q.add_argument("--start-frame", type=int, default=None,
                   help="fixed-camera footage: start the still-view rollout at this frame (default: the report's)")
    f = sub.add_parser("first-step", help="what the run-time first step loses: its candidates, mask and flow")
    f.add_argument("run", type=Path)
    f.add_argument("dataset", type=Path)
    f.add_argument("--split", default="test", choices=["train", "test"])
    f.add_argument("--temperature", type=float, default=1.0)
    f.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a setting tried on the trained weights, e.g. warp_leak=0.05 (repeatable)")
    r = sub.add_parser("protocols", help="gain over copy-first: one sample (run time), mean of samples, best of samples")
    r.add_argument("run", type=Path)
    r.add_argument("dataset", type=Path)
    r.add_argument("--samples", type=int, default=8)
    r.add_argument("--temperature", type=float, default=1.0)
    r.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a setting tried on the trained weights (repeatable)")
    m = sub.add_parser("motion", help="where the still-view motion goes: energy ratio per block of steps and temperature")
    m.add_argument("run", type=Path)
    m.add_argument("dataset", type=Path)
    m.add_argument("--capture", type=Path, default=None,
                   help="the synthetic capture (still-view truth rendered once, cached beside the run as .RUN.still.pt)")
    m.add_argument("--start-frame", type=int, default=0, help="fixed-camera footage without a cache: the rollout's start")
    m.add_argument("--temperature", type=float, action="append", default=[], help="repeatable (default 0, 1, 2)")
    m.add_argument("--samples", type=int, default=3, help="sampled rollouts per temperature above 0")
    m.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a setting tried on the trained weights (repeatable)")
    d = sub.add_parser("subset", help="a dataset with the training frames of the first SECONDS only (same test split)")
    d.add_argument("dataset", type=Path)
    d.add_argument("--seconds", type=float, required=True)
    d.add_argument("-o", "--output", type=Path, required=True)
    n = sub.add_parser("new-path", help="rollouts along viewpoint paths the footage never followed (synthetic truth)")
    n.add_argument("run", type=Path)
    n.add_argument("dataset", type=Path)
    n.add_argument("--capture", type=Path, required=True, help="the synthetic capture the dataset came from")
    n.add_argument("--shift", type=float, nargs="+", default=list(NEW_PATH_SHIFTS),
                   help="the new paths' viewpoints: those these fractions of the capture later (pooled, and each)")
    n.add_argument("--windows", type=int, default=32)
    n.add_argument("--anchor", type=Path, default=None,
                   help="a dbb-train plenoctree run on the same dataset: its renders scored too, as 'anchor'")
    n.add_argument("--temperature", type=float, default=None, help="sampling temperature (default: the run's)")
    b = sub.add_parser("blurred-copy", help="the score of copy-first blurred more at each step (a hedge)")
    b.add_argument("dataset", type=Path)
    b.add_argument("--sigma", type=float, action="append", default=[], help="pixels at step 1 (repeatable)")
    a = ap.parse_args()
    torch.set_num_threads(getattr(a, "threads", 1))
    if a.cmd == "protocols":
        out = protocols(a.run, a.dataset, a.samples, a.temperature,
                        model=with_settings(load_model(a.run), a.set))
    elif a.cmd == "subset":
        out = subset(a.dataset, a.output, a.seconds)
    elif a.cmd == "first-step":
        out = first_step(a.run, a.dataset, a.split, a.temperature, model=with_settings(load_model(a.run), a.set))
    elif a.cmd == "motion":
        cache = a.run.parent / f".{a.run.name}.still.pt"
        if a.capture is not None and not cache.is_file():
            torch.save(still_truth(a.dataset, a.capture), cache)
        if cache.is_file():
            still = torch.load(cache, weights_only=False)
        else:                                   # a fixed camera: the footage is its own truth
            data = load_sequences(a.dataset, load_model(a.run).cfg.size)
            k = a.start_frame
            still = {"first": data.rgba[k], "view": data.views[k], "truth": data.rgba[k + 1:k + 151], "frame": k}
        out = motion(a.run, a.dataset, still, a.temperature or [0.0, 1.0, 2.0], a.samples,
                     model=with_settings(load_model(a.run), a.set))
    elif a.cmd == "new-path":
        out = new_path(a.run, a.dataset, a.capture, tuple(a.shift), a.windows, anchor=a.anchor, temperature=a.temperature)
    elif a.cmd == "blurred-copy":
        out = [blurred_copy(a.dataset, s) for s in (a.sigma or [0.5])]
    elif a.cmd == "speed":
        out = [{**speed(int(s), a.steps, a.set, a.repeat, a.preset), "settings": a.set, "preset": a.preset}
               for s in a.sizes.split(",")]
    else:
        out = quality(a.dataset, a.run, a.capture, a.minutes, a.steps, a.batch, a.lr, a.temperature, not a.no_train,
                      a.set, a.start_frame, a.resume, a.preset)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
