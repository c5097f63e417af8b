"""The static-object training stage: dataset -> voxel field -> PlenOctree run folder.

A run folder (``dbb-train plenoctree DATASET -o RUN``) describes itself in ``run.json``
(:class:`RunRecord`):

- ``tree.npz``: the PlenOctree, svox ``N3Tree`` format (``run.json: tree`` tells its data
  format, SH degree, colour activation, density units, depth and leaf lattice);
- ``density_grid.npz``: world density (float16, per world unit) sampled on a regular grid over
  the object's cube (``sigma`` (G, G, G) indexed [x, y, z], ``bbox_min``, ``bbox_max``), for
  proxy meshes and previews;
- ``checkpoint.pt``: the trained field, so a resumed run can train further;
- ``report/``: ``curve.png`` (loss and PSNR over steps), ``heldout_*.png`` (render | truth on
  white: the tree for objects, the field for scenes), ``metrics.json``.
- ``run.json: object`` is the object sphere in the dataset's world frame (board frame for
  captures) and whether it was estimated from the cameras.

Checkpoints during training go to ``.<RUN>.work/`` beside RUN; an interrupted run resumes from
there, and the folder goes away once RUN is written.
"""

from __future__ import annotations

import io
import json
import math
import shutil
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from ..core.device import pick_device
from ..core.errors import DbbError
from ..core.images import to_u8, upscale_nearest, with_header
from ..core.metrics import psnr_from_mse
from ..core.outputs import (
    atomic_dir,
    check_run_output,
    read_json,
    refuse_spent_budget,
    resume_checkpoint,
    run_work_dir,
    training_minutes,
    write_bytes_atomic,
    write_json,
)
from ..core.progress import console, progress, resumed_line
from ..datasets.records import (
    Frame,
    ObjectVolume,
    PosedDataset,
    estimate_volume,
    holdout_every,
    holdout_named,
)
from ..datasets.transforms import load_dataset, missing_crops
from ..geometry.cameras import scaled_intrinsics
from ..octree.render import TreeRenderer
from ..octree.tree import PlenOctree
from .bake import PRUNE_WEIGHT, bake
from .field import FieldConfig, VoxelField, lattice_for_views
from .rays import build_ray_bank, frame_tensors
from .render import render_image
from .train import Budget, TrainState, new_field, train

RUN_FORMAT = "dbb-plenoctree-run"
RUN_VERSION = 2      # runs of other versions are refused: train them again
TREE_FILE, DENSITY_GRID_FILE, CHECKPOINT_FILE, REPORT_DIR = "tree.npz", "density_grid.npz", "checkpoint.pt", "report"


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
class TreeRecord:
    """``run.json: tree``: the baked PlenOctree (svox N3Tree npz, density per world unit, leaves
    outside the object sphere trimmed)."""

    file: str                 # the tree's file in the run folder
    data_format: str          # "SH9" ...
    sh_degree: int
    colour_activation: str
    depth_limit: int
    nodes: int
    leaves_with_data: int
    bytes: int                # size of the file
    prune_weight: float       # the bake's weight pruning (0: none)

    @property
    def leaf_resolution(self) -> int:
        """Leaves per axis of the finest lattice."""
        return 1 << (self.depth_limit + 1)

    def to_json(self) -> dict:
        return {"file": self.file, "format": "svox N3Tree npz", "data_format": self.data_format,
                "sh_degree": self.sh_degree, "colour_activation": self.colour_activation,
                "density_units": "per world unit", "depth_limit": self.depth_limit,
                "leaf_resolution": self.leaf_resolution, "nodes": self.nodes,
                "leaves_with_data": self.leaves_with_data, "bytes": self.bytes, "prune_weight": self.prune_weight,
                "bounds_note": "leaves outside the object sphere are trimmed"}


@dataclass
class TrainingRecord:
    """``run.json: training``: how long and on what the field trained."""

    steps: int
    seconds: float                   # training time over every resume
    last_wall_seconds: float         # wall-clock time of the last call: its training, bake and report
    budget_minutes: float | None
    budget_steps: int | None
    downscale: float
    device: str
    train_frames: int
    test_frames: int
    final_train_psnr: float | None   # running mean over the last steps (dB)


@dataclass
class RunRecord:
    """``run.json`` of a PlenOctree run folder (format :data:`RUN_FORMAT`, version
    :data:`RUN_VERSION`): where the run came from, its tree, its field and training, the report's
    metrics (``report/metrics.json``). The file also names its other files (constant names)."""

    dataset: str              # the dataset path, absolute
    dataset_file: str         # its json file's name
    dataset_kind: str         # "crops", "transforms" or "blender"
    mode: str                 # "object" or "scene"
    volume: ObjectVolume      # run.json: object
    tree: TreeRecord
    field: FieldConfig        # the field's settings as trained ...
    final_res: int            # ... its final lattice per axis ...
    active_points: int        # ... and active points (all three in run.json: field)
    training: TrainingRecord
    metrics: dict

    def to_json(self) -> dict:
        return {
            "format": RUN_FORMAT, "version": RUN_VERSION,
            "dataset": self.dataset, "dataset_file": self.dataset_file, "dataset_kind": self.dataset_kind,
            "mode": self.mode, "object": self.volume.to_json(), "tree": self.tree.to_json(),
            "density_grid": {"file": DENSITY_GRID_FILE, "units": "per world unit",
                             "layout": "sigma[x, y, z] at cell centres of [bbox_min, bbox_max]"},
            "checkpoint": CHECKPOINT_FILE,
            "field": asdict(self.field) | {"final_res": self.final_res, "active_points": self.active_points},
            "training": asdict(self.training), "metrics": self.metrics, "report": REPORT_DIR + "/",
        }

    @classmethod
    def from_json(cls, d: object, where: Path) -> RunRecord:
        """The record of ``run.json`` content ``d`` of the run folder ``where``; one clear
        :class:`DbbError` for another format, another version or a missing entry."""
        if not isinstance(d, dict) or d.get("format") != RUN_FORMAT:
            got = d.get("format") if isinstance(d, dict) else None
            raise DbbError(f"{where} is not a PlenOctree run (run.json format {got!r})")
        if d.get("version") != RUN_VERSION:
            raise DbbError(f"{where} is a PlenOctree run of another version ({d.get('version')}, this toolkit "
                           f"reads {RUN_VERSION}): train it again")
        t = _entries(d, [f.name for f in fields(TreeRecord)], where, "tree")
        o = _entries(d, ("center", "radius", "estimated"), where, "object")
        fd = _entries(d, [f.name for f in fields(FieldConfig)] + ["final_res", "active_points"], where, "field")
        tr = _entries(d, [f.name for f in fields(TrainingRecord)], where, "training")
        top = _entries(d, ("dataset", "dataset_file", "dataset_kind", "mode", "metrics"), where)
        try:
            final_res, active = int(fd.pop("final_res")), int(fd.pop("active_points"))
            return cls(
                str(top["dataset"]), str(top["dataset_file"]), str(top["dataset_kind"]), str(top["mode"]),
                ObjectVolume(tuple(float(v) for v in o["center"]), float(o["radius"]), bool(o["estimated"])),
                TreeRecord(**t), FieldConfig(**(fd | {"upsample_at": tuple(fd["upsample_at"])})), final_res, active,
                TrainingRecord(**tr), dict(top["metrics"]))
        except (TypeError, ValueError) as e:
            raise DbbError(f"{where}/run.json is not a valid PlenOctree run record ({e})") from None


def _entries(d: dict, names, where: Path, key: str | None = None) -> dict:
    """The entries ``names`` of run.json content ``d`` (of its object ``key`` if given); a
    missing one is named in a :class:`DbbError`."""
    sec = d if key is None else d.get(key)
    for n in names:
        if not isinstance(sec, dict) or n not in sec:
            what = n if key is None else f"{key}.{n}"
            raise DbbError(f"{where}/run.json lacks {what}: is it a finished PlenOctree run?")
    return {n: sec[n] for n in names}


@dataclass
class Run:
    """A finished run folder, read back."""

    path: Path
    record: RunRecord

    @property
    def tree_path(self) -> Path:
        return self.path / self.record.tree.file

    @property
    def density_grid_path(self) -> Path:
        return self.path / DENSITY_GRID_FILE

    @property
    def checkpoint_path(self) -> Path:
        return self.path / CHECKPOINT_FILE

    @property
    def volume(self) -> ObjectVolume:
        return self.record.volume

    def tree(self) -> PlenOctree:
        return PlenOctree.load(self.tree_path)


def load_run(path: Path) -> Run:
    """Read ``run.json`` of a PlenOctree run folder (clear error if it is not one of this version)."""
    return Run(Path(path), RunRecord.from_json(read_json(Path(path) / "run.json", "run description"), Path(path)))


@dataclass
class HeldOut:
    """One set of held-out frames and what it is: ``name`` ("interleaved": every n-th view along
    the path, new views between trained ones; "test": a dataset's own test views; "named": the
    frames asked for), ``what`` in words."""

    name: str
    what: str
    frames: list[Frame]


@dataclass
class Split:
    """The frames trained on and the held-out sets scored in the report (the first is the
    run's headline figure; one set today, a list so a report can name each it scores)."""

    train: list[Frame]
    heldout: list[HeldOut]

    @property
    def test(self) -> list[Frame]:
        return [f for h in self.heldout for f in h.frames]


def split_frames(ds: PosedDataset, cfg: RunConfig) -> Split:
    """Train and held-out frames. Named frames if asked; a dataset's own test views (Blender's
    ``transforms_test.json``, a split file) if it has them; else every ``holdout_every``-th view
    held out between trained ones ("interleaved"). A capture's crops count as unsplit: their
    test split is the last stretch of the path in time, which the RSSM needs held out (it
    predicts forward in time) but which a static object would only lose views of, and whose
    score measures extrapolation beyond the path, not new views among the trained ones."""
    frames = ds.frames
    if cfg.holdout_names:
        frames = holdout_named(frames, set(cfg.holdout_names))
        missing = set(cfg.holdout_names) - {f.name for f in frames}
        if missing:
            raise DbbError(f"held-out frames not in the dataset: {', '.join(sorted(missing))}")
        name, what = "named", "the frames asked for"
    elif ds.kind != "crops" and any(f.split == "test" for f in frames):
        name, what = "test", "the dataset's test views"
    else:
        frames = holdout_every(frames, cfg.holdout_every)
        name, what = "interleaved", f"every {cfg.holdout_every}th view along the path, between trained ones"
    train_f = [f for f in frames if f.split == "train"]
    test_f = [f for f in frames if f.split == "test"]
    if not train_f:
        raise DbbError("no training frames left after the hold-out")
    return Split(train_f, [HeldOut(name, what, test_f)] if test_f else [])


def for_tree_depth(fcfg: FieldConfig, depth: int | None) -> FieldConfig:
    """The field's settings for a tree of ``depth``: a tree whose leaves (2^(depth+1) per axis) are
    finer than the lattice samples the trilinear field, so the nearest-lookup fine-tuning (which
    trains the lattice's piecewise-constant cells, as a tree at the lattice's own depth renders
    them) is left out (docs/decisions.md, ``--depth 7``)."""
    if depth is not None and fcfg.res_max is not None and (1 << (depth + 1)) > fcfg.res_max:
        return replace(fcfg, nearest_from=1.0)
    return fcfg


def train_run(dataset: Path, out: Path, cfg: RunConfig, field_cfg: FieldConfig | None = None,
              resume: bool = False, overwrite: bool = False, quiet: bool = False,
              resume_asks: tuple[str, ...] = ()) -> Run:
    """Train a field on ``dataset``, bake it, and write the run folder ``out`` (atomically).
    With ``resume``, training continues from the checkpoint of ``out`` (interrupted or finished),
    with the checkpoint's field settings: those named in ``resume_asks`` (``mode`` and
    :class:`FieldConfig` names the caller set on purpose) must agree with them."""
    out = Path(out)
    check_run_output(out, overwrite, resume)
    cfg = replace(cfg, minutes=training_minutes(cfg.minutes, cfg.steps, default=10.0))
    if resume:
        refuse_spent_budget(out, cfg.steps, cfg.minutes)
    if cfg.downscale < 1:
        raise DbbError("the downscale factor must be at least 1")
    why = missing_crops(Path(dataset))
    if why is not None:
        # Its transforms.json holds the whole room: trained as a scene it says nothing of the object.
        raise DbbError(f"{why} (or give {Path(dataset) / 'transforms.json'} to train the whole room)")
    ds = load_dataset(Path(dataset))
    split = split_frames(ds, cfg)
    train_f, test_f = split.train, split.test
    mode = cfg.mode if cfg.mode != "auto" else ("object" if ds.rgba else "scene")
    volume = ds.volume or estimate_volume(ds.frames)
    device = pick_device()
    work = run_work_dir(out)
    ckpt = work / CHECKPOINT_FILE
    state = None
    if resume:
        src = resume_checkpoint(out, CHECKPOINT_FILE)
        state = TrainState.load(src, device)
        volume = state.field.volume
        mode = state.field.cfg.mode
        _refuse_other_field(replace(field_cfg or FieldConfig(), mode=cfg.mode), state.field.cfg, resume_asks)
        if not quiet:
            console.print(resumed_line(state.step, state.seconds, cfg.steps, cfg.minutes, src,
                                       src.parent == run_work_dir(out)), markup=False)
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
    with progress(disable=quiet) as prog:
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
        nbytes = tree.save(tmp / TREE_FILE)
        shutil.copyfile(ckpt, tmp / CHECKPOINT_FILE)
        write_density_grid(state.field, tmp / DENSITY_GRID_FILE)
        metrics = write_report(state, tree, split.heldout or [HeldOut(
            "training", "training views (no held-out ones: fit, not new views)", train_f)], cfg, tmp / REPORT_DIR)
        record = RunRecord(
            dataset=str(Path(dataset).resolve()), dataset_file=ds.source.name, dataset_kind=ds.kind, mode=mode,
            volume=volume,
            tree=TreeRecord(TREE_FILE, tree.data_format, tree.sh_degree, tree.colour_activation, tree.depth_limit,
                            tree.n_nodes, tree.n_leaves_with_data(), nbytes, cfg.prune_weight),
            field=state.field.cfg, final_res=state.field.res, active_points=state.field.n_active,
            training=TrainingRecord(
                state.step, round(state.seconds, 1), round(time.perf_counter() - t0, 1), cfg.minutes, cfg.steps,
                cfg.downscale, str(device), len(train_f), len(test_f),
                state.history[-1]["psnr"] if state.history else None),
            metrics=metrics)
        write_json(tmp / "run.json", record.to_json())
    shutil.rmtree(work, ignore_errors=True)
    return Run(out, record)


def _refuse_other_field(asked: FieldConfig, run: FieldConfig, names: tuple[str, ...]) -> None:
    """A resumed run trains its checkpoint's field (``run``): the settings ``names`` of ``asked``
    must be its own (``mode`` "auto" agrees with either)."""
    differ = [f"{{={n}}} {getattr(asked, n)} (the run's {getattr(run, n)})" for n in names
              if getattr(asked, n) != getattr(run, n) and not (n == "mode" and asked.mode == "auto")]
    if differ:
        raise DbbError(f"a resumed run keeps its field's settings, and these differ from them: {'; '.join(differ)}; "
                       "drop them or train a new run")


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
    b = io.BytesIO()
    np.savez_compressed(b, **buf)
    write_bytes_atomic(path, b.getvalue())


def write_report(state: TrainState, tree: PlenOctree, sets: list[HeldOut], cfg: RunConfig, folder: Path) -> dict:
    """Loss/PSNR curve and renders beside truth (on white) of up to ``max_report_views`` views of
    each set, spread over it; returns the metrics written (per set, the first set's means also
    at the top)."""
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
    # A scene's tree holds only the inner sphere: show the whole field beside the truth.
    scene = state.field.cfg.mode == "scene"
    out_sets = {}
    for hs in sets:
        picked = np.unique(np.linspace(0, len(hs.frames) - 1, min(cfg.max_report_views, len(hs.frames)))
                           .round().astype(int))
        rows = []
        for f in (hs.frames[i] for i in picked):
            intr = scaled_intrinsics(f.intr, cfg.downscale)
            o, d, rgba = frame_tensors(f, cfg.downscale)
            gt = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
            img_tree = rend.render(f.c2w, intr, (1.0, 1.0, 1.0))
            img_field = render_image(state.field, torch.from_numpy(o), torch.from_numpy(d), (1.0, 1.0, 1.0))
            rows.append({"frame": f.name,
                         "psnr_tree_white": psnr_from_mse(float(((img_tree - gt) ** 2).mean())),
                         "psnr_field_white": psnr_from_mse(float(((img_field - gt) ** 2).mean()))})
            p = rows[-1]["psnr_field_white" if scene else "psnr_tree_white"]
            cv2.imwrite(str(folder / f"heldout_{f.name}.png"), cv2.cvtColor(
                truth_and_render(gt, img_field if scene else img_tree, f"render ({'field' if scene else 'tree'}), "
                                 f"{p:.1f} dB"), cv2.COLOR_RGB2BGR))
        out_sets[hs.name] = {"what": hs.what, "views": len(hs.frames), "scored": len(rows), "per_view": rows,
                             "mean_psnr_tree_white": mean_of(rows, "psnr_tree_white"),
                             "mean_psnr_field_white": mean_of(rows, "psnr_field_white")}
    first = sets[0].name if sets else None
    metrics = {"views": "training (no held-out frames)" if first == "training" else "held-out",
               "headline": first, "sets": out_sets}
    if first is not None:
        metrics |= {k: out_sets[first][k] for k in ("mean_psnr_tree_white", "mean_psnr_field_white")}
    (folder / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    return metrics


REPORT_VIEW_PX = 256     # held-out views in the report are shown at least this large (repeated pixels)


def truth_and_render(truth: np.ndarray, render: np.ndarray, label: str = "render") -> np.ndarray:
    """The report's picture of one view: ``truth`` | ``render`` (each (H, W, 3) float RGB in [0, 1]),
    enlarged to at least :data:`REPORT_VIEW_PX` with repeated pixels, under a band naming each ->
    uint8 RGB."""
    side = to_u8(np.concatenate([truth, render], 1))
    big = upscale_nearest(side, REPORT_VIEW_PX, side=min(truth.shape[:2]))
    w = big.shape[1] // 2
    return with_header(big, ["truth", label], [w, big.shape[1] - w])


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
