"""The background stage's settings, and the size its training crops are cut at."""

from __future__ import annotations

from dataclasses import dataclass

from ..core.errors import DbbError


@dataclass(frozen=True)
class BackgroundConfig:
    """The field's shape and its training. Lengths are multiples of the object radius ``R``."""

    layers: int = 16
    layer_px: int = 384             # texels along each side of a layer
    env_width: int = 1024           # azimuth texels of the far sphere (height: half of it)
    env_depths: int = 24            # radii the far sphere's depth sweep tries per texel (0: one sphere)
    top: float = 1.5                # highest layer: this many R above the object centre
    r_out_factor: float = 2.0       # far sphere: this many times the farthest camera distance
    train_size: int = 64            # side of the training crops (pixels); preprocess sizes them to
                                    # the matte's pixels, never below this (:func:`training_size`)
    train_fill: float = 0.6         # the sphere fills less of a training crop: a margin around it
    minutes: float = 2.0
    steps: int | None = None        # stop after this many steps (tests), else the time budget
    batch_rays: int = 8192
    lr: float = 0.05
    tv_weight: float = 1e-4
    sphere_margin: float = 1.08     # without a clean plate: rays within this many R are left out
    refine_share: float = 0.5       # without a clean plate: then trained again on what the first mattes call
                                    # room, for this share of the budget (minutes or steps; 0: not)
    refine_grow_px: int = 2         # ... keeping this far from anything they call object
    max_frames: int = 400
    video_room: bool = True         # with a clean plate: also learn from the object video's rays that
                                    # pass the object's sphere (beyond sphere_margin R; the plate's
                                    # path need not cover the video's viewpoints)
    seed: int = 0

    def validate(self) -> None:
        if self.layers < 3 or self.layer_px < 16 or self.minutes <= 0 and not self.steps:
            raise DbbError("background field: need >= 3 layers, >= 16 texels and a positive budget")


def training_size(cfg: BackgroundConfig, matte_px: int, crop_fill: float, window_px: float) -> int:
    """Side (pixels) of the training crops for crops matted at ``matte_px`` pixels with the object
    sphere filling ``crop_fill`` of them, whose windows span ``window_px`` source pixels (median).

    The field learns the room at the size of a matte pixel, so the board's pattern right behind
    the object comes out as sharp as the matte compares it; never finer than the footage (one
    training pixel per source pixel) nor coarser than ``cfg.train_size``. At 64 px the 640x480
    capture's 256 px mattes met a room blurred over 3-4 of their pixels: 128 px crops'
    background near the outline 24-25 dB in frames where the board shows behind the object,
    28-32 dB at 160 px; crops against the truth +0.9 dB on white (docs/decisions.md, train_size).
    """
    want = matte_px * cfg.train_fill / crop_fill
    footage = window_px * crop_fill / cfg.train_fill      # the training window in source pixels
    return int(round(max(cfg.train_size, min(want, footage))))
