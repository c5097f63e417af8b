"""Image helpers: straight RGBA resized on premultiplied colour; PSNR of known errors."""

from __future__ import annotations

import numpy as np
import pytest

from dbb_capture.core.images import resize_rgba, to_u8
from dbb_capture.core.metrics import psnr, psnr_from_mse


def test_resize_keeps_the_colour_of_a_half_transparent_edge():
    rgba = np.zeros((4, 4, 4), np.float32)
    rgba[:, :2] = [1.0, 0.0, 0.0, 1.0]           # opaque red on the left
    rgba[:, 2:] = [0.0, 1.0, 0.0, 0.0]           # transparent "green" that must not bleed in
    out = resize_rgba(rgba, 2)
    np.testing.assert_allclose(out[:, 0], [[1, 0, 0, 1]] * 2, atol=1e-6)
    assert out[:, 1, 3].max() < 1e-6
    assert resize_rgba(rgba, 4) is rgba
    assert to_u8(np.array([-0.1, 0.5, 1.2])).tolist() == [0, 128, 255]


def test_psnr_of_known_errors():
    assert psnr_from_mse(0.01) == pytest.approx(20.0)
    assert psnr_from_mse(0.0) == pytest.approx(120.0)
    a = np.zeros((8, 8, 3))
    assert psnr(a + 0.1, a) == pytest.approx(20.0)
