"""dbb-serve under bad input: every malformed message gets an error code and the connection stays
usable; clients that vanish, workers that die, bad bundles, foreign origins, missing tokens,
paths out of the viewer's folder; a clean stop."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from dbb_capture.serve.client import ServerError, StreamClient, look_from
from dbb_capture.serve.protocol import ViewRequest
from dbb_capture.serve.server import resolve_static

from .conftest import run, start_server

async def opened(url: str, **kw):
    ws = await connect(url, **kw)
    await ws.close()


CAM = look_from([0.0, 0.3, 0.6], [0.0, 0.0, 0.0])


def valid(obj: int = 0, seq: int = 1) -> bytes:
    return ViewRequest(seq, 0.0, obj, CAM, size_px=32).pack()


def with_matrix(m: np.ndarray) -> bytes:
    b = bytearray(valid())
    struct.pack_into("<16f", b, 20, *np.asarray(m, np.float32).ravel())
    return bytes(b)


BAD = {
    "too_large": b"\0" * 5000,
    "bad_request": b"DBBQ" + b"\0" * 10,
    "bad_request ": b"XXXX" + valid()[4:],
    "unknown_object": valid(obj=7),
    "bad_value": with_matrix(np.full((4, 4), np.nan)),
    "bad_value ": with_matrix(np.zeros((4, 4))),                       # singular
    "bad_value  ": with_matrix(np.diag([2.0, 2.0, 2.0, 1.0])),         # not rigid
    "too_close": b"",                                                  # made from the hello below
}
BAD_TEXT = {
    "bad_request": "not json",
    "bad_request ": json.dumps({"type": "explode"}),
    "bad_value": json.dumps({"type": "quality", "max_size": -3}),
    "unknown_object": json.dumps({"type": "reset", "object": 9}),
    "too_large": json.dumps({"type": "ping", "pad": "x" * 5000}),
}


def test_every_bad_message_gets_its_error_and_the_connection_stays_usable(server):
    async def go():
        async with StreamClient.connect(server.ws) as c:
            got = {}
            for name, data in {**BAD, **BAD_TEXT}.items():
                if name == "too_close":          # 1 cm from object 0's centre
                    pos = np.asarray(c.hello["objects"][0]["position"])
                    data = ViewRequest(1, 0.0, 0, look_from(pos + [0, 0, 0.01], pos), size_px=32).pack()
                await c.ws.send(data if isinstance(data, bytes) else data)
                while True:
                    m = await c.next_message()
                    if isinstance(m, dict) and m["type"] == "error":
                        break
                got[name] = (m["code"], m["message"])
            frame = await c.view(CAM, 0, size_px=32)                         # still works
            return got, frame
    got, frame = run(go())
    for name, (code, message) in got.items():
        assert code == name.strip(), (name, code, message)
        assert message and "\n" not in message
    assert frame.rgba.shape == (32, 32, 4)
    assert server.proc.poll() is None


def test_a_vanishing_client_affects_no_other(server):
    async def go():
        for _ in range(3):
            ws = await connect(server.ws)
            await ws.recv()
            await ws.send(ViewRequest(1, 0.0, 0, CAM, size_px=512, lossless=True).pack())
            ws.transport.abort()                                  # gone mid-frame, no close handshake
        async with StreamClient.connect(server.ws) as c:
            return await c.view(CAM, 0, size_px=48)
    assert run(go()).rgba.shape == (48, 48, 4)


def test_a_dead_worker_is_restarted_and_its_clients_told(static_bundle):
    srv = start_server(static_bundle)
    try:
        async def go():
            async with StreamClient.connect(srv.ws) as c:
                await c.view(CAM, 0, size_px=32)
                (pid,) = srv.workers()
                await c.send_view(CAM, 0, size_px=512, lossless=True)
                os.kill(pid, signal.SIGKILL)
                m = await c.next_message()
                deadline = time.monotonic() + 120
                while True:                                      # served again once it is back
                    try:
                        f = await c.view(CAM, 0, size_px=40, timeout=120)
                        break
                    except ServerError:
                        assert time.monotonic() < deadline
                        await asyncio.sleep(0.5)
                return m, f, pid
        m, f, pid = run(go())
        # Either the frame got out before the kill, or its client was told why it never will.
        assert (isinstance(m, dict) and m["code"] == "worker_restarted") or m.header.seq == 2
        assert f.rgba.shape == (40, 40, 4)
        assert srv.workers() and pid not in srv.workers()
    finally:
        srv.stop()


def test_a_damaged_bundle_is_refused_with_one_line_naming_it(static_bundle, tmp_path):
    bad = tmp_path / "bad_bundle"
    shutil.copytree(static_bundle, bad)
    p = bad / "model" / "plenoctree.npz"
    b = bytearray(p.read_bytes())
    b[len(b) // 2] ^= 0xFF
    p.write_bytes(bytes(b))
    res = subprocess.run([sys.executable, "-c", "from dbb_capture.cli.serve import main; main()", str(bad),
                          "--port", "0"], capture_output=True, text=True, timeout=240, check=False)
    assert res.returncode == 2
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert lines[-1].startswith("error:") and "bad_bundle" in lines[-1] and "sha256" in lines[-1]


def test_foreign_origin_is_refused_and_files_stay_in_their_folder(server, static_bundle, tmp_path):
    base = server.url.split("?")[0]
    with pytest.raises(InvalidStatus) as e:
        run(opened(server.ws, origin="http://evil.example"))
    assert e.value.response.status_code == 403
    glb = urllib.request.urlopen(base + "objects/0/proxy.glb").read()
    assert glb == (static_bundle / "proxy.glb").read_bytes()
    for path in ("objects/9/proxy.glb", "..%2f..%2fetc%2fpasswd", "%2e%2e/%2e%2e/etc/passwd", "//etc/passwd"):
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(base + path)
        assert e.value.code == 404, path
    # The resolver itself: nothing outside the root, no symlinks even to inside.
    root = tmp_path / "www"
    (root / "sub").mkdir(parents=True)
    (root / "index.html").write_text("hi")
    (root / "sub" / "a.js").write_text("x")
    (tmp_path / "secret.txt").write_text("s")
    (root / "link.txt").symlink_to(tmp_path / "secret.txt")
    (root / "inside.html").symlink_to(root / "index.html")
    roots = {"/": root}
    assert resolve_static(roots, "/") == root / "index.html"
    assert resolve_static(roots, "/sub/a.js") == root / "sub" / "a.js"
    for p in ("/../secret.txt", "/sub/../../secret.txt", "/link.txt", "/inside.html", "/sub//a.js",
              "/" + str(tmp_path / "secret.txt"), "/sub\\..\\..\\secret.txt", "/index.html\x00"):
        assert resolve_static(roots, p) is None, p


def test_non_loopback_needs_the_token_and_ctrl_c_stops_cleanly(static_bundle):
    srv = start_server(static_bundle, "--host", "0.0.0.0")
    try:
        assert "token=" in srv.url
        token = srv.url.split("token=")[1]
        local = f"ws://127.0.0.1:{srv.port}/ws"
        with pytest.raises(InvalidStatus) as e:
            run(opened(local))
        assert e.value.response.status_code == 401
        with pytest.raises(InvalidStatus):
            run(opened(local + "?token=wrong"))

        async def go():
            async with StreamClient.connect(f"{local}?token={token}") as c:
                return (await c.view(CAM, 0, size_px=24)).rgba.shape
        assert run(go()) == (24, 24, 4)
        workers = srv.workers()
        assert workers
    finally:
        rc = srv.stop(signal.SIGINT)
    assert rc == 0
    assert any("stopped" in x for x in srv.lines)
    time.sleep(0.5)
    for pid in workers:
        assert not os.path.exists(f"/proc/{pid}") or "zombie" in open(f"/proc/{pid}/status").read().lower()
