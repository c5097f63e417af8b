"""dbb-batch against the same commands run one after another, on this machine; and a paper
projection for N nodes with G GPUs each from the measured stage times.

    python bench/bench_batch.py OUT [--minutes 1] [--background-minutes 0.25] [--json PATH]

Four synthetic captures (two static, two dynamic, 320x240) go through ``dbb-capture preprocess``
-> ``dbb-train`` -> ``dbb-export bundle`` -> ``dbb-export verify``, one command at a time, each
training for ``--minutes``; then ``dbb-batch`` does the same work: the same room budget, and for
each kind the mean number of steps the sequential trainings reached (a minutes budget would let
two overlapping trainings on two cores do half the work each). The two run back to back (the
machine may be shared). Then ``dbb-batch`` runs again, and must skip all four. Ray's overhead:
its start and the output-folder check, a warm no-op task's round trip, and per stage task the
batch's wall time minus the stage's own work (queueing for a free CPU included, so its minimum
is the overhead). Bars: batch <= 1.1x sequential, re-run < 30 s.
"""

from __future__ import annotations

import argparse
import heapq
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

from common import emit  # bench/ is the script folder: on sys.path

BIN = Path(sys.executable).parent
CAPTURES = {  # name: (kind, seconds, fps, clean-plate seconds, seed)
    "static_a": ("static", 4.0, 8, 3.0, 31), "static_b": ("static", 4.0, 8, 3.0, 32),
    "dynamic_a": ("dynamic", 8.0, 8, 3.0, 35), "dynamic_b": ("dynamic", 8.0, 8, 3.0, 36)}


def _run(*cmd: str) -> float:
    """Run one command, quietly (its error output shown only if it fails); its wall seconds."""
    t0 = time.perf_counter()
    r = subprocess.run([str(BIN / cmd[0]), *cmd[1:]], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr[-2000:]}")
    return time.perf_counter() - t0


def make_captures(root: Path) -> None:
    for name, (kind, secs, fps, plate, seed) in CAPTURES.items():
        if not (root / name).is_dir():
            _run("dbb-capture", "synth", str(root / name), "--kind", kind, "--seconds", str(secs), "--fps", str(fps),
                 "--background-seconds", str(plate), "--resolution", "320x240", "--seed", str(seed))


def sequential(caps: Path, out: Path, minutes: float, bg: float) -> dict:
    """Each capture's four commands in turn; seconds per command and the steps each training made."""
    rows = {}
    for name, (kind, *_rest) in CAPTURES.items():
        d, run, b = out / name / "dataset", out / name / "run", out / name / "bundle"
        t = {"preprocess": _run("dbb-capture", "preprocess", str(caps / name), "-o", str(d), "--background-minutes",
                                str(bg), "--overwrite"),      # crop sizes as dbb-batch's: the defaults
             "train": _run("dbb-train", "plenoctree" if kind == "static" else "rssm", str(d), "-o", str(run),
                           "--minutes", str(minutes), "--overwrite"),
             "bundle": _run("dbb-export", "bundle", str(run), "-o", str(b), "--overwrite"),
             "verify": _run("dbb-export", "verify", str(b))}
        steps = json.loads((run / "run.json").read_text())["training"]["steps"]
        rows[name] = {"kind": kind, "seconds": {k: round(v, 1) for k, v in t.items()}, "steps": steps}
    return rows


def batch(caps: Path, out: Path, steps: dict[str, int], bg: float, force: bool) -> tuple[float, dict]:
    args = ["dbb-batch", str(caps), "-o", str(out), "--background-minutes", str(bg),
            "--static-steps", str(steps["static"]), "--dynamic-steps", str(steps["dynamic"])]
    wall = _run(*args, *(["--force"] if force else []))
    return wall, json.loads((out / "summary.json").read_text())


def ray_overhead(caps: Path, out: Path) -> dict:
    """Ray's start and output check in this process, and the round trip of a warm no-op task."""
    import ray

    from dbb_capture.batch.cluster import claim_output, connect, disconnect

    t0 = time.perf_counter()
    info = connect(None)
    t1 = time.perf_counter()
    claim_output(out, caps)
    t2 = time.perf_counter()
    noop = ray.remote(num_cpus=1)(lambda: 0)
    ray.get(noop.remote())
    trips = []
    for _ in range(20):
        s = time.perf_counter()
        ray.get(noop.remote())
        trips.append(time.perf_counter() - s)
    disconnect(info)
    return {"ray_start_s": round(t1 - t0, 2), "output_check_s": round(t2 - t1, 2),
            "warm_task_round_trip_ms": round(1000 * statistics.median(trips), 1)}


def project(stage_s: dict[str, dict[str, float]], n_captures: int, nodes: int, cpus: int, gpus: int,
            minutes: dict[str, float], per_train: float = 1.0) -> float:
    """Wall seconds for ``n_captures`` (half static, half dynamic) on ``nodes`` nodes of ``cpus``
    CPUs and ``gpus`` GPUs: stages chained per capture, each placed on the first node with room
    (FIFO, as Ray does), preprocess taking 2 CPUs, training 1 CPU and ``per_train`` GPU (none
    without GPUs) for its budget in ``minutes``, bundle and verify 1 CPU, their times as measured
    here. A minutes budget is the same wall time on a GPU (it buys more steps, not less time)."""
    free = [[cpus, gpus] for _ in range(nodes)]
    order = ("preprocess", "train", "bundle", "verify")
    want = {"preprocess": (min(2, cpus), 0), "train": (1, per_train if gpus else 0), "bundle": (1, 0),
            "verify": (1, 0)}
    queue = [(i, "static" if i % 2 == 0 else "dynamic", 0) for i in range(n_captures)]
    events: list = []
    now = 0.0
    while queue or events:
        placed = True
        while placed:
            placed = False
            for q in list(queue):
                i, kind, k = q
                c, g = want[order[k]]
                node = next((n for n in free if n[0] >= c and n[1] >= g), None)
                if node is None:
                    continue
                node[0] -= c
                node[1] -= g
                queue.remove(q)
                dur = 60 * minutes[kind] if order[k] == "train" else stage_s[kind][order[k]]
                heapq.heappush(events, (now + dur, i, kind, k, id(node)))
                placed = True
        now, i, kind, k, nid = heapq.heappop(events)
        node = next(n for n in free if id(n) == nid)
        c, g = want[order[k]]
        node[0] += c
        node[1] += g
        if k + 1 < len(order):
            queue.append((i, kind, k + 1))
    return now


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--minutes", type=float, default=1.0, help="training budget of each sequential run")
    ap.add_argument("--background-minutes", type=float, default=0.25)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    caps = a.out / "captures"
    make_captures(caps)
    t0 = time.perf_counter()
    seq = sequential(caps, a.out / "sequential", a.minutes, a.background_minutes)
    seq_wall = time.perf_counter() - t0
    steps = {k: round(statistics.mean(r["steps"] for r in seq.values() if r["kind"] == k)) for k in ("static", "dynamic")}
    wall, summ = batch(caps, a.out / "batch", steps, a.background_minutes, force=True)
    rerun, summ2 = batch(caps, a.out / "batch", steps, a.background_minutes, force=False)
    tasks = [s for c in summ["captures"] for s in c["stages"]]
    extra = [s["wall_seconds"] - s["seconds"] for s in tasks]
    stage_s = {k: {st: statistics.mean(s["seconds"] for c in summ["captures"] if c["kind"] == k
                                       for s in c["stages"] if s["stage"] == st)
                   for st in ("preprocess", "bundle", "verify")} for k in ("static", "dynamic")}
    overhead = ray_overhead(caps, a.out / "batch")
    budgets = {"static": 10.0, "dynamic": 15.0}        # dbb-batch's default training minutes
    projection = {f"{n} nodes x {g} GPUs, {p:g} GPU per training": round(
        project(stage_s, 100, n, 8, g, budgets, p) / 3600, 2)
        for n in (1, 4, 16) for g, p in ((0, 0), (1, 1), (1, 0.25), (4, 1))}
    result = {
        "captures": {n: {"kind": k, "seconds": s, "fps": f} for n, (k, s, f, _, _) in CAPTURES.items()},
        "sequential": {"wall_s": round(seq_wall, 1), "per_capture": seq},
        "batch": {"wall_s": round(wall, 1), "steps": steps, "counts": summ["counts"],
                  "per_capture": {c["name"]: c["stage_seconds"] for c in summ["captures"]},
                  "nodes": sorted({s["node_ip"] for s in tasks})},
        "ratio_batch_over_sequential": round(wall / seq_wall, 3),
        "rerun": {"wall_s": round(rerun, 1), "counts": summ2["counts"]},
        "ray_overhead": overhead | {"stage_tasks": len(tasks),
                                    "task_wall_minus_work_s": {"min": round(min(extra), 2),
                                                               "median": round(statistics.median(extra), 2)}},
        "projection_hours_100_captures_8_cpu_nodes": projection,
        "projection_note": "half static (10 min), half dynamic (15 min) at the default budgets; preprocess, "
                           "bundle and verify as measured here (2 CPUs for preprocess); FIFO placement",
        "bars": {"ratio_le_1.1": wall / seq_wall <= 1.1, "rerun_lt_30s": rerun < 30,
                 "rerun_skipped_all": summ2["counts"].get("skipped") == len(CAPTURES)},
    }
    return emit(result, a.json)


if __name__ == "__main__":
    sys.exit(main())
