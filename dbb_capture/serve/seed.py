"""The thesis's own billboard protocol (``--seed-port``), byte for byte as its published Unity
client (``ControlBillboard.cs``) and server (``db_command.py``) speak it, so that client works
unchanged. One TCP port per object: ``seed_port + index``.

Request: UTF-8 text, 7 or 8 comma-separated floats, no terminator, one per ``recv(1024)``: the
camera position relative to the billboard in Unity's left-handed y-up frame sent as
``(z, -x, y)`` (Unity units taken as metres, the billboard at the object's centre), the
billboard's rotation (``-w, z, -x, y``; not needed: the canvas always faces the camera with
image up along the world's up, which is what Unity's ``LookAt`` gives), and a mode: 0 RGBA,
1 RGBA with a one-pixel white border, 2 colour without alpha (BGR).

Reply: ``"%04d    "`` (8 ASCII bytes) giving the length of a view string, the view string
(``"0.0 0.0 0.0 0.0 0.0 0.0"``, unused by the client), then PNG bytes with no length. A pose that
moved less than 1e-5 (summed absolute change of the numbers) gets the previous reply again.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time

import numpy as np

from ..core.progress import console
from .worker import SEED_BGR, SEED_BORDER, SEED_RGBA, Failed, Job, Rendered

VIEW = b"0.0 0.0 0.0 0.0 0.0 0.0"
MODES = {0: SEED_RGBA, 1: SEED_BORDER, 2: SEED_BGR}
SAME_POSE = 1e-5
NEAREST = 1.05               # a camera inside the bounding sphere is moved out to this many radii


def parse_request(data: bytes) -> list[float] | None:
    """The request's numbers, or None when it is not 7 or 8 finite comma-separated floats."""
    try:
        v = [float(s) for s in data.decode("utf-8").split(",")]
    except (UnicodeDecodeError, ValueError):
        return None
    if len(v) not in (7, 8) or not all(math.isfinite(x) for x in v):
        return None
    if len(v) == 8 and v[7] not in MODES:
        return None
    return v


def bundle_eye(v: list[float]) -> np.ndarray:
    """The camera centre in bundle space (glTF axes: +Y up, right-handed) from a request's
    ``(z, -x, y)`` of Unity's left-handed frame: Unity (x, y, z) is glTF (x, y, -z)."""
    a, b, c = v[:3]
    return np.array([-b, c, -a])


def reply(png: bytes) -> bytes:
    return f"{len(VIEW):04d}    ".encode() + VIEW + png


async def seed_handler(server, obj, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Serve one Unity client of object ``obj`` until it disconnects or sends what the protocol
    cannot hold (the published server drops such a connection too)."""
    client = server.new_client()
    last: list[float] | None = None
    cached: bytes | None = None
    peer = writer.get_extra_info("peername")
    try:
        while data := await reader.read(1024):
            v = parse_request(data)
            if v is None:
                console.print(f"seed port: closing {peer}: not 7 or 8 comma-separated numbers "
                              f"({len(data)} bytes)", markup=False)
                break
            if last is not None and cached is not None and len(v) == len(last) and \
                    sum(abs(a - b) for a, b in zip(v, last, strict=True)) < SAME_POSE:
                writer.write(cached)
                await writer.drain()
                continue
            last = v
            reply_bytes = await _render(server, obj, client, v)
            if reply_bytes is None:
                break
            cached = reply_bytes
            writer.write(cached)
            await writer.drain()
    except (ConnectionError, asyncio.IncompleteReadError):
        pass
    finally:
        server.forget(client)
        writer.close()
        with contextlib.suppress(Exception):
            await writer.wait_closed()


async def _render(server, obj, client: int, v: list[float]) -> bytes | None:
    m = obj.manifest
    eye_b = bundle_eye(v)
    d = float(np.linalg.norm(eye_b))
    if d < NEAREST * m.radius:
        eye_b = eye_b / max(d, 1e-9) * NEAREST * m.radius if d > 1e-9 else np.array([0, 0, NEAREST * m.radius])
    eye = (np.linalg.inv(m.T) @ np.append(eye_b, 1.0))[:3]
    mode = int(v[7]) if len(v) == 8 else 0
    # The canvas's up when looking straight down: the bundle's -Z (Unity's forward).
    hint = np.linalg.inv(m.T)[:3, :3] @ np.array([0.0, 0.0, -1.0])
    job = Job(client, (client, obj.index, "seed"), eye, server.seed_size, MODES[mode], up_hint=hint,
              now=time.monotonic())
    done: asyncio.Future = asyncio.get_running_loop().create_future()

    async def deliver(msg) -> None:
        if not done.done():
            done.set_result(msg)

    server.submit(obj, job, deliver)
    msg = await done
    if isinstance(msg, Failed):
        console.print(f"seed port: object {obj.placement.id}: {msg.message}", markup=False)
        return None
    assert isinstance(msg, Rendered)
    return reply(msg.colour)
