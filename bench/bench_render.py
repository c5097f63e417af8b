"""Render speed of the PlenOctree renderer (the rendering bars; figures in docs/results.md).
Run one benchmark at a time: timings of overlapping jobs say little.

    python bench/bench_render.py run RUN [RUN ...]   # trees of dbb-train plenoctree run folders
    python bench/bench_render.py shell               # a synthetic opaque-shell tree (no haze)
    python bench/bench_render.py rebake RUN OUT      # RUN's checkpoint baked by the current bake
    python bench/bench_render.py prune RUN OUT --prune-weight W   # RUN's tree weight-pruned

For a run: straight-RGBA frames/s at 256x256 and 800x800 (all cores) from the first held-out
camera of its dataset, the best CPU seconds per frame on one thread (other
jobs on a shared machine move it far less than the frame rate; the load average is recorded),
the tree's size, and with ``--psnr`` the held-out PSNR on white and black
(the quality a bake setting costs or buys). ``--torch`` also times the PyTorch path at 256.
The shell tree is a sphere of opaque leaves at depth 7 (256^3), what a well-converged object
looks like to the renderer, seen from 2.5 radii (of the tree cube) with a 40 degree field of
view, so that it covers about as much of the frame as lego does.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from common import emit  # bench/ is the script folder: on sys.path

from dbb_capture.datasets.transforms import load_dataset
from dbb_capture.geometry.cameras import Intrinsics, scaled_intrinsics
from dbb_capture.geometry.transforms import look_at
from dbb_capture.octree.render import TreeRenderer
from dbb_capture.octree.tree import PlenOctree, build_tree
from dbb_capture.static.bake import PRUNE_WEIGHT
from dbb_capture.static.run import (
    RunConfig,
    evaluate_views,
    load_run,
    mean_of,
    split_frames,
)


def fps(renderer: TreeRenderer, c2w: np.ndarray, intr: Intrinsics, repeats: int) -> float:
    """Frames per second rendering straight RGBA with ``intr`` (after one warm-up frame)."""
    renderer.render(c2w, intr)
    t = time.perf_counter()
    for _ in range(repeats):
        renderer.render(c2w, intr)
    return repeats / (time.perf_counter() - t)


def cpu_seconds(renderer: TreeRenderer, c2w: np.ndarray, intr: Intrinsics, repeats: int) -> float:
    """CPU seconds per frame on one thread (best of ``repeats``): what other jobs on a shared
    machine change least. n idle cores give about n / this frames/s."""
    threads, renderer.impl.threads = renderer.impl.threads, 1
    renderer.render(c2w, intr)
    best = math.inf
    for _ in range(repeats):
        t = time.process_time()
        renderer.render(c2w, intr)
        best = min(best, time.process_time() - t)
    renderer.impl.threads = threads
    return best


def speeds(r: TreeRenderer, c2w: np.ndarray, base: Intrinsics, repeats: int) -> dict:
    out = {"load_average_before": os.getloadavg()[0]}
    for s in (256, 800):
        intr = scaled_intrinsics(base, base.width / s)
        n = repeats if s <= 256 else max(2, repeats // 4)
        out[f"fps_{s}"] = fps(r, c2w, intr, n)
        out[f"cpu_s_per_frame_{s}"] = cpu_seconds(r, c2w, intr, n)
    out["load_average_after"] = os.getloadavg()[0]
    return out


def split(run) -> tuple[list, list]:
    """Training and held-out views of a run, as ``dbb-train plenoctree`` split them (every 8th
    held out)."""
    sp = split_frames(load_dataset(Path(run.record.dataset)), RunConfig(holdout_every=8))
    return sp.train, sp.test


def heldout(run) -> list:
    return split(run)[1]


def rebake(run_dir: Path, out: Path, prune_weight: float) -> dict:
    """Bake ``run_dir``'s checkpoint with the current :func:`bake` (weight pruning with its
    training cameras) into ``out`` (a run folder sharing the checkpoint, so it can be
    benchmarked like the original)."""
    import torch

    from dbb_capture.static.bake import bake
    from dbb_capture.static.train import TrainState

    run = load_run(run_dir)
    st = TrainState.load(run.checkpoint_path, torch.device("cpu"))
    t = time.perf_counter()
    tree = bake(st.field, cameras=[(f.c2w, f.intr) for f in split(run)[0]], prune_weight=prune_weight)
    return _write_tree(run_dir, out, tree, time.perf_counter() - t, prune_weight)


def prune(run_dir: Path, out: Path, prune_weight: float) -> dict:
    """``run_dir``'s stored tree weight-pruned (:func:`prune_by_weight`, its training cameras)
    into the run folder ``out``: the bake's last step alone, so thresholds compare quickly."""
    from dbb_capture.static.bake import prune_by_weight

    run = load_run(run_dir)
    t = time.perf_counter()
    tree = prune_by_weight(run.tree(), [(f.c2w, f.intr) for f in split(run)[0]], prune_weight)
    return _write_tree(run_dir, out, tree, time.perf_counter() - t, prune_weight)


def _write_tree(run_dir: Path, out: Path, tree: PlenOctree, seconds: float, prune_weight: float) -> dict:
    import shutil

    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(run_dir / "run.json", out / "run.json")
    size = tree.save(out / "tree.npz")
    return {"run": str(run_dir), "out": str(out), "prune_weight": prune_weight, "seconds": seconds,
            "tree_mb": size / 1e6, "leaves_with_data": tree.n_leaves_with_data()}


def bench_run(run_dir: Path, repeats: int, with_psnr: bool, with_torch: bool) -> dict:
    run = load_run(run_dir)
    test = heldout(run)
    tree = run.tree()
    t = time.perf_counter()
    r = TreeRenderer(tree)
    out = {"run": str(run_dir), "tree_mb": run.tree_path.stat().st_size / 1e6,
           "leaves_with_data": tree.n_leaves_with_data(), "depth": tree.depth_limit,
           "renderer_setup_s": time.perf_counter() - t, "threads": r.impl.threads}
    out.update(speeds(r, test[0].c2w, test[0].intr, repeats))
    if with_torch:
        rt = TreeRenderer(tree, backend="torch")
        out["torch_fps_256"] = fps(rt, test[0].c2w, scaled_intrinsics(test[0].intr, test[0].intr.width / 256), 1)
    if with_psnr:
        rows = evaluate_views(r, test, run.record.training.downscale, ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
        out.update(heldout_views=len(test), psnr_white=mean_of(rows, "psnr_white"),
                   ssim_white=mean_of(rows, "ssim_white"), psnr_black=mean_of(rows, "psnr_black"))
    return out


def shell_tree(depth: int = 7, radius: float = 0.6, seed: int = 0) -> PlenOctree:
    """Opaque spherical shell (two leaves thick, alpha 0.95 per leaf) of random SH9 colour."""
    L = 1 << (depth + 1)
    g = (np.arange(L) + 0.5) / L * 2 - 1
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    dist = np.sqrt(x * x + y * y + z * z)
    cells = np.argwhere(np.abs(dist - radius) < 2.0 / L)
    rng = np.random.default_rng(seed)
    coef = rng.normal(0, 0.5, (len(cells), 27))
    sigma = np.full((len(cells), 1), -math.log(0.05) / (2.0 / L))      # per world unit, radius 1
    data, child, pd = build_tree(cells, np.concatenate([coef, sigma], 1).astype(np.float32), depth)
    inv = np.full(3, 0.5, np.float32)
    return PlenOctree(data.astype(np.float16), child, pd, inv, np.full(3, 0.5, np.float32), depth, "SH9")


def bench_shell(repeats: int) -> dict:
    tree = shell_tree()
    r = TreeRenderer(tree)
    f = 400 / math.tan(math.radians(20))
    base = Intrinsics(800, 800, f, f, 399.5, 399.5)
    c2w = look_at(np.array([0.0, -2.4, -0.7]), np.zeros(3), np.array([0.0, 0.0, -1.0]))   # 2.5 radii
    out = {"tree": "opaque shell, depth 7", "leaves_with_data": tree.n_leaves_with_data(),
           "threads": r.impl.threads}
    out.update(speeds(r, c2w, base, repeats))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("part", choices=["run", "shell", "rebake", "prune"])
    ap.add_argument("runs", type=Path, nargs="*",
                    help="run folders of dbb-train plenoctree (rebake, prune: RUN OUT)")
    ap.add_argument("--prune-weight", type=float, default=PRUNE_WEIGHT,
                    help="rebake, prune: drop leaves no training ray gives this weight (0: keep all)")
    ap.add_argument("--repeats", type=int, default=8)
    ap.add_argument("--psnr", action="store_true", help="also held-out PSNR on white")
    ap.add_argument("--torch", action="store_true", help="also time the PyTorch path at 256")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = ap.parse_args(argv)
    if a.part in ("rebake", "prune"):
        if len(a.runs) != 2:
            ap.error(f"{a.part} takes RUN OUT")
        res = [(rebake if a.part == "rebake" else prune)(*a.runs, a.prune_weight)]
    elif a.part == "run":
        res = [bench_run(p, a.repeats, a.psnr, a.torch) for p in a.runs]
    else:
        res = [bench_shell(a.repeats)]
    return emit(res, a.json)


if __name__ == "__main__":
    sys.exit(main())
