"""Generator truth: what the synthetic renderer draws is where its ground truth says.

In the style of OpenCV's ChArUco tests: render the board from known poses, detect it with plain
OpenCV, and require the recovered pose to match; project the object's geometry independently
(cv2.projectPoints of each ellipsoid's silhouette) and require the masks to match.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from dbb_capture.capture.board import BoardSpec
from dbb_capture.geometry.transforms import invert_rigid, look_at
from dbb_capture.geometry.conventions import opencv_from_opengl
from dbb_capture.synth.objects import UP
from dbb_capture.synth.render import Renderer, render_object_rgba, sensor
from dbb_capture.synth.scene import SynthConfig, make_scene
from dbb_capture.synth.capture import load_ground_truth


def _pose_on_sphere(center, dist, az_deg, el_deg, roll_deg=0.0):
    az, el = np.radians(az_deg), np.radians(el_deg)
    fwd, side = np.array([0.0, -1, 0]), np.array([1.0, 0, 0])
    eye = center + dist * (np.cos(el) * (np.cos(az) * fwd + np.sin(az) * side) + np.sin(el) * UP)
    c2w = look_at(eye, center, UP)
    Rz, _ = cv2.Rodrigues(np.array([0, 0, np.radians(roll_deg)]))
    c2w[:3, :3] = c2w[:3, :3] @ Rz
    return c2w


def _solve_board_pose(gray, board: BoardSpec, intr):
    det = cv2.aruco.CharucoDetector(board.cv_board())
    corners, ids, _, _ = det.detectBoard(gray)
    assert ids is not None and len(ids) >= 12, "board not detected"
    obj, img = board.cv_board().matchImagePoints(corners, ids)
    ok, rvec, tvec = cv2.solvePnP(obj, img, intr.K, intr.dist_array, flags=cv2.SOLVEPNP_IPPE)
    assert ok
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, intr.K, intr.dist_array, rvec, tvec)
    w2c = np.eye(4)
    w2c[:3, :3] = cv2.Rodrigues(rvec)[0]
    w2c[:3, 3] = tvec.ravel()
    return invert_rigid(w2c), len(ids)


@pytest.mark.parametrize("board, dist", [
    (BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"), (0, 0, 0, 0, 0)),
    (BoardSpec(6, 8, 0.035, 0.026, "DICT_6X6_250", legacy_pattern=True), (-0.12, 0.05, 0.0008, -0.0005, 0)),
    (BoardSpec(5, 5, 0.06, 0.04, "DICT_APRILTAG_36h11"), (0.05, -0.02, 0, 0, 0)),
])
def test_opencv_recovers_rendered_board_pose(board, dist):
    cfg = SynthConfig(kind="static", width=1280, height=960, board=board, dist=dist)
    scene = make_scene(cfg, np.random.default_rng(1))
    intr = cfg.intrinsics()
    r = Renderer(intr, 2)
    rng = np.random.default_rng(2)
    for az, el, roll in [(0, 70, 0), (-35, 50, 3), (40, 45, -4)]:
        c2w = _pose_on_sphere(board.center, 0.6, az, el, roll)
        img, _ = r.render(scene, c2w, 0.0)
        gray = cv2.cvtColor(sensor(img, cfg.noise, rng), cv2.COLOR_RGB2GRAY)
        est, n = _solve_board_pose(gray, board, intr)
        cosang = (np.trace(est[:3, :3].T @ c2w[:3, :3]) - 1) / 2
        rot_err = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
        trans_err_mm = 1000 * np.linalg.norm(est[:3, 3] - c2w[:3, 3])
        assert rot_err < 0.1, (az, el, rot_err, n)
        assert trans_err_mm < 1.0, (az, el, trans_err_mm, n)


def _silhouette_mask(model, t, c2w, intr, n=720):
    """The object's silhouette drawn from projected contour points of every ellipsoid (H, W) bool.

    Independent of the renderer's ray casting: the contour of an ellipsoid seen from a point
    is the circle where the polar plane of the eye cuts it (in the ellipsoid's unit-sphere
    frame); its points are projected with cv2.projectPoints (distortion included) and filled.
    """
    from matplotlib.path import Path as PolyPath

    w2c = invert_rigid(c2w)
    rvec = cv2.Rodrigues(w2c[:3, :3])[0]
    mask = np.zeros((intr.height, intr.width), bool)
    for c, R, e in model.posed(t):
        r = np.asarray(e.radii)
        o = (R.T @ (c2w[:3, 3] - c)) / r
        o2 = o @ o
        center, rho = o / o2, np.sqrt(1 - 1 / o2)
        a = np.cross(o, [1.0, 0, 0] if abs(o[0]) < 0.9 * np.sqrt(o2) else [0, 1.0, 0])
        a /= np.linalg.norm(a)
        b = np.cross(o / np.sqrt(o2), a)
        th = np.linspace(0, 2 * np.pi, n, endpoint=False)
        q = center + rho * (np.cos(th)[:, None] * a + np.sin(th)[:, None] * b)
        pts = c + (q * r) @ R.T
        uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, w2c[:3, 3], intr.K, intr.dist_array)
        # A pixel is inside when its centre (integer coordinates, OpenCV) is inside the contour.
        uv = uv.reshape(-1, 2)
        x0, y0 = np.maximum(np.floor(uv.min(0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(uv.max(0)).astype(int) + 1, [intr.width, intr.height])
        if x1 <= x0 or y1 <= y0:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        inside = PolyPath(uv).contains_points(np.stack([xx.ravel(), yy.ravel()], 1).astype(float))
        mask[y0:y1, x0:x1] |= inside.reshape(yy.shape)
    return mask


@pytest.mark.parametrize("kind, dist", [("static", (0, 0, 0, 0, 0)), ("dynamic", (-0.2, 0.04, 0, 0, 0))])
def test_masks_equal_projected_object_geometry(kind, dist):
    cfg = SynthConfig(kind=kind, width=480, height=360, dist=dist)
    scene = make_scene(cfg, np.random.default_rng(5))
    intr = cfg.intrinsics()
    r = Renderer(intr, 3)
    for t, (az, el) in [(0.0, (0, 30)), (1.3, (-50, 15)), (4.1, (45, 70))]:
        c2w = _pose_on_sphere(scene.obj_sphere[0], 0.45, az, el)
        _, cover = r.render(scene, c2w, t)
        truth = _silhouette_mask(scene.obj, t, c2w, intr)
        rendered = cover >= 0.5
        iou = (rendered & truth).sum() / (rendered | truth).sum()
        assert truth.sum() > 2000 and iou > 0.985, (t, iou)
        # Disagreements only on the silhouette's edge: coverage there is fractional.
        wrong = rendered != truth
        assert np.all((cover[wrong] > 0.05) & (cover[wrong] < 0.95)) or wrong.sum() < 0.002 * truth.sum()


def test_written_capture_is_consistent(tiny_dynamic_capture):
    import av

    cap = tiny_dynamic_capture
    intr, cams, model = load_ground_truth(cap)
    board = BoardSpec.load(cap / "board.json")
    sphere = json.loads((cap / "object.json").read_text())
    frames = cams["video"]
    assert len(frames) == 15 and cams["background"] == []
    assert not (cap / "background.mp4").exists()
    with av.open(str(cap / "video.mp4")) as c:
        decoded = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(decoded) == len(frames) and decoded[0].shape == (240, 320, 3)
    assert np.allclose(np.diff([f["time"] for f in frames]), 0.2)
    # The bounding sphere holds every ellipsoid at every frame time.
    c, rad = np.array(sphere["center"]), sphere["radius"]
    u = np.random.default_rng(0).standard_normal((500, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    for f in frames:
        for ce, R, e in model.posed(f["time"]):
            surface = ce + (u * np.asarray(e.radii)) @ R.T
            assert np.linalg.norm(surface - c, axis=1).max() <= rad + 1e-6
    # Ground-truth RGBA renders agree with the stored masks, and the decoded video shows the
    # object where the mask says (object pixels differ from the clean-plate-free board region).
    ious = []
    for i in (0, 7, 14):
        c2w = opencv_from_opengl(np.array(frames[i]["transform_matrix"]))
        rgba = render_object_rgba(model, intr, c2w, frames[i]["time"], samples=2)
        mask = cv2.imread(str(cap / "ground_truth" / "masks" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED)
        a, m = rgba[..., 3] >= 128, mask >= 128
        ious.append((a & m).sum() / max((a | m).sum(), 1))
        assert np.abs(decoded[i][m].astype(int) - rgba[m][:, :3].astype(int)).mean() < 12
    assert min(ious) > 0.99
    assert board.dictionary == "DICT_5X5_100"


def test_clean_plate_has_no_object(tiny_static_capture):
    import av

    cap = tiny_static_capture
    _, cams, _ = load_ground_truth(cap)
    assert len(cams["background"]) == 5
    with av.open(str(cap / "background.mp4")) as c:
        n = sum(1 for _ in c.decode(video=0))
    assert n == 5
    # The clean plate's path differs from the object video's.
    a = np.array(cams["video"][0]["transform_matrix"])
    b = np.array(cams["background"][0]["transform_matrix"])
    assert np.linalg.norm(a[:3, 3] - b[:3, 3]) > 0.01


def test_worker_processes_render_the_same_capture(tmp_path):
    import av
    from dbb_capture.synth.capture import write_capture

    outs = []
    for workers in (1, 2):
        cfg = SynthConfig(kind="dynamic", seconds=0.8, fps=5, width=160, height=120,
                          background_seconds=0.4, seed=9, workers=workers)
        write_capture(cfg, tmp_path / f"w{workers}")
        with av.open(str(tmp_path / f"w{workers}" / "video.mp4")) as c:
            outs.append(np.stack([f.to_ndarray(format="rgb24") for f in c.decode(video=0)]))
        masks = sorted((tmp_path / f"w{workers}" / "ground_truth" / "masks").iterdir())
        outs.append(np.stack([cv2.imread(str(m), cv2.IMREAD_UNCHANGED) for m in masks]))
    assert outs[0].shape == (4, 120, 160, 3)
    assert np.array_equal(outs[0], outs[2]) and np.array_equal(outs[1], outs[3])


def test_adaptive_antialiasing_matches_brute_force():
    """Supersampling only the pixels an edge or texture step crosses: as close to a 4x4 render
    as brute-force 2x2 is, with the same fractional coverage on the object's silhouette."""
    cfg = SynthConfig(kind="dynamic", width=320, height=240)
    scene = make_scene(cfg, np.random.default_rng(3))
    intr = cfg.intrinsics()
    adaptive, brute, ref, single = (Renderer(intr, 2), Renderer(intr, 2, adaptive=False),
                                    Renderer(intr, 4, adaptive=False), Renderer(intr, 1))
    target = 0.5 * (scene.obj_sphere[0] + scene.board.center)
    for t, (az, el) in [(0.0, (0, 35)), (2.3, (-40, 60))]:
        c2w = _pose_on_sphere(target, 0.6, az, el, 3.0)
        img, cover = adaptive.render(scene, c2w, t)
        b_img, b_cover = brute.render(scene, c2w, t)
        r_img, _ = ref.render(scene, c2w, t)
        s_img, _ = single.render(scene, c2w, t)
        assert 0.01 < adaptive.refined < 0.6, adaptive.refined
        mad, b_mad, s_mad = (np.abs(x - r_img).mean() * 255 for x in (img, b_img, s_img))
        assert mad < 1.25 * b_mad + 0.05 and mad < 0.7 * s_mad, (mad, b_mad, s_mad)
        # Silhouette pixels: a proper coverage average (the brute-force one), not 0 or 1.
        edge = (b_cover > 0) & (b_cover < 1)
        assert edge.sum() > 50 and np.mean(cover[edge] == b_cover[edge]) > 0.98
        assert np.allclose(img[edge], b_img[edge], atol=1e-5)
