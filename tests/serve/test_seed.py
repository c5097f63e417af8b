"""The thesis's TCP protocol, fed the exact bytes its published Unity client (ControlBillboard.cs) sends."""

from __future__ import annotations

import socket

import cv2
import numpy as np

from dbb_capture.serve.seed import VIEW, bundle_eye, parse_request


def unity_request(rel_pos, quat_xyzw=(0.0, 0.0, 0.0, 1.0), mode: int | None = 0) -> bytes:
    """What ControlBillboard.cs writes: (z, -x, y) of the camera relative to the billboard, the
    billboard's rotation as (-w, z, -x, y), the mode; C#'s float ToString, comma-joined, UTF-8."""
    x, y, z = rel_pos
    qx, qy, qz, qw = quat_xyzw
    vals = [z, -x, y, -qw, qz, -qx, qy] + ([] if mode is None else [float(mode)])
    return ",".join(f"{v:g}" for v in vals).encode("utf-8")


def exchange(port: int, data: bytes, sock: socket.socket | None = None) -> tuple[bytes, bytes]:
    """Send one request; read the reply as the client's single Read does (here: until the PNG ends)."""
    s = sock or socket.create_connection(("127.0.0.1", port), timeout=60)
    s.sendall(data)
    buf = b""
    while not buf.endswith(b"IEND\xaeB`\x82"):
        chunk = s.recv(4194304)
        assert chunk, "the server closed the connection"
        buf += chunk
    if sock is None:
        s.close()
    return buf[:8 + int(buf[:8])], buf[8 + int(buf[:8]):]


def test_request_parsing_and_the_unity_frame():
    assert parse_request(b"0.5,-0.25,0.3,-1,0,0,0,2") == [0.5, -0.25, 0.3, -1, 0, 0, 0, 2]
    assert parse_request(b"1,2,3,4,5,6,7") is not None
    for bad in (b"1,2,3", b"1,2,3,4,5,6,7,8,9", b"a,b,c,d,e,f,g", b"1,2,3,4,5,6,nan", b"1,2,3,4,5,6,7,5", b"\xff"):
        assert parse_request(bad) is None
    # Unity: camera 1 m in front (+z, Unity's forward) and 0.5 m up of the billboard -> bundle space
    # (glTF axes: Unity's forward is -Z).
    assert np.allclose(bundle_eye(parse_request(unity_request((0, 0.5, 1.0)))), [0, 0.5, -1.0])
    assert np.allclose(bundle_eye(parse_request(unity_request((0.3, 0, 0)))), [0.3, 0, 0])


def test_each_mode_gives_a_png_of_its_kind(server):
    port = server.seed_port
    header, png = exchange(port, unity_request((0.2, 0.3, 0.5), mode=0))
    assert header == b"0023    " + VIEW and len(VIEW) == 23
    rgba = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert rgba.shape == (256, 256, 4)
    assert rgba[..., 3].min() == 0 and rgba[..., 3].max() > 200          # transparent around the object

    _, png = exchange(port, unity_request((0.2, 0.3, 0.5), mode=1))
    border = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert border.shape == (256, 256, 4)
    for edge in (border[0], border[-1], border[:, 0], border[:, -1]):
        assert (edge == 255).all()
    assert np.array_equal(border[1:-1, 1:-1], rgba[1:-1, 1:-1])

    _, png = exchange(port, unity_request((0.2, 0.3, 0.5), mode=2))
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert bgr.shape == (256, 256, 3)
    a = rgba[..., 3:].astype(np.float32) / 255
    assert np.abs(bgr.astype(np.float32) - rgba[..., :3] * a).max() <= 1.01   # colour on black

    _, png7 = exchange(port, unity_request((0.2, 0.3, 0.5), mode=None))      # 7 numbers: mode 0
    assert np.array_equal(cv2.imdecode(np.frombuffer(png7, np.uint8), cv2.IMREAD_UNCHANGED), rgba)
    assert len(png) < 4194304 and len(png7) < 4194304                      # fits the client's one Read


def test_one_connection_many_frames_a_still_pose_resent_and_the_object_keeps_its_size(server):
    with socket.create_connection(("127.0.0.1", server.seed_port), timeout=60) as s:
        near = exchange(0, unity_request((0, 0.2, 0.4)), s)[1]
        same = exchange(0, unity_request((0, 0.2, 0.4 + 1e-7)), s)[1]
        far = exchange(0, unity_request((0, 0.4, 0.8)), s)[1]
    assert same == near
    a_near = cv2.imdecode(np.frombuffer(near, np.uint8), cv2.IMREAD_UNCHANGED)[..., 3] > 128
    a_far = cv2.imdecode(np.frombuffer(far, np.uint8), cv2.IMREAD_UNCHANGED)[..., 3] > 128
    # The thesis's server scales the focal length with distance: twice as far, about the same size.
    assert 0.8 < a_far.sum() / a_near.sum() < 1.25


def test_dynamic_object_on_its_own_port_and_bad_bytes_close_only_that_connection(server):
    _, png = exchange(server.seed_port + 1, unity_request((0.1, 0.3, 0.6)))
    assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED).shape[2] == 4
    with socket.create_connection(("127.0.0.1", server.seed_port), timeout=30) as s:
        s.sendall(b"hello, server")
        assert s.recv(100) == b""                                           # closed
    _, png = exchange(server.seed_port, unity_request((0.1, 0.3, 0.6)))     # the port still serves
    assert server.proc.poll() is None
