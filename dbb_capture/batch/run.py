"""The driver of a batch: every capture's stages chained as Ray tasks (the next one submitted as
the last one ends), so captures overlap across the cluster; a live table meanwhile, and
``OUT/summary.json`` after each capture and at the end.

Per capture: ``check`` (only where a bundle exists: if it verifies, the capture is done) ->
``preprocess`` -> ``train`` -> ``bundle`` -> ``verify``. A stage whose output is there and complete
is skipped, unless --force or a stage before it made new output. One capture's failure ends only
that capture; a lost worker or node is retried by Ray (``retries``); a :class:`DbbError` is not.
"""

from __future__ import annotations

import time
import traceback
from dataclasses import asdict
from pathlib import Path

from ..bundle.manifest import MANIFEST
from ..core.errors import DbbError
from ..core.progress import console
from .captures import CaptureJob, find_captures
from .cluster import (
    StageLauncher,
    claim_output,
    connect,
    disconnect,
    import_ray,
    resources,
)
from .config import BatchConfig, Resources
from .records import (
    FAILED,
    INTERRUPTED,
    OK,
    RUNNING,
    SKIPPED,
    BatchSummary,
    CaptureRecord,
    StageRecord,
)
from .stages import RAN, STAGES, StageTask
from .table import error_lines, live_table, summary_table

ERROR_LOG = "error.log"      # OUT/<capture>/error.log: the traceback of an unexpected error
WAIT_SECONDS = 0.5           # how often the live table is redrawn while stages run


def settings_json(cfg: BatchConfig, res: Resources) -> dict:
    """The settings that shape every capture's result, for ``summary.json``."""
    s, d = cfg.static, cfg.dynamic
    return {"default_kind": cfg.default_kind, "force": cfg.force, "retries": cfg.retries,
            "static": {"minutes": s.run.minutes, "steps": s.run.steps, "crop_size": s.preprocess.crop_size,
                       "background_minutes": s.preprocess.background.minutes,
                       "background_steps": s.preprocess.background.steps},
            "dynamic": {"minutes": d.train.minutes, "steps": d.train.steps, "crop_size": d.preprocess.crop_size,
                        "background_minutes": d.preprocess.background.minutes,
                        "background_steps": d.preprocess.background.steps},
            "resources": asdict(res)}


class _Batch:
    """The state of a running batch: records, the stage each capture is in, its pending task."""

    def __init__(self, jobs: list[CaptureJob], cfg: BatchConfig, res: Resources, marker: Path, token: str,
                 summary: BatchSummary):
        self.jobs = {j.name: j for j in jobs}
        self.cfg, self.res, self.marker, self.token = cfg, res, marker, token
        self.summary = summary
        self.records = {c.name: c for c in summary.captures}
        self.launcher = StageLauncher(cfg.retries)
        self.pending: dict = {}             # ObjectRef -> (capture, stage, submitted at)
        self.new_output: dict[str, bool] = {j.name: cfg.force for j in jobs}   # redo later stages
        self.rebuild_bundle: dict[str, bool] = {j.name: False for j in jobs}

    def start(self, job: CaptureJob) -> None:
        rec = self.records[job.name]
        rec.began = time.monotonic()
        if job.problem:
            self._fail(rec, "check", job.problem)
            return
        has_bundle = (job.paths.bundle / MANIFEST).is_file()
        self._submit(job, "check" if has_bundle and not self.cfg.force else "preprocess")

    def _submit(self, job: CaptureJob, stage: str) -> None:
        redo = self.new_output[job.name] or (stage == "bundle" and self.rebuild_bundle[job.name])
        task = StageTask(stage, job, self.cfg, self.res, redo, self.marker, self.token)
        self.pending[self.launcher.submit(task)] = (job.name, stage, time.monotonic())
        rec = self.records[job.name]
        rec.status, rec.stage, rec.stage_since = RUNNING, stage, time.monotonic()

    def finished(self, ref) -> None:
        """A stage's task ended: record it and submit the capture's next stage (or close it)."""
        ray = import_ray()
        name, stage, submitted = self.pending.pop(ref)
        rec, job = self.records[name], self.jobs[name]
        try:
            st: StageRecord = ray.get(ref)
        except Exception as e:          # noqa: BLE001 - any failure of one capture ends only that capture
            self._fail(rec, stage, self._task_error(job, stage, e))
            return
        st.wall_seconds = round(time.monotonic() - submitted, 2)
        rec.stages.append(st)
        rec.metrics = rec.metrics.merged(st.metrics)
        if st.status == FAILED:
            self._fail(rec, stage, st.error or "failed")
            return
        if st.status == RAN and stage in ("preprocess", "train", "bundle"):
            self.new_output[name] = True
        if stage == "check":
            if st.verified:
                self._close(rec, SKIPPED)
                return
            self.rebuild_bundle[name] = True
            self._submit(job, "preprocess")
        elif stage == "verify":
            self._close(rec, OK)
        else:
            self._submit(job, STAGES[STAGES.index(stage) + 1])

    def _task_error(self, job: CaptureJob, stage: str, e: Exception) -> str:
        """One line for a task that raised (a lost worker after its retries, or a bug), with the
        traceback kept in ``OUT/<capture>/error.log``."""
        ray = import_ray()
        if isinstance(e, ray.exceptions.RayTaskError):
            cause = e.cause if e.cause is not None else e
            msg = f"{type(cause).__name__}: {' '.join(str(cause).split())[:300]}"
        elif isinstance(e, (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                            ray.exceptions.LocalRayletDiedError)):
            msg = f"its worker was lost {self.cfg.retries + 1} times ({type(e).__name__})"
        else:
            msg = f"{type(e).__name__}: {' '.join(str(e).split())[:300]}"
        try:
            job.paths.root.mkdir(parents=True, exist_ok=True)
            (job.paths.root / ERROR_LOG).write_text("".join(traceback.format_exception(e)))
            msg += f" (details in {job.paths.root / ERROR_LOG})"
        except OSError:
            pass
        return msg

    def _fail(self, rec: CaptureRecord, stage: str, message: str) -> None:
        rec.stage, rec.error = stage, f"{stage}: {message}"
        self._close(rec, FAILED)

    def _close(self, rec: CaptureRecord, status: str) -> None:
        rec.status = status
        rec.seconds = time.monotonic() - rec.began if rec.began is not None else None
        if status in (OK, SKIPPED):
            bundle = self.jobs[rec.name].paths.bundle
            rec.bundle = str(bundle) if (bundle / MANIFEST).is_file() else None
        line = {OK: "[green]ok[/green]", SKIPPED: "[cyan]skipped[/cyan]", FAILED: "[red]failed[/red]"}[status]
        console.print(f"{line} {rec.name}" + (f": {rec.error}" if rec.error else
                                               f": {rec.bundle}" if rec.bundle else ""), soft_wrap=True,
                      markup=True, highlight=False)
        self.summary.write()

    def interrupt(self) -> None:
        """Cancel what runs (its stage is lost; finished ones stay) and mark those captures."""
        ray = import_ray()
        for ref, (name, stage, _) in list(self.pending.items()):
            ray.cancel(ref, force=True)
            rec = self.records[name]
            rec.status, rec.error = INTERRUPTED, f"{stage}: interrupted"
        self.pending.clear()
        self.summary.interrupted = True


def run_batch(captures_dir: Path, out: Path, cfg: BatchConfig | None = None, address: str | None = None,
              live: bool = True) -> BatchSummary:
    """Every capture in ``captures_dir`` through preprocess -> train -> bundle -> verify on Ray into
    ``out/<capture>/{dataset,run,bundle}``; ``out/summary.json`` says how each went. ``address``:
    a cluster to join (None: start a local Ray). Raises :class:`DbbError` only for what stops the
    whole batch (no captures, no Ray, an output folder the nodes do not share)."""
    from rich.live import Live

    cfg = cfg or BatchConfig()
    cfg.validate()
    captures_dir, out = Path(captures_dir), Path(out)
    if out.exists() and not out.is_dir():
        raise DbbError(f"the output {out} is a file, not a folder")
    jobs, others = find_captures(captures_dir, out, cfg.default_kind)
    t0 = time.monotonic()
    info = connect(address)
    try:
        res = resources(cfg, info)
        marker, token = claim_output(out, captures_dir)
        summary = BatchSummary(captures_dir, out, info, settings_json(cfg, res),
                               [CaptureRecord(j.name, j.kind, j.kind_source) for j in jobs], others)
        batch = _Batch(jobs, cfg, res, marker, token, summary)
        console.print(f"dbb-batch: {len(jobs)} captures on {info.nodes} node(s), {info.cpus:g} CPUs, "
                      f"{info.gpus:g} GPUs ({info.address}); outputs in {out}", soft_wrap=True)
        ray = import_ray()
        with Live(live_table(summary.captures), console=console, transient=True, auto_refresh=False,
                  redirect_stderr=False) if live else _NoLive() as view:
            try:
                for job in jobs:
                    batch.start(job)
                while batch.pending:
                    ready, _ = ray.wait(list(batch.pending), num_returns=1, timeout=WAIT_SECONDS)
                    for ref in ready:
                        batch.finished(ref)
                    view.update(live_table(summary.captures), refresh=True)
            except KeyboardInterrupt:
                batch.interrupt()
                raise
            finally:
                summary.wall_seconds = time.monotonic() - t0
                summary.write()
    finally:
        disconnect(info)
    console.print(summary_table(summary))
    for line in error_lines(summary):
        console.print(line, soft_wrap=True)
    return summary


class _NoLive:
    """Stands in for rich's Live where no live table is wanted."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def update(self, *a, **kw) -> None:
        return None

