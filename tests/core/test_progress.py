"""Progress without a terminal: plain lines every few seconds instead of nothing."""

from __future__ import annotations

import io
import time

from rich.console import Console

from dbb_capture.core.progress import EVERY_ENV, PlainProgress, duration, plain_every_s, progress


def _console(terminal: bool) -> tuple[Console, io.StringIO]:
    buf = io.StringIO()
    return Console(file=buf, force_terminal=terminal, width=120), buf


def test_without_a_terminal_running_tasks_print_periodic_lines_and_a_last_one():
    out, buf = _console(terminal=False)
    with progress(transient=True, every_s=0.05, out=out) as prog:
        assert isinstance(prog, PlainProgress)
        poses = prog.add_task("poses", total=120, info="")
        train = prog.add_task("train field", total=100, info="")
        prog.update(poses, advance=40)
        prog.update(train, completed=25.4, info="psnr 21.30 dB")
        time.sleep(0.3)
        n_running = buf.getvalue().count("poses: 40/120 (33 %), 0 s")
        prog.update(poses, advance=80)
    lines = buf.getvalue().splitlines()
    assert n_running >= 2, lines                                   # periodic, not once
    assert "train field: 25 %, 0 s, psnr 21.30 dB" in lines        # percent tasks: the share only
    assert lines[-1] == "poses: 120/120 (100 %) in 0 s"            # one line as a task finishes
    assert lines.count("poses: 120/120 (100 %) in 0 s") == 1
    assert not any("━" in line or "\x1b" in line for line in lines)   # no bar, no escape codes


def test_a_step_that_does_not_advance_still_shows_it_runs_and_disable_is_silent():
    out, buf = _console(terminal=False)
    with progress(every_s=0.05, out=out) as prog:
        prog.add_task("detect board", total=None, info="")
        time.sleep(0.2)
    assert buf.getvalue().splitlines()[0] == "detect board: 0 done, 0 s"
    out, buf = _console(terminal=False)
    with progress(every_s=0.05, out=out) as prog:       # a task waiting its turn stays quiet
        crops = prog.add_task("cut crops", total=10, info="")
        prog.add_task("train", total=100, info="")
        prog.update(crops, advance=3)
        time.sleep(0.2)
    assert "cut crops: 3/10 (30 %), 0 s" in buf.getvalue() and "train" not in buf.getvalue()
    out, buf = _console(terminal=False)
    with progress(every_s=0.05, out=out, disable=True) as prog:
        t = prog.add_task("train rssm", total=3, info="")
        time.sleep(0.15)
        prog.update(t, completed=3)
    assert buf.getvalue() == ""


def test_a_terminal_keeps_the_rich_bar():
    out, _ = _console(terminal=True)
    assert not isinstance(progress(out=out), PlainProgress)


def test_durations_read_as_people_say_them():
    assert [duration(s) for s in (0.4, 12, 65, 3 * 3600 + 4 * 60)] == ["0 s", "12 s", "1 min 05 s", "3 h 04 min"]


def test_the_interval_comes_from_the_environment_and_0_turns_the_lines_off(monkeypatch):
    for value, want in (("12", 12.0), ("0", 0.0), ("soon", 5.0), ("-3", 5.0), ("nan", 5.0)):
        monkeypatch.setenv(EVERY_ENV, value)
        assert plain_every_s() == want
    monkeypatch.setenv(EVERY_ENV, "0")
    out, buf = _console(terminal=False)
    with progress(out=out) as prog:
        prog.update(prog.add_task("poses", total=2, info=""), completed=2)
    assert buf.getvalue() == ""
