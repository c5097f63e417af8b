"""The batch's tables: a live one while it runs (each capture's stage, time and result) and the
summary at the end (quality figures, stage times, the bundle or the error)."""

from __future__ import annotations

import time

from rich.markup import escape
from rich.table import Table

from .records import (
    FAILED,
    INTERRUPTED,
    OK,
    PENDING,
    RUNNING,
    SKIPPED,
    BatchSummary,
    CaptureRecord,
)

_STYLE = {OK: "green", SKIPPED: "cyan", FAILED: "red", INTERRUPTED: "yellow", RUNNING: "", PENDING: "dim"}


def _clock(seconds: float | None) -> str:
    if seconds is None:
        return ""
    s = round(seconds)
    return f"{s // 60}:{s % 60:02d}"


def _result(c: CaptureRecord, width: int | None) -> str:
    if c.status == FAILED and c.error:
        text = c.error if width is None or len(c.error) <= width else c.error[: width - 1] + "…"
        return f"[red]failed[/red] {escape(text)}"
    if c.status == SKIPPED:
        return "[cyan]skipped[/cyan] (its bundle verifies)"
    return f"[{_STYLE[c.status]}]{c.status}[/]" if _STYLE[c.status] else c.status


def live_table(captures: list[CaptureRecord], now: float | None = None) -> Table:
    """Each capture's stage (and node), the time since its first stage was submitted, its result."""
    now = time.monotonic() if now is None else now
    t = Table(title="dbb-batch", title_justify="left", expand=False)
    for col in ("capture", "kind", "stage", "time", "result"):
        t.add_column(col, no_wrap=col != "result")
    for c in captures:
        where = ""
        if c.stages and c.stages[-1].node_ip and c.done:
            where = f" @ {c.stages[-1].node_ip}"
        elapsed = c.seconds if c.done else (None if c.began is None else now - c.began)
        t.add_row(escape(c.name), c.kind or "?", (c.stage or "") + where, _clock(elapsed), _result(c, 70))
    return t


def _figure(c: CaptureRecord) -> str:
    m = c.metrics
    if m.heldout_psnr_db is not None:
        return f"{m.heldout_psnr_db:.2f} dB" + ("" if m.psnr_views == "held-out" else " (train views)")
    if m.rssm_gain_db is not None:
        return f"{m.rssm_gain_db:+.2f} dB"
    return ""


def _times(c: CaptureRecord) -> str:
    """Each stage's own seconds, in pipeline order ("-" not reached, "skip" output complete)."""
    by = {s.stage: s for s in c.stages}
    cells = []
    for stage in ("preprocess", "train", "bundle", "verify"):
        s = by.get(stage)
        cells.append("-" if s is None else "skip" if s.status == "skipped" else f"{s.seconds:.0f}")
    return "/".join(cells)


def summary_table(summary: BatchSummary) -> Table:
    """Per capture: kind, result, frames posed, held-out PSNR (static) or RSSM gain over copy-first
    (dynamic), each stage's own seconds and the bundle (errors: :func:`error_lines`)."""
    t = Table(title=f"dbb-batch: {len(summary.captures)} captures in {_clock(summary.wall_seconds)} "
                    f"(summary.json beside the outputs)", title_justify="left")
    t.add_column("capture", overflow="fold")
    t.add_column("kind", no_wrap=True)
    t.add_column("result", no_wrap=True)
    t.add_column("frames", justify="right", no_wrap=True)
    t.add_column("PSNR/gain", justify="right", no_wrap=True)
    t.add_column("seconds p/t/b/v", no_wrap=True)
    t.add_column("bundle", overflow="fold")
    for c in summary.captures:
        status = f"[{_STYLE[c.status]}]{c.status}[/]" if _STYLE[c.status] else c.status
        t.add_row(escape(c.name), c.kind or "?", status,
                  "" if c.metrics.frames_posed is None else str(c.metrics.frames_posed), _figure(c), _times(c),
                  "(error below)" if c.error else escape(c.bundle or ""))
    return t


def error_lines(summary: BatchSummary) -> list[str]:
    """One line per capture that failed or was interrupted: its name, stage and message."""
    return [f"[red]{c.status}[/red] {escape(c.name)}: {escape(c.error)}" for c in summary.captures if c.error]
