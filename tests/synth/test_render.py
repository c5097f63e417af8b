"""Rendering synthetic scenes: the board's pose, the object's silhouette, anti-aliasing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dbb_capture.capture.board import BoardSpec
from dbb_capture.synth.render import Renderer, sensor
from dbb_capture.synth.scene import SynthConfig, make_scene

from .conftest import pose_on_sphere, silhouette_mask, solve_board_pose


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
        c2w = pose_on_sphere(board.center, 0.6, az, el, roll)
        img, _ = r.render(scene, c2w, 0.0)
        gray = cv2.cvtColor(sensor(img, cfg.noise, rng), cv2.COLOR_RGB2GRAY)
        est, n = solve_board_pose(gray, board, intr)
        cosang = (np.trace(est[:3, :3].T @ c2w[:3, :3]) - 1) / 2
        rot_err = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
        trans_err_mm = 1000 * np.linalg.norm(est[:3, 3] - c2w[:3, 3])
        assert rot_err < 0.1, (az, el, rot_err, n)
        assert trans_err_mm < 1.0, (az, el, trans_err_mm, n)


@pytest.mark.parametrize("kind, dist", [("static", (0, 0, 0, 0, 0)), ("dynamic", (-0.2, 0.04, 0, 0, 0))])
def test_masks_equal_projected_object_geometry(kind, dist):
    cfg = SynthConfig(kind=kind, width=480, height=360, dist=dist)
    scene = make_scene(cfg, np.random.default_rng(5))
    intr = cfg.intrinsics()
    r = Renderer(intr, 3)
    for t, (az, el) in [(0.0, (0, 30)), (1.3, (-50, 15)), (4.1, (45, 70))]:
        c2w = pose_on_sphere(scene.obj_sphere[0], 0.45, az, el)
        _, cover = r.render(scene, c2w, t)
        truth = silhouette_mask(scene.obj, t, c2w, intr)
        rendered = cover >= 0.5
        iou = (rendered & truth).sum() / (rendered | truth).sum()
        assert truth.sum() > 2000 and iou > 0.985, (t, iou)
        # Disagreements only on the silhouette's edge: coverage there is fractional.
        wrong = rendered != truth
        assert np.all((cover[wrong] > 0.05) & (cover[wrong] < 0.95)) or wrong.sum() < 0.002 * truth.sum()


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
        c2w = pose_on_sphere(target, 0.6, az, el, 3.0)
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
