"""dbb-serve's front end: one asyncio process that speaks ``dbb-stream/1`` over a websocket (and
serves the viewer's files and proxy meshes over HTTP on the same port), with one render process
per object (:mod:`.worker`) behind it.

Scheduling: each (client, object, eye) has one slot. A request is sent to the object's worker
when its slot is free; while a frame is in flight a newer request replaces the waiting one
(latest pose wins: overtaken requests are dropped, never queued). The slot frees once the frame
is written to the client, so a slow client slows only itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import json
import math
import mimetypes
import os
import pickle
import secrets
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit

import numpy as np
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from ..bundle.manifest import Manifest, open_bundle
from ..core.errors import DbbError
from ..geometry.conventions import opengl_from_opencv
from . import protocol as P
from .scene import Placement
from .worker import JPEG, PNG, RAW, Control, Failed, Fatal, Job, Ready, Rendered

MAX_SIZE = 512                   # default cap on a canvas's side (pixels)
MIN_SIZE = 16
SIZE_STEP = 8                    # canvas sides are rounded up to this (fewer distinct sizes, more cache hits)
JPEG_QUALITY = 90
WIRE_FORMATS = {JPEG: P.FORMAT_JPEG, PNG: P.FORMAT_PNG, RAW: P.FORMAT_RAW}
WS_MAX_BYTES = 1 << 20           # websockets closes the connection above this; our own cap is P.MAX_MESSAGE
RESTARTS = 3                     # a worker that dies more often than this within RESTART_WINDOW_S is given up
RESTART_WINDOW_S = 60.0
# Render processes' defaults (the environment overrides them): torch's OpenMP threads sleep between
# parallel regions instead of spinning. Spinning threads on cores that the front end, the clients
# and other objects' processes also want made a dynamic object's step 10-30x slower.
WORKER_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass
class Served:
    """An object as the front end knows it: its placement, manifest and proxy mesh."""

    index: int
    placement: Placement
    manifest: Manifest
    proxy: bytes
    kind: str = ""
    fps: float = 0.0
    checks: list[str] = field(default_factory=list)

    @property
    def scene_from_board(self) -> np.ndarray:
        return self.placement.scene_from_bundle @ self.manifest.T

    @property
    def canvas_fill(self) -> float:
        if self.manifest.kind == "dynamic":
            return float(self.manifest.inputs["crop_fill"])
        return 2 * self.manifest.radius / float(self.manifest.canvas["size_m"])

    def hello(self) -> dict:
        p = self.placement
        return {"index": self.index, "id": p.id, "kind": self.manifest.kind,
                "scene_from_bundle": p.scene_from_bundle.tolist(),
                "position": list(p.position), "yaw_deg": p.yaw_deg, "scale": p.scale,
                "radius_m": self.manifest.radius * p.scale,
                "support_y": self.support_y(),
                "canvas_size_m": float(self.manifest.canvas["size_m"]) * p.scale,
                "proxy_url": f"/objects/{self.index}/proxy.glb",
                "fps": self.fps if self.manifest.kind == "dynamic" else None,
                "frame_size": int(self.manifest.inputs["frame_size"]) if self.manifest.kind == "dynamic" else None}

    def support_y(self) -> float | None:
        """Scene height (metres) of the plane the object stood on (its bundle's support plane; the
        placement turns only about +Y, so the plane stays level), None if the bundle has none."""
        s = self.manifest.support
        if s is None:
            return None
        return float((self.placement.scene_from_bundle @ np.append(s[0], 1.0))[1])

    def board_eye(self, c2w_scene_gl: np.ndarray) -> np.ndarray:
        """The camera centre (3,) in this object's board frame."""
        return (invert_rigid_scaled(self.scene_from_board) @ np.append(c2w_scene_gl[:3, 3], 1.0))[:3]

    def board_up_hint(self, c2w_scene_gl: np.ndarray) -> np.ndarray:
        """The camera's image up in the board frame (used when it looks along the object's up)."""
        return invert_rigid_scaled(self.scene_from_board)[:3, :3] @ c2w_scene_gl[:3, 1]

    def scene_camera(self, c2w_board_cv: np.ndarray) -> np.ndarray:
        """A canvas camera (OpenCV axes, board frame) as a scene-frame pose with OpenGL axes
        (rotation orthonormal, centre scaled with the object)."""
        M = self.scene_from_board
        s = self.placement.scale
        out = np.eye(4)
        out[:3, :3] = (M[:3, :3] / s) @ c2w_board_cv[:3, :3]
        out[:3, 3] = (M @ np.append(c2w_board_cv[:3, 3], 1.0))[:3]
        return opengl_from_opencv(out)

    def scene_centre(self) -> np.ndarray:
        return (self.scene_from_board @ np.append(self.manifest.center, 1.0))[:3]


def invert_rigid_scaled(M: np.ndarray) -> np.ndarray:
    """Inverse of a rotation, uniform scale and translation (4, 4)."""
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    R = M[:3, :3] / s
    out = np.eye(4)
    out[:3, :3] = R.T / s
    out[:3, 3] = -(R.T @ M[:3, 3]) / s
    return out


class Worker:
    """One object's render process, restarted when it dies."""

    def __init__(self, obj: Served, threads: int, on_reply: Callable[[Served, object], None],
                 on_exit: Callable[[Served], None]):
        self.obj, self.threads = obj, threads
        self.on_reply, self.on_exit = on_reply, on_exit
        self.proc: asyncio.subprocess.Process | None = None
        self.ready = False
        self.deaths: list[float] = []
        self._reader: asyncio.Task | None = None

    async def start(self) -> Ready | Fatal:
        """Start the process; returns once it has verified and loaded its bundle (or failed)."""
        self.proc = await asyncio.create_subprocess_exec(
            # Not ``-m``: replies must unpickle as this module's classes, not as ``__main__``'s.
            sys.executable, "-c", "import sys; from dbb_capture.serve.worker import main; sys.exit(main())",
            str(self.obj.placement.bundle),
            "--threads", str(self.threads), stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
            env=WORKER_ENV | dict(os.environ),
            start_new_session=True)          # Ctrl-C reaches the server, which stops its workers
        first = await self._read()
        if isinstance(first, Ready):
            self.ready = True
            self._reader = asyncio.create_task(self._read_loop(self.proc))
            return first
        await self.stop()
        return first if isinstance(first, Fatal) else Fatal(f"{self.obj.placement.bundle}: its render process exited")

    async def _read(self, proc=None) -> object | None:
        proc = proc or self.proc
        try:
            head = await proc.stdout.readexactly(4)
            return pickle.loads(await proc.stdout.readexactly(int.from_bytes(head, "little")))
        except (asyncio.IncompleteReadError, ConnectionError):
            return None

    async def _read_loop(self, proc) -> None:
        while (msg := await self._read(proc)) is not None:
            self.on_reply(self.obj, msg)
        if proc is self.proc and self.ready:
            self.ready = False
            self.on_exit(self.obj)

    def send(self, msg: Job | Control) -> bool:
        if not self.ready or self.proc.stdin.is_closing():
            return False
        body = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
        try:
            self.proc.stdin.write(len(body).to_bytes(4, "little") + body)
        except (ConnectionError, RuntimeError):
            return False
        return True

    def may_restart(self) -> bool:
        now = time.monotonic()
        self.deaths = [t for t in self.deaths if now - t < RESTART_WINDOW_S] + [now]
        return len(self.deaths) <= RESTARTS

    async def stop(self) -> None:
        self.ready = False
        p = self.proc
        if p is None or p.returncode is not None:
            return
        with contextlib.suppress(Exception):
            p.stdin.close()
        try:
            await asyncio.wait_for(p.wait(), 3.0)
        except asyncio.TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                p.kill()
            await p.wait()


@dataclass
class Slot:
    """One (client, object, eye): the job in flight and the one waiting (latest pose wins)."""

    inflight: bool = False
    pending: tuple | None = None        # (Job, deliver)
    deliver: Callable[[object], Awaitable[None]] | None = None
    dropped: int = 0


@dataclass
class Quality:
    max_size: int | None = None
    lossless: bool = False
    raw: bool = False
    jpeg_quality: int = JPEG_QUALITY


class Server:
    """Objects, their workers and the clients' slots. ``start`` loads everything; ``serve`` runs
    until ``stop`` is called."""

    def __init__(self, placements: list[Placement], host: str = "127.0.0.1", port: int = 8765,
                 seed_port: int | None = None, seed_size: int = 256, max_size: int = MAX_SIZE,
                 token: str | None = None, static_roots: dict[str, Path] | None = None):
        if not placements:
            raise DbbError("nothing to serve: give one or more bundles or a scene file")
        if not MIN_SIZE <= max_size <= 4096:
            raise DbbError(f"{{=max_size}} must be from {MIN_SIZE} to 4096 pixels")
        self.placements, self.host, self.port = placements, host, port
        self.seed_port, self.seed_size, self.max_size = seed_port, seed_size, max_size
        self.token = token if token is not None else (None if is_loopback(host) else secrets.token_urlsafe(18))
        self.static_roots = {k: Path(v).resolve() for k, v in (static_roots or {}).items()}
        self.objects: list[Served] = []
        self.workers: list[Worker] = []
        self.slots: dict[tuple, Slot] = {}
        self._next_client = 0
        self._stack = contextlib.ExitStack()
        self._servers: list = []
        self._stopped = asyncio.Event()
        self._tasks: set[asyncio.Task] = set()

    # ---- start and stop ----
    async def start(self, on_loaded: Callable[[Served], None] | None = None) -> None:
        """Open every bundle, start and await its worker (they verify in parallel), then listen."""
        for i, p in enumerate(self.placements):
            b = self._stack.enter_context(open_bundle(p.bundle))
            self.objects.append(Served(i, p, b.manifest, b.file(b.manifest.proxy_mesh["file"]).read_bytes()))
        threads = max(1, _cores() // len(self.objects))
        self.workers = [Worker(o, threads, self._on_reply, self._on_exit) for o in self.objects]

        async def start_one(w: Worker) -> None:
            r = await w.start()
            if isinstance(r, Fatal):
                raise DbbError(f"cannot serve {w.obj.placement.bundle}: {r.message}")
            w.obj.kind, w.obj.fps, w.obj.checks = r.kind, r.fps, r.checks
            if on_loaded:
                on_loaded(w.obj)

        try:
            await asyncio.gather(*(start_one(w) for w in self.workers))
            self._servers.append(await serve(self._ws_handler, self.host, self.port, process_request=self._http,
                                             max_size=WS_MAX_BYTES, compression=None, ping_interval=20))
            if self.seed_port is not None:
                from .seed import seed_handler

                for o in self.objects:
                    self._servers.append(await asyncio.start_server(
                        lambda r, w, o=o: seed_handler(self, o, r, w), self.host, self.seed_port + o.index))
        except OSError as e:
            await self.close()
            raise DbbError(f"cannot listen on {self.host}: {e.strerror or e}") from None
        except BaseException:
            await self.close()
            raise

    @property
    def bound_port(self) -> int:
        """The port listened on (the one asked for, or the system's choice for port 0)."""
        return self._servers[0].sockets[0].getsockname()[1] if self._servers else self.port

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.bound_port}/" + (f"?token={self.token}" if self.token else "")

    def stop(self) -> None:
        self._stopped.set()

    async def serve(self) -> None:
        await self._stopped.wait()
        await self.close()

    async def close(self) -> None:
        for s in self._servers:
            s.close()
        for s in self._servers:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(s.wait_closed(), 3.0)
        self._servers = []
        await asyncio.gather(*(w.stop() for w in self.workers), return_exceptions=True)
        for t in list(self._tasks):
            t.cancel()
        self._stack.close()

    def new_client(self) -> int:
        self._next_client += 1
        return self._next_client

    def _spawn(self, coro) -> None:
        t = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)

    # ---- scheduling ----
    def submit(self, obj: Served, job: Job, deliver: Callable[[object], Awaitable[None]]) -> None:
        """Render ``job`` on ``obj``'s worker and hand the reply to ``deliver``; a job for a busy
        slot waits in its place, replacing (dropping) any job that waited there."""
        slot = self.slots.setdefault(job.key, Slot())
        if slot.inflight or not self.workers[obj.index].ready:
            if slot.pending is not None:
                slot.dropped += 1
            slot.pending = (job, deliver)
            return
        self._dispatch(obj, slot, job, deliver)

    def _dispatch(self, obj: Served, slot: Slot, job: Job, deliver) -> None:
        slot.inflight, slot.deliver, slot.pending = True, deliver, None
        if not self.workers[obj.index].send(job):
            slot.inflight, slot.pending = False, (job, deliver)

    def _on_reply(self, obj: Served, msg: object) -> None:
        slot = self.slots.get(getattr(msg, "key", None))
        if slot is None or not slot.inflight:
            return

        async def deliver_then_next() -> None:
            try:
                await slot.deliver(msg)
            finally:
                slot.inflight = False
                if slot.pending is not None and msg.key in self.slots:
                    self._dispatch(obj, slot, *slot.pending)

        self._spawn(deliver_then_next())

    def _on_exit(self, obj: Served) -> None:
        """A worker died: its clients' jobs in flight get an error, and it is started again."""
        w = self.workers[obj.index]
        for key, slot in list(self.slots.items()):
            if key[1] == obj.index and slot.inflight:
                slot.inflight = False
                failed = Failed(key[0], key, "worker_restarted",
                                f"the render process of object {obj.placement.id} died; it is being restarted")
                self._spawn(slot.deliver(failed))
        if self._stopped.is_set():
            return

        async def restart() -> None:
            again = w.may_restart()
            r = await w.start() if again else Fatal("it died too often")
            for key, slot in list(self.slots.items()):
                if key[1] != obj.index or slot.pending is None:
                    continue
                if isinstance(r, Fatal):
                    job, deliver = slot.pending
                    slot.pending = None
                    self._spawn(deliver(Failed(job.client, key, "unavailable",
                                               f"object {obj.placement.id} cannot be rendered: {r.message}")))
                else:
                    self._dispatch(obj, slot, *slot.pending)

        self._spawn(restart())

    def forget(self, client: int) -> None:
        for key in [k for k in self.slots if k[0] == client]:
            del self.slots[key]
        for w in self.workers:
            w.send(Control(client, "forget"))

    # ---- dbb-stream/1 ----
    def hello(self) -> dict:
        return {"type": "hello", "protocol": P.PROTOCOL, "objects": [o.hello() for o in self.objects],
                "max_size": self.max_size, "formats": list(P.FORMATS.values()),
                "conventions": {"scene": "metres, +Y up, right-handed (glTF axes)",
                                "bundle_space": "object-centred, metres, +Y up (docs/bundle-format.md)",
                                "camera": "camera-to-world 4x4, row-major, OpenGL camera axes (+x right, +y up, "
                                          "looking along -z)",
                                "pixels": "origin at the image's top-left corner (cx = w / 2 when centred)",
                                "images": "straight (not premultiplied) alpha, rows top to bottom"}}

    async def _ws_handler(self, ws: ServerConnection) -> None:
        client = self.new_client()
        quality = Quality()

        async def send(data) -> None:
            with contextlib.suppress(ConnectionClosed):
                await ws.send(data)

        try:
            await ws.send(json.dumps(self.hello()))
            async for message in ws:
                if isinstance(message, bytes):
                    self._on_request(client, quality, message, send)
                else:
                    await self._on_control(client, quality, message, send)
        except ConnectionClosed:
            pass
        finally:
            self.forget(client)

    def _on_request(self, client: int, quality: Quality, data: bytes, send) -> None:
        try:
            if len(data) > P.MAX_MESSAGE:
                raise P.ProtocolError("too_large", f"a message of {len(data)} bytes (at most {P.MAX_MESSAGE})")
            req = P.ViewRequest.unpack(data)
            if req.object != P.ALL_OBJECTS and req.object >= len(self.objects):
                raise P.ProtocolError("unknown_object", f"object {req.object}: the scene has objects 0 to "
                                                        f"{len(self.objects) - 1}")
        except P.ProtocolError as e:
            self._spawn(send(P.error_message(e.code, str(e))))
            return
        targets = self.objects if req.object == P.ALL_OBJECTS else [self.objects[req.object]]
        for obj in targets:
            try:
                job = self._job(client, quality, req, obj)
            except P.ProtocolError as e:
                self._spawn(send(P.error_message(e.code, str(e), seq=req.seq, object=obj.index)))
                continue
            self.submit(obj, job, lambda msg, obj=obj, req=req: send(self._frame(obj, req, msg)))

    def _job(self, client: int, quality: Quality, req: P.ViewRequest, obj: Served) -> Job:
        eye = obj.board_eye(req.c2w)
        m = obj.manifest
        D = float(np.linalg.norm(eye - m.center))
        if D <= m.radius * 1.01:
            raise P.ProtocolError("too_close", f"the camera is inside object {obj.placement.id}'s bounding sphere "
                                               f"({D * obj.placement.scale:.3f} m from its centre)")
        from ..crops.camera import canvas_side

        side = canvas_side(D, m.radius, obj.canvas_fill) * obj.placement.scale
        px = req.screen_size(side, D * obj.placement.scale)
        cap = min(self.max_size, quality.max_size or self.max_size)
        size = int(min(cap, max(MIN_SIZE, SIZE_STEP * math.ceil(px / SIZE_STEP))))
        encoding = (RAW if req.raw or quality.raw else
                    PNG if req.lossless or quality.lossless else JPEG)
        return Job(client, (client, obj.index, req.eye), eye, size, encoding,
                   quality.jpeg_quality, obj.board_up_hint(req.c2w), time.monotonic())

    def _frame(self, obj: Served, req: P.ViewRequest, msg: object) -> bytes | str:
        if isinstance(msg, Failed):
            return P.error_message(msg.code, msg.message, seq=req.seq, object=obj.index)
        assert isinstance(msg, Rendered)
        h = P.FrameHeader(req.seq, req.client_ms, obj.index, req.eye,
                          WIRE_FORMATS[msg.encoding], time.time() * 1e3,
                          msg.render_ms, obj.scene_camera(msg.c2w), obj.scene_centre(),
                          msg.side_m * obj.placement.scale, msg.size, msg.size, msg.step,
                          len(msg.colour), len(msg.alpha))
        return h.pack() + msg.colour + msg.alpha

    async def _on_control(self, client: int, quality: Quality, text: str, send) -> None:
        try:
            c = P.parse_control(text)
            if c.object is not None and c.object >= len(self.objects):
                raise P.ProtocolError("unknown_object", f"object {c.object}: the scene has objects 0 to "
                                                        f"{len(self.objects) - 1}")
        except P.ProtocolError as e:
            await send(P.error_message(e.code, str(e)))
            return
        if c.type in ("reset", "pause"):
            what = "reset" if c.type == "reset" else ("pause" if c.paused else "resume")
            for o in (self.objects if c.object is None else [self.objects[c.object]]):
                self.workers[o.index].send(Control(client, what, time.monotonic()))
        elif c.type == "quality":
            if c.max_size is not None:
                quality.max_size = c.max_size
            if c.lossless is not None:
                quality.lossless = c.lossless
            if c.raw is not None:
                quality.raw = c.raw
            if c.jpeg_quality is not None:
                quality.jpeg_quality = c.jpeg_quality
        reply = {"type": "pong" if c.type == "ping" else "ack", "of": c.type, "id": c.id, "server_ms": time.time() * 1e3}
        await send(json.dumps(reply))

    # ---- HTTP: the viewer's files, proxy meshes, auth ----
    def _authorized(self, request: Request) -> bool:
        if self.token is None:
            return True
        q = parse_qs(urlsplit(request.path).query).get("token", [""])[0]
        cookie = ""
        for part in request.headers.get("Cookie", "").split(";"):
            k, _, v = part.strip().partition("=")
            if k == "dbb_token":
                cookie = v
        auth = request.headers.get("Authorization", "").removeprefix("token ").strip()
        return any(hmac.compare_digest(t, self.token) for t in (q, cookie, auth) if t)

    def _http(self, conn: ServerConnection, request: Request) -> Response | None:
        origin = request.headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc != request.headers.get("Host", ""):
            return _response(403, b"origin not allowed\n")
        if not self._authorized(request):
            return _response(401, b"a token is required: open the URL dbb-serve printed\n")
        path = unquote(urlsplit(request.path).path)
        if path == "/ws":
            return None
        headers = {}
        if self.token:
            headers["Set-Cookie"] = f"dbb_token={self.token}; Path=/; HttpOnly; SameSite=Strict"
        parts = path.strip("/").split("/")
        if len(parts) == 3 and parts[0] == "objects" and parts[2] == "proxy.glb":
            obj = next((o for o in self.objects if parts[1] in (str(o.index), o.placement.id)), None)
            if obj is None:
                return _response(404, b"no such object\n")
            return _response(200, obj.proxy, "model/gltf-binary", headers)
        if path == "/hello.json":
            return _response(200, json.dumps(self.hello()).encode(), "application/json", headers)
        f = resolve_static(self.static_roots, path)
        if f is None:
            return _response(404, b"not found\n")
        kind = mimetypes.guess_type(f.name)[0] or "application/octet-stream"
        if f.suffix in (".js", ".mjs"):
            kind = "text/javascript"
        return _response(200, f.read_bytes(), kind, headers)


def _response(status: int, body: bytes, kind: str = "text/plain; charset=utf-8", extra: dict | None = None) -> Response:
    from http import HTTPStatus

    h = Headers({"Content-Type": kind, "Content-Length": str(len(body)), "Cache-Control": "no-store",
                 "X-Content-Type-Options": "nosniff", **(extra or {})})
    return Response(status, HTTPStatus(status).phrase, h, body)


def resolve_static(roots: dict[str, Path], url_path: str) -> Path | None:
    """The file a URL path names under one of ``roots`` (URL prefix -> folder), or None.

    Nothing outside a root is ever served: ``..``, absolute parts, backslashes and NUL are
    refused, and so is any symlink on the way (even one pointing inside)."""
    if "\x00" in url_path or "\\" in url_path:
        return None
    for prefix in sorted(roots, key=len, reverse=True):
        if not url_path.startswith(prefix):
            continue
        rel = url_path[len(prefix):].lstrip("/") or "index.html"
        parts = rel.split("/")
        if any(p in ("", ".", "..") for p in parts) or Path(rel).is_absolute():
            return None
        root = roots[prefix]
        p = root
        for part in parts:
            p = p / part
            if p.is_symlink():
                return None
        if p.is_dir():
            p = p / "index.html"
        if p.is_file() and not p.is_symlink() and p.resolve().is_relative_to(root):
            return p
        return None
    return None

