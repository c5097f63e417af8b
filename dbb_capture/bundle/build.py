"""Packaging a finished training run (static or dynamic) as a bundle: model, proxy mesh,
previews and manifest, written aside and renamed (or zipped) into place."""

from __future__ import annotations

import os
import shutil
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

from ..core.errors import DbbError
from ..core.images import to_u8
from ..core.outputs import atomic_dir, empty_dir, read_json, scratch_prefix, sweep_stale
from ..core.progress import progress
from ..datasets.transforms import load_poses
from ..geometry.viewpoint import up_from_cameras, viewpoint
from .manifest import CHECKSUM, MANIFEST, Bundle, Manifest, write_manifest
from .previews import write_dynamic_previews, write_png, write_static_previews
from .proxy import SupportPlane, bundle_from_board, dynamic_proxy, static_proxy, write_glb
from .render import DynamicRenderer


def _dataset_cameras(dataset: Path) -> tuple[list[float], np.ndarray, bool]:
    """Up (3,), camera poses (N, 4, 4, OpenCV, board frame) of a dataset, without its images, and
    whether the dataset is in a measured board frame.

    Up is the board normal on the cameras' side: the dataset's recorded "up" (a dbb-capture
    dataset: its board plane z = 0 is the table), else from its poses (another tool's dataset,
    whose z = 0 need not be a support).
    """
    c2w, meta = load_poses(dataset)
    if isinstance(meta.get("up"), list) and len(meta["up"]) == 3:
        return [float(v) for v in meta["up"]], c2w, True
    return [float(v) for v in up_from_cameras(c2w)], c2w, False


def mean_azimuth(c2w: np.ndarray, center: np.ndarray, up: np.ndarray) -> float:
    """Circular mean of the cameras' azimuths about ``up`` (degrees): the side best seen."""
    a = np.radians([viewpoint(T[:3, 3], center, up).azimuth_deg for T in c2w])
    return float(np.degrees(np.arctan2(np.sin(a).mean(), np.cos(a).mean()))) if len(a) else 0.0


def _run_dataset(recorded: str, run: Path, dataset: Path | None) -> Path:
    """The dataset a run was trained on (``recorded`` in its run.json), or ``dataset`` instead."""
    ds = Path(dataset) if dataset is not None else Path(recorded)
    if not ds.exists():
        raise DbbError(f"the dataset of {run} is gone ({ds}): pass {{=dataset}} to point at it")
    return ds


def _created(run: Path, fmt: str, steps: int, seconds: float) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("dbb-capture")
    except PackageNotFoundError:
        v = "unknown"
    return {"tool": "dbb-export bundle", "tool_version": v,
            "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "run": str(Path(run).resolve()), "run_format": fmt, "training_steps": steps, "training_seconds": seconds}


def read_run(run: Path):
    """The typed record of a finished ``dbb-train`` run: a static :class:`~..static.run.Run` or a
    dynamic :class:`~..dynamic.record.RunRecord` (one clear error otherwise, e.g. an older version)."""
    from ..dynamic.record import RUN_FORMAT as RSSM_FORMAT
    from ..dynamic.record import RunRecord
    from ..static.run import RUN_FORMAT as TREE_FORMAT
    from ..static.run import load_run

    if not Path(run).is_dir():
        raise DbbError(f"run folder not found: {run}")
    meta = read_json(Path(run) / "run.json", "run description (is this a finished training run?)")
    fmt = meta.get("format") if isinstance(meta, dict) else None
    if fmt == TREE_FORMAT:
        return load_run(run)
    if fmt == RSSM_FORMAT:
        return RunRecord.read(run)
    raise DbbError(f"{run} is not a finished dbb-train run (run.json format {fmt!r})")


def _need(run: Path, *names: str) -> None:
    for n in names:
        if not (Path(run) / n).is_file():
            raise DbbError(f"{run} is not a finished training run: {n} is missing")


def build_static(r, tmp: Path, dataset: Path | None, prog) -> Manifest:
    """The static bundle of the PlenOctree run ``r`` (:class:`~..static.run.Run`) into ``tmp``."""
    from ..octree.tree import PlenOctree
    from ..static.run import RUN_FORMAT

    run, rec = r.path, r.record
    _need(run, rec.tree.file, r.density_grid_path.name)
    tree = PlenOctree.load(r.tree_path)     # a damaged tree is refused here, not copied into the bundle
    center, radius = np.asarray(rec.volume.center, float), float(rec.volume.radius)
    up, cams, board_frame = _dataset_cameras(_run_dataset(rec.dataset, run, dataset))
    T = bundle_from_board(center, up)
    support = SupportPlane.board(np.asarray(up)) if board_frame else None
    (tmp / "model").mkdir()
    shutil.copyfile(r.tree_path, tmp / "model" / "plenoctree.npz")
    task = prog.add_task("proxy mesh", total=1, info="marching cubes")
    proxy = static_proxy(r.density_grid_path, T, support=support)
    write_glb(tmp / "proxy.glb", proxy)
    prog.advance(task)
    previews = write_static_previews(tmp / "previews", tree, T, radius,
                                     round(mean_azimuth(cams, center, np.asarray(up)), 1), prog)
    return Manifest(
        kind="static",
        model={"type": "plenoctree", "file": "model/plenoctree.npz", "format": "svox N3Tree npz",
               "data_format": rec.tree.data_format, "sh_degree": rec.tree.sh_degree,
               "depth_limit": rec.tree.depth_limit, "density_units": "per metre (board frame)",
               "frame": "board (tree: offset + board_point * invradius3 in [0, 1]^3)"},
        inputs={"camera": "a ray per pixel in the board frame (bundle-space rays: apply the inverse of "
                          "bundle_from_board first)", "output": "straight RGBA"},
        proxy_mesh=proxy.to_json("proxy.glb"), bundle_from_board=T.tolist(),
        object={"center": center.tolist(), "radius": radius}, up=list(up),
        canvas={"size_m": 2 * radius, "note": "a camera-facing square of this side, centred on the object, "
                                                 "holds the object sphere"},
        colour_activation=rec.tree.colour_activation, previews=previews,
        created=_created(run, RUN_FORMAT, rec.training.steps, rec.training.seconds),
        support_plane=None if support is None else support.in_bundle(T))


def build_dynamic(run: Path, rec, tmp: Path, dataset: Path | None, prog) -> Manifest:
    """The dynamic bundle of the RSSM run ``run`` (its :class:`~..dynamic.record.RunRecord` ``rec``)
    into ``tmp``."""
    from ..datasets.images import load_rgba
    from ..datasets.transforms import find_dataset_file, load_dataset
    from ..dynamic.record import RUN_FORMAT

    _need(run, rec.stepper.file, rec.model_file)
    ds_file = find_dataset_file(_run_dataset(rec.dataset, run, dataset))
    o = rec.object or {}
    if "center" not in o or "radius" not in o:
        raise DbbError(f"{run}/run.json has no object sphere")
    center, radius = np.asarray(o["center"], float), float(o["radius"])
    # The run records the dataset's up; a dataset without one has no measured board plane.
    up, _, board_frame = (rec.up, None, True) if rec.up else _dataset_cameras(ds_file)
    T = bundle_from_board(center, up)
    support = SupportPlane.board(np.asarray(up, float)) if board_frame else None
    (tmp / "model").mkdir()
    shutil.copyfile(Path(run) / rec.stepper.file, tmp / "model" / "stepper.ts")
    shutil.copyfile(Path(run) / rec.model_file, tmp / "model" / "rssm.pt")
    anchor = Path(run) / "anchor" / "tree.npz"      # the view anchor (its renders are in stepper.ts)
    if rec.config.anchor:
        _need(run, "anchor/tree.npz")
        shutil.copyfile(anchor, tmp / "model" / "anchor.npz")
    size = rec.stepper.frame_size
    fill = float(rec.crop.get("fill") or 0.9)
    first = load_dataset(ds_file).frames[0]
    write_png(tmp / "model" / "first_frame.png", to_u8(load_rgba(first)))
    vp = viewpoint(first.c2w[:3, 3], center, np.asarray(up, float))
    task = prog.add_task("proxy mesh", total=1, info="visual hull")
    proxy = dynamic_proxy(ds_file, center, radius, T, support=support)
    write_glb(tmp / "proxy.glb", proxy)
    prog.advance(task)
    m = Manifest(
        kind="dynamic",
        model={"type": "rssm", "file": "model/stepper.ts", "format": "TorchScript",
               "weights": "model/rssm.pt", "api": rec.stepper.to_json()["api"],
               "temperature": rec.stepper.temperature, "temperature_warmup_steps": rec.stepper.warmup,
               "fps": rec.stepper.fps,
               **({"anchor": {"file": "model/anchor.npz", "format": "svox N3Tree npz",
                              "note": "the view anchor: a PlenOctree of the capture's mean shape, whose renders "
                                      "the stepper reads (stepper.ts carries them as an atlas)"}}
                  if rec.config.anchor else {})},
        inputs={"first_frame": "model/first_frame.png", "first_view": [vp.azimuth_deg, vp.elevation_deg,
                                                                       vp.distance_m],
                "view": "[azimuth_deg, elevation_deg, distance_m] of the camera from the object centre: "
                        "elevation from the board plane toward up, azimuth right-handed about up from the "
                        "board's x axis (bundle space: about +Y from +X)",
                "frame_size": size, "crop_fill": fill, "output": "straight RGBA (B, 4, S, S) in 0..1 per step"},
        proxy_mesh=proxy.to_json("proxy.glb"), bundle_from_board=T.tolist(),
        object={"center": center.tolist(), "radius": radius}, up=[float(v) for v in up],
        canvas={"size_m": 2 * radius / fill, "note": "side of the camera-facing square the model's frame "
                                                      "covers at the object centre (far camera)"},
        colour_activation="sigmoid (decoder output, straight RGBA)", previews={},
        created=_created(run, RUN_FORMAT, rec.training.steps, rec.training.seconds),
        support_plane=None if support is None else support.in_bundle(T))
    b = Bundle(tmp, tmp, m)
    m.previews = write_dynamic_previews(tmp / "previews", DynamicRenderer(b), prog)
    return m


def make_bundle(run: Path, out: Path, zip_it: bool = False, dataset: Path | None = None,
                overwrite: bool = False) -> Manifest:
    """Package the finished training run ``run`` as a bundle at ``out`` (a ``.dbb`` zip if ``zip_it``).

    Nothing appears at ``out`` unless the whole bundle was written.
    """
    from ..static.run import Run

    run, out = Path(run), Path(out)
    rec = read_run(run)
    if out.exists() and not (overwrite or empty_dir(out)):
        raise DbbError(f"{out} already exists (pass {{=overwrite}} to replace it)")

    def build(tmp: Path, prog) -> Manifest:
        if isinstance(rec, Run):
            return build_static(rec, tmp, dataset, prog)
        return build_dynamic(run, rec, tmp, dataset, prog)

    with progress() as prog:
        if not zip_it:
            with atomic_dir(out, overwrite=True) as tmp:
                m = build(tmp, prog)
                write_manifest(tmp, m)
            return m
        out.parent.mkdir(parents=True, exist_ok=True)
        sweep_stale(out)
        with tempfile.TemporaryDirectory(prefix=scratch_prefix(out), dir=out.parent) as t:
            tmp = Path(t) / "bundle"
            tmp.mkdir()
            m = build(tmp, prog)
            write_manifest(tmp, m)
            z = Path(t) / "bundle.dbb"
            with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf:
                for p in [tmp / MANIFEST, tmp / CHECKSUM] + [tmp / e.path for e in m.files]:
                    zf.write(p, p.relative_to(tmp).as_posix())
            if out.is_dir():
                shutil.rmtree(out)
            os.replace(z, out)
        return m
