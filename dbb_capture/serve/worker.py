"""One object's render process: loads and verifies a bundle, then renders billboard canvases.

The server starts one per object (:func:`main`, arguments ``BUNDLE --threads N``) and talks to it
over its stdin and stdout with length-prefixed pickles of the records below (both ends are this
package; nothing from a client reaches a pickle). Jobs are handled in arrival order, which
shares the process fairly between the clients that the front end lets have one job each.

A canvas is the image of a :func:`~..crops.camera.facing_camera` at the viewer's eye: it looks at
the object's centre with image up along the object's up, and covers the square of side
:func:`~..crops.camera.canvas_side` through the centre.
"""

from __future__ import annotations

import argparse
import os
import pickle
import struct
import sys
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from ..bundle.manifest import Bundle, open_bundle
from ..bundle.render import load_stepper, read_rgba, rgba_tensor
from ..bundle.verify import verify_bundle
from ..core.errors import DbbError
from ..core.images import to_u8
from ..core.parallel import die_with_parent
from ..crops.camera import canvas_side, facing_camera
from ..geometry.viewpoint import viewpoint

_LEN = struct.Struct("<I")
MAX_CATCH_UP_S = 1.0          # a dynamic state more than this behind the clock skips ahead
STATIC_CACHE = 16             # encoded canvases kept per static object (an unchanged pose is free)

# Alpha planes as PNG: run-length deflate after the "up" filter is 2-3x faster than zlib's default
# strategy with adaptive filters, and smaller (mattes are long runs and row-to-row alike).
ALPHA_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE,
             cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]

# Encodings of a canvas (the protocol's formats and the thesis protocol's three modes).
JPEG, PNG, RAW, SEED_RGBA, SEED_BORDER, SEED_BGR = "jpeg", "png", "raw", "seed-rgba", "seed-border", "seed-bgr"


@dataclass(frozen=True)
class Job:
    """Render object's canvas for ``client`` from ``eye`` (3,) board frame, metres, at ``size``
    pixels (static; dynamic objects use their model's size), at server time ``now`` (s)."""

    client: int
    key: tuple                 # echoed: what the front end needs to route the reply
    eye: np.ndarray
    size: int
    encoding: str = JPEG
    jpeg_quality: int = 90
    up_hint: np.ndarray | None = None   # image up when the view runs along the object's up
    now: float = 0.0


@dataclass(frozen=True)
class Control:
    """``reset`` a client's dynamic state, ``pause``/``resume`` its clock, or ``forget`` the client."""

    client: int
    what: str
    now: float = 0.0


@dataclass(frozen=True)
class Rendered:
    client: int
    key: tuple
    c2w: np.ndarray            # the canvas camera, OpenCV axes, board frame
    side_m: float              # canvas side, metres, board frame
    size: int
    step: int                  # dynamic: frames since the state started; static: 0
    encoding: str
    colour: bytes
    alpha: bytes
    render_ms: float


@dataclass(frozen=True)
class Failed:
    client: int
    key: tuple
    code: str
    message: str


@dataclass(frozen=True)
class Ready:
    kind: str
    fps: float
    checks: list[str]


@dataclass(frozen=True)
class Fatal:
    message: str


def encode(rgba: np.ndarray, encoding: str, jpeg_quality: int = 90) -> tuple[bytes, bytes]:
    """Straight RGBA (H, W, 4) uint8 -> (colour, alpha) bytes of ``encoding``.

    JPEG colour cannot hold alpha, so transparent pixels take their neighbours' colour first:
    blocks that straddle the silhouette then carry no dark edge into the object.
    """
    if encoding == JPEG:
        # OpenCV's arithmetic on whole interleaved images (the same float32 operations, the same
        # bytes): numpy broadcasting (H, W, 1) over a strided (H, W, 3) view is several times slower.
        a = rgba[..., 3].astype(np.float32) / 255.0
        a3 = cv2.merge((a, a, a))
        rgb = cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB)
        pm = cv2.multiply(rgb.astype(np.float32), a3)
        k = max(3, rgba.shape[0] // 32) | 1
        den = np.maximum(cv2.blur(a, (k, k)), 1e-3)
        bleed = cv2.divide(cv2.blur(pm, (k, k)), cv2.merge((den, den, den)))
        out = np.clip(cv2.add(cv2.multiply(bleed, 1 - a3), pm), 0, 255).astype(np.uint8)
        cv2.copyTo(rgb, (rgba[..., 3] > 127).view(np.uint8), out)          # where a > 0.5: the colour
        ok1, c = cv2.imencode(".jpg", cv2.cvtColor(out, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        ok2, al = cv2.imencode(".png", np.ascontiguousarray(rgba[..., 3]), ALPHA_PNG)
        assert ok1 and ok2
        return c.tobytes(), al.tobytes()
    if encoding == RAW:
        return np.ascontiguousarray(rgba).tobytes(), b""
    if encoding == SEED_BGR:
        # The thesis's server sent colour without alpha: straight colour on black.
        img = (rgba[..., :3].astype(np.uint16) * rgba[..., 3:] // 255).astype(np.uint8)
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    else:
        img = cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA)
        if encoding == SEED_BORDER:
            img = img.copy()
            img[0], img[-1], img[:, 0], img[:, -1] = 255, 255, 255, 255
    ok, c = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    assert ok
    return c.tobytes(), b""


def _camera(b: Bundle, job: Job, size: int, fill: float) -> tuple[np.ndarray, object]:
    m = b.manifest
    up = np.asarray(m.up, float)
    d = m.center - job.eye
    if job.up_hint is not None and abs(d @ up) > 0.999 * np.linalg.norm(d):
        up = job.up_hint
    return facing_camera(job.eye, m.center, m.radius, up, size, fill)


class StaticCanvas:
    """Canvases of a static bundle, ray cast through its PlenOctree (a pose seen again comes from
    the cache: the thesis's server re-sent its last frame for an unchanged pose)."""

    def __init__(self, b: Bundle, threads: int):
        from ..core.device import pick_device
        from ..octree.render import TreeRenderer
        from ..octree.tree import PlenOctree

        self.b = b
        self.renderer = TreeRenderer(PlenOctree.load(b.file(b.manifest.model["file"])), pick_device(),
                                     threads=threads)
        self.fill = 2 * b.manifest.radius / float(b.manifest.canvas["size_m"])

    def render(self, job: Job) -> tuple[np.ndarray, np.ndarray, int]:
        """Straight RGBA (size, size, 4) uint8, the canvas camera (4, 4), step 0."""
        c2w, intr = _camera(self.b, job, job.size, self.fill)
        return to_u8(self.renderer.render(c2w, intr)), c2w, 0

    def cache_key(self, job: Job) -> tuple:
        hint = None if job.up_hint is None else tuple(np.round(job.up_hint, 3))
        return tuple(np.round(job.eye, 6)), job.size, job.encoding, job.jpeg_quality, hint

    def control(self, c: Control) -> None:
        pass


# The stepper's per-rollout attributes (dbb_capture.dynamic.stepper.Stepper): swapped per client.
# ``t`` (steps since the first frame: the temperature's warm-up) is absent from older stepper.ts files.
_STEPPER_STATE = ("ctx", "ctx_pm", "ctx_view", "warp", "prev_view", "t")


@dataclass
class Rollout:
    """One client's run of a dynamic object: latent state, its step, and its clock."""

    h: torch.Tensor
    z: torch.Tensor
    base: dict                  # stepper attributes before this step's frame was decoded
    after: dict                 # ... and after the last decode
    started: float              # server time at step 0, moved on by pauses and skips
    step: int = 0
    paused_at: float | None = None
    frame: np.ndarray | None = None
    frame_view: np.ndarray = field(default_factory=lambda: np.full(3, np.nan, np.float32))


class DynamicCanvas:
    """Canvases of a dynamic bundle: each client's own rollout of the stepper, advanced at the
    model's fps on the server clock, decoded for the client's latest viewpoint."""

    def __init__(self, b: Bundle, threads: int):
        m = b.manifest
        torch.set_num_threads(threads)
        self.b = b
        self.stepper = load_stepper(b.file(m.model["file"]))
        self.size = int(m.inputs["frame_size"])
        self.fill = float(m.inputs["crop_fill"])
        self.fps = float(m.model.get("fps") or 10.0)
        self.first = rgba_tensor(read_rgba(b.file(m.inputs["first_frame"])), self.size)
        self.first_view = torch.as_tensor(np.asarray(m.inputs["first_view"], np.float32))[None]
        self.rollouts: dict[int, Rollout] = {}
        self.state_keys = tuple(k for k in _STEPPER_STATE if hasattr(self.stepper, k))

    def _get(self) -> dict:
        return {k: getattr(self.stepper, k) for k in self.state_keys}

    def _set(self, state: dict) -> None:
        for k, v in state.items():
            setattr(self.stepper, k, v)

    @torch.no_grad()
    def _start(self, now: float) -> Rollout:
        h, z = self.stepper.start(self.first, self.first_view)
        s = self._get()
        return Rollout(h, z, s, s, now)

    def view_of(self, eye: np.ndarray) -> np.ndarray:
        m = self.b.manifest
        p = viewpoint(eye, m.center, np.asarray(m.up, float))
        return np.array([p.azimuth_deg, p.elevation_deg, p.distance_m], np.float32)

    @torch.no_grad()
    def render(self, job: Job) -> tuple[np.ndarray, np.ndarray, int]:
        """Straight RGBA (S, S, 4) uint8 at the model's size, the canvas camera (4, 4), the step."""
        c2w, _ = _camera(self.b, job, self.size, self.fill)
        r = self.rollouts.get(job.client) or self.rollouts.setdefault(job.client, self._start(job.now))
        clock = (r.paused_at if r.paused_at is not None else job.now) - r.started
        target = int(clock * self.fps)
        if target - r.step > MAX_CATCH_UP_S * self.fps:     # away too long: skip ahead, don't replay
            skip = target - r.step - int(MAX_CATCH_UP_S * self.fps)
            r.started += skip / self.fps
            target -= skip
        view = self.view_of(job.eye)
        v = torch.from_numpy(view)[None]
        while r.step < target:
            self._set(r.after)
            r.h, r.z, x = self.stepper.step(r.h, r.z, v)
            r.base, r.after, r.step = r.after, self._get(), r.step + 1
            r.frame, r.frame_view = x, view
        if r.frame is None or not np.array_equal(view, r.frame_view):
            # The same moment from a new viewpoint: decode from the state before this step's frame.
            self._set(r.base)
            r.frame, r.frame_view = self.stepper.decode(r.h, r.z, v), view
            r.after = self._get()
        return to_u8(r.frame[0].permute(1, 2, 0).numpy()), c2w, r.step

    def cache_key(self, job: Job) -> None:
        return None                 # the clock moves: nothing repeats

    def control(self, c: Control) -> None:
        r = self.rollouts.get(c.client)
        if c.what in ("reset", "forget"):
            self.rollouts.pop(c.client, None)
        elif r is not None and c.what == "pause" and r.paused_at is None:
            r.paused_at = c.now
        elif r is not None and c.what == "resume" and r.paused_at is not None:
            r.started += c.now - r.paused_at
            r.paused_at = None


def load_canvas(b: Bundle, threads: int) -> StaticCanvas | DynamicCanvas:
    return (StaticCanvas if b.manifest.kind == "static" else DynamicCanvas)(b, threads)


def handle(canvas: StaticCanvas | DynamicCanvas, job: Job, cache: OrderedDict) -> Rendered | Failed:
    """Render and encode one job; a bad camera becomes a :class:`Failed` reply, not a crash.
    ``cache``: encoded canvases by :meth:`cache_key` (the most recent :data:`STATIC_CACHE`)."""
    t0 = time.perf_counter()
    key = canvas.cache_key(job)
    if key is not None and key in cache:
        cache.move_to_end(key)
        c2w, colour, alpha = cache[key]
        step = 0
    else:
        try:
            rgba, c2w, step = canvas.render(job)
        except DbbError as e:
            code = "too_close" if "inside the object" in str(e) else "bad_value"
            return Failed(job.client, job.key, code, str(e))
        colour, alpha = encode(rgba, job.encoding, job.jpeg_quality)
        if key is not None:
            cache[key] = (c2w, colour, alpha)
            while len(cache) > STATIC_CACHE:
                cache.popitem(last=False)
    m = canvas.b.manifest
    side = canvas_side(float(np.linalg.norm(job.eye - m.center)), m.radius, canvas.fill)
    size = canvas.size if isinstance(canvas, DynamicCanvas) else job.size
    return Rendered(job.client, job.key, c2w, side, size, step, job.encoding, colour, alpha,
                    1e3 * (time.perf_counter() - t0))


def read_message(stream) -> object | None:
    """One length-prefixed pickle from a binary stream, or None at its end."""
    head = stream.read(_LEN.size)
    if len(head) < _LEN.size:
        return None
    body = stream.read(_LEN.unpack(head)[0])
    return pickle.loads(body) if body else None


def write_message(stream, msg: object) -> None:
    body = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LEN.pack(len(body)) + body)
    stream.flush()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="dbb-serve's render process for one bundle (started by dbb-serve).")
    ap.add_argument("bundle")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    die_with_parent()                       # a killed server takes its render processes with it
    # Replies go to a private copy of stdout; anything a library prints goes to stderr instead.
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    inp = sys.stdin.buffer
    try:
        checks = verify_bundle(args.bundle)
        with open_bundle(args.bundle) as b:
            canvas = load_canvas(b, max(1, args.threads))
            cache: OrderedDict = OrderedDict()
            write_message(out, Ready(b.manifest.kind, getattr(canvas, "fps", 0.0), checks))
            while (msg := read_message(inp)) is not None:
                if isinstance(msg, Job):
                    write_message(out, handle(canvas, msg, cache))
                elif isinstance(msg, Control):
                    canvas.control(msg)
    except DbbError as e:
        write_message(out, Fatal(str(e)))
        return 2
    except (BrokenPipeError, KeyboardInterrupt):
        return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
