"""Training the room: parallax coverage, mattes from plate and video, the far room's depth, refinement."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from conftest import UP, ring_cameras

from dbb_capture.background.config import BackgroundConfig
from dbb_capture.background.field import LayerField
from dbb_capture.background.train import new_field, parallax_coverage, train_background
from dbb_capture.crops.camera import crop_camera
from dbb_capture.crops.object import object_crop
from dbb_capture.geometry.viewpoint import up_from_cameras

from .conftest import capture_views, matte_ious, true_alpha, wall_bank


def test_parallax_coverage_measures_what_other_views_see_behind_the_object():
    center = np.array([0.3, 0.2, -0.08])
    assert parallax_coverage(ring_cameras(center), center, 0.08, UP) > 0.6
    still = np.repeat(ring_cameras(center, n=1), 10, 0)  # a camera that never moves sees nothing behind
    assert parallax_coverage(still, center, 0.08, UP) < 0.1
    narrow = np.stack([ring_cameras(center, n=12)[5]] * 5 + [ring_cameras(center, n=12)[6]] * 5)
    assert parallax_coverage(narrow, center, 0.08, UP) < parallax_coverage(ring_cameras(center), center, 0.08, UP)


@pytest.mark.parametrize("plate", [True, False])
def test_background_field_mattes_the_object(plate_capture, plate):
    """Trained from the clean plate (or the object video, object sphere left out), the field
    predicts the room well enough that the matte matches the true silhouette."""
    cap = plate_capture
    obj = json.loads((cap / "object.json").read_text())
    center, radius = np.array(obj["center"]), obj["radius"]
    video = capture_views(cap, "video.mp4", "video")
    up = up_from_cameras(np.stack([v.c2w for v in video]))
    train = capture_views(cap, "background.mp4", "background") if plate else video
    cfg = BackgroundConfig(steps=100, layer_px=128, batch_rays=4096)
    model = train_background(iter(train), len(train), center, radius, up, clean_plate=plate, cfg=cfg)
    assert model.mode == ("clean plate" if plate else "object video") and model.log.steps == 100
    # Without a plate the board plane behind the object is a guess, and the field knows where.
    assert (model.field.guess is None) == plate
    if not plate:
        cam = crop_camera(video[0].c2w, video[0].intr, center, radius, up, 64, 0.9)
        guessed = model.guessed(cam)
        assert 0.02 < guessed.mean() < 0.6 and not guessed[0, 0]   # behind the object, not the corners
    ious = matte_ious(cap, model, video, center, radius, up)
    assert np.median(ious) > (0.78 if plate else 0.5), ious  # 12 frames: little parallax without a plate


def test_video_room_fills_in_where_the_plate_was_not_filmed(plate_capture):
    """A plate filmed from two viewpoints only: the object video's rays past the object's sphere
    teach the field the room the plate never saw, so the room around the object is predicted
    better in the video's frames and the mattes recover."""
    cap = plate_capture
    obj = json.loads((cap / "object.json").read_text())
    center, radius = np.array(obj["center"]), obj["radius"]
    video = capture_views(cap, "video.mp4", "video")
    up = up_from_cameras(np.stack([v.c2w for v in video]))
    plate = capture_views(cap, "background.mp4", "background")[:2]
    cfg = BackgroundConfig(steps=400, layer_px=128, batch_rays=4096)
    got = {}
    for room in (False, True):
        model = train_background(iter(plate), len(plate), center, radius, up, clean_plate=True, cfg=cfg,
                                 room_views=iter(video) if room else ())
        assert model.frames == len(plate) and model.field.guess is None
        psnrs = []
        for i, v in enumerate(video):   # the predicted room where the truth shows room (2 px from the object)
            oc = object_crop(v.image, v.intr, v.c2w, center, radius, up, 64, 0.9, model.render)
            truth = true_alpha(cap, i, oc.cam, v.intr, v.c2w)
            room_px = cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
            err = ((oc.observed.astype(float) - oc.predicted.astype(float)) / 255) ** 2
            psnrs.append(-10 * np.log10(err[room_px].mean()))
        got[room] = (model.rays, np.mean(psnrs), np.mean(matte_ious(cap, model, video, center, radius, up)))
    assert got[True][0] > 2 * got[False][0]                          # the video's rays joined the plate's
    # Measured: room 20.6 -> 23.8 dB, mean IoU 0.69 -> 0.77.
    assert got[True][1] > got[False][1] + 1.5 and got[True][2] > got[False][2] + 0.03, got


def test_far_sphere_depth_sweep_finds_the_wall():
    """The sweep puts the far sphere's texels at the wall's distance (the views' rays agree there),
    and the field renders the wall from its texels sharper than a sphere at the default radius."""
    from dbb_capture.background.panorama import env_coords
    from dbb_capture.background.train import with_env_depth

    center = np.array([0.3, 0.2, -0.08])
    bank = wall_bank(center)
    fld = new_field(BackgroundConfig(layers=4, env_width=256), center, 0.1, UP, ring_cameras(center), bank, 32)
    assert not np.isclose(fld.r_out, 2.5, rtol=0.2)          # the default sphere is not at the wall
    deep = with_env_depth(fld, bank, 24)
    seen = deep.env_depth[np.isfinite(deep.env_depth)]
    ou = (bank.origins.numpy() - center) @ fld.basis.numpy().T
    du = bank.dirs.numpy() @ fld.basis.numpy().T
    x, y = env_coords(ou, du, deep.env_start, fld.he, fld.we, deep.env_depth)
    hit = deep.env_depth[np.clip(np.round(y).astype(int), 0, fld.he - 1), np.round(x).astype(int) % fld.we]
    assert abs(np.median(hit) - 2.5) < 0.35, np.median(hit)
    assert seen.min() > 0
    # Colours from the sweep's mean at the found depth: the field renders the bank closely.
    with torch.no_grad():
        err_deep = (deep.composite(bank.origins, bank.dirs) - bank.rgb).abs().mean()
        flat = with_env_depth(fld, bank, 1)                    # one radius: a sphere just outside the cameras
        err_flat = (flat.composite(bank.origins, bank.dirs) - bank.rgb).abs().mean()
    assert err_deep < 0.6 * err_flat, (err_deep, err_flat)
    back = LayerField.from_state(deep.state())
    assert np.array_equal(back.env_depth, deep.env_depth)


def test_refine_on_room_trains_again_and_sees_under_a_moving_object(plate_capture, tmp_path):
    """Without a plate the field is trained again on the first mattes' room rays (full size, its
    own budget); board-plane texels those rays reach stop being guesses; the model round-trips."""
    from dbb_capture.background.model import BackgroundModel
    from dbb_capture.background.rays import room_rays
    from dbb_capture.background.train import refine_on_room

    cap = plate_capture
    obj = json.loads((cap / "object.json").read_text())
    center, radius = np.array(obj["center"]), obj["radius"]
    video = capture_views(cap, "video.mp4", "video")
    up = up_from_cameras(np.stack([v.c2w for v in video]))
    cfg = BackgroundConfig(steps=40, layer_px=96, batch_rays=2048, refine_share=0.5)
    model = train_background(iter(video), len(video), center, radius, up, clean_plate=False, cfg=cfg)
    rays = []
    for v in video:
        oc = object_crop(v.image, v.intr, v.c2w, center, radius, up, 48, 0.9, model.render, guessed=model.guessed)
        rays.append(room_rays(oc.cam, oc.observed, oc.rgba[..., 3], oc.inside))
    before = float(model.field.guess.sum())
    refined = refine_on_room(model, rays)
    assert refined.refine is not None and refined.refine.steps == 20 and refined.log.steps == 40
    assert refined.field.s == model.field.s and float(refined.field.guess.sum()) < before
    refined.save(tmp_path / "f.pt")
    back = BackgroundModel.load(tmp_path / "f.pt")
    assert back.refine.steps == 20 and torch.equal(back.field.guess, refined.field.guess)
