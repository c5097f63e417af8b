"""Mattes against a predicted room: exact, blurred or misregistered rooms, guesses, noise, rims."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from dbb_capture.crops.camera import crop_camera, cut_crop
from dbb_capture.crops.matte import (
    CaptureMatte,
    MatteConfig,
    capture_matte,
    colour_distance,
    local_variation,
    matte,
    matte_and_noise,
    noise_level,
    noise_map,
    room_by_colour,
    room_detail,
    sharp_distance,
    sphere_disc,
    sure_object_counts,
    temporal_median,
)
from dbb_capture.geometry.transforms import look_at
from dbb_capture.synth.objects import UP
from dbb_capture.synth.render import Renderer, render_object_rgba, sensor
from dbb_capture.synth.scene import SynthConfig, make_scene


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


def _table_scene(size=64, seed=0):
    """A striped table (two browns), a blue object disc in the middle, a band of table below it."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    stripes = (np.sin(yy / 2.5 + 0.3 * np.sin(xx / 7)) > 0)[..., None]
    room = np.where(stripes, [150, 90, 50], [95, 55, 35]).astype(np.float64)
    obj = (xx - 32) ** 2 + (yy - 30) ** 2 <= 11 ** 2
    obs = np.where(obj[..., None], [40, 70, 200], room)
    noisy = lambda im: np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8)
    return noisy(obs), noisy(room), obj, room


def test_guessed_prediction_does_not_make_table_into_object():
    """Where the prediction is a guess (a smooth fill of the table), the table's own colours say room."""
    obs, pred, obj, room = _table_scene()
    guessed = np.zeros(obj.shape, bool)
    guessed[28:50, 14:50] = True                        # the table behind the object, never seen
    pred[guessed] = room[guessed].mean(0).astype(np.uint8)
    disc = sphere_disc(64, 0.9, 1.04)
    plain = matte(obs, pred, disc)[..., 3] > 127
    told = matte(obs, pred, disc, guessed=guessed)[..., 3] > 127
    iou = lambda a: (a & obj).sum() / (a | obj).sum()
    assert iou(plain) < 0.8                             # the guess's error looks like object
    assert iou(told) > 0.93, iou(told)


def test_room_by_colour_keeps_object_colours():
    obs, _, obj, _ = _table_scene()
    room = ~sphere_disc(64, 0.9, 1.04)
    table_in_core = np.zeros(obj.shape, bool)
    table_in_core[42:48, 20:44] = True                  # room wrongly decided object
    core = obj | table_in_core
    out = room_by_colour(obs, core, room, core)
    assert out[table_in_core].mean() > 0.95 and out[obj].mean() < 0.02
    assert not room_by_colour(obs, core, np.zeros_like(room), core).any()   # no room to learn from


def test_noise_level_survives_a_mispredicted_room_part():
    """Most of the room outside the disc predicted wrong (a far wall; pixels next to the right part
    find it within the 1-px shifts): the object is still found."""
    obs, pred, obj, _ = _table_scene()
    outside = ~sphere_disc(64, 0.9, 1.04)
    wrong = outside & (np.mgrid[0:64, 0:64][0] < 56)
    pred[wrong] = np.clip(pred[wrong].astype(int) + 60, 0, 255).astype(np.uint8)
    assert wrong.sum() > 0.7 * outside.sum()
    a = matte(obs, pred, ~outside)[..., 3] > 127
    assert (a & obj).sum() / (a | obj).sum() > 0.93


def test_capture_noise_level_keeps_a_faint_object():
    """A crop whose room is predicted badly (a far wall around the object, too bright) measures too much
    noise and loses a faint object; the capture's usual noise level (second pass) finds it."""
    _, _, obj, room = _table_scene()
    rng = np.random.default_rng(1)
    noisy = lambda im: np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8)
    disc = sphere_disc(64, 0.9, 1.04)
    wall = ~disc & (np.mgrid[0:64, 0:64][0] < 60)
    room = np.where(wall[..., None], 128.0, room)
    obs = noisy(np.where(obj[..., None], room + 14, room))          # the table's colour, a little lighter
    pred = noisy(room)
    bad = pred.copy()
    bad[wall] = np.clip(bad[wall].astype(int) + rng.normal(0, 4, bad[wall].shape) + 12, 0, 255).astype(np.uint8)
    iou = lambda a: (a & obj).sum() / (a | obj).sum()
    usual = noise_level(obs, pred, disc)
    assert noise_level(obs, bad, disc) > 2 * usual
    assert iou(matte(obs, bad, disc)[..., 3] > 127) < 0.5
    assert iou(matte(obs, bad, disc, capture=CaptureMatte(usual))[..., 3] > 127) > 0.95


def test_capture_colours_keep_a_table_coloured_part_over_the_guessed_table():
    """Without a plate, a part coloured like the table and seen only against the guessed table in
    this crop goes with the table; the object's colours from another view (against a wall) keep it."""
    _, pred, obj, room = _table_scene()
    rng = np.random.default_rng(2)
    noisy = lambda im: np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8)
    yy = np.mgrid[0:64, 0:64][0]
    lower = obj & (yy > 30)
    colours = np.where(lower[..., None], [150, 90, 50], [40, 70, 200])   # lower half: the table's light brown
    obs = noisy(np.where(obj[..., None], colours, room))
    guessed = cv2.dilate(lower.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)   # the table behind it
    pred[guessed] = room[guessed].mean(0).astype(np.uint8)
    disc = sphere_disc(64, 0.9, 1.04)
    wall = np.full(room.shape, 128.0)
    other = matte(noisy(np.where(obj[..., None], colours, wall)), noisy(wall), disc)
    cap = capture_matte([0.013], sure_object_counts(other, None))
    iou = lambda a: (a & obj).sum() / (a | obj).sum()
    assert iou(matte(obs, pred, disc, guessed=guessed)[..., 3] > 127) < 0.7
    assert iou(matte(obs, pred, disc, guessed=guessed, capture=cap)[..., 3] > 127) > 0.95


def test_temporal_median_outvotes_one_frame():
    a = np.zeros((8, 8), np.uint8)
    a[2:6, 2:6] = 255
    missed = a.copy()
    missed[2:4, 2:6] = 0                                  # one frame lost the top of the object
    assert np.array_equal(temporal_median([a, missed, a]), a)
    assert np.array_equal(temporal_median([missed, a]), ((a.astype(int) + missed) / 2).round().astype(np.uint8))


def _wood_scene(object_colour, shift_rows=0, seed=0):
    """A smooth wood grain (1-px colour change up to ~0.15), an elliptic object of one colour; the
    prediction is the grain, ``shift_rows`` rows off."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:64, 0:64]
    base = np.array([150.0, 100.0, 70.0])
    room = base + np.sin(2 * np.pi * (yy + 0.3 * xx) / 7.0)[..., None] * np.array([30.0, 20.0, 12.0])
    obj = (xx - 32) ** 2 / 14 ** 2 + (yy - 32) ** 2 / 18 ** 2 <= 1
    noisy = lambda im: np.clip(np.round(im + rng.normal(0, 1.5, im.shape)), 0, 255).astype(np.uint8)
    return noisy(np.where(obj[..., None], object_colour, room)), noisy(np.roll(room, shift_rows, 0)), obj


def test_sharp_distance_lies_between_the_robust_and_the_plain_distance():
    obs, pred, _ = _wood_scene(np.array([162.0, 86.0, 86.0]))
    robust, plain = colour_distance(obs, pred, 1), colour_distance(obs, pred, 0)
    assert np.allclose(sharp_distance(obs, pred, robust, 1.0), robust)
    assert np.allclose(sharp_distance(obs, pred, robust, 0.0), plain)
    mid = sharp_distance(obs, pred, robust, 0.25)
    assert (mid >= robust - 1e-6).all() and (mid <= plain + 1e-6).all()
    flat = np.full_like(pred, 120)
    assert local_variation(flat).max() == 0
    assert np.allclose(sharp_distance(obs, flat, colour_distance(obs, flat, 1), 0.25), colour_distance(obs, flat, 0))


def test_matte_keeps_a_part_coloured_like_a_textured_room():
    """An object whose colour the wood grain shows within a pixel (a pale head on a wood table):
    the minimum over shifts loses it, the sharper distance keeps it."""
    obs, pred, obj = _wood_scene(np.array([162.0, 86.0, 86.0]))
    disc = sphere_disc(64, 0.9, 1.04)
    iou = lambda a: (a & obj).sum() / (a | obj).sum()
    assert iou(matte(obs, pred, disc, MatteConfig(sharp_shift=1.0))[..., 3] > 127) < 0.6
    assert iou(matte(obs, pred, disc)[..., 3] > 127) > 0.9


def test_sharp_distance_stays_off_where_it_lights_up_the_room():
    """A prediction two rows off: the sharper distance would call the grain object, so in this
    crop it is not used (with one noise level; the room's error per predicted colour would absorb
    it too)."""
    obs, pred, obj = _wood_scene(np.array([40.0, 60.0, 200.0]), shift_rows=2)
    disc = sphere_disc(64, 0.9, 1.04)
    one_level = MatteConfig(room_levels=0)
    rgba = matte(obs, pred, disc, one_level)
    assert np.array_equal(rgba, matte(obs, pred, disc, replace(one_level, sharp_shift=1.0)))
    a = rgba[..., 3] > 127
    assert (a & obj).sum() / (a | obj).sum() > 0.95


def test_capture_with_a_blurred_field_turns_the_sharp_distance_off():
    """A field that renders the room blurred keeps too little of its detail: the capture's
    median crop turns the sharper distance off, and the pale object is then left to the robust one."""
    obs, pred, obj = _wood_scene(np.array([162.0, 86.0, 86.0]))
    disc = sphere_disc(64, 0.9, 1.04)
    blurred = cv2.GaussianBlur(pred, (0, 0), 1.2)
    _, _, kept = matte_and_noise(obs, pred, disc)
    _, _, kept_blurred = matte_and_noise(obs, blurred, disc)
    assert kept > 0.8 > kept_blurred
    assert room_detail(obs, pred, np.zeros(disc.shape, bool)) != room_detail(obs, pred, np.zeros(disc.shape, bool))
    assert capture_matte([0.013] * 3, None, [0.9, float("nan"), 0.85]).sharp
    off = capture_matte([0.013] * 3, None, [kept_blurred, 0.9, kept_blurred])
    assert not off.sharp
    noise = noise_level(obs, pred, disc)
    assert np.array_equal(matte(obs, pred, disc, capture=replace(off, noise=noise)),
                          matte(obs, pred, disc, MatteConfig(sharp_shift=1.0), capture=CaptureMatte(noise)))


def test_noise_map_keeps_a_mispredicted_wall_out_of_the_object():
    """The field renders a far wall (a grey checker) as smooth grey, across the top of the crop and
    into the sphere, touching the object: one noise level for the crop calls it object; the
    room's error per predicted colour, seen outside the sphere, keeps it out."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:64, 0:64]
    room = np.where((np.sin(yy / 2.5 + 0.3 * np.sin(xx / 7)) > 0)[..., None], [150, 90, 50], [95, 55, 35]).astype(float)
    wall = yy < 13
    checker = np.where((((yy // 2) + (xx // 2)) % 2 == 0)[..., None], 110.0, 150.0)
    obj = (xx - 32) ** 2 / 12 ** 2 + (yy - 32) ** 2 / 21 ** 2 <= 1
    noisy = lambda im: np.clip(np.round(im + rng.normal(0, 2.0, im.shape)), 0, 255).astype(np.uint8)
    obs = noisy(np.where(obj[..., None], [40.0, 70.0, 200.0], np.where(wall[..., None], checker, room)))
    pred = noisy(np.where(wall[..., None], 130.0, room))
    disc = sphere_disc(64, 0.9, 1.04)
    levels = noise_map(colour_distance(obs, pred), pred, ~disc, 0.013)
    assert np.median(levels[wall & disc]) > 0.1 and levels[~wall].max() < 0.02
    assert (noise_map(colour_distance(obs, pred), pred, ~disc, 0.013, levels=0) == np.float32(0.013)).all()
    iou = lambda a: (a & obj).sum() / (a | obj).sum()
    one_level = matte(obs, pred, disc, MatteConfig(room_levels=0))[..., 3] > 127
    assert (one_level & wall & ~obj).sum() > 100
    per_colour = matte(obs, pred, disc)[..., 3] > 127
    assert (per_colour & wall & ~obj).sum() < 5 and iou(per_colour) > 0.97


def test_edge_gain_and_ramp_map_the_compositing_alpha_of_mixed_pixels():
    """A shaded rim reads as part room: the compositing alpha of the band's mixed pixels is
    scaled by ``gain`` (clipped to 1), or steepened by ``ramp``; inside and hard-decided pixels
    keep 1 / 0."""
    from dbb_capture.crops.matte import _edge_alpha

    F, B = np.array([60.0, 90.0, 220.0]), np.array([200.0, 170.0, 120.0])
    obs = np.tile(B, (16, 16, 1))
    obs[:, :8] = F
    obs[:, 8] = 0.4 * F + 0.6 * B                      # a column 40% covered
    core = np.zeros((16, 16), bool)
    core[:, :8] = True
    pred = np.tile(B, (16, 16, 1)).astype(np.uint8)
    plain = _edge_alpha(obs.astype(np.uint8), pred, core, 1, 1.0)
    gained = _edge_alpha(obs.astype(np.uint8), pred, core, 1, 1.25)
    assert np.allclose(plain[4:12, 8], 0.4, atol=0.02) and np.allclose(gained[4:12, 8], 0.5, atol=0.025)
    assert (gained[:, :6] == 1).all() and (gained[:, 10:] == 0).all()
    assert np.allclose(gained[plain < 1], np.minimum(1, 1.25 * plain[plain < 1]), atol=1e-6)
    ramped = _edge_alpha(obs.astype(np.uint8), pred, core, 1, 1.0, ramp=(0.25, 0.75))
    assert np.allclose(ramped[4:12, 8], 0.3, atol=0.04)            # (0.4 - 0.25) / 0.5
    assert (ramped[:, :6] == 1).all() and (ramped[:, 10:] == 0).all()


def test_shaded_rim_alpha_recovers_the_coverage_where_the_plain_equation_runs_low():
    """A rim shaded darker than the object's inside: I = (1 - a) B + a (s F) with s < 1. The
    plain compositing equation (F from inside) reads it low; the shaded-rim model recovers a
    wherever room and object differ in hue, and leaves same-hue pixels to the plain equation."""
    from dbb_capture.crops.matte import _edge_alpha, rim_alpha

    rng = np.random.default_rng(3)
    F = rng.uniform(40, 230, (200, 3))
    B = rng.uniform(40, 230, (200, 3))
    a = rng.uniform(0.1, 0.9, 200)
    s = rng.uniform(0.6, 1.1, 200)
    I = (1 - a[:, None]) * B + a[:, None] * s[:, None] * F
    rim, holds = rim_alpha(I, B, F, 0.3)
    off = np.linalg.norm(B - ((B * F).sum(1) / (F * F).sum(1))[:, None] * F, axis=1)
    assert holds[off > 0.35 * np.linalg.norm(F - B, axis=1)].all() and not holds[off < 0.25 * np.linalg.norm(F - B, axis=1)].any()
    assert np.abs(rim - a)[holds].max() < 1e-6
    grey = rim_alpha(np.array([[100.0, 100, 100]]), np.array([[150.0, 150, 150]]), np.array([[50.0, 50, 50]]), 0.3)
    assert not grey[1][0]                               # same hue: the model cannot tell shading from coverage

    F, B = np.array([220.0, 120.0, 60.0]), np.array([90.0, 110.0, 60.0])   # a bright object on a darker room
    obs = np.tile(B, (16, 16, 1))
    obs[:, :8] = F
    obs[:, 8] = 0.6 * (0.7 * F) + 0.4 * B               # a column 60% covered by a rim at 70% brightness
    core = np.zeros((16, 16), bool)
    core[:, :8] = True
    pred = np.tile(B, (16, 16, 1)).astype(np.uint8)
    plain = _edge_alpha(obs.astype(np.uint8), pred, core, 1, 1.0)
    shaded = _edge_alpha(obs.astype(np.uint8), pred, core, 1, 1.0, 0.3)
    assert np.all(plain[4:12, 8] < 0.45)                # the plain equation calls it mostly room
    assert np.allclose(shaded[4:12, 8], 0.6, atol=0.02)
    assert (shaded[:, :6] == 1).all() and (shaded[:, 10:] == 0).all()
