"""Mattes from a predicted background match the true object masks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dbb_capture.crops import crop_camera, cut_crop
from dbb_capture.matte import colour_distance, matte, sphere_disc
from dbb_capture.synth import UP, Renderer, SynthConfig, make_scene, render_object_rgba, sensor
from dbb_capture.cameras import look_at


@pytest.fixture(scope="module")
def frames():
    cfg = SynthConfig(kind="static", width=640, height=480)
    scene = make_scene(cfg, np.random.default_rng(7))
    intr = cfg.intrinsics()
    r = Renderer(intr, 2)
    rng = np.random.default_rng(0)
    center, radius = scene.obj_sphere
    out = []
    for eye_off in ([0.0, -0.45, -0.35], [0.35, -0.3, -0.2]):
        c2w = look_at(center + np.array(eye_off), center, UP)
        img, _ = r.render(scene, c2w, 0.0)
        clean, _ = r.render(scene.without_object(), c2w, 0.0)
        cam = crop_camera(c2w, intr, center, radius, UP, size=128, fill=0.9)
        obs, _ = cut_crop(sensor(img, 0.01, rng), cam, intr, c2w)
        bg, _ = cut_crop(sensor(clean, 0.01, rng), cam, intr, c2w)
        truth = render_object_rgba(scene.obj, cam.intr, cam.c2w, 0.0, samples=3)[..., 3] >= 128
        out.append((obs, bg, truth))
    return out


def _iou(rgba, truth):
    a = rgba[..., 3] >= 128
    return (a & truth).sum() / (a | truth).sum()


def test_matte_with_exact_background(frames):
    disc = sphere_disc(128, 0.9, 1.04)
    for obs, bg, truth in frames:
        assert _iou(matte(obs, bg, disc), truth) > 0.95


def test_matte_with_blurred_misregistered_background(frames):
    """A background field's prediction is blurrier, a little off and a little darker."""
    disc = sphere_disc(128, 0.9, 1.04)
    for obs, bg, truth in frames:
        pred = cv2.GaussianBlur(bg, (0, 0), 1.0)
        pred = np.roll(pred, 1, axis=1)
        pred = np.clip(pred.astype(float) * 0.97, 0, 255).astype(np.uint8)
        assert _iou(matte(obs, pred, disc), truth) > 0.88


def test_matte_is_straight_alpha_with_object_colours(frames):
    obs, bg, truth = frames[0]
    rgba = matte(obs, bg, sphere_disc(128, 0.9, 1.04))
    inner = cv2.erode(truth.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert (rgba[inner, 3] == 255).mean() > 0.98
    solid = rgba[..., 3] == 255
    assert np.abs(rgba[solid, :3].astype(int) - obs[solid].astype(int)).max() <= 1
    assert (rgba[..., 3][~sphere_disc(128, 0.9, 1.04)] == 0).all()


def test_colour_distance_ignores_one_pixel_shifts():
    rng = np.random.default_rng(0)
    img = (rng.random((32, 32, 3)) * 255).astype(np.uint8)
    img = cv2.GaussianBlur(img, (0, 0), 2)
    shifted = np.roll(img, 1, axis=0)
    assert colour_distance(img, shifted, 1)[2:-2, 2:-2].max() < 1e-6
    assert colour_distance(img, shifted, 0)[2:-2, 2:-2].max() > 0.01
