"""The kill test: preprocess and both trainers stopped by SIGKILL and SIGTERM early and mid-run.

After each stop no process of the command's session is left (after a SIGKILL within 5 s: its
spawned workers die with it), a SIGTERM ends with exit 143 and one line, and the next run (the
same command for preprocess, which sweeps what a killed run left and says so; ``--resume`` for
the trainers) succeeds with outputs that load and, for trained runs, bundle and verify.

Each command runs in a session of its own, so its processes are found by session id in /proc;
the stops wait for what the command prints or writes, never for a fixed time.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch
from conftest import REPO, synthetic_object_frames

BIN = Path(sys.executable).parent
CAPTURE = REPO / "sample_data" / "static"     # 120 frames: detection splits over 2 spawned workers
GONE_AFTER_KILL_S = 5.0
MARKER_TIMEOUT_S = 180.0                      # a loaded machine is slow, never wrong

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="finds processes in /proc (Linux)")


def session(sid: int) -> list[int]:
    """Live (not zombie) processes of session ``sid``."""
    out = []
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            stat = (p / "stat").read_text()
        except OSError:
            continue
        state, _ppid, _pgrp, sess = stat[stat.rindex(")") + 2:].split()[:4]
        if int(sess) == sid and state != "Z":
            out.append(int(p.name))
    return out


class Command:
    """A command running in its own session, its output (stdout and stderr) collected as it comes."""

    def __init__(self, *args: str, cwd: Path):
        env = dict(os.environ, DBB_PROGRESS_SECONDS="0.2")    # progress lines to wait for
        self.proc = subprocess.Popen([str(BIN / args[0]), *args[1:]], cwd=cwd, env=env, start_new_session=True,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True)
        self._reader.start()

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def wait_for(self, what: str, ready) -> None:
        """Until ``ready()`` holds (the command must still be running)."""
        t0 = time.monotonic()
        while not ready():
            assert self.proc.poll() is None, f"ended (exit {self.proc.returncode}) before {what}:\n{self.output}"
            assert time.monotonic() - t0 < MARKER_TIMEOUT_S, f"no {what} after {MARKER_TIMEOUT_S} s:\n{self.output}"
            time.sleep(0.05)

    def stop(self, sig: int) -> int:
        """Send ``sig`` to the command; its exit status once no process of its session is left."""
        os.kill(self.proc.pid, sig)
        t0 = time.monotonic()
        rc = self.proc.wait(timeout=120)
        while session(self.proc.pid) and time.monotonic() - t0 < 120:
            time.sleep(0.05)
        left, took = session(self.proc.pid), time.monotonic() - t0
        assert not left, f"processes {left} outlived the command"
        if sig == signal.SIGKILL:
            assert took < GONE_AFTER_KILL_S, f"its processes took {took:.1f} s to die"
        self._reader.join(timeout=10)
        if sig == signal.SIGTERM:
            assert rc == 143 and self.lines[-1].strip() == "stopped (SIGTERM)", (rc, self.output)
            assert "Traceback" not in self.output, self.output
        return rc

    def finish(self) -> str:
        rc = self.proc.wait(timeout=600)
        self._reader.join(timeout=10)
        assert rc == 0, self.output
        return self.output


def test_preprocess_stopped_then_run_again(tmp_path):
    args = ("dbb-capture", "preprocess", str(CAPTURE), "-o", "ds", "--stop-after", "poses", "--workers", "2",
            "--camera", str(CAPTURE / "ground_truth" / "camera.json"))
    partials = lambda: sorted(tmp_path.glob(".ds.partial-*"))    # noqa: E731
    workers = lambda c: len(session(c.proc.pid)) >= 3            # noqa: E731 - itself and two detecting
    # SIGTERM with the workers at work: a clean stop, nothing left behind.
    c = Command(*args, cwd=tmp_path)
    c.wait_for("spawned workers", lambda: workers(c))
    c.stop(signal.SIGTERM)
    assert not partials() and not (tmp_path / "ds").exists()
    # SIGKILL early (the partial dataset just made): the partial stays, as any killed process leaves it.
    c = Command(*args, cwd=tmp_path)
    c.wait_for("the partial dataset", partials)
    c.stop(signal.SIGKILL)
    (stale,) = partials()
    # SIGKILL mid-run: the workers die with the command; the earlier run's partial was swept and said so.
    c = Command(*args, cwd=tmp_path)
    c.wait_for("spawned workers", lambda: workers(c))
    c.stop(signal.SIGKILL)
    assert f"removed {stale.name}, left in " in c.output and not stale.exists()
    (stale,) = partials()
    # The same command again: it sweeps, says so, and writes a dataset that loads.
    out = Command(*args, cwd=tmp_path).finish()
    assert f"removed {stale.name}, left in " in out and not partials()
    from dbb_capture.datasets.transforms import load_dataset

    assert len(load_dataset(tmp_path / "ds").frames) == 120


def _trainer_stopped_and_resumed(tmp_path: Path, args: tuple[str, ...], mid: str, finish: tuple[str, ...]):
    """``args`` SIGKILLed as soon as its checkpoint exists; resumed and SIGTERMed, then resumed and
    SIGKILLed, each once a progress line matches ``mid``; resumed with ``finish`` to the end; then
    bundled and verified."""
    from dbb_capture.bundle.build import make_bundle
    from dbb_capture.bundle.verify import verify_bundle

    ckpt = tmp_path / ".run.work" / "checkpoint.pt"
    c = Command(*args, cwd=tmp_path)
    c.wait_for("a checkpoint", ckpt.is_file)
    c.stop(signal.SIGKILL)
    c = Command(*args, "--resume", cwd=tmp_path)
    c.wait_for("training progress", lambda: re.search(mid, c.output))
    c.stop(signal.SIGTERM)
    step = torch.load(ckpt, weights_only=False)["step"]
    assert step > 0 and not (tmp_path / "run").exists()
    c = Command(*args, "--resume", cwd=tmp_path)
    c.wait_for("training progress", lambda: re.search(rf"resumed from step {step}\b", c.output) and re.search(mid, c.output))
    c.stop(signal.SIGKILL)
    step = torch.load(ckpt, weights_only=False)["step"]      # the SIGTERM's, or a later periodic one
    out = Command(*args, "--resume", *finish, cwd=tmp_path).finish()
    assert re.search(rf"resumed from step {step}\b", out) and not ckpt.parent.exists()
    make_bundle(tmp_path / "run", tmp_path / "bundle")
    assert verify_bundle(tmp_path / "bundle")           # raises at the first failure
    assert not list(tmp_path.glob(".*partial*"))


def test_plenoctree_stopped_then_resumed(tmp_path):
    (tmp_path / "ds").mkdir()
    frames, vol = synthetic_object_frames(tmp_path / "ds", n=12, size=24, seed=2)
    from dbb_capture.datasets.transforms import write_transforms

    write_transforms(tmp_path / "ds" / "transforms.json", frames, vol)
    args = ("dbb-train", "plenoctree", "ds", "-o", "run", "--minutes", "5", "--res-max", "16",
            "--batch-rays", "256", "--threads", "1")
    _trainer_stopped_and_resumed(tmp_path, args, r"train field: .*psnr", ("--steps", "300"))


def test_rssm_stopped_then_resumed(tmp_path):
    from dbb_capture.synth.crops import synthetic_crops

    synthetic_crops(tmp_path / "ds", seconds=3.0, fps=10, size=32, still_steps=1, samples=1)
    args = ("dbb-train", "rssm", "ds", "-o", "run", "--minutes", "5", "--size", "32", "--batch", "2",
            "--threads", "1", "--set", "anchor_share=0.05", "--set", "deter=16", "--set", "stoch=16", "--set", "hidden=64", "--set", "embed=64")
    _trainer_stopped_and_resumed(tmp_path, args, r"train rssm: .*step ([2-9]|\d\d)", ("--steps", "20"))
