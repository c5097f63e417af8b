"""The ``dbb-stream/1`` wire format (docs/protocol.md): binary view requests and frames, JSON
control messages, error codes. Shared by the server and :mod:`.client`; numpy and the standard
library only.

All binary fields are little-endian. Matrices are 4x4 row-major (column vectors). Poses are
camera-to-world with OpenGL camera axes (+x right, +y up, looking along -z) in the scene frame
(metres, +Y up, as glTF); intrinsics put the pixel origin at the image's top-left corner.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass

import numpy as np

PROTOCOL = "dbb-stream/1"
ALL_OBJECTS = 0xFFFF                 # a request's object field: every object of the scene
MAX_MESSAGE = 4096                   # bytes: longer messages are refused (error "too_large")

EYES = ("mono", "left", "right")
FORMAT_JPEG = 0                      # colour JPEG, then alpha as a greyscale PNG
FORMAT_PNG = 1                       # one straight-RGBA PNG (lossless)
FORMAT_RAW = 2                       # the straight RGBA bytes themselves (lossless, nothing to decode)
FORMATS = {FORMAT_JPEG: "jpeg+png-alpha", FORMAT_PNG: "png", FORMAT_RAW: "rgba8"}
FLAG_LOSSLESS = 1                    # request flags, bit 0
FLAG_RAW = 2                         # bit 1: raw RGBA bytes (a client on the same machine or a fast link)

REQUEST = struct.Struct("<4sIdHBB16f5f4H")
REQUEST_MAGIC = b"DBBQ"
FRAME = struct.Struct("<4sIdHBBdf16f4f2HIII")
FRAME_MAGIC = b"DBBF"

# Error codes of {"type": "error", "code": ...}; each comes with one line of text.
ERRORS = {
    "bad_request": "a message that is not a valid request or control message",
    "too_large": f"a message over {MAX_MESSAGE} bytes",
    "bad_value": "a number that is not finite, a pose that is not a rigid transform, a size out of range",
    "unknown_object": "an object index or id the scene does not have",
    "too_close": "a camera inside the object's bounding sphere",
    "worker_restarted": "the object's render process died and was restarted; state was lost",
    "unavailable": "the object's render process could not be started",
    "unauthorized": "a missing or wrong token",
}


class ProtocolError(ValueError):
    """A message the protocol refuses: ``code`` (a key of :data:`ERRORS`) and one line of text."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class ViewRequest:
    """A client's view of one object (or all): ``c2w`` (4, 4) OpenGL axes, scene frame.

    The canvas is rendered at ``size_px`` (the billboard's side on screen); 0 lets the server
    work it out from ``fov_y_deg`` or ``fx`` and the viewport height.
    """

    seq: int
    client_ms: float
    object: int
    c2w: np.ndarray
    fov_y_deg: float = 60.0
    fx: float = 0.0
    fy: float = 0.0
    cx: float = 0.0
    cy: float = 0.0
    viewport_w: int = 0
    viewport_h: int = 0
    size_px: int = 256
    eye: int = 0
    lossless: bool = False
    raw: bool = False

    def pack(self) -> bytes:
        flags = (FLAG_LOSSLESS if self.lossless else 0) | (FLAG_RAW if self.raw else 0)
        return REQUEST.pack(REQUEST_MAGIC, self.seq & 0xFFFFFFFF, self.client_ms, self.object, self.eye,
                            flags, *np.asarray(self.c2w, np.float32).ravel(),
                            self.fov_y_deg, self.fx, self.fy, self.cx, self.cy,
                            self.viewport_w, self.viewport_h, self.size_px, 0)

    @classmethod
    def unpack(cls, data: bytes) -> ViewRequest:
        """Parse and check a request; raises :class:`ProtocolError`."""
        if len(data) != REQUEST.size or data[:4] != REQUEST_MAGIC:
            raise ProtocolError("bad_request", f"a view request is {REQUEST.size} bytes starting with "
                                               f"{REQUEST_MAGIC.decode()}; got {len(data)} bytes")
        f = REQUEST.unpack(data)
        seq, client_ms, obj, eye, flags = f[1:6]
        c2w = np.asarray(f[6:22], np.float64).reshape(4, 4)
        fov, fx, fy, cx, cy = f[22:27]
        vw, vh, size, _ = f[27:31]
        if not (np.all(np.isfinite(c2w)) and all(math.isfinite(v) for v in (client_ms, fov, fx, fy, cx, cy))):
            raise ProtocolError("bad_value", "the request holds a number that is not finite")
        if eye >= len(EYES):
            raise ProtocolError("bad_value", f"eye must be 0 (mono), 1 (left) or 2 (right), not {eye}")
        check_rigid(c2w)
        if size == 0 and (vh == 0 or (fx <= 0 and not 0 < fov < 180)):
            raise ProtocolError("bad_value", "size_px 0 needs the viewport height and a field of view or fx")
        return cls(seq, client_ms, obj, c2w, fov, fx, fy, cx, cy, vw, vh, size, eye, bool(flags & FLAG_LOSSLESS),
                   bool(flags & FLAG_RAW))

    @property
    def eye_position(self) -> np.ndarray:
        return self.c2w[:3, 3]

    def screen_size(self, canvas_side_m: float, distance_m: float) -> float:
        """The billboard's side on screen (pixels): ``size_px``, or from the camera's focal length."""
        if self.size_px:
            return float(self.size_px)
        f = self.fy if self.fy > 0 else (self.fx if self.fx > 0 else
                                         0.5 * self.viewport_h / math.tan(math.radians(self.fov_y_deg) / 2))
        return f * canvas_side_m / max(distance_m, 1e-9)


def check_rigid(c2w: np.ndarray, tol: float = 1e-3) -> None:
    """Refuse a pose whose rotation is not orthonormal with determinant +1 or whose last row is not
    [0, 0, 0, 1] (float32 on the wire, hence the tolerance)."""
    R = c2w[:3, :3]
    if (not np.allclose(c2w[3], [0, 0, 0, 1], atol=tol) or not np.allclose(R @ R.T, np.eye(3), atol=tol)
            or np.linalg.det(R) < 0):
        raise ProtocolError("bad_value", "c2w is not a rigid transform (rotation must be orthonormal, "
                                         "determinant +1, last row 0 0 0 1)")


@dataclass(frozen=True)
class FrameHeader:
    """What precedes a frame's image bytes: the request echoed, and how to place the image.

    ``c2w``: the camera the canvas was rendered from (OpenGL axes, scene frame; it looks at the
    object's centre with image up along the scene's up). The canvas is the square of side
    ``canvas_side_m`` centred on ``canvas_centre``, square to that camera's view axis.
    """

    seq: int
    client_ms: float
    object: int
    eye: int
    format: int
    server_ms: float
    render_ms: float
    c2w: np.ndarray
    canvas_centre: np.ndarray
    canvas_side_m: float
    width: int
    height: int
    step: int
    colour_bytes: int
    alpha_bytes: int

    def pack(self) -> bytes:
        return FRAME.pack(FRAME_MAGIC, self.seq & 0xFFFFFFFF, self.client_ms, self.object, self.eye, self.format,
                          self.server_ms, self.render_ms, *np.asarray(self.c2w, np.float32).ravel(),
                          *np.asarray(self.canvas_centre, np.float32), self.canvas_side_m, self.width,
                          self.height, self.step, self.colour_bytes, self.alpha_bytes)

    @classmethod
    def unpack(cls, data: bytes) -> FrameHeader:
        if len(data) < FRAME.size or data[:4] != FRAME_MAGIC:
            raise ProtocolError("bad_request", "not a dbb-stream frame")
        f = FRAME.unpack_from(data)
        return cls(f[1], f[2], f[3], f[4], f[5], f[6], f[7], np.asarray(f[8:24], np.float64).reshape(4, 4),
                   np.asarray(f[24:27], np.float64), f[27], f[28], f[29], f[30], f[31], f[32])


def error_message(code: str, message: str, **extra) -> str:
    """The JSON text of an error message (``extra``: e.g. the request's ``seq`` and ``object``)."""
    assert code in ERRORS, code
    return json.dumps({"type": "error", "code": code, "message": message, **extra})


CONTROL_TYPES = ("reset", "pause", "quality", "ping")


@dataclass(frozen=True)
class Control:
    """A JSON control message: ``reset`` / ``pause`` (``object`` index or None for all, ``paused``),
    ``quality`` (``max_size`` pixels or None for the server's, ``lossless``, ``raw``, ``jpeg_quality``),
    ``ping``."""

    type: str
    object: int | None = None
    paused: bool = True
    max_size: int | None = None
    lossless: bool | None = None
    jpeg_quality: int | None = None
    raw: bool | None = None
    id: object = None


def parse_control(text: str) -> Control:
    """Parse and check a JSON control message; raises :class:`ProtocolError`."""
    if len(text) > MAX_MESSAGE:
        raise ProtocolError("too_large", f"control messages are at most {MAX_MESSAGE} bytes")
    try:
        d = json.loads(text)
    except ValueError:
        raise ProtocolError("bad_request", "a text message must be a JSON object") from None
    if not isinstance(d, dict) or d.get("type") not in CONTROL_TYPES:
        raise ProtocolError("bad_request", f"control messages have a type among {', '.join(CONTROL_TYPES)}")
    obj = d.get("object")
    if obj is not None and (not isinstance(obj, int) or isinstance(obj, bool) or obj < 0):
        raise ProtocolError("bad_value", "object must be an object index (or null for all)")
    c = Control(d["type"], obj, id=d.get("id"))
    if c.type == "pause":
        if not isinstance(d.get("paused", True), bool):
            raise ProtocolError("bad_value", "paused must be true or false")
        c = Control("pause", obj, bool(d.get("paused", True)), id=c.id)
    elif c.type == "quality":
        size, lossless, q, raw = d.get("max_size"), d.get("lossless"), d.get("jpeg_quality"), d.get("raw")
        if size is not None and (not isinstance(size, int) or isinstance(size, bool) or not 16 <= size <= 4096):
            raise ProtocolError("bad_value", "max_size must be an integer from 16 to 4096 (or null)")
        if lossless is not None and not isinstance(lossless, bool):
            raise ProtocolError("bad_value", "lossless must be true or false")
        if raw is not None and not isinstance(raw, bool):
            raise ProtocolError("bad_value", "raw must be true or false")
        if q is not None and (not isinstance(q, int) or isinstance(q, bool) or not 1 <= q <= 100):
            raise ProtocolError("bad_value", "jpeg_quality must be an integer from 1 to 100")
        c = Control("quality", None, max_size=size, lossless=lossless, jpeg_quality=q, raw=raw, id=c.id)
    return c
