"""One stage of one capture, as a worker runs it: skipped where its output is already there and
complete, else run by the library into ``OUT/<capture>/...`` (written aside, renamed into place).
No Ray here: :mod:`.cluster` wraps :func:`run_stage` as a task.

A stage whose output exists is complete, because every output is renamed into place whole
(``core.outputs.atomic_dir``); what a killed worker leaves is a hidden scratch folder beside it,
which the next attempt removes. A training run interrupted mid-way continues from the checkpoint
in ``.run.work/`` when that is newer than the dataset (and, with ``force``, than the batch).
"""

from __future__ import annotations

import shutil
import socket
import time
from dataclasses import dataclass, replace
from pathlib import Path

from ..core.errors import DbbError
from ..core.outputs import read_json, run_work_dir
from .captures import CaptureJob
from .config import BatchConfig, Resources
from .records import CaptureMetrics, StageRecord

STAGES = ("preprocess", "train", "bundle", "verify")    # "check" comes first where a bundle exists
RAN, SKIPPED, FAILED = "ran", "skipped", "failed"


@dataclass(frozen=True)
class StageTask:
    """What the driver sends a worker: the stage, the capture, the settings, and whether the
    stage must run again (``redo``: --force, or a stage before it produced new output)."""

    stage: str
    job: CaptureJob
    cfg: BatchConfig
    resources: Resources
    redo: bool
    marker: Path                 # OUT/.dbb-batch, holding ``token``: this node sees OUT, and no
    token: str                   # other batch has taken OUT over since


def run_stage(task: StageTask, node_id: str | None = None, node_ip: str | None = None) -> StageRecord:
    """Run (or skip) ``task.stage`` of ``task.job``. A :class:`DbbError` (bad input: not worth a
    retry) comes back as a failed record with its one-line message; anything else is raised."""
    t0, began = time.perf_counter(), time.time()
    try:
        _check_marker(task)
        _set_threads(task.resources.cpus(task.stage))
        status, note, verified, metrics = _STAGE_FUNCS[task.stage](task)
        error = None
    except DbbError as e:
        status, note, verified, metrics, error = FAILED, "", False, CaptureMetrics(), " ".join(str(e).split())
    return StageRecord(task.stage, status, time.perf_counter() - t0, node_id, node_ip, began, note, error,
                       verified, metrics)


def _check_marker(task: StageTask) -> None:
    try:
        seen = task.marker.read_text().strip()
    except OSError:
        seen = None
    if seen != task.token:
        why = "does not see it" if seen is None else "another dbb-batch has started on it since"
        raise DbbError(f"{task.marker.parent}: this node ({socket.gethostname()}) {why}")


def _set_threads(cpus: float) -> None:
    """Use as many threads as the task was given CPUs (a reused worker keeps the last task's)."""
    import numba
    import torch

    n = max(1, int(cpus))
    torch.set_num_threads(n)
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))


def clear_scratch(final: Path) -> None:
    """Remove the scratch folders a killed worker left beside ``final`` (``atomic_dir``'s)."""
    for p in list(final.parent.glob(f".{final.name}.partial-*")) + list(final.parent.glob(f".{final.name}.old-*")):
        shutil.rmtree(p, ignore_errors=True)


def dataset_complete(dataset: Path) -> bool:
    """Whether ``dataset`` is a finished preprocess output (every stage through the crops)."""
    try:
        meta = read_json(dataset / "preprocess.json", "preprocess record")
    except DbbError:
        return False
    return isinstance(meta, dict) and "crops" in (meta.get("stages_run") or []) and \
        (dataset / "crops.json").is_file() and (dataset / "dataset.json").is_file()


def dataset_metrics(dataset: Path) -> CaptureMetrics:
    """Frames posed, from the dataset's ``dataset.json`` (none where it is gone)."""
    try:
        stats = read_json(dataset / "dataset.json", "dataset statistics")
        return CaptureMetrics(frames_posed=int(stats["frames_posed"]))
    except (DbbError, KeyError, TypeError, ValueError):
        return CaptureMetrics()


def run_metrics(run: Path) -> CaptureMetrics:
    """Held-out PSNR (static) or the RSSM's gain over copying the first frame (dynamic), from
    ``run.json`` (none where the run is gone or unreadable)."""
    from ..bundle.build import read_run
    from ..static.run import Run

    try:
        r = read_run(run)
    except DbbError:
        return CaptureMetrics()
    if isinstance(r, Run):
        m = r.record.metrics
        return CaptureMetrics(heldout_psnr_db=m.get("mean_psnr_tree_white"), psnr_views=m.get("views"))
    gain = (r.eval or {}).get("psnr_gain_db") or {}
    return CaptureMetrics(rssm_gain_db=gain.get("vs_copy_first"))


def run_complete(run: Path, kind: str) -> bool:
    """Whether ``run`` is a finished training run of ``kind`` (of this toolkit's run version)."""
    from ..bundle.build import read_run
    from ..static.run import Run

    try:
        r = read_run(run)
    except DbbError:
        return False
    return isinstance(r, Run) == (kind == "static")


def _check(task: StageTask):
    """Does the capture's existing bundle verify? Then the capture is done."""
    from ..bundle.verify import verify_bundle

    p = task.job.paths
    try:
        lines = verify_bundle(p.bundle)
    except DbbError as e:
        return RAN, f"the bundle did not verify ({e}): making it again", False, CaptureMetrics()
    return RAN, lines[-1], True, dataset_metrics(p.dataset).merged(run_metrics(p.run))


def _preprocess(task: StageTask):
    from ..preprocess.inputs import resolve_capture
    from ..preprocess.run import run_preprocess

    job, p = task.job, task.job.paths
    if not task.redo and dataset_complete(p.dataset):
        return SKIPPED, "dataset complete", False, dataset_metrics(p.dataset)
    settings = task.cfg.static if job.kind == "static" else task.cfg.dynamic
    cfg = replace(settings.preprocess, workers=max(1, int(task.resources.preprocess_cpus)))
    clear_scratch(p.dataset)
    res = run_preprocess(resolve_capture(job.folder), p.dataset, cfg, overwrite=True)
    return RAN, "; ".join(res.notes), False, dataset_metrics(p.dataset)


def _resumable(task: StageTask) -> bool:
    """Whether the run's interrupted checkpoint is worth continuing: newer than the dataset and,
    with --force, than this batch (else it is from an older dataset or run)."""
    ckpt = run_work_dir(task.job.paths.run) / "checkpoint.pt"
    if not ckpt.is_file():
        return False
    t = ckpt.stat().st_mtime
    newer = t > (task.job.paths.dataset / "preprocess.json").stat().st_mtime
    return newer and (not task.cfg.force or t > task.marker.stat().st_mtime)


def _train(task: StageTask):
    job, p = task.job, task.job.paths
    if not task.redo and run_complete(p.run, job.kind):
        return SKIPPED, "run complete", False, run_metrics(p.run)
    resume = _resumable(task)          # if not, the trainers' overwrite removes the old checkpoints
    clear_scratch(p.run)
    if job.kind == "static":
        from ..static.run import train_run

        s = task.cfg.static
        train_run(p.dataset, p.run, s.run, s.field, resume=resume, overwrite=True, quiet=True)
    else:
        from ..dynamic.run import train_run as train_rssm

        d = task.cfg.dynamic
        train_rssm(p.dataset, p.run, d.model, d.train, resume=resume, overwrite=True, quiet=True)
    return RAN, "resumed from its checkpoint" if resume else "", False, run_metrics(p.run)


def _bundle(task: StageTask):
    from ..bundle.build import make_bundle
    from ..bundle.manifest import MANIFEST

    p = task.job.paths
    if not task.redo and (p.bundle / MANIFEST).is_file():
        return SKIPPED, "bundle there (verified next)", False, CaptureMetrics()
    clear_scratch(p.bundle)
    m = make_bundle(p.run, p.bundle, dataset=p.dataset, overwrite=True)   # OUT may have moved
    return RAN, f"{m.kind} bundle, {len(m.files)} files", False, CaptureMetrics()


def _verify(task: StageTask):
    from ..bundle.verify import verify_bundle

    return RAN, verify_bundle(task.job.paths.bundle)[-1], True, CaptureMetrics()


_STAGE_FUNCS = {"check": _check, "preprocess": _preprocess, "train": _train, "bundle": _bundle, "verify": _verify}
