"""The layered field: its fast render equals volume rendering; its state round-trips."""

from __future__ import annotations

import numpy as np
import torch
from conftest import UP, ring_cameras, small_intrinsics

from dbb_capture.background.config import BackgroundConfig
from dbb_capture.background.field import LayerField
from dbb_capture.background.rays import RayBank
from dbb_capture.background.train import new_field
from dbb_capture.crops.camera import crop_camera
from dbb_capture.geometry.rays import pixel_rays


def test_fast_render_equals_volume_rendering():
    """The cv2 path used at preprocess time gives the image the training renderer gives."""
    center = np.array([0.3, 0.2, -0.08])
    c2ws = ring_cameras(center)
    o, d = [a.reshape(-1, 3) for a in pixel_rays(crop_camera(c2ws[0], small_intrinsics(), center, 0.1, UP, 32, 0.6).intr, c2ws[0], np.float64)]
    bank = RayBank(torch.from_numpy(o).float(), torch.from_numpy(d).float(), torch.rand(len(o), 3))
    fld = new_field(BackgroundConfig(layers=8), center, 0.1, UP, c2ws, bank, 64)
    g = torch.Generator().manual_seed(0)
    fld = LayerField(torch.randn(8, 64, 64, 4, generator=g), torch.randn(64, 128, 4, generator=g), fld.center,
                     fld.basis, fld.heights, fld.half, fld.r_out)
    cam = crop_camera(c2ws[3], small_intrinsics(), center, 0.1, UP, 48, 0.7)
    fast = fld.render(cam).astype(float)
    o, d = [a.reshape(-1, 3) for a in pixel_rays(cam.intr, cam.c2w, np.float64)]
    with torch.no_grad():
        slow = fld.composite(torch.from_numpy(o).float(), torch.from_numpy(d).float()).numpy()
    slow = np.round(np.clip(slow, 0, 1) * 255).reshape(fast.shape)
    assert np.abs(fast - slow).mean() < 0.5 and np.percentile(np.abs(fast - slow), 99) <= 2


def test_field_state_keeps_where_the_board_plane_is_a_guess(tmp_path):
    center = np.array([0.3, 0.2, -0.08])
    c2ws = ring_cameras(center)
    o, d = [a.reshape(-1, 3) for a in pixel_rays(crop_camera(c2ws[0], small_intrinsics(), center, 0.1, UP, 32, 0.6).intr, c2ws[0], np.float64)]
    bank = RayBank(torch.from_numpy(o).float(), torch.from_numpy(d).float(), torch.rand(len(o), 3))
    fld = new_field(BackgroundConfig(layers=8), center, 0.1, UP, c2ws, bank, 64)
    guess = torch.zeros(64, 64)
    guess[24:40, 24:40] = 1.0                            # a square around the centre
    fld = LayerField(fld.layers, fld.env, fld.center, fld.basis, fld.heights, fld.half, fld.r_out, guess)
    cam = crop_camera(c2ws[5], small_intrinsics(), center, 0.1, UP, 48, 0.7)
    g = fld.guessed(cam)
    assert g[24, 24] and not g[0, 0] and not g[47, 47]   # the board plane under the centre only
    back = LayerField.from_state(fld.state())
    assert np.array_equal(back.guessed(cam), g)
    plain = LayerField(fld.layers, fld.env, fld.center, fld.basis, fld.heights, fld.half, fld.r_out)
    assert not plain.guessed(cam).any() and "guess" not in plain.state()
