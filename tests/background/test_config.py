"""The background stage's settings: the training crops' size."""

from __future__ import annotations

from dbb_capture.background.config import BackgroundConfig, training_size


def test_training_crops_are_sized_to_the_matte_within_the_footage():
    cfg = BackgroundConfig(train_size=64, train_fill=0.6)
    # 128 px crops matted at 2x, sphere filling 0.9: a matte pixel is 1/171 of a 0.6-fill window.
    assert training_size(cfg, 256, 0.9, window_px=179.0) == 171
    # Footage coarser than the matte: one training pixel per source pixel (the window at 0.6 fill).
    assert training_size(cfg, 256, 0.9, window_px=100.0) == 150
    # Small crops never go below the configured size.
    assert training_size(cfg, 64, 0.9, window_px=500.0) == 64
