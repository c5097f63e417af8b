"""One frame's object crop: the matte's scale and the averaging down to the output."""

from __future__ import annotations

import numpy as np

from dbb_capture.crops.camera import crop_camera, cut_crop
from dbb_capture.crops.object import (
    at_output,
    matte_config_at,
    matte_scale,
    object_crop,
    premultiplied_down,
)
from dbb_capture.synth.render import render_object_rgba
from dbb_capture.synth.scene import SynthConfig, make_scene

from .conftest import SRC, UP, camera_pose


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
    c2w = camera_pose(center, 10, 40, 0.6, -4)
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


def test_matte_config_at_twice_the_size_spreads_the_band_over_the_resampled_outline():
    """At 2x the fractional band reaches ``supersampled_spread`` source pixels to each side (at
    least one output pixel) and is ramped; at 1x the settings are untouched."""
    from dataclasses import replace

    from dbb_capture.crops.matte import MatteConfig

    cfg = MatteConfig()
    cam = crop_camera(camera_pose(np.zeros(3), 10, 40, 0.6, -4), SRC, np.zeros(3), 0.1, UP, size=64, fill=0.9)
    fine = replace(cam, intr=replace(cam.intr, width=640, height=640), window_px=327.0)   # 1 source px a crop px
    coarse = replace(cam, intr=replace(cam.intr, width=128, height=128), window_px=205.0)  # 3.2 source px a crop px
    assert matte_config_at(cfg, 1, cam) is cfg
    at_fine, at_coarse = matte_config_at(cfg, 2, fine), matte_config_at(cfg, 2, coarse)
    assert at_fine.edge_px == 4 and at_coarse.edge_px == 2
    assert at_fine.edge_ramp == at_coarse.edge_ramp == cfg.supersampled_ramp != (0.0, 1.0)
