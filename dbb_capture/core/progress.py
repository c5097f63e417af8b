"""Shared rich console and progress bars (to stderr, so stdout stays for results)."""

from __future__ import annotations

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

# soft_wrap: messages are never broken across lines (paths stay copyable, logs greppable).
console = Console(stderr=True, highlight=False, soft_wrap=True)


def progress(transient: bool = False) -> Progress:
    """A progress bar with count, elapsed and remaining time, and a free-text ``info`` field."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        console=console,
        transient=transient,
    )
