"""The run report's strips: frames large enough to judge, rows and steps named in the image."""

from __future__ import annotations

import numpy as np

from dbb_capture.core.images import LABEL_PX
from dbb_capture.dynamic.figures import FIGURE_PX, strip_image


def test_strip_frames_are_enlarged_with_their_pixels_and_rows_are_named():
    rng = np.random.default_rng(0)
    rows = [rng.uniform(0, 1, (10, 32, 32, 4)).astype(np.float32) for _ in range(3)]
    for r in rows:
        r[..., :3] *= r[..., 3:]                          # premultiplied
    img = strip_image(rows, ["truth", "prediction", "near (training)"], [f"step {k}" for k in range(1, 11)])
    k = FIGURE_PX // 32                                   # 32 px frames, shown 8x
    cell = k * (32 + 2)
    assert img.shape == (LABEL_PX + 3 * cell, 110 + 10 * cell, 3)
    frame = img[LABEL_PX:LABEL_PX + 32 * k, 110:110 + 32 * k]
    assert (frame[::k, ::k].repeat(k, 0).repeat(k, 1) == frame).all()       # nearest: whole pixels
    for i in range(3):                                    # a name in each row's label cell
        assert (img[LABEL_PX + i * cell:LABEL_PX + (i + 1) * cell, :110] > 200).any()
    for j in range(10):                                   # and over each step's column
        assert (img[:LABEL_PX, 110 + j * cell:110 + (j + 1) * cell] > 200).any()
