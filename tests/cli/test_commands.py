"""Every command: --help, one clear line and exit 2 on bad input, outputs kept."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from dbb_capture.cli import capture, export, train

GROUPS = {"dbb-capture": capture.main, "dbb-train": train.main, "dbb-export": export.main}


BIN = Path(sys.executable).parent


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / args[0]), *args[1:]], capture_output=True, text=True, timeout=120)


def _all_commands():
    for name, group in GROUPS.items():
        yield (name,)
        for sub in group.commands:
            yield (name, sub)


@pytest.mark.parametrize("cmd", list(_all_commands()), ids=" ".join)
def test_help(cmd):
    r = _run(*cmd, "--help")
    assert r.returncode == 0, r.stderr
    assert "Usage:" in r.stdout and len(r.stdout.splitlines()) >= 3


def _one_clear_line(r: subprocess.CompletedProcess, *words: str) -> None:
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("error:")
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("args, words", [
    (("dbb-capture", "nosuchcommand"), ("No such command",)),
    (("dbb-capture", "synth"), ("Missing argument",)),
    (("dbb-capture", "synth", "OUT", "--kind", "wobbly"), ("--kind", "wobbly")),
    (("dbb-capture", "synth", "OUT", "--kind", "static", "--resolution", "big"), ("WIDTHxHEIGHT",)),
    (("dbb-capture", "synth", "OUT", "--kind", "static", "--dictionary", "DICT_7X7_9"), ("dictionary",)),
    (("dbb-capture", "synth", "OUT", "--kind", "static", "--distortion", "0.1,x"), ("--distortion",)),
    (("dbb-capture", "synth", "OUT", "--kind", "static", "--resolution", "641x480"), ("even",)),
    (("dbb-capture", "preprocess", "sample_data/static", "-o", "OUT", "--crop-size", "8"), ("--crop-size 8",)),
    (("dbb-capture", "preprocess", "in/my toy [v2]", "-o", "OUT"), ("in/my toy [v2]",)),
    (("dbb-train", "nosuchcommand"), ("No such command",)),
    (("dbb-export", "nosuchcommand"), ("No such command",)),
])
def test_bad_arguments_exit_2_with_one_line(tmp_path, args, words):
    args = tuple(str(tmp_path / a) if a == "OUT" else a for a in args)
    _one_clear_line(_run(*args), *words)
    assert not any(tmp_path.iterdir()), "nothing may be left behind"


@pytest.mark.parametrize("args, words", [
    (("dbb-capture", "calibrate", "no/such.mp4", "-o", "OUT"), ("footage not found: no/such.mp4",)),
    (("dbb-capture", "preprocess", "CAP", "-o", "OUT", "--crop-window", "0,0,64", "--board", "b.json"),
     ("--board: not used with --crop-window",)),
    (("dbb-capture", "preprocess", "CAP", "-o", "OUT", "--no-matte"), ("--no-matte: applies with --crop-window only",)),
    (("dbb-capture", "preprocess", "CAP", "-o", "OUT", "--stop-after", "poses", "--crop-size", "128"),
     ("--crop-size: not used with --stop-after poses (the background and crops stages do not run)",)),
    (("dbb-capture", "preprocess", "CAP", "-o", "OUT", "--stop-after", "background", "--sequence-length", "5"),
     ("--sequence-length: not used with --stop-after background",)),
    (("dbb-capture", "preprocess", "CAP", "-o", "OUT", "--background-minutes", "1", "--background-steps", "9"),
     ("give one",)),
    (("dbb-capture", "preprocess", "CAP", "-o", "OUT", "--background", "p.mp4", "--no-clean-plate"), ("give one",)),
    (("dbb-capture", "preprocess", "CAP", "-o", "OUT", "--no-clean-plate", "--no-video-room"),
     ("--no-video-room applies with a clean plate only",)),
    (("dbb-train", "plenoctree", "DS", "-o", "OUT", "--resume", "--overwrite"), ("give one of them",)),
    (("dbb-train", "rssm", "DS", "-o", "OUT", "--resume", "--overwrite"), ("give one of them",)),
    (("dbb-serve", "B", "--seed-size", "128"), ("--seed-size: applies with --seed-port only",)),
])
def test_contradictions_and_missing_inputs_are_named_first(tmp_path, args, words):
    """Contradictory options are refused before the inputs are read, and a missing input is named
    before the options it would make unnecessary (in-process: no interpreter start per case)."""
    from click.testing import CliRunner

    from dbb_capture.cli import serve

    mains = GROUPS | {"dbb-serve": serve.main}
    args = tuple(str(tmp_path / a) if a == "OUT" else a for a in args)
    r = CliRunner().invoke(mains[args[0]], list(args[1:]), prog_name=args[0])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error:"), r.output
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not any(tmp_path.iterdir()), "nothing may be left behind"


@pytest.mark.parametrize("args", [
    ("dbb-capture", "synth", "OUT", "--kind", "static"),
    ("dbb-capture", "calibrate", "sample_data/static/video.mp4", "--board", "sample_data/static/board.json", "-o", "OUT"),
    ("dbb-capture", "preprocess", "sample_data/static", "-o", "OUT"),
    ("dbb-train", "plenoctree", "sample_data/static", "-o", "OUT"),
    ("dbb-train", "rssm", "sample_data/dynamic", "-o", "OUT"),
])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(tmp_path, args):
    """Every writer asks its output's folder first (a file stands where a folder should be)."""
    (tmp_path / "file").write_text("x")
    out = str(tmp_path / "file" / "out")
    _one_clear_line(_run(*(out if a == "OUT" else a for a in args)), "cannot write", "is a file, not a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_existing_output_is_kept(tmp_path):
    out = tmp_path / "cap"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    _one_clear_line(_run("dbb-capture", "synth", str(out), "--kind", "static"), "already exists")
    assert (out / "keep.txt").read_text() == "mine"


def test_synth_command_writes_capture(tmp_path):
    out = tmp_path / "cap"
    r = _run("dbb-capture", "synth", str(out), "--kind", "dynamic", "--seconds", "0.4", "--fps", "5",
             "--resolution", "160x120", "--board-squares", "5x4", "--dictionary", "DICT_4X4_50",
             "--distortion", "-0.1,0.01,0,0,0", "--camera-json")
    assert r.returncode == 0, r.stderr
    assert "wrote" in r.stderr and "2 frames" in r.stderr
    board = json.loads((out / "board.json").read_text())
    assert board["squares_x"] == 5 and board["dictionary"] == "DICT_4X4_50"
    cam = json.loads((out / "camera.json").read_text())
    assert cam["width"] == 160 and cam["dist"][0] == -0.1
    assert sorted(p.name for p in (out / "ground_truth" / "masks").iterdir()) == ["00000.png", "00001.png"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no scratch folder left"
