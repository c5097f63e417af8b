"""``dbb-batch``: --help (the installed command), one clear line and exit 2 on bad input before Ray
starts (in-process: no interpreter start per case). Exit 1 naming the captures that failed is in
tests/batch/test_run.py, on the session's Ray."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from dbb_capture.cli.batch import main

BIN = Path(sys.executable).parent


def _run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "dbb-batch"), *args], check=False, capture_output=True, text=True,
                          timeout=timeout)


def test_help():
    r = _run("--help")
    assert r.returncode == 0 and "Usage:" in r.stdout and "--address" in r.stdout
    assert "--static-steps" not in r.stdout        # hidden: for tests and benchmarks


@pytest.mark.parametrize("args, words", [
    (("CAPS", "-o", "OUT", "--kind", "wobbly"), ("--kind", "wobbly")),
    (("CAPS", "-o", "OUT", "--retries", "-1"), ("--retries",)),
    (("CAPS", "-o", "OUT", "--static-minutes", "0"), ("--static-minutes", "positive")),
    (("CAPS", "-o", "OUT"), ("no captures in",)),
    (("CAPS/nope", "-o", "OUT"), ("captures folder not found",)),
    (("CAPS", "-o", "FILE"), ("is a file",)),
    (("CAPS",), ("Missing option", "--output")),
])
def test_bad_arguments_exit_2_with_one_line(tmp_path, args, words):
    (tmp_path / "caps").mkdir()
    (tmp_path / "file").write_text("x")
    subst = {"CAPS": str(tmp_path / "caps"), "CAPS/nope": str(tmp_path / "caps" / "nope"),
             "OUT": str(tmp_path / "out"), "FILE": str(tmp_path / "file")}
    r = CliRunner().invoke(main, [subst.get(a, a) for a in args])
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), r.output
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not (tmp_path / "out").exists()
