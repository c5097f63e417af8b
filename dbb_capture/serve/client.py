"""A Python client of ``dbb-stream/1`` (docs/protocol.md), used by the tests and benchmarks.

    async with StreamClient.connect("ws://127.0.0.1:8765/ws") as c:
        print(c.hello["objects"])
        frame = await c.view(c2w, size_px=256)          # c2w: (4, 4) OpenGL axes, scene frame
        frame.rgba                                      # (H, W, 4) uint8, straight alpha
"""

from __future__ import annotations

import asyncio
import itertools
import json
import time
from dataclasses import dataclass

import cv2
import numpy as np
from websockets.asyncio.client import ClientConnection, connect

from ..geometry.conventions import opengl_from_opencv
from ..geometry.transforms import look_at
from . import protocol as P


@dataclass(frozen=True)
class Frame:
    """A decoded frame: its header (:class:`~.protocol.FrameHeader`), straight RGBA pixels, bytes."""

    header: P.FrameHeader
    rgba: np.ndarray
    nbytes: int


class ServerError(RuntimeError):
    """An error message from the server: ``code``, text, and the request it answers (if any)."""

    def __init__(self, msg: dict):
        super().__init__(f"{msg.get('code')}: {msg.get('message')}")
        self.code, self.seq, self.object = msg.get("code"), msg.get("seq"), msg.get("object")


def decode_frame(data: bytes) -> Frame:
    """Header and straight RGBA (H, W, 4) uint8 of a binary frame message."""
    h = P.FrameHeader.unpack(data)
    body = memoryview(data)[P.FRAME.size:]
    colour = np.frombuffer(body[:h.colour_bytes], np.uint8)
    if h.format == P.FORMAT_RAW:
        rgba = colour.reshape(h.height, h.width, 4).copy()
    elif h.format == P.FORMAT_PNG:
        bgra = cv2.imdecode(colour, cv2.IMREAD_UNCHANGED)
        rgba = cv2.cvtColor(bgra, cv2.COLOR_BGRA2RGBA)
    else:
        rgb = cv2.cvtColor(cv2.imdecode(colour, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        alpha = cv2.imdecode(np.frombuffer(body[h.colour_bytes:h.colour_bytes + h.alpha_bytes], np.uint8),
                             cv2.IMREAD_UNCHANGED)
        rgba = np.concatenate([rgb, alpha[..., None]], -1)
    return Frame(h, rgba, len(data))


class StreamClient:
    """One websocket connection. ``send_view`` / ``next_message`` are the raw protocol; ``view``
    sends a request and waits for its frame (or raises :class:`ServerError`)."""

    def __init__(self, ws: ClientConnection, hello: dict):
        self.ws, self.hello = ws, hello
        self._seq = itertools.count(1)
        self._ids = itertools.count(1)

    @classmethod
    def connect(cls, url: str, **kw) -> _Connecting:
        """``async with StreamClient.connect(url) as c``, or ``c = await StreamClient.connect(url)``."""
        return _Connecting(url, kw)

    async def close(self) -> None:
        await self.ws.close()

    async def send_view(self, c2w: np.ndarray, object: int = 0, size_px: int = 256, lossless: bool = False,
                        eye: int = 0, raw: bool = False, **camera) -> int:
        """Send a view request; returns its sequence number. ``camera``: other
        :class:`~.protocol.ViewRequest` fields (``fov_y_deg``, ``fx`` ..., ``viewport_h``)."""
        seq = next(self._seq)
        req = P.ViewRequest(seq, time.time() * 1e3, object, np.asarray(c2w, float), size_px=size_px,
                            lossless=lossless, eye=eye, raw=raw, **camera)
        await self.ws.send(req.pack())
        return seq

    async def next_message(self, timeout: float = 30.0) -> Frame | dict:
        """The next frame (decoded) or JSON message (a dict)."""
        msg = await asyncio.wait_for(self.ws.recv(), timeout)
        return decode_frame(msg) if isinstance(msg, bytes) else json.loads(msg)

    async def view(self, c2w: np.ndarray, object: int = 0, timeout: float = 30.0, **kw) -> Frame:
        """Request one view and wait for its frame; JSON messages in between are skipped."""
        seq = await self.send_view(c2w, object, **kw)
        while True:
            m = await self.next_message(timeout)
            if isinstance(m, Frame) and m.header.seq == seq:
                return m
            if isinstance(m, dict) and m.get("type") == "error" and m.get("seq") in (seq, None):
                raise ServerError(m)

    async def control(self, type: str, timeout: float = 30.0, **fields) -> dict:
        """Send a control message (``reset``, ``pause``, ``quality``, ``ping``) and wait for its reply."""
        mid = next(self._ids)
        await self.ws.send(json.dumps({"type": type, "id": mid, **fields}))
        while True:
            m = await self.next_message(timeout)
            if isinstance(m, dict) and m.get("id") == mid:
                return m
            if isinstance(m, dict) and m.get("type") == "error" and m.get("seq") is None:
                raise ServerError(m)


class _Connecting:
    def __init__(self, url: str, kw: dict):
        self.url, self.kw, self.client = url, kw, None

    async def _open(self) -> StreamClient:
        ws = await connect(self.url, max_size=None, compression=None, **self.kw)
        hello = json.loads(await asyncio.wait_for(ws.recv(), 30.0))
        if hello.get("protocol") != P.PROTOCOL:
            await ws.close()
            raise RuntimeError(f"{self.url} speaks {hello.get('protocol')!r}, not {P.PROTOCOL}")
        self.client = StreamClient(ws, hello)
        return self.client

    def __await__(self):
        return self._open().__await__()

    async def __aenter__(self) -> StreamClient:
        return await self._open()

    async def __aexit__(self, *exc) -> None:
        await self.client.close()


def look_from(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """A camera-to-world (4, 4) with OpenGL axes at ``eye`` looking at ``target`` (scene frame)."""
    return opengl_from_opencv(look_at(eye, target, up))
