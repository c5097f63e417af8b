"""The static-object training stage: dataset -> voxel field -> PlenOctree run folder.

A run folder (``dbb-train plenoctree DATASET -o RUN``) describes itself in ``run.json``:

- ``tree.npz``: the PlenOctree, svox ``N3Tree`` format (``run.json: tree`` tells its data
  format, SH degree, colour activation, density units, depth and leaf lattice);
- ``density_grid.npz``: world density (float16, per world unit) sampled on a regular grid over
  the object's cube (``sigma`` (G, G, G) indexed [x, y, z], ``bbox_min``, ``bbox_max``), for
  proxy meshes and previews;
- ``checkpoint.pt``: the trained field, so ``--resume`` can train further;
- ``report/``: ``curve.png`` (loss and PSNR over steps), ``heldout_*.png`` (render | truth on
  white: the tree for objects, the field for scenes), ``metrics.json``.
- ``run.json: object`` is the object sphere in the dataset's world frame (board frame for
  captures) and whether it was estimated from the cameras.

Checkpoints during training go to ``.<RUN>.work/`` beside RUN; an interrupted run resumes from
there with ``--resume``, and the folder goes away once RUN is written.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from ..datasets.records import (
    Frame,
    ObjectVolume,
    PosedDataset,
    estimate_volume,
    holdout_every,
    holdout_named,
    load_dataset,
)
from ..geometry.cameras import scaled_intrinsics
from ..core.errors import DbbError
from ..geometry.sh import COLOUR_ACTIVATION
from .field import (
    Budget,
    FieldConfig,
    TrainState,
    VoxelField,
    build_ray_bank,
    frame_tensors,
    lattice_for_views,
    new_field,
    render_image,
    train,
)
from ..core.device import pick_device
from ..core.metrics import psnr_from_mse
from ..octree.render import PRUNE_WEIGHT, PlenOctree, TreeRenderer, bake
from ..core.outputs import (atomic_dir, check_run_output, read_json, resume_checkpoint, run_work_dir,
                      training_minutes, write_json)
from ..core.progress import progress

RUN_FORMAT = "dbb-plenoctree-run"


@dataclass
class RunConfig:
    """Everything ``dbb-train plenoctree`` decides, besides the field's own settings."""

    minutes: float | None = None
    steps: int | None = None
    downscale: float = 1.0
    mode: str = "auto"                 # auto: object when the images carry alpha, else scene
    holdout_every: int = 8             # when the dataset has no split: every n-th frame is test
    holdout_names: tuple[str, ...] = ()
    depth: int | None = None           # octree depth (None: match the field's lattice)
    prune_weight: float = PRUNE_WEIGHT  # bake drops leaves no training ray weights this much (0: off)
    max_report_views: int = 8


@dataclass
class Run:
    """A finished run folder, read back."""

    path: Path
    meta: dict

    @property
    def tree_path(self) -> Path:
        return self.path / self.meta["tree"]["file"]

    @property
    def volume(self) -> ObjectVolume:
        o = self.meta["object"]
        return ObjectVolume(tuple(o["center"]), float(o["radius"]), bool(o.get("estimated", False)))

    def tree(self) -> PlenOctree:
        return PlenOctree.load(self.tree_path)


def load_run(path: Path) -> Run:
    """Read ``run.json`` of a PlenOctree run folder (clear error if it is not one)."""
    meta = read_json(Path(path) / "run.json", "run description")
    if meta.get("format") != RUN_FORMAT:
        raise DbbError(f"{path} is not a PlenOctree run (run.json format {meta.get('format')!r})")
    return Run(Path(path), meta)


def split_frames(ds: PosedDataset, cfg: RunConfig) -> tuple[list[Frame], list[Frame]]:
    """Train and held-out frames: the dataset's own split, else the configured hold-out."""
    frames = ds.frames
    if cfg.holdout_names:
        frames = holdout_named(frames, set(cfg.holdout_names))
        missing = set(cfg.holdout_names) - {f.name for f in frames}
        if missing:
            raise DbbError(f"held-out frames not in the dataset: {', '.join(sorted(missing))}")
    elif all(f.split == "train" for f in frames):
        frames = holdout_every(frames, cfg.holdout_every)
    train_f = [f for f in frames if f.split == "train"]
    test_f = [f for f in frames if f.split == "test"]
    if not train_f:
        raise DbbError("no training frames left after the hold-out")
    return train_f, test_f


def for_tree_depth(fcfg: FieldConfig, depth: int | None) -> FieldConfig:
    """The field's settings for a tree of ``depth``: a tree whose leaves (2^(depth+1) per axis) are
    finer than the lattice samples the trilinear field, so the nearest-lookup fine-tuning (which
    trains the lattice's piecewise-constant cells, as a tree at the lattice's own depth renders
    them) is left out. 640x480 static capture, 128^3 lattice baked at depth 7: +0.3 dB on white
    (docs/benchmarks.md, issue 4, tenth session)."""
    if depth is not None and fcfg.res_max is not None and (1 << (depth + 1)) > fcfg.res_max:
        return replace(fcfg, nearest_from=1.0)
    return fcfg


def train_run(dataset: Path, out: Path, cfg: RunConfig, field_cfg: FieldConfig | None = None,
              resume: bool = False, overwrite: bool = False, quiet: bool = False) -> Run:
    """Train a field on ``dataset``, bake it, and write the run folder ``out`` (atomically)."""
    out = Path(out)
    check_run_output(out, overwrite, resume)
    cfg = replace(cfg, minutes=training_minutes(cfg.minutes, cfg.steps, default=10.0))
    if cfg.downscale < 1:
        raise DbbError("--downscale must be >= 1")
    ds = load_dataset(Path(dataset))
    train_f, test_f = split_frames(ds, cfg)
    mode = cfg.mode if cfg.mode != "auto" else ("object" if ds.rgba else "scene")
    volume = ds.volume or estimate_volume(ds.frames)
    device = pick_device()
    work = run_work_dir(out)
    ckpt = work / "checkpoint.pt"
    state = None
    if resume:
        state = TrainState.load(resume_checkpoint(out), device)
        volume = state.field.volume
        mode = state.field.cfg.mode
    fcfg = field_cfg or FieldConfig()
    fcfg = replace(fcfg, mode=mode).for_dataset(ds.kind)
    if fcfg.res_max is None:
        fcfg = replace(fcfg, res_max=lattice_for_views([(f.c2w, f.intr) for f in train_f], volume, mode,
                                                       cfg.downscale, fcfg.res_start))
    fcfg = for_tree_depth(fcfg, cfg.depth)
    fcfg.validate()
    bank = build_ray_bank(train_f, cfg.downscale, volume, mode,
                          observed=(state.field.cfg if state is not None else fcfg).observed_loss)
    if state is None:
        state = TrainState(new_field(fcfg, volume, device))
    work.mkdir(parents=True, exist_ok=True)
    budget = Budget(cfg.minutes, cfg.steps)
    t0 = time.perf_counter()
    with progress() as prog:
        task = prog.add_task("train field", total=100, info="")

        def on_step(st: TrainState, p: float) -> None:
            done = 100 * budget.fraction(st.step, st.seconds)
            prog.update(task, completed=done,
                        info=f"psnr {p:5.2f} dB  {st.field.res}^3  {st.field.n_active / 1e6:.2f}M pts")

        state = train(state, bank, budget, None if quiet else on_step, ckpt)
        prog.update(task, completed=100)
    del bank
    tree = bake(state.field, cfg.depth, cameras=[(f.c2w, f.intr) for f in train_f], prune_weight=cfg.prune_weight)
    with atomic_dir(out, overwrite=True) as tmp:
        nbytes = tree.save(tmp / "tree.npz")
        shutil.copyfile(ckpt, tmp / "checkpoint.pt")
        write_density_grid(state.field, tmp / "density_grid.npz")
        metrics = write_report(state, tree, test_f or train_f[:: max(1, len(train_f) // 4)],
                               cfg, tmp / "report", heldout=bool(test_f))
        meta = {
            "format": RUN_FORMAT, "version": 1,
            "dataset": str(Path(dataset).resolve()), "dataset_file": ds.source.name,
            "dataset_kind": ds.kind, "mode": mode,
            "object": volume.to_json(),
            "tree": {"file": "tree.npz", "format": "svox N3Tree npz", "data_format": tree.data_format,
                     "sh_degree": tree.sh_degree, "colour_activation": COLOUR_ACTIVATION,
                     "density_units": "per world unit", "depth_limit": tree.depth_limit,
                     "leaf_resolution": 1 << (tree.depth_limit + 1), "nodes": tree.n_nodes,
                     "leaves_with_data": tree.n_leaves_with_data(), "bytes": nbytes,
                     "prune_weight": cfg.prune_weight,
                     "bounds_note": "leaves outside the object sphere are trimmed"},
            "density_grid": {"file": "density_grid.npz", "units": "per world unit",
                             "layout": "sigma[x, y, z] at cell centres of [bbox_min, bbox_max]"},
            "checkpoint": "checkpoint.pt",
            "field": asdict(state.field.cfg) | {"final_res": state.field.res,
                                                "active_points": state.field.n_active},
            "training": {"steps": state.step, "seconds": round(state.seconds, 1),
                         "wall_seconds_this_session": round(time.perf_counter() - t0, 1),
                         "budget_minutes": cfg.minutes, "budget_steps": cfg.steps,
                         "downscale": cfg.downscale, "device": str(device),
                         "train_frames": len(train_f), "test_frames": len(test_f),
                         "final_train_psnr": state.history[-1]["psnr"] if state.history else None},
            "metrics": metrics,
            "report": "report/",
        }
        write_json(tmp / "run.json", meta)
    shutil.rmtree(work, ignore_errors=True)
    return Run(out, meta)


@torch.no_grad()
def write_density_grid(field: VoxelField, path: Path, max_res: int = 256) -> None:
    """World density on a regular grid over the object's cube (float16, per world unit)."""
    G = min(field.res if field.cfg.mode == "object" else field.res // 2, max_res)
    dev = field.device
    ax = (torch.arange(G, device=dev, dtype=torch.float32) + 0.5) / G * 2 - 1
    sig = torch.empty(G, G, G)
    for i in range(G):
        yy, zz = torch.meshgrid(ax, ax, indexing="ij")
        x = torch.stack([torch.full_like(yy, float(ax[i])), yy, zz], -1).view(-1, 3)
        sig[i] = (field.query(x)[0] / field.radius).view(G, G).cpu()
    c = np.asarray(field.volume.center, np.float32)
    r = np.float32(field.radius)
    buf = {"sigma": sig.numpy().astype(np.float16), "bbox_min": c - r, "bbox_max": c + r,
           "units": np.array("per world unit")}
    import io

    from ..core.outputs import write_bytes_atomic
    b = io.BytesIO()
    np.savez_compressed(b, **buf)
    write_bytes_atomic(path, b.getvalue())


def write_report(state: TrainState, tree: PlenOctree, frames: list[Frame], cfg: RunConfig,
                 folder: Path, heldout: bool) -> dict:
    """Loss/PSNR curve and renders beside truth (on white); returns the metrics written."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    h = state.history
    if h:
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
        ax[0].semilogy([e["step"] for e in h], [e["loss"] for e in h])
        ax[0].set_xlabel("step")
        ax[0].set_ylabel("loss")
        ax[1].plot([e["seconds"] / 60 for e in h], [e["psnr"] for e in h])
        ax[1].set_xlabel("minutes")
        ax[1].set_ylabel("train PSNR (dB, running mean)")
        for a in ax:
            a.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(folder / "curve.png", dpi=100)
        plt.close(fig)
    rend = TreeRenderer(tree, state.field.device)
    rows = []
    for f in frames[: cfg.max_report_views]:
        intr = scaled_intrinsics(f.intr, cfg.downscale)
        o, d, rgba = frame_tensors(f, cfg.downscale)
        gt = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
        img_tree = rend.render(f.c2w, intr, (1.0, 1.0, 1.0))
        img_field = render_image(state.field, torch.from_numpy(o), torch.from_numpy(d), (1.0, 1.0, 1.0))
        rows.append({"frame": f.name,
                     "psnr_tree_white": psnr_from_mse(float(((img_tree - gt) ** 2).mean())),
                     "psnr_field_white": psnr_from_mse(float(((img_field - gt) ** 2).mean()))})
        # A scene's tree holds only the inner sphere: show the whole field beside the truth.
        shown = img_field if state.field.cfg.mode == "scene" else img_tree
        side = np.concatenate([shown, gt], 1)
        cv2.imwrite(str(folder / f"heldout_{f.name}.png"),
                    cv2.cvtColor((np.clip(side, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
    metrics = {"views": "held-out" if heldout else "training (no held-out frames)",
               "per_view": rows}
    if rows:
        metrics["mean_psnr_tree_white"] = float(np.mean([r["psnr_tree_white"] for r in rows]))
        metrics["mean_psnr_field_white"] = float(np.mean([r["psnr_field_white"] for r in rows]))
    (folder / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    return metrics


def evaluate_views(renderer: TreeRenderer, frames: list[Frame], downscale: float,
                   backgrounds: tuple[tuple[float, float, float], ...] = ((1.0, 1.0, 1.0),)) -> list[dict]:
    """PSNR and SSIM (Gaussian window, sigma 1.5) of tree renders against the frames, per background."""
    from skimage.metrics import structural_similarity

    out = []
    for f in frames:
        intr = scaled_intrinsics(f.intr, downscale)
        _, _, rgba = frame_tensors(f, downscale)
        row = {"frame": f.name}
        for bg in backgrounds:
            gt = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]) * np.asarray(bg, np.float32)
            img = renderer.render(f.c2w, intr, bg)
            key = "white" if bg == (1.0, 1.0, 1.0) else ("black" if bg == (0.0, 0.0, 0.0) else str(bg))
            row[f"psnr_{key}"] = psnr_from_mse(float(((img - gt) ** 2).mean()))
            row[f"ssim_{key}"] = float(structural_similarity(
                img, gt, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                use_sample_covariance=False))
        out.append(row)
    return out


def mean_of(rows: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in rows])) if rows else math.nan
