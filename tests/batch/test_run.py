"""A batch end to end on a local Ray: bundles verified, a bad capture failing alone with its
message, a second run skipping what is done, a damaged bundle rebuilt, a killed worker retried."""

from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

from dbb_capture.batch.run import run_batch
from dbb_capture.bundle.verify import verify_bundle

from .tiny import tiny_config


def test_bundles_verified_and_the_bad_capture_fails_alone(first_batch, batch_captures):
    out, summary = first_batch
    by = {c.name: c for c in summary.captures}
    assert set(by) == {"broken", "dynamic", "static"} and summary.not_captures == ["notes"]
    assert (by["static"].kind, by["static"].kind_source) == ("static", "default")
    assert (by["dynamic"].kind, by["dynamic"].kind_source) == ("dynamic", "object.json")
    for name in ("static", "dynamic"):
        c = by[name]
        assert c.status == "ok", c.error
        assert [s.stage for s in c.stages] == ["preprocess", "train", "bundle", "verify"]
        assert all(s.status == "ran" and s.node_id for s in c.stages)
        assert c.bundle == str(out / name / "bundle") and verify_bundle(Path(c.bundle))
        assert c.metrics.frames_posed >= 6
    assert by["static"].metrics.heldout_psnr_db > 10 and by["static"].metrics.psnr_views == "held-out"
    assert by["dynamic"].metrics.rssm_gain_db is not None
    bad = by["broken"]
    assert bad.status == "failed" and bad.error.startswith("preprocess: ") and "video.mp4" in bad.error
    assert "\n" not in bad.error and not (out / "broken" / "dataset").exists()
    doc = json.loads((out / "summary.json").read_text())
    assert doc["format"] == "dbb-batch-summary" and doc["counts"] == {"failed": 1, "ok": 2}
    row = {c["name"]: c for c in doc["captures"]}
    assert row["broken"]["error"] == bad.error and row["broken"]["failed_stage"] == "preprocess"
    assert set(row["static"]["stage_seconds"]) == {"preprocess", "train", "bundle", "verify"}
    assert not [p for p in (out / "static").iterdir() if p.name.startswith(".")], "no scratch left"


def test_second_run_skips_the_done_captures(first_batch, batch_captures, local_ray):
    out, _ = first_batch
    summary = run_batch(batch_captures, out, tiny_config(), live=False)
    by = {c.name: c for c in summary.captures}
    assert by["static"].status == by["dynamic"].status == "skipped"
    assert [s.stage for s in by["static"].stages] == ["check"] and by["static"].metrics.frames_posed >= 6
    assert by["dynamic"].metrics.rssm_gain_db is not None
    # only the check ran (the re-run's time is a benchmark: bench/bench_batch.py)
    assert by["broken"].status == "failed" and [c.name for c in summary.failed] == ["broken"]


def test_a_damaged_bundle_is_made_again_from_the_run(first_batch, batch_captures, local_ray, tmp_path):
    out, _ = first_batch
    new = tmp_path / "out"
    shutil.copytree(out / "static", new / "static")
    (new / "static" / "bundle" / "proxy.glb").write_bytes(b"damaged")
    only = tmp_path / "captures"
    shutil.copytree(batch_captures / "static", only / "static")
    c = run_batch(only, new, tiny_config(), live=False).captures[0]
    assert c.status == "ok", c.error
    assert [(s.stage, s.status) for s in c.stages] == [
        ("check", "ran"), ("preprocess", "skipped"), ("train", "skipped"), ("bundle", "ran"), ("verify", "ran")]
    assert "did not verify" in c.stages[0].note


def _kill_when_running(title: str, seen: list[int], stop: threading.Event, after: float = 1.0) -> None:
    """SIGKILL the first process titled ``title`` (Ray names a worker after its task) once it has
    run ``after`` seconds; its pid goes to ``seen``."""
    first: dict[int, float] = {}
    while not stop.is_set() and not seen:
        for d in os.listdir("/proc"):
            if not d.isdigit():
                continue
            try:
                with open(f"/proc/{d}/cmdline", "rb") as f:
                    cmd = f.read().split(b"\0")[0].decode(errors="replace").strip()
            except OSError:
                continue
            if cmd == title:
                pid = int(d)
                if time.monotonic() - first.setdefault(pid, time.monotonic()) >= after:
                    os.kill(pid, signal.SIGKILL)
                    seen.append(pid)
                    return
        time.sleep(0.05)


def test_a_worker_killed_mid_stage_is_retried(first_batch, batch_captures, local_ray, tmp_path):
    out, _ = first_batch
    new = tmp_path / "out"
    shutil.copytree(out / "static" / "dataset", new / "static" / "dataset")
    only = tmp_path / "captures"
    shutil.copytree(batch_captures / "static", only / "static")
    killed: list[int] = []
    stop = threading.Event()
    killer = threading.Thread(target=_kill_when_running, args=("ray::train static", killed, stop))
    killer.start()
    try:
        c = run_batch(only, new, tiny_config(static_steps=400, retries=1), live=False).captures[0]
    finally:
        stop.set()
        killer.join()
    assert killed, "the training worker was never seen running"
    assert c.status == "ok", c.error
    assert [(s.stage, s.status) for s in c.stages] == [
        ("preprocess", "skipped"), ("train", "ran"), ("bundle", "ran"), ("verify", "ran")]
    assert verify_bundle(new / "static" / "bundle")
    assert not [p for p in (new / "static").iterdir() if ".partial-" in p.name], "the killed run's scratch is gone"


def test_the_command_exits_1_naming_the_failed_captures(batch_captures, local_ray, tmp_path):
    from click.testing import CliRunner
    from dbb_capture.cli.batch import main

    caps = tmp_path / "captures"
    shutil.copytree(batch_captures / "broken", caps / "bad one")
    r = CliRunner().invoke(main, [str(caps), "-o", str(tmp_path / "out")])
    assert r.exit_code == 1, r.output
    assert "failed: bad one" in r.output
    doc = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert doc["captures"][0]["status"] == "failed" and doc["captures"][0]["error"].startswith("preprocess: ")
    r = CliRunner().invoke(main, [str(caps), "-o", str(tmp_path / "out"), "--gpus-per-train", "1"])
    assert r.exit_code == 2 and r.output.strip().splitlines() == [
        "error: --gpus-per-train 1: the cluster has no GPU (give 0 to train on CPUs)"]
