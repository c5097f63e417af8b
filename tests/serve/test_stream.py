"""dbb-serve over dbb-stream/1: frames equal dbb-export render of the same camera, dynamic objects
move by themselves and follow the pose, latest pose wins, the canvas follows the screen."""

from __future__ import annotations

import asyncio
import json

import cv2
import numpy as np

from dbb_capture.bundle.render import render_bundle
from dbb_capture.core.metrics import psnr
from dbb_capture.geometry.conventions import corner_from_centre_px
from dbb_capture.serve.client import StreamClient, look_from
from dbb_capture.serve.protocol import FORMAT_JPEG, FORMAT_PNG, FORMAT_RAW

from .conftest import run


def object_eye(hello: dict, index: int, direction, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """A camera (scene frame, OpenGL axes) ``distance`` m from object ``index``'s centre, looking at it."""
    o = hello["objects"][index]
    centre = np.asarray(o["position"], float)
    d = np.asarray(direction, float)
    return look_from(centre + distance * d / np.linalg.norm(d), centre), centre


def render_as_export(bundle, hello, index, frame, tmp_path, name="view") -> np.ndarray:
    """``dbb-export render`` of the camera a frame says it was rendered from (bundle space)."""
    h = frame.header
    M = np.asarray(hello["objects"][index]["scene_from_bundle"])
    c2w_bundle = np.linalg.inv(M) @ h.c2w
    # The canvas: a square image whose side covers canvas_side_m at the centre's distance.
    D = float(np.linalg.norm(h.c2w[:3, 3] - h.canvas_centre))
    f = h.width * D / h.canvas_side_m
    c = corner_from_centre_px((h.width - 1) / 2)
    cams = {"w": h.width, "h": h.height, "fl_x": f, "fl_y": f, "cx": c, "cy": c,
            "frames": [{"file_path": f"{name}.png", "transform_matrix": c2w_bundle.tolist()}]}
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(cams))
    out = tmp_path / f"{name}_render"
    render_bundle(bundle, path, out, space="bundle")
    return cv2.cvtColor(cv2.imread(str(out / f"{name}.png"), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)


def composited_psnr(a: np.ndarray, b: np.ndarray) -> float:
    """The lower PSNR of two straight-RGBA images composited on black and on white."""
    out = []
    for bg in (0.0, 1.0):
        fa, fb = a.astype(np.float32) / 255, b.astype(np.float32) / 255
        ca = fa[..., :3] * fa[..., 3:] + bg * (1 - fa[..., 3:])
        cb = fb[..., :3] * fb[..., 3:] + bg * (1 - fb[..., 3:])
        out.append(psnr(ca, cb))
    return min(out)


def test_hello_describes_objects_and_conventions(server):
    async def go():
        async with StreamClient.connect(server.ws) as c:
            return c.hello
    hello = run(go())
    assert hello["protocol"] == "dbb-stream/1"
    kinds = [o["kind"] for o in hello["objects"]]
    assert kinds == ["static", "dynamic"]
    s, d = hello["objects"]
    assert d["fps"] > 0 and s["fps"] is None and s["canvas_size_m"] > 0
    assert s["proxy_url"] == "/objects/0/proxy.glb"
    # The table the dynamic object was filmed on (its bundle's support plane), in the scene; the
    # static test bundle's dataset measured none.
    assert s["support_y"] is None and -d["radius_m"] < d["support_y"] - d["position"][1] < 0
    assert "OpenGL" in hello["conventions"]["camera"]
    # Side by side along +X without overlapping.
    assert d["position"][0] - s["position"][0] >= (s["canvas_size_m"] + d["canvas_size_m"]) / 2


def test_static_frame_equals_export_render(server, static_bundle, tmp_path):
    async def go():
        async with StreamClient.connect(server.ws) as c:
            cam, _ = object_eye(c.hello, 0, [0.3, 0.5, 1.0], 0.5)
            lossless = await c.view(cam, 0, size_px=96, lossless=True)
            jpeg = await c.view(cam, 0, size_px=96)
            raw = await c.view(cam, 0, size_px=96, raw=True)
            await c.ws.send(json.dumps({"type": "quality", "raw": True}))        # the connection's default
            raw2 = await c.view(cam, 0, size_px=96, lossless=True)
            return c.hello, lossless, jpeg, raw, raw2
    hello, lossless, jpeg, raw, raw2 = run(go())
    assert lossless.header.format == FORMAT_PNG and jpeg.header.format == FORMAT_JPEG
    assert raw.header.format == raw2.header.format == FORMAT_RAW
    assert raw.header.colour_bytes == 96 * 96 * 4 and raw.header.alpha_bytes == 0
    assert np.array_equal(raw.rgba, lossless.rgba) and np.array_equal(raw2.rgba, lossless.rgba)
    assert lossless.rgba.shape == (96, 96, 4)
    assert lossless.rgba[..., 3].max() > 200 and lossless.rgba[..., 3].mean() < 200   # an object, not a wall
    want = render_as_export(static_bundle, hello, 0, lossless, tmp_path)
    assert composited_psnr(lossless.rgba, want) >= 45
    assert composited_psnr(jpeg.rgba, want) >= 32
    assert jpeg.nbytes < lossless.nbytes


def test_canvas_follows_the_screen_and_a_repeated_pose_is_cached(server):
    async def go():
        async with StreamClient.connect(server.ws) as c:
            cam, _ = object_eye(c.hello, 0, [0, 0.4, 1.0], 0.6)
            small = await c.view(cam, 0, size_px=50)
            huge = await c.view(cam, 0, size_px=3000)
            by_fov = await c.view(cam, 0, size_px=0, fov_y_deg=50.0, viewport_h=720)
            again = await c.view(cam, 0, size_px=3000)
            return c.hello, small, huge, by_fov, again
    hello, small, huge, by_fov, again = run(go())
    assert small.header.width == 56                          # rounded up to a multiple of 8
    assert huge.header.width == hello["max_size"] == 512     # clamped to the server's maximum
    f = 0.5 * 720 / np.tan(np.radians(25))
    D = np.linalg.norm(by_fov.header.c2w[:3, 3] - by_fov.header.canvas_centre)
    expect = f * by_fov.header.canvas_side_m / D
    assert abs(by_fov.header.width - expect) <= 8
    assert again.header.render_ms < 0.2 * huge.header.render_ms
    assert np.array_equal(again.rgba, huge.rgba)


def test_dynamic_object_moves_by_itself_and_follows_the_pose(server):
    async def go():
        async with StreamClient.connect(server.ws) as c:
            fps = c.hello["objects"][1]["fps"]
            cam, _ = object_eye(c.hello, 1, [0.2, 0.5, 1.0], 0.6)
            side, _ = object_eye(c.hello, 1, [1.0, 0.5, -0.3], 0.6)
            first = await c.view(cam, 1, lossless=True)
            await asyncio.sleep(3 / fps)
            later = await c.view(cam, 1, lossless=True)
            await c.control("pause", object=1, paused=True)
            still = await c.view(cam, 1, lossless=True)
            turned = await c.view(side, 1, lossless=True)           # the same moment from another side
            back = await c.view(cam, 1, lossless=True)
            await asyncio.sleep(3 / fps)
            paused = await c.view(cam, 1, lossless=True)
            await c.control("pause", object=1, paused=False)
            await c.control("reset", object=1)
            restarted = await c.view(cam, 1, lossless=True)
            return c.hello, first, later, still, turned, back, paused, restarted
    hello, first, later, still, turned, back, paused, restarted = run(go())
    size = hello["objects"][1]["frame_size"]
    assert first.rgba.shape == (size, size, 4)
    assert first.header.step == 0 and later.header.step >= 2
    assert not np.array_equal(first.rgba, later.rgba)                 # moves while the pose is still
    assert turned.header.step == still.header.step == back.header.step == paused.header.step
    assert not np.array_equal(turned.rgba, still.rgba)                # follows the pose
    assert np.array_equal(back.rgba, still.rgba)                      # ... and back again, exactly
    assert restarted.header.step <= 1


def test_latest_pose_wins(server):
    async def go():
        async with StreamClient.connect(server.ws) as c:
            seqs = []
            for i in range(30):
                cam, _ = object_eye(c.hello, 0, [np.cos(i / 5), 0.5, np.sin(i / 5)], 0.6)
                seqs.append(await c.send_view(cam, 0, size_px=256, lossless=True))
            got = []
            while not got or got[-1] != seqs[-1]:
                m = await c.next_message()
                got.append(m.header.seq)
            return seqs, got
    seqs, got = run(go())
    assert got == sorted(got) and got[-1] == seqs[-1]
    assert len(got) < len(seqs)           # overtaken requests were dropped, not queued


def test_all_objects_in_one_request(server):
    async def go():
        async with StreamClient.connect(server.ws) as c:
            cam = look_from([0.2, 0.6, 1.2], [0, 0, 0])
            seq = await c.send_view(cam, 0xFFFF, size_px=64)
            frames = [await c.next_message() for _ in c.hello["objects"]]
            return seq, frames
    seq, frames = run(go())
    assert sorted(f.header.object for f in frames) == [0, 1]
    assert all(f.header.seq == seq for f in frames)


def test_eyes_have_their_own_slots(server):
    async def go():
        async with StreamClient.connect(server.ws) as c:
            cam, _ = object_eye(c.hello, 0, [0, 0.5, 1], 0.6)
            a = await c.send_view(cam, 0, size_px=64, eye=1)
            b = await c.send_view(cam, 0, size_px=64, eye=2)
            got = {(await c.next_message()).header.seq for _ in range(2)}
            return {a, b}, got
    want, got = run(go())
    assert got == want
