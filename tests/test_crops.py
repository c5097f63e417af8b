"""Crops: object centred, constant projected size, upright; resampling exact through distortion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dbb_capture.geometry.cameras import Intrinsics, project_points
from dbb_capture.geometry.transforms import look_at
from dbb_capture.crops.object import at_output, matte_scale, object_crop, premultiplied_down
from dbb_capture.crops.camera import crop_camera, crop_maps, cut_crop
from dbb_capture.crops.sequences import follows_previous, sequence_windows, split_by_time
from dbb_capture.geometry.viewpoint import up_from_cameras, viewpoint
from dbb_capture.synth.scene import SynthConfig, make_scene
from dbb_capture.synth.render import render_object_rgba

UP = np.array([0.0, 0.0, -1.0])
SRC = Intrinsics(640, 480, 520.0, 522.0, 321.4, 238.2, (-0.25, 0.07, 0.0006, -0.0004, -0.008))


def _camera(center, az, el, dist, roll_deg):
    import cv2

    a, e = np.radians(az), np.radians(el)
    eye = center + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), 0]) + dist * np.sin(e) * UP
    # Aim a little off the object so it is not at the image centre, and roll the camera.
    c2w = look_at(eye, center + np.array([0.03, -0.02, 0.01]), UP)
    c2w[:3, :3] = c2w[:3, :3] @ cv2.Rodrigues(np.array([0, 0, np.radians(roll_deg)]))[0]
    return c2w


POSES = [(-60, 15, 0.5, 4), (0, 45, 0.7, -3), (50, 70, 0.9, 6), (120, 30, 0.6, -8)]


@pytest.mark.parametrize("az, el, dist, roll", POSES)
def test_crop_geometry(az, el, dist, roll):
    center, radius = np.array([0.45, 0.12, -0.09]), 0.11
    c2w = _camera(center, az, el, dist, roll)
    cam = crop_camera(c2w, SRC, center, radius, UP, size=64, fill=0.9)
    # Centre exactly at the crop centre.
    uv = project_points(center, cam.c2w, cam.intr)
    assert np.allclose(uv, [31.5, 31.5], atol=1e-6)
    # The object's up points up in the crop.
    up_uv = project_points(center + 0.05 * UP, cam.c2w, cam.intr) - uv
    assert math.degrees(math.atan2(up_uv[0], -up_uv[1])) == pytest.approx(0, abs=1e-6)
    # The sphere's silhouette is a circle of radius fill * size / 2.
    eye = c2w[:3, 3]
    v = (center - eye) / np.linalg.norm(center - eye)
    a = np.cross(v, [0, 0, 1.0]); a /= np.linalg.norm(a)
    b = np.cross(v, a)
    D = np.linalg.norm(center - eye)
    # Tangent points of the sphere seen from the eye: a circle around the centre.
    ang = math.asin(radius / D)
    th = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    ring = center - v * radius * math.sin(ang) + radius * math.cos(ang) * (np.cos(th)[:, None] * a + np.sin(th)[:, None] * b)
    r_px = np.linalg.norm(project_points(ring, cam.c2w, cam.intr) - uv, axis=1)
    assert np.allclose(r_px, 0.9 * 32, rtol=1e-6)
    vp = viewpoint(eye, center, UP)
    assert vp.distance_m == pytest.approx(dist)
    assert vp.elevation_deg == pytest.approx(el, abs=1e-6)
    # Right-handed about up = -z: the board's -y side is at +90 degrees.
    assert ((vp.azimuth_deg + az + 180) % 360 - 180) == pytest.approx(0, abs=1e-6)


def test_crop_window_shrinks_with_distance():
    center = np.array([0.45, 0.12, -0.09])
    near = crop_camera(_camera(center, 0, 40, 0.5, 0), SRC, center, 0.1, UP)
    far = crop_camera(_camera(center, 0, 40, 1.0, 0), SRC, center, 0.1, UP)
    # ~ r / D: exactly tan(asin(r / D)), the sphere's apparent half-angle.
    expect = math.tan(math.asin(0.1 / 0.5)) / math.tan(math.asin(0.1 / 1.0))
    assert near.window_px / far.window_px == pytest.approx(expect, rel=1e-9)
    assert expect == pytest.approx(2.0, rel=0.05)


def test_cut_crop_centres_a_projected_point_through_distortion():

    center, radius = np.array([0.45, 0.12, -0.09]), 0.11
    for az, el, dist, roll in POSES:
        c2w = _camera(center, az, el, dist, roll)
        cam = crop_camera(c2w, SRC, center, radius, UP, size=64)
        # A small bright Gaussian blob at the object centre's projection in the source frame.
        u, v = project_points(center, c2w, SRC)
        yy, xx = np.mgrid[0:SRC.height, 0:SRC.width]
        sigma = 0.05 * cam.window_px
        blob = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma ** 2))
        img = np.round(255 * blob).astype(np.uint8)
        crop, touched = cut_crop(img[..., None].repeat(3, 2), cam, SRC, c2w)
        w = crop[..., 0].astype(float)
        cy, cx = (np.mgrid[0:64, 0:64] * w).reshape(2, -1).sum(1) / w.sum()
        assert abs(cx - 31.5) < 0.1 and abs(cy - 31.5) < 0.1, (az, cx, cy)
        assert not touched


@pytest.mark.parametrize("size", [128, 256])
def test_cut_crop_keeps_the_footage_detail(size):
    """Where a crop pixel spans about one source pixel (640x480 footage, 128 px crops and their
    2x matte), a grating of 4 source px keeps its contrast (bilinear taps keep ~0.8 of it: the
    outline blur issue 4 measured)."""
    import cv2

    src = Intrinsics(640, 480, 520.0, 522.0, 321.4, 238.2, (0.0,) * 5)
    center, radius = np.array([0.45, 0.12, -0.09]), 0.11
    c2w = _camera(center, 0, 45, 0.9, 0)
    cam = crop_camera(c2w, src, center, radius, UP, size=size)
    assert 0.5 < cam.window_px / size < 1.2                     # ~1 source pixel per crop pixel
    xx = np.mgrid[0:src.height, 0:src.width][1]
    wave = lambda x: 100 * np.sin(2 * np.pi * x / 4.0)
    crop, _ = cut_crop(np.round(127.5 + wave(xx)).astype(np.uint8)[..., None], cam, src, c2w)
    k = math.ceil(cam.window_px / size)           # cut_crop's samples per pixel (box-filtered)
    mx, my = crop_maps(cam, src, c2w, k)
    ideal = cv2.resize(wave(mx).astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    inside = cv2.resize(((mx > 2) & (mx < src.width - 3) & (my > 2) & (my < src.height - 3)).astype(np.float32),
                        (size, size), interpolation=cv2.INTER_AREA) == 1
    ideal, got = ideal[inside], crop.reshape(size, size).astype(float)[inside] - 127.5
    assert (got * ideal).sum() / (ideal ** 2).sum() > 0.95


def test_cut_crop_equals_rendering_the_crop_camera():
    """Cropping a distorted frame of the object = rendering the object with the crop camera."""
    cfg = SynthConfig(kind="static")
    scene = make_scene(cfg, np.random.default_rng(2))
    center, radius = scene.obj_sphere
    c2w = _camera(center, -20, 35, 0.55, 5)
    cam = crop_camera(c2w, SRC, center, radius, UP, size=64)
    frame = render_object_rgba(scene.obj, SRC, c2w, 0.0, samples=2)
    crop, _ = cut_crop(frame, cam, SRC, c2w)
    direct = render_object_rgba(scene.obj, cam.intr, cam.c2w, 0.0, samples=4)
    a, b = crop[..., 3] / 255.0, direct[..., 3] / 255.0
    iou = np.minimum(a, b).sum() / np.maximum(a, b).sum()
    assert iou > 0.93, iou
    both = (a > 0.9) & (b > 0.9)
    assert np.abs(crop[both, :3].astype(int) - direct[both, :3].astype(int)).mean() < 8


def test_crop_touching_the_border_is_flagged_and_padded():
    center, radius = np.array([0.45, 0.12, -0.09]), 0.11
    c2w = look_at(center + np.array([0.0, -0.25, -0.2]), center + np.array([0.25, 0, 0]), UP)
    cam = crop_camera(c2w, SRC, center, radius, UP)
    img = np.full((SRC.height, SRC.width, 4), 255, np.uint8)
    crop, touched = cut_crop(img, cam, SRC, c2w)
    assert touched and crop[..., 3].min() == 0 and crop[..., 3].max() == 255


def test_up_from_cameras():
    c2w = np.stack([np.eye(4)] * 3)
    c2w[:, 2, 3] = [-0.5, -0.4, 0.1]
    assert np.allclose(up_from_cameras(c2w), [0, 0, -1])
    c2w[:, 2, 3] = [0.5, 0.4, -0.1]
    assert np.allclose(up_from_cameras(c2w), [0, 0, 1])


def test_split_and_windows_respect_time_gaps_and_splits():
    t = np.arange(40) * 0.1
    t = np.delete(t, [15])                      # a dropped frame breaks sequences through it
    split = split_by_time(t, 0.2)
    assert (split == "test").sum() == 8 and split[-1] == "test" and split[0] == "train"
    wins = sequence_windows(t, split, length=11)
    starts = [s for s, _ in wins]
    for s, sp in wins:
        assert np.allclose(np.diff(t[s:s + 11]), 0.1) and len(set(split[s:s + 11])) == 1
    assert 0 in starts and 4 in starts and 5 not in starts    # 4..14 fits before the gap
    assert 15 in starts                                       # starts right after the gap


def test_follows_previous_breaks_at_gaps():
    """The matte's temporal vote links a crop only to frames right next to it in time."""
    t = np.array([0.0, 0.1, 0.2, 0.5, 0.6, 0.7])        # frames 0.3 and 0.4 dropped
    assert follows_previous(t).tolist() == [False, True, True, False, True, True]
    assert follows_previous(np.array([1.0])).tolist() == [False]


def test_resized_crop_camera_sees_the_same_rays():
    """A crop camera at twice the size: the same view, pixel centres where the box filter puts them."""
    center, radius = np.array([0.45, 0.12, -0.09]), 0.11
    c2w = _camera(center, 30, 40, 0.6, 3)
    cam = crop_camera(c2w, SRC, center, radius, UP, size=64, fill=0.9)
    big = cam.resized(128)
    assert big.intr.width == 128 and big.window_px == cam.window_px
    pts = center + np.array([[0.0, 0, 0], [0.05, -0.03, 0.02], [-0.04, 0.06, -0.05]])
    uv, uv2 = project_points(pts, cam.c2w, cam.intr), project_points(pts, big.c2w, big.intr)
    assert np.allclose(uv2, 2 * uv + 0.5, atol=1e-6)          # fine pixel 2i, 2i+1 average to coarse i
    assert np.allclose(big.resized(64).intr.K, cam.intr.K)
    assert crop_camera(c2w, SRC, center, radius, UP, size=128, fill=0.9).intr.fx == pytest.approx(big.intr.fx)


def test_premultiplied_down_keeps_the_object_colour_at_the_outline():
    fine = np.zeros((4, 4, 4), np.uint8)
    fine[..., :3] = (255, 0, 0)                # the room's colour behind transparent pixels
    fine[:, :3] = (0, 0, 200, 255)              # the object: three columns of four
    out = premultiplied_down(fine, 2)
    assert out.shape == (2, 2, 4)
    assert (out[:, 0] == (0, 0, 200, 255)).all()
    assert (out[:, 1, :3] == (0, 0, 200)).all() and (out[:, 1, 3] == 128).all()   # half covered, no red


def test_matte_scale_is_one_per_capture_and_only_for_small_windows():
    assert matte_scale(np.array([150.0, 180, 230]), 64, (1.0, 6.0)) == 2     # 640x480: ~3 source px a crop px
    assert matte_scale(np.array([450.0, 576, 700]), 64, (1.0, 6.0)) == 1     # 1920x1440: the 1x matte, real time
    assert matte_scale(np.array([150.0, 180, 230]), 128, (1.0, 6.0)) == 2    # ~1.4: bicubic taps upsample it
    assert matte_scale(np.array([150.0, 180, 230]), 256, (1.0, 6.0)) == 1    # the doubled crop would over-resolve
    assert matte_scale(np.array([180.0]), 64, (0.0, 0.0)) == 1                # turned off
    assert matte_scale(np.zeros(0), 64, (1.0, 6.0)) == 1


def test_object_crop_at_twice_the_size_averages_down_to_the_output_crop():
    """Matted at 2x, the crop brought to its output size is the crop cut at that size, with the
    same camera, and its alpha is the object's coverage."""
    cfg = SynthConfig(kind="static")
    scene = make_scene(cfg, np.random.default_rng(3))
    center, radius = scene.obj_sphere
    c2w = _camera(center, 10, 40, 0.6, -4)
    rgba = render_object_rgba(scene.obj, SRC, c2w, 0.0, samples=2)
    room = np.array([90, 140, 60], np.float32)
    a = rgba[..., 3:] / 255.0
    frame = np.round(rgba[..., :3] * a + room * (1 - a)).astype(np.uint8)
    predict = lambda cam: np.broadcast_to(room.astype(np.uint8), (cam.intr.height, cam.intr.width, 3)).copy()
    oc = object_crop(frame, SRC, c2w, center, radius, UP, 48, 0.9, predict, scale=2)
    assert oc.scale == 2 and oc.observed.shape == (96, 96, 3)
    out = at_output(oc)
    cam = crop_camera(c2w, SRC, center, radius, UP, size=48, fill=0.9)
    assert out.scale == 1 and out.rgba.shape == (48, 48, 4) and np.allclose(out.cam.intr.K, cam.intr.K)
    assert np.abs(out.observed.astype(int) - cut_crop(frame, cam, SRC, c2w)[0].astype(int)).mean() < 2
    truth = cut_crop(rgba, cam, SRC, c2w)[0][..., 3] > 127
    got = out.rgba[..., 3] > 127
    assert (truth & got).sum() / (truth | got).sum() > 0.95
