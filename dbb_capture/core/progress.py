"""Shared rich console and progress reporting (to stderr, so stdout stays for results).

On a terminal, :func:`progress` is rich's live bar. Anywhere else (a log file, CI, ``tee``, a
pipe) rich draws nothing until the end, so a long step would look hung: there it prints a plain
line per running task every few seconds, and one when the task finishes::

    detect board: 40/120 (33 %), 12 s, eta 24 s
    train field: 40 %, 1 min 12 s, eta 1 min 48 s, psnr 24.10 dB  64^3  0.26M pts
    detect board: 120/120 (100 %) in 36 s

``DBB_PROGRESS_SECONDS`` sets the interval (0: no plain lines at all; the test suite sets it, so
that outputs hold only what a test looks for).
"""

from __future__ import annotations

import math
import os
import threading
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    Task,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

# soft_wrap: messages are never broken across lines (paths stay copyable, logs greppable).
console = Console(stderr=True, highlight=False, soft_wrap=True)

PLAIN_EVERY_S = 5.0      # without a terminal: a line per running task this often
EVERY_ENV = "DBB_PROGRESS_SECONDS"


def plain_every_s() -> float:
    """The plain lines' interval: ``DBB_PROGRESS_SECONDS`` if it is a number >= 0, else 5 s."""
    try:
        v = float(os.environ.get(EVERY_ENV, PLAIN_EVERY_S))
    except ValueError:
        return PLAIN_EVERY_S
    return v if math.isfinite(v) and v >= 0 else PLAIN_EVERY_S


def progress(transient: bool = False, disable: bool = False, every_s: float | None = None,
             out: Console | None = None) -> Progress:
    """A progress bar with count, elapsed and remaining time, and a free-text ``info`` field;
    plain lines every ``every_s`` seconds (default :func:`plain_every_s`; 0: none) where ``out``
    (default: the shared console) is not a terminal; nothing at all with ``disable``."""
    out = out or console
    if not out.is_terminal or out.is_dumb_terminal:
        every_s = plain_every_s() if every_s is None else every_s
        return PlainProgress(every_s, console=out, disable=disable or every_s <= 0)
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        console=out,
        transient=transient,
        disable=disable,
    )


def duration(seconds: float) -> str:
    """``12 s``, ``3 min 05 s``, ``2 h 04 min``: a duration as people read it."""
    s = int(round(max(seconds, 0.0)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def resumed_line(step: int, seconds: float, steps: int | None, minutes: float | None, checkpoint: Path,
                 interrupted: bool) -> str:
    """What a resumed training says first: the step and training time it continues from, against
    the run's budget (``steps`` and/or ``minutes`` over all resumptions), and which checkpoint."""
    of = f" of {steps}" if steps else ""
    budget = f" of {minutes:g} min" if minutes else ""
    which = "the interrupted run" if interrupted else "the finished run"
    return (f"resumed from step {step}{of}, {duration(seconds)}{budget} trained "
            f"(checkpoint of {which}: {checkpoint})")


def task_line(task: Task) -> str:
    """One plain line for ``task``: description, count (or share), time, eta and its info."""
    done, total = task.completed, task.total
    if total is None:                         # not known yet
        count = f"{done:.0f} done"
    elif total == 100:                        # trainers count their budget in percent
        count = f"{done:.0f} %"
    else:
        count = f"{done:.0f}/{total:.0f} ({100 * done / max(total, 1e-9):.0f} %)"
    if task.finished:
        line = f"{task.description}: {count} in {duration(task.finished_time or 0.0)}"
    else:
        line = f"{task.description}: {count}, {duration(task.elapsed or 0.0)}"
        if task.time_remaining is not None and done > 0:
            line += f", eta {duration(task.time_remaining)}"
    info = str(task.fields.get("info") or "").strip()
    return f"{line}, {info}" if info else line


class PlainProgress(Progress):
    """Rich's task bookkeeping without its live display: a plain line per unfinished task every
    ``every_s`` seconds (from a timer thread, so a step that does not advance still shows it is
    running; tasks still at 0 only while none has begun) and one line as each task finishes."""

    def __init__(self, every_s: float = PLAIN_EVERY_S, console: Console | None = None, disable: bool = False):
        super().__init__(console=console, disable=True)
        self.every_s = float(every_s)
        self.silent = disable
        self._reported: set[TaskID] = set()
        self._stop = threading.Event()
        self._timer: threading.Thread | None = None

    def start(self) -> None:
        if self.silent or self._timer is not None:
            return
        self._stop.clear()
        self._timer = threading.Thread(target=self._tick, name="plain-progress", daemon=True)
        self._timer.start()

    def stop(self) -> None:
        if self._timer is not None:
            self._stop.set()
            self._timer.join()
            self._timer = None

    def _tick(self) -> None:
        while not self._stop.wait(self.every_s):
            with self._lock:
                running = [t for t in self._tasks.values() if t.visible and t.started and not t.finished]
                # A task added ahead of its turn stays at 0 while another works: say the one at work.
                lines = [task_line(t) for t in ([t for t in running if t.completed > 0] or running)]
            for line in lines:
                self._print(line)

    def _print(self, line: str) -> None:
        if not self.silent:
            self.console.print(line, markup=False, highlight=False)

    def _finished(self, task_id: TaskID) -> None:
        with self._lock:
            task = self._tasks.get(task_id)
            if task is None or not task.finished or task_id in self._reported:
                return
            self._reported.add(task_id)
            line = task_line(task)
        self._print(line)

    def update(self, task_id: TaskID, **kwargs: Any) -> None:        # type: ignore[override]
        super().update(task_id, **kwargs)
        self._finished(task_id)

    def advance(self, task_id: TaskID, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._finished(task_id)
