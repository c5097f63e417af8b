"""Streaming speed of dbb-serve on localhost (dbb-stream/1, docs/protocol.md), with Python
clients (:class:`dbb_capture.serve.client.StreamClient`) as the load.

    python bench/bench_serve.py                  # every part, then the 5-minute soak
    python bench/bench_serve.py static scene     # some parts (static, scene, dynamic, soak)
    python bench/bench_serve.py soak --soak-seconds 60

Each client runs a closed loop: it sends a view, waits for its frame (header parsed, pixels not
decoded unless ``--decode``), then sends the next pose along an orbit of the object (elevation
20 degrees, a new azimuth every frame, so the server's cache of static canvases never hits;
frames whose ``render_ms`` says they came from the cache are counted). JPEG frames (the
default, ``lossless=False``). Clients are separate processes (``--clients-as process``, the
default: fairer on a small machine than one process's event loop carrying four clients) or
asyncio tasks in one process (``--clients-as task``). All clients of a run start together; a
run measures ``--seconds`` after ``--warmup``; each figure is the median of ``--repeats`` runs.

Per run: frames/s of each client, the pose-to-frame latency (the request's ``client_ms`` echoed
in the frame, to when the frame is received) p50/p95, bytes per frame, the worker's own
``render_ms`` (render + encode) and the CPU seconds per second of the server's front end, its
render processes and the clients. Beside each stream figure, measured in the same run with the
server idle: the renderer alone (static: ``TreeRenderer.render`` of the canvas camera
:func:`~dbb_capture.crops.camera.facing_camera` with the server's threads; dynamic: the
TorchScript stepper's ``step``, and its ``decode``, at the model's size: a frame for a new
viewpoint is a decode, a step happens at the model's fps) and the worker's whole job
(:func:`dbb_capture.serve.worker.handle`: render, uint8, encode), so that stream / renderer
shows what the stream costs.

Parts: ``static`` (the static bundle at 256 and at 800 on a ``--max-size 800`` server, 1, 2
and 4 clients), ``scene`` (a scene.json placing the static bundle 5 times: one client asking
for every object at once, whose frames/s count every object's frames, and 5 clients one object
each; per-object frames/s and min/max; the renderer figures are one object's, on its share of
the cores),
``dynamic`` (the demo's 64-pixel RSSM bundle and a 256-pixel one), ``soak`` (4 clients on the
static bundle at 256 for ``--soak-seconds``: no error message, and the resident memory of the
server and its render processes after ``--soak-warmup`` and at the end grows < 10 %).

Results go to ``--json`` (parts run earlier and not run now are kept), and a table is printed.
Run one benchmark at a time: timings of overlapping jobs say little (the load average is kept).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import multiprocessing as mp
import os
import re
import statistics
import subprocess
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from common import emit  # bench/ is the script folder: on sys.path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "out" / "bench_serve"
READY = re.compile(r"dbb-serve ready: (http://\S+)")
TROUBLE = re.compile(r"traceback|error|exception|warning", re.IGNORECASE)
ELEVATION_DEG = 20.0
AZIMUTH_STEP_DEG = 1.37      # per frame: ~263 distinct poses per turn, far more than the cache's 16
CACHE_HIT_MS = 0.5           # a frame the worker produced faster than this came from its cache
FAIR = 0.8                   # objects are "shared fairly" when the slowest gets >= this of the fastest
GOALS = {"static_256": {"fps": 60.0, "p50_ms": 25.0}, "static_800": {"fps": 10.0},
         "scene5_256": {"fps": 15.0, "fair": FAIR}, "dynamic_256": {"fps": 20.0}}


# ---------------------------------------------------------------- the server process
def cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


class ServerProcess:
    """``dbb-serve SOURCES --port 0 [--max-size N]``, once it printed its ready line; its output
    (stdout and stderr) is kept in :attr:`lines`."""

    def __init__(self, sources: list[Path], max_size: int | None = None, timeout: float = 300.0):
        cmd = [sys.executable, "-c", "from dbb_capture.cli.serve import main; main()", *map(str, sources),
               "--port", "0"] + (["--max-size", str(max_size)] if max_size else [])
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     env={**os.environ, "COLUMNS": "200"})
        self.lines: list[str] = []
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                break
            self.lines.append(line.rstrip())
            m = READY.search(line)
            if m:
                self.url = m.group(1)
                threading.Thread(target=lambda: [self.lines.append(x.rstrip()) for x in self.proc.stdout],
                                 daemon=True).start()
                return
        self.proc.kill()
        raise RuntimeError("dbb-serve did not get ready:\n" + "\n".join(self.lines))

    @property
    def ws(self) -> str:
        return self.url.split("?")[0].replace("http", "ws", 1) + "ws"

    @property
    def pid(self) -> int:
        return self.proc.pid

    def workers(self) -> list[int]:
        out = subprocess.run(["pgrep", "-P", str(self.pid)], capture_output=True, text=True, check=False)
        return [int(p) for p in out.stdout.split()]

    def rss_mb(self) -> dict:
        """Resident memory (VmRSS, MB) of the front end and of each render process."""
        return {"server": vm_rss_mb(self.pid), "workers": {str(w): vm_rss_mb(w) for w in self.workers()}}

    def cpu_s(self) -> tuple[float, float]:
        """CPU seconds so far of the front end and of its render processes together."""
        return cpu_seconds_of(self.pid), sum(cpu_seconds_of(w) for w in self.workers())

    def trouble(self, since: int = 0) -> list[str]:
        """Lines it printed (from line ``since``) that look like an error or a warning."""
        return [x for x in self.lines[since:] if TROUBLE.search(x)]

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(2)          # SIGINT: the server stops its render processes
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def vm_rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return math.nan


def cpu_seconds_of(pid: int) -> float:
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return 0.0
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")       # utime + stime


# ---------------------------------------------------------------- the load (clients)
def orbit_eye(centre, distance: float, k: int, phase_deg: float) -> np.ndarray:
    """The ``k``-th camera position of an orbit about ``centre`` (scene frame, +Y up)."""
    az, el = math.radians(phase_deg + k * AZIMUTH_STEP_DEG), math.radians(ELEVATION_DEG)
    d = np.array([math.cos(el) * math.cos(az), math.sin(el), math.cos(el) * math.sin(az)])
    return np.asarray(centre, float) + distance * d


def _warm() -> int:
    import dbb_capture.serve.client  # noqa: F401  (the pool's processes import it before timing)

    time.sleep(0.3)
    return os.getpid()


async def _session(url: str, obj: int, start_at: float, warmup: float, seconds: float, size_px: int,
                   phase_deg: float, decode: bool) -> dict:
    """One client's closed loop. ``obj`` 65535: every object per request (the centre of the orbit is
    then the objects' centroid). Counts only frames received in the measuring window."""
    from dbb_capture.serve import protocol as P
    from dbb_capture.serve.client import StreamClient, decode_frame, look_from

    async with StreamClient.connect(url, open_timeout=60) as c:
        objs = c.hello["objects"]
        targets = list(range(len(objs))) if obj == P.ALL_OBJECTS else [obj]
        centres = np.array([objs[i]["position"] for i in targets], float)
        centre = centres.mean(0)
        reach = max(np.linalg.norm(p - centre) + objs[i]["radius_m"] for i, p in zip(targets, centres, strict=True))
        distance = 3.0 * reach if len(targets) == 1 else 1.6 * reach
        await asyncio.sleep(max(0.0, start_at - time.time()))
        t0, t1 = (start_at + warmup) * 1e3, (start_at + warmup + seconds) * 1e3
        lat, nbytes, render_ms, errors = [], [], [], []
        per_object = {i: 0 for i in targets}
        hits = stale = k = 0
        cpu0 = None
        while time.time() * 1e3 < t1:
            if cpu0 is None and time.time() * 1e3 >= t0:
                cpu0 = time.process_time()
            eye = orbit_eye(centre, distance, k, phase_deg)
            seq = await c.send_view(look_from(eye, centre), object=obj, size_px=size_px)
            k += 1
            need = len(targets)
            while need:
                msg = await asyncio.wait_for(c.ws.recv(), 60.0)
                now = time.time() * 1e3
                if isinstance(msg, str):
                    m = json.loads(msg)
                    if m.get("type") == "error":
                        errors.append(m)
                        need -= m.get("seq") == seq
                    continue
                h = P.FrameHeader.unpack(msg)
                if h.seq != seq:
                    stale += 1
                    continue
                need -= 1
                if decode:
                    decode_frame(msg)
                if t0 <= now <= t1:
                    lat.append(now - h.client_ms)
                    nbytes.append(len(msg))
                    render_ms.append(h.render_ms)
                    per_object[h.object] += 1
                    hits += h.render_ms < CACHE_HIT_MS
        cpu = time.process_time() - (cpu0 if cpu0 is not None else time.process_time())
    return {"frames": len(lat), "fps": len(lat) / seconds,
            "per_object_fps": {str(i): n / seconds for i, n in per_object.items()},
            "latency_ms": lat, "bytes": nbytes, "render_ms": render_ms, "cache_hits": hits, "stale": stale,
            "errors": errors, "client_cpu_s": cpu}


def client_process(*args) -> dict:
    return asyncio.run(_session(*args))


def client_tasks(sessions: list[tuple]) -> list[dict]:
    async def all_of():
        return await asyncio.gather(*(_session(*s) for s in sessions))
    return asyncio.run(all_of())


class Load:
    """A pool of client processes, started once (their imports are not timed)."""

    def __init__(self, n: int, how: str, decode: bool):
        self.how, self.decode, self.runs = how, decode, 0
        self.pool = ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"))
        for f in [self.pool.submit(_warm) for _ in range(n)]:
            f.result()

    def run(self, srv: ServerProcess, targets: list[int], size_px: int, warmup: float, seconds: float) -> dict:
        """One run: ``len(targets)`` clients (client i asks for object ``targets[i]``) together."""
        n = len(targets)
        self.runs += 1              # each run's orbits start elsewhere: no pose of an earlier run repeats
        start_at = time.time() + 2.0
        sessions = [(srv.ws, t, start_at, warmup, seconds, size_px, i * 360.0 / n + 3.1 * self.runs, self.decode)
                    for i, t in enumerate(targets)]
        load0 = os.getloadavg()[0]
        done = ([self.pool.submit(client_process, *s) for s in sessions] if self.how == "process"
                else [self.pool.submit(client_tasks, sessions)])
        cpu = None
        wait = start_at + warmup - time.time()
        if wait > 0:
            time.sleep(wait)
            c0, m0 = time.monotonic(), srv.cpu_s()
            time.sleep(max(0.0, start_at + warmup + seconds - time.time()))
            c1, m1 = time.monotonic(), srv.cpu_s()
            cpu = {"server_cpu": (m1[0] - m0[0]) / (c1 - c0), "workers_cpu": (m1[1] - m0[1]) / (c1 - c0)}
        out = [f.result() for f in done]
        clients = out if self.how == "process" else out[0]
        return summarise(clients, seconds, cpu, load0)

    def close(self) -> None:
        self.pool.shutdown()


def pct(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else math.nan


def summarise(clients: list[dict], seconds: float, cpu: dict | None, load0: float) -> dict:
    lat = [x for c in clients for x in c["latency_ms"]]
    nb = [x for c in clients for x in c["bytes"]]
    rm = [x for c in clients for x in c["render_ms"]]
    per_object: dict[str, float] = {}
    for c in clients:
        for k, v in c["per_object_fps"].items():
            per_object[k] = per_object.get(k, 0.0) + v
    fps = [c["fps"] for c in clients]
    per_frame = {f"{k}_ms_per_frame": 1e3 * cpu[k] / max(sum(fps), 1e-9) for k in ("server_cpu", "workers_cpu")
                 } if cpu else {}
    return {"clients": len(clients), "fps_per_client": fps, "fps_per_client_mean": statistics.fmean(fps),
            "fps_total": sum(fps), "per_object_fps": per_object,
            "fair_min_over_max": min(per_object.values()) / max(max(per_object.values()), 1e-9),
            "p50_ms": pct(lat, 50), "p95_ms": pct(lat, 95), "bytes_per_frame": statistics.fmean(nb) if nb else math.nan,
            "worker_render_ms_p50": pct(rm, 50), "cache_hits": sum(c["cache_hits"] for c in clients),
            "errors": [e for c in clients for e in c["errors"]][:5],
            "n_errors": sum(len(c["errors"]) for c in clients),
            "client_cpu": sum(c["client_cpu_s"] for c in clients) / seconds, **(cpu or {}), **per_frame,
            "load_average_before": load0}


# ---------------------------------------------------------------- the renderer alone
def board_eyes(manifest, placement_position, n: int, distance_factor: float = 3.0) -> list[np.ndarray]:
    """Board-frame eyes of the client's orbit about a lone object (placed unturned, unscaled)."""
    inv = np.linalg.inv(manifest.T)
    centre = np.asarray(placement_position, float)
    eyes = [orbit_eye(centre, distance_factor * manifest.radius, k, 7.0) - centre for k in range(n)]
    return [(inv @ np.append(e, 1.0))[:3] for e in eyes]


def cpu_ms(fn, items: list, repeats: int = 8) -> float:
    """The least CPU milliseconds of one ``fn(item)`` (all of the process's threads): what other
    jobs on a shared machine change least."""
    fn(items[0])
    best = math.inf
    for i in range(repeats):
        t = time.process_time()
        fn(items[(i * 37) % len(items)])
        best = min(best, time.process_time() - t)
    return 1e3 * best


def timed(fn, items: list, seconds: float) -> float:
    """Calls per second of ``fn(item)`` over ``items`` in turn (one warm-up call), for about ``seconds``."""
    fn(items[0])
    n, t = 0, time.perf_counter()
    while time.perf_counter() - t < seconds:
        fn(items[n % len(items)])
        n += 1
    return n / (time.perf_counter() - t)


def renderer_static(bundle: Path, size: int, threads: int, seconds: float) -> dict:
    from dbb_capture.bundle.manifest import open_bundle
    from dbb_capture.core.images import to_u8
    from dbb_capture.crops.camera import facing_camera
    from dbb_capture.octree.render import TreeRenderer
    from dbb_capture.octree.tree import PlenOctree
    from dbb_capture.serve.worker import JPEG, Job, StaticCanvas, encode, handle

    with open_bundle(bundle) as b:
        m = b.manifest
        r = TreeRenderer(PlenOctree.load(b.file(m.model["file"])), threads=threads)
        canvas = StaticCanvas(b, threads)
        fill = 2 * m.radius / float(m.canvas["size_m"])
        up = np.asarray(m.up, float)
        eyes = board_eyes(m, (0, 0, 0), 263)
        cams = [facing_camera(e, m.center, m.radius, up, size, fill) for e in eyes]
        render = timed(lambda cam: r.render(*cam), cams, seconds)
        jobs = [Job(1, (1, 0, 0), e, size, JPEG, 90) for e in eyes]
        whole = timed(lambda j: handle(canvas, j, {}), jobs, seconds)      # an empty cache: never a hit
        r1 = TreeRenderer(r.impl.tree, threads=1)
        cpu_render = cpu_ms(lambda cam: r1.render(*cam), cams)
        rgba = [to_u8(r.render(*cam)) for cam in cams[:8]]
        cpu_encode = cpu_ms(lambda x: encode(x, JPEG, 90), rgba)
    return {"renderer_fps": render, "worker_job_fps": whole, "threads": threads,
            "renderer_cpu_ms_1thread": cpu_render, "encode_cpu_ms": cpu_encode}


def renderer_dynamic(bundle: Path, threads: int, seconds: float) -> dict:
    import torch

    from dbb_capture.bundle.manifest import open_bundle
    from dbb_capture.serve.worker import JPEG, DynamicCanvas, Job, handle

    with open_bundle(bundle) as b:
        m = b.manifest
        canvas = DynamicCanvas(b, threads)          # sets torch's threads as the worker does
        st = canvas.stepper
        eyes = board_eyes(m, (0, 0, 0), 263)
        views = [torch.from_numpy(canvas.view_of(e))[None] for e in eyes]
        with torch.no_grad():
            h, z = st.start(canvas.first, canvas.first_view)
            state = {"h": h, "z": z}

            def step(v):
                state["h"], state["z"], _ = st.step(state["h"], state["z"], v)

            step_fps = timed(step, views, seconds)
            decode_fps = timed(lambda v: st.decode(state["h"], state["z"], v), views, seconds)
            cpu_step = cpu_ms(step, views)
            cpu_decode = cpu_ms(lambda v: st.decode(state["h"], state["z"], v), views)
        def job(e):         # one client's rollout on the real clock, as the worker runs it
            return handle(canvas, Job(1, (1, 0, 0), e, canvas.size, JPEG, 90, None, time.monotonic()), {})

        whole = timed(job, eyes, seconds)
    return {"renderer_fps": step_fps, "renderer": "stepper.step", "decode_fps": decode_fps,
            "worker_job_fps": whole, "threads": threads, "frame_size": canvas.size,
            "step_cpu_ms": cpu_step, "decode_cpu_ms": cpu_decode}


# ---------------------------------------------------------------- the parts
def median_of(runs: list[dict]) -> dict:
    """Per field, the median over runs (numbers; lists and dicts of numbers element-wise)."""
    out = {}
    for k, v in runs[0].items():
        vals = [r[k] for r in runs]
        if isinstance(v, bool) or v is None or isinstance(v, str):
            out[k] = v
        elif isinstance(v, (int, float)):
            out[k] = statistics.median(vals)
        elif isinstance(v, dict) and all(isinstance(x, (int, float)) for x in v.values()):
            out[k] = {kk: statistics.median(r[k][kk] for r in runs) for kk in v}
        elif isinstance(v, list) and v and all(isinstance(x, (int, float)) for x in v):
            out[k] = [statistics.median(r[k][i] for r in runs) for i in range(len(v))]
        else:
            out[k] = [e for r in runs for e in r[k]] if isinstance(v, list) else v
    return out


def case(name: str, srv: ServerProcess, load: Load, a, targets: list[int], size_px: int,
         renderer: dict | None) -> dict:
    runs = [load.run(srv, targets, size_px, a.warmup, a.seconds) for _ in range(a.repeats)]
    med = median_of(runs)
    out = {"case": name, "size": size_px, **med, "runs": runs}
    for r in runs:
        r.pop("errors", None)
    if renderer:
        out["renderer"] = renderer
        out["stream_total_over_renderer"] = med["fps_total"] / renderer["renderer_fps"]
        out["stream_total_over_worker_job"] = med["fps_total"] / renderer["worker_job_fps"]
    print(f"  {name}: {med['fps_per_client_mean']:.1f} frames/s per client, p50 {med['p50_ms']:.1f} ms",
          file=sys.stderr, flush=True)
    return out


def renderer_medians(fn, repeats: int) -> dict:
    return median_of([fn() for _ in range(repeats)])


def part_static(a, load: Load) -> list[dict]:
    out = []
    for size, max_size in ((256, None), (800, 800)):
        with ServerProcess([a.static_bundle], max_size) as srv:
            threads = max(1, cores())           # one object: the server gives its worker every core
            ren = renderer_medians(lambda s=size, t=threads: renderer_static(a.static_bundle, s, t,
                                                                             a.renderer_seconds), a.repeats)
            for n in a.clients:
                out.append(case(f"static_{size}_x{n}", srv, load, a, [0] * n, size, ren))
            out[-1]["server_trouble"] = srv.trouble()
    return out


def write_scene(bundle: Path, n: int = 5, ring_m: float = 0.35) -> Path:
    """A scene.json placing ``bundle`` ``n`` times on a ring (each turned differently)."""
    d = OUT / "scene5"
    d.mkdir(parents=True, exist_ok=True)
    objs = [{"bundle": str(bundle.resolve()), "id": f"copy{i}",
             "position": [round(ring_m * math.cos(2 * math.pi * i / n), 4), 0.0,
                          round(ring_m * math.sin(2 * math.pi * i / n), 4)],
             "yaw_deg": 360.0 * i / n} for i in range(n)]
    (d / "scene.json").write_text(json.dumps({"objects": objs}, indent=2) + "\n")
    return d / "scene.json"


def part_scene(a, load: Load) -> list[dict]:
    from dbb_capture.serve.protocol import ALL_OBJECTS

    scene = write_scene(a.static_bundle)
    with ServerProcess([scene]) as srv:
        threads = max(1, cores() // 5)
        ren = renderer_medians(lambda: renderer_static(a.static_bundle, 256, threads, a.renderer_seconds),
                               a.repeats)
        out = [case("scene5_256_one_client_all", srv, load, a, [ALL_OBJECTS], 256, ren),
               case("scene5_256_five_clients", srv, load, a, list(range(5)), 256, ren)]
        for o in out:
            o["renderer_note"] = f"one object's renderer with {threads} thread (the server's share per object)"
        out[-1]["server_trouble"] = srv.trouble()
    return out


def part_dynamic(a, load: Load) -> list[dict]:
    out = []
    for bundle, size in ((a.dynamic_bundle, 64), (a.dynamic256_bundle, 256)):
        if not Path(bundle).exists():
            print(f"  skipping dynamic {size}: no bundle {bundle} (see --help)", file=sys.stderr)
            continue
        with ServerProcess([bundle]) as srv:
            threads = max(1, cores())
            ren = renderer_medians(lambda b=bundle, t=threads: renderer_dynamic(b, t, a.renderer_seconds),
                                   a.repeats)
            for n in a.clients:
                out.append(case(f"dynamic_{size}_x{n}", srv, load, a, [0] * n, size, ren))
            out[-1]["server_trouble"] = srv.trouble()
    return out


def part_soak(a, load: Load) -> dict:
    with ServerProcess([a.static_bundle]) as srv:
        n, start_at = 4, time.time() + 2.0
        sessions = [(srv.ws, 0, start_at, a.soak_warmup, a.soak_seconds, 256, i * 90.0 + 7.0, a.decode)
                    for i in range(n)]
        futures = [load.pool.submit(client_process, *s) for s in sessions]
        time.sleep(max(0.0, start_at + a.soak_warmup - time.time()))
        since = len(srv.lines)
        samples = [{"t_s": 0.0, **srv.rss_mb()}]
        t0 = time.time()
        while time.time() - t0 < a.soak_seconds - 2.0:
            time.sleep(min(30.0, max(0.1, a.soak_seconds - 2.0 - (time.time() - t0))))
            samples.append({"t_s": time.time() - t0, **srv.rss_mb()})
        clients = [f.result() for f in futures]
        trouble = srv.trouble(since)
        alive = srv.proc.poll() is None
    res = summarise(clients, a.soak_seconds, None, math.nan)

    def total(s):
        return s["server"] + sum(s["workers"].values())

    first, last = samples[0], samples[-1]
    growth = {"server": last["server"] / first["server"] - 1, "total": total(last) / total(first) - 1}
    for w in first["workers"]:
        if w in last["workers"]:
            growth[f"worker_{w}"] = last["workers"][w] / first["workers"][w] - 1
    ok = res["n_errors"] == 0 and not trouble and alive and max(growth.values()) < 0.10 \
        and first["workers"].keys() == last["workers"].keys()
    return {"case": "soak_static_256_x4", "seconds": a.soak_seconds, "warmup_s": a.soak_warmup,
            "fps_per_client": res["fps_per_client"], "p50_ms": res["p50_ms"], "p95_ms": res["p95_ms"],
            "bytes_per_frame": res["bytes_per_frame"], "n_errors": res["n_errors"], "errors": res["errors"],
            "server_trouble": trouble, "server_alive_at_end": alive, "cache_hits": res["cache_hits"],
            "rss_mb_samples": samples, "rss_growth": growth, "passed": ok}


# ---------------------------------------------------------------- goals and the table
def goals(results: dict) -> list[dict]:
    by = {c["case"]: c for part in ("static", "scene", "dynamic") for c in results.get(part, [])}
    out = []

    def add(goal, case_name, value, target, ok, extra=""):
        out.append({"goal": goal, "case": case_name, "value": value, "target": target, "met": ok,
                    "by": value / target - 1 if target else None, "note": extra})

    for n in (1, 2, 4):
        c = by.get(f"static_256_x{n}")
        if c:
            add(f"static 256 >= 60 frames/s per client ({n} client{'s' * (n > 1)})", c["case"],
                c["fps_per_client_mean"], GOALS["static_256"]["fps"], c["fps_per_client_mean"] >= 60)
            add(f"static 256 p50 <= 25 ms ({n} client{'s' * (n > 1)})", c["case"], c["p50_ms"],
                GOALS["static_256"]["p50_ms"], c["p50_ms"] <= 25)
        c = by.get(f"static_800_x{n}")
        if c:
            add(f"static 800 >= 10 frames/s per client ({n} client{'s' * (n > 1)})", c["case"],
                c["fps_per_client_mean"], 10.0, c["fps_per_client_mean"] >= 10)
        c = by.get(f"dynamic_256_x{n}")
        if c:
            add(f"dynamic 256 >= 20 frames/s per client ({n} client{'s' * (n > 1)})", c["case"],
                c["fps_per_client_mean"], 20.0, c["fps_per_client_mean"] >= 20)
    for name in ("scene5_256_one_client_all", "scene5_256_five_clients"):
        c = by.get(name)
        if c:
            lo = min(c["per_object_fps"].values())
            add(f"5 objects at 256 >= 15 frames/s each ({name})", name, lo, 15.0, lo >= 15)
            add(f"5 objects shared fairly: min/max >= {FAIR} ({name})", name, c["fair_min_over_max"], FAIR,
                c["fair_min_over_max"] >= FAIR)
    s = results.get("soak")
    if s:
        add("soak: no errors, RSS growth < 10 %", s["case"], max(s["rss_growth"].values()), 0.10, s["passed"],
            f"{s['n_errors']} client errors, {len(s['server_trouble'])} server lines")
    return out


def table(results: dict) -> str:
    rows = [("case", "clients", "fps/client", "fps total", "p50 ms", "p95 ms", "bytes/frame", "renderer fps",
             "job fps", "stream/renderer", "stream/job", "srv cpu", "wrk cpu", "cli cpu", "srv ms/f", "wrk ms/f", "hits")]
    for part in ("static", "scene", "dynamic"):
        for c in results.get(part, []):
            r = c.get("renderer", {})
            rows.append((c["case"], str(c["clients"]), f"{c['fps_per_client_mean']:.1f}", f"{c['fps_total']:.1f}",
                         f"{c['p50_ms']:.1f}", f"{c['p95_ms']:.1f}", f"{c['bytes_per_frame']:.0f}",
                         f"{r.get('renderer_fps', math.nan):.1f}", f"{r.get('worker_job_fps', math.nan):.1f}",
                         f"{c.get('stream_total_over_renderer', math.nan):.2f}",
                         f"{c.get('stream_total_over_worker_job', math.nan):.2f}",
                         f"{c.get('server_cpu', math.nan):.2f}", f"{c.get('workers_cpu', math.nan):.2f}",
                         f"{c['client_cpu']:.2f}", f"{c.get('server_cpu_ms_per_frame', math.nan):.1f}",
                         f"{c.get('workers_cpu_ms_per_frame', math.nan):.1f}", str(c["cache_hits"])))
            if len(c["per_object_fps"]) > 1:
                rows.append(("  per object", "", " ".join(f"{v:.1f}" for v in c["per_object_fps"].values()),
                             f"min/max {c['fair_min_over_max']:.2f}", *[""] * 13))
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(x.ljust(w[i]) for i, x in enumerate(r)) for r in rows]
    s = results.get("soak")
    if s:
        g = s["rss_growth"]
        lines += ["", f"soak {s['seconds']:.0f} s, 4 clients, static 256: fps/client "
                      + " ".join(f"{x:.1f}" for x in s["fps_per_client"])
                  + f", p50 {s['p50_ms']:.1f} ms, p95 {s['p95_ms']:.1f} ms, {s['n_errors']} errors, "
                  f"{len(s['server_trouble'])} server warnings; RSS MB start {_rss(s['rss_mb_samples'][0])} "
                  f"end {_rss(s['rss_mb_samples'][-1])}; growth total {100 * g['total']:+.1f} %, "
                  f"largest {100 * max(g.values()):+.1f} %: {'PASS' if s['passed'] else 'FAIL'}"]
    lines += ["", "goals:"]
    for g in results.get("goals", []):
        by = "" if g["by"] is None else f" ({100 * g['by']:+.0f} %)"
        lines.append(f"  [{'met' if g['met'] else 'MISSED'}] {g['goal']}: {g['value']:.3g} vs {g['target']:.3g}{by}"
                     + (f"; {g['note']}" if g["note"] else ""))
    return "\n".join(lines)


def _rss(s: dict) -> str:
    return f"{s['server']:.0f} + " + " + ".join(f"{v:.0f}" for v in s["workers"].values())


PARTS = {"static": part_static, "scene": part_scene, "dynamic": part_dynamic, "soak": part_soak}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("parts", nargs="*", metavar="PART",
                    help="static, scene, dynamic, soak (default: all four, in this order)")
    ap.add_argument("--static-bundle", type=Path, default=REPO / "out/demo/static_bundle")
    ap.add_argument("--dynamic-bundle", type=Path, default=REPO / "out/demo/dynamic_bundle",
                    help="a dynamic bundle with 64-pixel frames (scripts/demo.sh)")
    ap.add_argument("--dynamic256-bundle", type=Path, default=OUT / "dynamic256_bundle",
                    help="a dynamic bundle with 256-pixel frames: dbb-train rssm DATASET --size 256 --steps 3, "
                         "then dbb-export bundle (quality does not matter for speed)")
    ap.add_argument("--clients", type=lambda s: [int(x) for x in s.split(",")], default=[1, 2, 4],
                    help="client counts of the static and dynamic parts (default 1,2,4)")
    ap.add_argument("--clients-as", choices=["process", "task"], default="process",
                    help="each client its own process, or all as asyncio tasks of one process")
    ap.add_argument("--decode", action="store_true", help="clients also decode each frame's pixels")
    ap.add_argument("--seconds", type=float, default=10.0, help="measuring window of a run")
    ap.add_argument("--warmup", type=float, default=3.0, help="seconds of load before a run's window")
    ap.add_argument("--repeats", type=int, default=3, help="runs per figure (the median is reported)")
    ap.add_argument("--renderer-seconds", type=float, default=3.0, help="timing of each renderer-only figure")
    ap.add_argument("--soak-seconds", type=float, default=300.0)
    ap.add_argument("--soak-warmup", type=float, default=20.0, help="load before the soak's first memory reading")
    ap.add_argument("--json", type=Path, default=OUT / "results.json",
                    help="results (parts not run now are kept from an earlier run)")
    a = ap.parse_args(argv)
    # The renderer-only figures run here: torch's OpenMP threads as in dbb-serve's render processes
    # (server.WORKER_ENV; set OMP_WAIT_POLICY to measure otherwise, "" for OpenMP's own default).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parts = a.parts or list(PARTS)
    if set(parts) - set(PARTS):
        ap.error(f"unknown part {min(set(parts) - set(PARTS))!r} (static, scene, dynamic, soak)")
    OUT.mkdir(parents=True, exist_ok=True)
    results = json.loads(a.json.read_text()) if a.json.is_file() else {}
    results["machine"] = {"cores": cores(), "clients_as": a.clients_as, "decode": a.decode,
                          "omp_wait_policy": os.environ["OMP_WAIT_POLICY"],
                          "seconds": a.seconds, "warmup": a.warmup, "repeats": a.repeats,
                          "dynamic256_note": "an untrained-quality model (3 training steps), for speed only"}
    load = Load(5 if a.clients_as == "process" else 1, a.clients_as, a.decode)
    try:
        for p in parts:
            print(f"{p} ...", file=sys.stderr, flush=True)
            results[p] = PARTS[p](a, load)
            results["goals"] = goals(results)
            a.json.write_text(json.dumps(results, indent=2) + "\n")
    finally:
        load.close()
    emit(results["goals"], None)
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
