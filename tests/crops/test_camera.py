"""Crop cameras: distance-normalized, upright, each its own pinhole; the resampling into them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dbb_capture.crops.camera import crop_camera, crop_maps, cut_crop
from dbb_capture.geometry.cameras import Intrinsics, project_points
from dbb_capture.geometry.transforms import look_at
from dbb_capture.geometry.viewpoint import viewpoint
from dbb_capture.synth.render import render_object_rgba
from dbb_capture.synth.scene import SynthConfig, make_scene

from .conftest import POSES, SRC, UP, camera_pose


@pytest.mark.parametrize("az, el, dist, roll", POSES)
def test_crop_geometry(az, el, dist, roll):
    center, radius = np.array([0.45, 0.12, -0.09]), 0.11
    c2w = camera_pose(center, az, el, dist, roll)
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
    near = crop_camera(camera_pose(center, 0, 40, 0.5, 0), SRC, center, 0.1, UP)
    far = crop_camera(camera_pose(center, 0, 40, 1.0, 0), SRC, center, 0.1, UP)
    # ~ r / D: exactly tan(asin(r / D)), the sphere's apparent half-angle.
    expect = math.tan(math.asin(0.1 / 0.5)) / math.tan(math.asin(0.1 / 1.0))
    assert near.window_px / far.window_px == pytest.approx(expect, rel=1e-9)
    assert expect == pytest.approx(2.0, rel=0.05)


def test_cut_crop_centres_a_projected_point_through_distortion():

    center, radius = np.array([0.45, 0.12, -0.09]), 0.11
    for az, el, dist, roll in POSES:
        c2w = camera_pose(center, az, el, dist, roll)
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
    c2w = camera_pose(center, 0, 45, 0.9, 0)
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
    c2w = camera_pose(center, -20, 35, 0.55, 5)
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


def test_resized_crop_camera_sees_the_same_rays():
    """A crop camera at twice the size: the same view, pixel centres where the box filter puts them."""
    center, radius = np.array([0.45, 0.12, -0.09]), 0.11
    c2w = camera_pose(center, 30, 40, 0.6, 3)
    cam = crop_camera(c2w, SRC, center, radius, UP, size=64, fill=0.9)
    big = cam.resized(128)
    assert big.intr.width == 128 and big.window_px == cam.window_px
    pts = center + np.array([[0.0, 0, 0], [0.05, -0.03, 0.02], [-0.04, 0.06, -0.05]])
    uv, uv2 = project_points(pts, cam.c2w, cam.intr), project_points(pts, big.c2w, big.intr)
    assert np.allclose(uv2, 2 * uv + 0.5, atol=1e-6)          # fine pixel 2i, 2i+1 average to coarse i
    assert np.allclose(big.resized(64).intr.K, cam.intr.K)
    assert crop_camera(c2w, SRC, center, radius, UP, size=128, fill=0.9).intr.fx == pytest.approx(big.intr.fx)


def test_crop_size_follows_the_footage_within_its_bounds():
    from dbb_capture.crops.camera import crop_size_for

    # a crop pixel spans at least one source pixel: the median window rounded down to 16 px
    assert crop_size_for(np.array([150.0, 191.0, 400.0]), 512) == 176
    assert crop_size_for(np.array([176.0]), 512) == 176
    assert crop_size_for(np.array([900.0]), 512) == 512 and crop_size_for(np.array([5.0]), 512) == 32


def test_the_crop_size_is_given_chosen_or_the_rssm_s():
    from dbb_capture.dynamic.config import RssmConfig
    from dbb_capture.preprocess.inputs import DYNAMIC_CROP_SIZE, PreprocessConfig

    w = np.array([300.0, 310.0])
    assert PreprocessConfig().crop_size_for(w, None)[0] == 304
    assert PreprocessConfig().crop_size_for(w, "static")[0] == 304
    assert PreprocessConfig(max_crop_size=256).crop_size_for(w, None) == (
        256, "from the footage: the object's crop window spans 305 source pixels (median), capped by the maximum 256 px")
    assert PreprocessConfig().crop_size_for(w, "dynamic")[0] == DYNAMIC_CROP_SIZE == RssmConfig().size
    assert PreprocessConfig(crop_size=96).crop_size_for(w, "dynamic") == (96, "given")
