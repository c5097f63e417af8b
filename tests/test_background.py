"""Background field and the preprocess stages after poses (render, matte, crop), against synth truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dbb_capture.background.config import BackgroundConfig, training_size
from dbb_capture.background.field import LayerField
from dbb_capture.background.rays import TrainingView, RayBank
from dbb_capture.background.train import new_field, parallax_coverage, train_background
from dbb_capture.geometry.cameras import Intrinsics, project_points
from dbb_capture.geometry.transforms import look_at
from dbb_capture.geometry.conventions import opencv_from_opengl
from dbb_capture.cli.capture import main
from dbb_capture.crops.camera import crop_camera, crop_maps
from dbb_capture.crops.object import object_crop
from dbb_capture.geometry.viewpoint import up_from_cameras
from dbb_capture.capture.footage import open_footage
from dbb_capture.synth.scene import SynthConfig
from dbb_capture.synth.capture import load_ground_truth, write_capture
from dbb_capture.geometry.rays import pixel_rays

UP = np.array([0.0, 0.0, -1.0])


def _ring(center, n=12, dist=0.6, el_deg=40.0):
    out = []
    for a in np.linspace(-60, 60, n):
        a, e = np.radians(a), np.radians(el_deg)
        eye = center + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), -np.sin(e)])
        out.append(look_at(eye, center, UP))
    return np.stack(out)


def test_fast_render_equals_volume_rendering():
    """The cv2 path used at preprocess time gives the image the training renderer gives."""
    center = np.array([0.3, 0.2, -0.08])
    c2ws = _ring(center)
    o, d = [a.reshape(-1, 3) for a in pixel_rays(crop_camera(c2ws[0], _intr(), center, 0.1, UP, 32, 0.6).intr, c2ws[0], np.float64)]
    bank = RayBank(torch.from_numpy(o).float(), torch.from_numpy(d).float(), torch.rand(len(o), 3))
    fld = new_field(BackgroundConfig(layers=8), center, 0.1, UP, c2ws, bank, 64)
    g = torch.Generator().manual_seed(0)
    fld = LayerField(torch.randn(8, 64, 64, 4, generator=g), torch.randn(64, 128, 4, generator=g), fld.center,
                     fld.basis, fld.heights, fld.half, fld.r_out)
    cam = crop_camera(c2ws[3], _intr(), center, 0.1, UP, 48, 0.7)
    fast = fld.render(cam).astype(float)
    o, d = [a.reshape(-1, 3) for a in pixel_rays(cam.intr, cam.c2w, np.float64)]
    with torch.no_grad():
        slow = fld.composite(torch.from_numpy(o).float(), torch.from_numpy(d).float()).numpy()
    slow = np.round(np.clip(slow, 0, 1) * 255).reshape(fast.shape)
    assert np.abs(fast - slow).mean() < 0.5 and np.percentile(np.abs(fast - slow), 99) <= 2


def _intr():
    return Intrinsics(320, 240, 260.0, 260.0, 159.5, 119.5)


def test_parallax_coverage_measures_what_other_views_see_behind_the_object():
    center = np.array([0.3, 0.2, -0.08])
    assert parallax_coverage(_ring(center), center, 0.08, UP) > 0.6
    still = np.repeat(_ring(center, n=1), 10, 0)  # a camera that never moves sees nothing behind
    assert parallax_coverage(still, center, 0.08, UP) < 0.1
    narrow = np.stack([_ring(center, n=12)[5]] * 5 + [_ring(center, n=12)[6]] * 5)
    assert parallax_coverage(narrow, center, 0.08, UP) < parallax_coverage(_ring(center), center, 0.08, UP)


@pytest.fixture(scope="module")
def plate_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("bg") / "cap"
    write_capture(SynthConfig(kind="static", seconds=2.0, fps=6, width=320, height=240,
                              background_seconds=2.0, seed=21), out)
    return out


def _views(cap, name, key):
    intr, cams, _ = load_ground_truth(cap)
    frames = list(open_footage(cap / name).read(range(len(cams[key]))))
    return [TrainingView(f.image, intr, opencv_from_opengl(np.array(c["transform_matrix"])))
            for f, c in zip(frames, cams[key])]


def _true_alpha(cap, index, cam, intr, c2w):
    m = cv2.imread(str(cap / "ground_truth" / "masks" / f"{index:05d}.png"), cv2.IMREAD_GRAYSCALE)
    mx, my = crop_maps(cam, intr, c2w, 1)
    return cv2.remap(m, mx, my, cv2.INTER_LINEAR) > 127


@pytest.mark.parametrize("plate", [True, False])
def test_background_field_mattes_the_object(plate_capture, plate):
    """Trained from the clean plate (or the object video, object sphere left out), the field
    predicts the room well enough that the matte matches the true silhouette."""
    cap = plate_capture
    obj = json.loads((cap / "object.json").read_text())
    center, radius = np.array(obj["center"]), obj["radius"]
    video = _views(cap, "video.mp4", "video")
    up = up_from_cameras(np.stack([v.c2w for v in video]))
    train = _views(cap, "background.mp4", "background") if plate else video
    cfg = BackgroundConfig(steps=100, layer_px=128, batch_rays=4096)
    model = train_background(iter(train), len(train), center, radius, up, clean_plate=plate, cfg=cfg)
    assert model.mode == ("clean plate" if plate else "object video") and model.log.steps == 100
    # Without a plate the board plane behind the object is a guess, and the field knows where.
    assert (model.field.guess is None) == plate
    if not plate:
        cam = crop_camera(video[0].c2w, video[0].intr, center, radius, up, 64, 0.9)
        guessed = model.guessed(cam)
        assert 0.02 < guessed.mean() < 0.6 and not guessed[0, 0]   # behind the object, not the corners
    ious = _matte_ious(cap, model, video, center, radius, up)
    assert np.median(ious) > (0.78 if plate else 0.5), ious  # 12 frames: little parallax without a plate


def _matte_ious(cap, model, video, center, radius, up):
    """IoU of the matte (64 px crops) with the true silhouette in every second video frame."""
    ious = []
    for i, v in enumerate(video[::2]):
        oc = object_crop(v.image, v.intr, v.c2w, center, radius, up, 64, 0.9, model.render,
                         guessed=model.guessed)
        truth = _true_alpha(cap, 2 * i, oc.cam, v.intr, v.c2w)
        pred = oc.rgba[..., 3] > 127
        ious.append((truth & pred).sum() / (truth | pred).sum())
    return np.array(ious)


def test_video_room_fills_in_where_the_plate_was_not_filmed(plate_capture):
    """A plate filmed from two viewpoints only: the object video's rays past the object's sphere
    teach the field the room the plate never saw, so the room around the object is predicted
    better in the video's frames and the mattes recover."""
    cap = plate_capture
    obj = json.loads((cap / "object.json").read_text())
    center, radius = np.array(obj["center"]), obj["radius"]
    video = _views(cap, "video.mp4", "video")
    up = up_from_cameras(np.stack([v.c2w for v in video]))
    plate = _views(cap, "background.mp4", "background")[:2]
    cfg = BackgroundConfig(steps=400, layer_px=128, batch_rays=4096)
    got = {}
    for room in (False, True):
        model = train_background(iter(plate), len(plate), center, radius, up, clean_plate=True, cfg=cfg,
                                 room_views=iter(video) if room else ())
        assert model.frames == len(plate) and model.field.guess is None
        psnrs = []
        for i, v in enumerate(video):   # the predicted room where the truth shows room (2 px from the object)
            oc = object_crop(v.image, v.intr, v.c2w, center, radius, up, 64, 0.9, model.render)
            truth = _true_alpha(cap, i, oc.cam, v.intr, v.c2w)
            room_px = cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
            err = ((oc.observed.astype(float) - oc.predicted.astype(float)) / 255) ** 2
            psnrs.append(-10 * np.log10(err[room_px].mean()))
        got[room] = (model.rays, np.mean(psnrs), np.mean(_matte_ious(cap, model, video, center, radius, up)))
    assert got[True][0] > 2 * got[False][0]                          # the video's rays joined the plate's
    # Measured: room 20.6 -> 23.8 dB, mean IoU 0.69 -> 0.77.
    assert got[True][1] > got[False][1] + 1.5 and got[True][2] > got[False][2] + 0.03, got


def test_field_state_keeps_where_the_board_plane_is_a_guess(tmp_path):
    center = np.array([0.3, 0.2, -0.08])
    c2ws = _ring(center)
    o, d = [a.reshape(-1, 3) for a in pixel_rays(crop_camera(c2ws[0], _intr(), center, 0.1, UP, 32, 0.6).intr, c2ws[0], np.float64)]
    bank = RayBank(torch.from_numpy(o).float(), torch.from_numpy(d).float(), torch.rand(len(o), 3))
    fld = new_field(BackgroundConfig(layers=8), center, 0.1, UP, c2ws, bank, 64)
    guess = torch.zeros(64, 64)
    guess[24:40, 24:40] = 1.0                            # a square around the centre
    fld = LayerField(fld.layers, fld.env, fld.center, fld.basis, fld.heights, fld.half, fld.r_out, guess)
    cam = crop_camera(c2ws[5], _intr(), center, 0.1, UP, 48, 0.7)
    g = fld.guessed(cam)
    assert g[24, 24] and not g[0, 0] and not g[47, 47]   # the board plane under the centre only
    back = LayerField.from_state(fld.state())
    assert np.array_equal(back.guessed(cam), g)
    plain = LayerField(fld.layers, fld.env, fld.center, fld.basis, fld.heights, fld.half, fld.r_out)
    assert not plain.guessed(cam).any() and "guess" not in plain.state()


def test_preprocess_writes_crops_dataset(plate_capture, tmp_path):
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(plate_capture), "-o", str(ds), "--background-minutes", "0.05",
                                    "--camera", str(plate_capture / "ground_truth" / "camera.json"),
                                    "--crop-size", "48", "--sequence-length", "4"])
    assert res.exit_code == 0, res.output
    crops = json.loads((ds / "crops.json").read_text())
    assert crops["crop_size"] == 48 and crops["up"] == [0.0, 0.0, -1.0]
    fr = crops["frames"][0]
    for key in ("file_path", "transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h", "source_frame", "time",
                "viewpoint", "split"):
        assert key in fr
    assert set(fr["viewpoint"]) == {"azimuth_deg", "elevation_deg", "distance_m"}
    assert {f["split"] for f in crops["frames"]} == {"train", "test"}
    rgba = cv2.imread(str(ds / fr["file_path"]), cv2.IMREAD_UNCHANGED)
    assert rgba.shape == (48, 48, 4) and rgba[..., 3].max() == 255 and rgba[0, 0, 3] == 0
    tf = json.loads((ds / "transforms.json").read_text())
    mask = cv2.imread(str(ds / tf["frames"][0]["mask_path"]), cv2.IMREAD_GRAYSCALE)
    assert mask.shape == (240, 320) and 0 < (mask > 127).mean() < 0.5
    stats = json.loads((ds / "dataset.json").read_text())
    assert stats["crops"] == len(crops["frames"]) == stats["frames_posed"] >= 6
    assert stats["background"]["mode"] == "clean plate"
    assert json.loads((ds / "background" / "report.json").read_text())["train_px"] >= 64
    assert stats["sequences"]["train"] > 0
    assert (ds / "contact_sheet.png").stat().st_size > 10_000 and (ds / "background" / "field.pt").is_file()
    assert not (ds / "matte_scratch").exists()          # the matte's second pass cleans up after itself
    assert json.loads((ds / "preprocess.json").read_text())["stages_run"] == ["poses", "background", "crops"]


def test_training_crops_are_sized_to_the_matte_within_the_footage():
    cfg = BackgroundConfig(train_size=64, train_fill=0.6)
    # 128 px crops matted at 2x, sphere filling 0.9: a matte pixel is 1/171 of a 0.6-fill window.
    assert training_size(cfg, 256, 0.9, window_px=179.0) == 171
    # Footage coarser than the matte: one training pixel per source pixel (the window at 0.6 fill).
    assert training_size(cfg, 256, 0.9, window_px=100.0) == 150
    # Small crops never go below the configured size.
    assert training_size(cfg, 64, 0.9, window_px=500.0) == 64


def test_object_sphere_outside_the_views_is_an_error(plate_capture, tmp_path):
    bad = tmp_path / "object.json"
    bad.write_text(json.dumps({"center": [5.0, 5.0, -1.0], "radius": 0.1}))
    res = CliRunner().invoke(main, ["preprocess", str(plate_capture), "-o", str(tmp_path / "ds"),
                                    "--object", str(bad), "--camera",
                                    str(plate_capture / "ground_truth" / "camera.json")])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and "outside the view" in lines[0], res.output
    assert not (tmp_path / "ds").exists()


def test_fixed_camera_mode_mattes_a_moving_ball(tmp_path):
    """No board, a camera that never moves: the temporal median is the room, the window is cut as is."""
    cap = tmp_path / "fixed"
    (cap / "frames").mkdir(parents=True)
    rng = np.random.default_rng(0)
    room = cv2.GaussianBlur(rng.integers(60, 200, (120, 160, 3), dtype=np.uint8), (0, 0), 3)
    truth = []
    for i in range(30):
        img = room.copy()
        cx, cy = 80 + int(30 * np.sin(i / 3)), 70
        cv2.circle(img, (cx, cy), 9, (220, 40, 40), -1)
        m = np.zeros((120, 160), np.uint8)
        cv2.circle(m, (cx, cy), 9, 255, -1)
        truth.append(m[30:110, 40:120])
        cv2.imwrite(str(cap / "frames" / f"{i:04d}.png"), img[..., ::-1])
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(cap), "-o", str(ds), "--crop-window", "40,30,80",
                                    "--crop-size", "80", "--sequence-length", "5"])
    assert res.exit_code == 0, res.output
    crops = json.loads((ds / "crops.json").read_text())
    assert len(crops["frames"]) == 30 and crops["fixed_camera"]["window"] == [40, 30, 80]
    assert len({json.dumps(f["viewpoint"]) for f in crops["frames"]}) == 1   # one constant viewpoint
    # The recorded crop camera is the one the window's pixels came from: the object centre (on the
    # window's centre ray, below the frame's) projects to the crop's centre, the ball to its place.
    f0 = crops["frames"][0]
    intr = Intrinsics(f0["w"], f0["h"], f0["fl_x"], f0["fl_y"], f0["cx"], f0["cy"])
    c2w = opencv_from_opengl(np.array(f0["transform_matrix"]))
    assert np.allclose(project_points(np.array([crops["object"]["center"]]), c2w, intr), 39.5, atol=1e-6)
    ious = []
    for f, t in zip(crops["frames"], truth):
        a = cv2.imread(str(ds / f["file_path"]), cv2.IMREAD_UNCHANGED)[..., 3] > 127
        ious.append((a & (t > 127)).sum() / (a | (t > 127)).sum())
    assert np.median(ious) > 0.9, ious
    bad = CliRunner().invoke(main, ["preprocess", str(cap), "-o", str(tmp_path / "x"), "--crop-window", "500,0,50"])
    assert bad.exit_code == 2 and "outside" in bad.output


def test_fixed_camera_mode_on_real_pendulum_footage(tmp_path):
    from conftest import shared_data

    video = shared_data("pendulum", "ball.mp4")
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(video.parent), "-o", str(ds), "--crop-window", "0,270,360",
                                    "--no-matte", "--fps", "10"])
    assert res.exit_code == 0, res.output
    stats = json.loads((ds / "dataset.json").read_text())
    assert stats["crops"] > 100 and stats["sequences"]["train"] > 50 and stats["touching_border"] == 0


def test_second_matte_pass_votes_across_segment_cuts(tmp_path):
    """The crops stage's second pass gives the same crops in one segment or in three (each sees its
    neighbours across the cut), and the temporal median skips a gap in time."""
    from dbb_capture.crops.matte import CaptureMatte, MatteConfig
    from dbb_capture.preprocess.crop_stage import _FirstMatte, _matte_segment, _MatteSegment

    center = np.array([0.3, 0.2, -0.08])
    c2ws = _ring(center, n=8)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:32, 0:32]
    room = np.where((np.sin(yy / 2.0) > 0)[..., None], [150, 90, 50], [95, 55, 35]).astype(float)
    noisy = lambda im: np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8)
    crops, c2w = [], {}
    for i, m in enumerate(c2ws):
        disc = (xx - 16) ** 2 + (yy - 15) ** 2 <= (7 if i != 4 else 3) ** 2   # frame 4 misses most of it
        obs = noisy(np.where(disc[..., None], [40, 70, 200], room))
        np.savez(tmp_path / f"{i:05d}.npz", observed=obs, predicted=noisy(room), guessed=np.zeros(0, bool),
                 inside=np.zeros(0, np.uint8))
        crops.append(_FirstMatte(i, f"{i:05d}", crop_camera(m, _intr(), center, 0.1, UP, 32, 0.9), False, 0.01))
        c2w[i] = m
    follows = frozenset({1, 2, 4, 5, 6, 7})                 # frame 3 follows a gap

    def run(parts, out):
        (out / "crops").mkdir(parents=True)
        (out / "masks").mkdir()
        for a, b in parts:
            seg = _MatteSegment(tuple(crops[a:b]), crops[a - 1] if a else None, crops[b] if b < 8 else None,
                                follows, c2w, _intr(), 0.9, MatteConfig(), CaptureMatte(0.01), tmp_path, out,
                                frozenset())
            _matte_segment(seg, tick=lambda n: None)
        return [cv2.imread(str(out / "crops" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED) for i in range(8)]

    one = run([(0, 8)], tmp_path / "one")
    three = run([(0, 3), (3, 5), (5, 8)], tmp_path / "three")
    assert all(np.array_equal(a, b) for a, b in zip(one, three))
    big = (xx - 16) ** 2 + (yy - 15) ** 2 <= 6 ** 2
    assert (one[4][..., 3][big] > 127).mean() > 0.95      # outvoted by frames 3 and 5
    assert (one[2][..., 3][big] > 127).mean() > 0.95


def _wall_bank(center, radius_wall=2.5, n_views=16, size=40):
    """Rays of a ring of cameras looking up and away past the object at a textured spherical
    wall of radius ``radius_wall`` around ``center`` (none meets the board plane): colour from
    the wall point's direction, a checker of 8-degree cells."""
    o_all, d_all, c_all = [], [], []
    for m in _ring(center, n=n_views):
        eye = m[:3, 3]
        target = center + 2.0 * (center - eye) * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, -0.8])
        cam = look_at(eye, target, UP)
        from dbb_capture.geometry.cameras import Intrinsics

        o, d = [a.reshape(-1, 3) for a in pixel_rays(Intrinsics(size, size, 60.0, 60.0, (size - 1) / 2, (size - 1) / 2), cam, np.float64)]
        oc = o - center
        b = (oc * d).sum(1)
        t = -b + np.sqrt(b * b - (oc * oc).sum(1) + radius_wall ** 2)
        q = (oc + t[:, None] * d) / radius_wall
        az, el = np.degrees(np.arctan2(q[:, 1], q[:, 0])), np.degrees(np.arcsin(q[:, 2]))
        check = ((np.floor(az / 8) + np.floor(el / 8)) % 2)[:, None]
        o_all.append(o), d_all.append(d), c_all.append(np.where(check > 0, [0.8, 0.7, 0.3], [0.2, 0.3, 0.6]))
    o, d, c = (torch.from_numpy(np.concatenate(x)).float() for x in (o_all, d_all, c_all))
    return RayBank(o, d, c)


def test_far_sphere_depth_sweep_finds_the_wall():
    """The sweep puts the far sphere's texels at the wall's distance (the views' rays agree there),
    and the field renders the wall from its texels sharper than a sphere at the default radius."""
    from dbb_capture.background.panorama import env_coords
    from dbb_capture.background.train import with_env_depth

    center = np.array([0.3, 0.2, -0.08])
    bank = _wall_bank(center)
    fld = new_field(BackgroundConfig(layers=4, env_width=256), center, 0.1, UP, _ring(center), bank, 32)
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


def test_room_rays_keep_away_from_the_matte():
    from dbb_capture.background.rays import room_rays

    center = np.array([0.3, 0.2, -0.08])
    cam = crop_camera(_ring(center)[3], _intr(), center, 0.1, UP, 32, 0.9)
    obs = np.full((32, 32, 3), 128, np.uint8)
    alpha = np.zeros((32, 32), np.uint8)
    alpha[10:20, 10:20] = 255
    inside = np.full((32, 32), 255, np.uint8)
    inside[:, :4] = 0
    o, d, c = room_rays(cam, obs, alpha, inside, grow_px=2)
    assert len(o) == 28 * 32 - 14 * 14 and np.allclose(c, 128 / 255)
    assert len(room_rays(cam, obs, alpha, None, grow_px=0)[0]) == 32 * 32 - 100


def test_refine_on_room_trains_again_and_sees_under_a_moving_object(plate_capture, tmp_path):
    """Without a plate the field is trained again on the first mattes' room rays (full size, its
    own budget); board-plane texels those rays reach stop being guesses; the model round-trips."""
    from dbb_capture.background.model import BackgroundModel
    from dbb_capture.background.train import refine_on_room
    from dbb_capture.background.rays import room_rays

    cap = plate_capture
    obj = json.loads((cap / "object.json").read_text())
    center, radius = np.array(obj["center"]), obj["radius"]
    video = _views(cap, "video.mp4", "video")
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


def test_preprocess_without_plate_trains_the_field_again_on_the_mattes_room(plate_capture, tmp_path):
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(plate_capture), "-o", str(ds), "--background-minutes", "0.05",
                                    "--camera", str(plate_capture / "ground_truth" / "camera.json"),
                                    "--crop-size", "48", "--sequence-length", "4", "--no-clean-plate"])
    assert res.exit_code == 0, res.output
    rep = json.loads((ds / "background" / "report.json").read_text())
    assert rep["mode"].startswith("object video") and rep["refined_on_room"]["steps"] > 0
    from dbb_capture.background.model import BackgroundModel

    assert BackgroundModel.load(ds / "background" / "field.pt").refine.steps == rep["refined_on_room"]["steps"]
    fr = json.loads((ds / "crops.json").read_text())["frames"][0]
    rgba = cv2.imread(str(ds / fr["file_path"]), cv2.IMREAD_UNCHANGED)
    assert rgba[..., 3].max() == 255 and rgba[0, 0, 3] == 0
    assert not (ds / "matte_scratch").exists()
