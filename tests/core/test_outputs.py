"""Outputs written aside: killed runs' leftovers swept, files replaced without debris, workers
that die with their parent."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from dbb_capture.core import outputs
from dbb_capture.core.errors import DbbError
from dbb_capture.core.outputs import atomic_dir, scratch_prefix


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_leftovers_of_killed_runs_are_swept_and_live_ones_kept(tmp_path, capsys):
    host = outputs._host()
    stale = tmp_path / f".out.partial-{dead_pid()}-{host}-x1"
    stale_old = tmp_path / f".out.old-{dead_pid()}-{host}"
    live = tmp_path / f"{scratch_prefix(tmp_path / 'out')}mine"
    other_host = tmp_path / f".out.partial-{dead_pid()}-ffffff-x2"
    work = tmp_path / ".out.work"                        # an interrupted training run's checkpoint
    for p in (stale, stale_old, live, other_host, work):
        p.mkdir()
    with atomic_dir(tmp_path / "out") as t:
        (t / "a").write_text("a")
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([live.name, other_host.name, work.name, "out"])
    assert "killed" in capsys.readouterr().err


def test_replacing_a_file_leaves_nothing_behind_and_unwritable_places_say_so(tmp_path):
    (tmp_path / "out").write_text("old")
    with atomic_dir(tmp_path / "out", overwrite=True) as t:
        (t / "a").write_text("a")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and (tmp_path / "out" / "a").is_file()
    (tmp_path / "ro").mkdir()
    os.chmod(tmp_path / "ro", 0o500)
    try:
        if os.access(tmp_path / "ro", os.W_OK):
            pytest.skip("running as a user who can write anywhere")
        with pytest.raises(DbbError, match="cannot write"), atomic_dir(tmp_path / "ro" / "out"):
            pass
    finally:
        os.chmod(tmp_path / "ro", 0o700)


def test_spawned_workers_die_with_their_parent(tmp_path):
    code = ("import time\nfrom dbb_capture.core.parallel import map_spawned\n"
            "map_spawned(time.sleep, [600, 600], 2)\n")
    script = tmp_path / "parent.py"
    script.write_text(f"if __name__ == '__main__':\n    exec({code!r})\n")
    p = subprocess.Popen([sys.executable, str(script)])
    kids: list[str] = []
    deadline = time.monotonic() + 60
    while len(kids) < 2 and time.monotonic() < deadline:
        time.sleep(0.5)
        kids = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True, check=False).stdout.split()
    assert len(kids) >= 2
    time.sleep(2)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    # Within seconds, not the tasks' 600 s; a worker still importing on a loaded machine dies once
    # it gets to its start-up check.
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        alive = [k for k in kids if os.path.exists(f"/proc/{k}") and open(f"/proc/{k}/stat").read().split()[2] != "Z"]
        if not alive:
            break
        time.sleep(0.2)
    assert not alive


def test_a_file_where_a_folder_should_be_is_refused_before_any_work(tmp_path):
    (tmp_path / "f").write_text("x")
    target = tmp_path / "f" / "sub" / "out"
    with pytest.raises(DbbError, match=r"cannot write .*f is a file, not a folder"):
        outputs.check_writable(target)
    with pytest.raises(DbbError, match="not a folder"), atomic_dir(target):
        pass
    with pytest.raises(DbbError, match="cannot write"):
        outputs.write_json(target, {})
    with pytest.raises(DbbError, match="not a folder"):
        outputs.check_run_output(target, overwrite=False, resume=False)
    outputs.check_writable(tmp_path / "new" / "deeper" / "out")     # missing folders are made later
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]      # and nothing was made here


def test_an_interrupted_run_is_continued_or_replaced_never_taken_for_a_new_one(tmp_path):
    out = tmp_path / "run"
    work = outputs.run_work_dir(out)
    (work / "anchor").mkdir(parents=True)
    (work / "checkpoint.pt").write_bytes(b"an interrupted run's")
    with pytest.raises(DbbError, match=r"an interrupted run of .*run is in .*\.run\.work"):
        outputs.check_run_output(out, overwrite=False, resume=False)
    outputs.check_run_output(out, overwrite=False, resume=True)
    assert (work / "checkpoint.pt").is_file()                       # continued: kept
    outputs.check_run_output(out, overwrite=True, resume=False)
    assert not work.exists()                                        # replaced: nothing of it is reused
    outputs.check_run_output(out, overwrite=False, resume=False)    # and a new run may start
