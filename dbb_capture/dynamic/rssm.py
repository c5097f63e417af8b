"""The dynamic-object training stage: a viewpoint-conditioned recurrent state-space model (RSSM).

The model (PlaNet family, thesis chapter 6) keeps a deterministic GRU state ``h`` and a
Gaussian stochastic state ``z``. What it is built to avoid, and how:

- *Motion that depends on the viewpoint* (freezing when the viewer stands still): the
  transition ``h_t = GRU(h_{t-1}, z_{t-1})``, ``z_t ~ p(z_t | h_t)`` never sees the viewpoint;
  only the decoder ``x_t = dec(h_t, z_t, PE(view_t))`` does. The object's own motion cannot
  stall or repeat because of where the camera is (structural, tested).
- *A prior that never learns slow motion*: the run-time rollout uses the prior only, so the
  prior is trained the way it runs: every batch also rolls the prior open-loop from the first
  frame's posterior (sampled states), with a reconstruction loss on those frames and latent
  overshooting (KL from the stopped-gradient filtering posterior to the open-loop prior).
- *Free nats and KL balancing done right*: the dynamics term KL(sg(q) || p), which trains the
  prior, is never clamped (a clamp removes its gradient exactly when the per-step KL is small,
  i.e. for slow motion); free nats apply to the batch-mean representation term KL(q || sg(p))
  only, as max(KL, free nats). Balance 0.8 / 0.2 (Dreamer).
- *Shrinking motion at run time*: the stochastic state is sampled, not replaced by its mean.

Images are RGBA; losses and metrics use premultiplied colour and alpha in [0, 1] (colour where
alpha is 0 is undefined in straight RGBA and must not count).

A run folder (``dbb-train rssm DATASET -o RUN``) describes itself in ``run.json``:

- ``model.pt``: ``{"config": RssmConfig fields, "state_dict": ...}`` (plain torch save);
- ``stepper.ts``: TorchScript :class:`Stepper` (``start(rgba, view)``, ``step(h, z, view)``);
- ``checkpoint.pt``: model, optimiser, step and history, for ``--resume``;
- ``report/``: ``eval.json`` (per-step PSNR/SSIM vs baselines, motion-energy ratio),
  ``plots.png`` (per-step PSNR/SSIM, motion energy, losses), ``strip.png`` (truth / prediction / near),
  ``rollout.png`` (150 steps at a still viewpoint).

Checkpoints during training go to ``.<RUN>.work/`` beside RUN (like the PlenOctree stage).
"""

from __future__ import annotations

import copy
import math
import shutil
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from ..crops.camera import sequence_windows
from ..datasets.records import find_dataset_file, load_dataset, load_rgba
from ..core.errors import DbbError
from ..core.outputs import (atomic_dir, check_run_output, read_json, resume_checkpoint, run_work_dir,
                      training_minutes, write_json)
from ..core.progress import progress
from ..core.device import pick_device
from ..core.images import resize_rgba
from ..core.metrics import psnr, ssim

RUN_FORMAT = "dbb-rssm-run"
SIZES = (32, 64, 128, 256)
# The run-time sampling temperature when it cannot be fitted to the footage (no run of consecutive
# training frames; see calibrate_temperature): the prior as trained. No fixed value carries over
# between captures: on the sample, 1.3 lifted the still-view motion from 0.62-1.01 of the truth's
# into the band (0.80-1.23), but a second capture already moved 1.5-1.6x the truth at 1 and
# 1.8-2.0x at 1.3 (docs/benchmarks.md, nineteenth round).
RUN_TEMPERATURE = 1.0


# --------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class RssmConfig:
    """Model and loss settings. Sizes in pixels, KL in nats."""

    size: int = 64                 # square RGBA frames, a power of two in SIZES
    deter: int = 64                # deterministic GRU state
    stoch: int = 64                # Gaussian stochastic state
    hidden: int = 256              # MLP width
    embed: int = 256               # encoder output
    enc_depth: int = 8             # channels of the first encoder conv (doubling, capped at 256)
    dec_depth: int = 8             # decoder channels at 32 px (halving per doubling, >= 8)
    view_freqs: int = 4            # positional-encoding octaves of azimuth and elevation
    min_std: float = 0.1           # std = softplus(x) + min_std (PlaNet)
    free_nats: float = 1.0
    kl_balance: float = 0.8        # weight of the dynamics (prior-training) term
    kl_scale: float = 1.0
    overshoot_scale: float = 1.0   # latent overshooting along the open-loop rollout
    open_loop_scale: float = 0.0   # reconstruction of the open-loop (prior-only) frames; 0 (PlaNet: the
                                   # prior learns from the KL and overshooting): a sampled open loop scored
                                   # by squared error learns to hedge (arms smeared), and its decoding is
                                   # skipped (1.7x the steps)
    skip: bool = True              # decoder sees the context frame: its encoder maps (U-Net) and its
                                   # pixels, warped by a predicted flow and blended by a predicted mask
    max_flow: float = 0.5          # largest flow, in image half-widths (grid_sample units)
    compose: str = "accum"         # skip path: "copy3" = per-pixel softmax over the context frame as is,
                                   # warped, and generated (CDNA-style; static parts copied exactly);
                                   # "blend" = one mask between warped and generated (earlier runs);
                                   # "accum" = the context frame resampled through a warp that each step
                                   # moves a little further (accumulated_warp), blended with generated content
    max_step_flow: float = 0.25    # "accum": largest flow of one step, in image half-widths
    warp_leak: float = 0.1         # "accum": each step the warp's displacement shrinks by this fraction
                                   # (toward the context frame's layout), so its errors stay bounded
    warp_leak_fps: float = 0.0     # > 0: warp_leak is the leak of one frame at this frame rate; training
                                   # rescales it to the dataset's rate, the same fraction per second
                                   # (leak_at_frame_rate; 0.1 at 10 fps is 0.035 at 30 fps)
    flow_snap: float = 0.0         # skip path: a flow shorter than this many pixels is exactly zero (the
                                   # still parts are copied, not resampled; straight-through gradient)
    mask_snap: float = 0.0         # skip path: a warp share above 1 - this is exactly 1 (no generated
                                   # content mixed into what is copied; straight-through gradient)
    energy_scale: float = 0.0      # weight of the motion-energy match of the open loop (see energy_match)
    sharp_scale: float = 0.0       # weight of the sharpness match of the open loop (see sharpness_match:
                                   # a moving part must be drawn as sharp as the truth's, wherever it is)
    sharp_where: str = "all"       # where the sharpness match looks: "all" = the whole frame; "moving" =
                                   # only where the window's truth changes (motion_envelope), so a fixed
                                   # texture does not dominate it and no stripes are drawn to match it
    open_loop_temperature: float = 1.0  # training only: scale of the prior's std in the open-loop samples
                                   # (1 = as the run-time stepper at temperature 1)
    pyramid_scale: float = 0.0     # weight of the coarse-scale squared error of the filtering and open-loop
                                   # frames (pyramid_err): a warp's gradient reaches only a pixel or two, so a
                                   # part predicted far from the truth gets no pull toward it at full size
    pyramid_levels: int = 3        # halvings in that term (3: 1/2, 1/4, 1/8 of the size)
    pyramid_on: str = "both"       # which frames that term scores: "both", "filter" (the filtering frames
                                   # only: the flow gets its reach from the posterior, and the open loop is
                                   # not asked to meet a blurred truth) or "open_loop"
    prior_first: bool = True       # also decode frame 1 from a prior sample at h_1 (the run-time first step)
    first_step_scale: float = 1.0  # without open-loop pixel losses (open_loop_scale=0): weight of that
                                   # frame's reconstruction alone (one decode a window; the decoder then
                                   # meets prior samples, not only posteriors, at the step it runs first)
    open_loop_from: int = 1        # the training open loop starts from the filtering state of this frame:
                                   # 1 = after the posterior has seen frames 0 and 1 (see sequence_loss)
    motion_weight: float = 10.0    # extra weight of changing pixels in the reconstruction losses
    motion_weight_of: str = "both"  # whose change weighs: "truth" (the truth's change from its previous
                                   # frame) or "both" (also the prediction's change from that frame, so
                                   # change predicted where none comes weighs as much as change missed)
    decode_frames: int = 10        # frames decoded per window in each branch (a random subset of a
                                   # longer window: the transition runs the whole window, the decoder,
                                   # which costs most, only this many frames)
    filter_decode: str = "posterior"  # the filtering reconstruction decodes frame t from "posterior" z_t
                                   # (it has seen frame t) or from a "prior" sample at h_t (as it runs:
                                   # the generator cannot draw frames out of a z that has seen them)
    rec_scale: float = 1.0         # weight of the filtering reconstruction
    open_loop_samples: int = 1     # best-of-K: K sampled open loops per window, each window scored by
                                   # its best (the prior may cover several motions without averaging them)
    decoder_view: str = "relative"  # what the decoder (skip path) is told of the viewpoints: "relative" =
                                   # the encoding of their difference only (view_delta_encoding: the warp's
                                   # input; it carries over to viewpoints never seen in training and cannot
                                   # look a pose up by viewpoint); "absolute" = the encodings of the current
                                   # and the context view (runs before the fifth round); "both"
    keypoints: int = 0             # > 0: this many spatial-softmax keypoints join the encoder's embedding
                                   # (SpatialSoftmax): the flattened conv stack all but ignores a part a few
                                   # pixels wide (a 5-px ball moves its embedding by ~1e-5), a keypoint
                                   # follows it across the frame
    keypoint_scale: float = 0.0    # > 0 (needs keypoints): weight of predicting each frame's keypoints
                                   # (detached) from its state (h, z): the posterior's at every filtering
                                   # step, the prior samples' along the open loop; a target the warp's
                                   # vanishing gradient cannot hide, so z carries where the part is (on
                                   # the pendulum it does; the prior still lacks momentum: docs, 15th round)
    keypoints_frozen: bool = False  # the keypoint layer keeps its initial weights (a learned one may
                                   # spread its softmax until it no longer follows the part)
    keypoint_open_loop: bool = True  # the keypoint error also reads the open loop's states; False: the
                                   # filtering states only (a regression along a short open loop pulls
                                   # the prior toward the mean; yet on the pendulum off lost motion)
    keypoint_energy: float = 0.0   # > 0: the keypoint error also matches each keypoint's mean step length
                                   # along the open loop to the frames' (this weight, relative): a
                                   # regression alone lets a forecast settle (bench/momentum_toy.py;
                                   # on the pendulum's 16 keypoints no gain, 16th round)
    osc: int = 0                   # > 0: this many damped rotations (complex modes, LRU-style) take 2 x osc
                                   # of the deter units beside the GRU (OscCell): a state that rings at
                                   # its own frequency keeps a swing going after the trained horizon, where
                                   # a GRU's forecast settles (pendulum, twenty-first round)
    osc_keep_min: float = 0.0      # floor of each mode's kept length a step (e.g. 0.99: rings ~100 steps);
                                   # trained freely the modes learn to damp within 10-50 steps
    keypoint_prior: bool = False   # the keypoint error also reads each filtering step's prior mean
                                   # (h_t, its forecast before frame t is seen): one-step forecasts of
                                   # where the part goes, teacher forced (pendulum: no gain, 16th round)
    keypoint_maps: bool = False    # (needs keypoint_scale) the decoder draws from keypoints: Gaussian maps
                                   # of the keypoints its state predicts (kp_head) and, with skip, of the
                                   # context frame's join its layers (Minderer et al. 2019), so a small
                                   # part can be drawn where the state puts it, far from where the
                                   # context frame shows it (a warp moves it a few pixels at most)
    keypoint_map_std: float = 0.08  # those maps' std in [-1, 1] frame units (0.08: 2.6 px at 64 px);
                                   # at least half a cell at each coarser layer
    keypoint_teacher: bool = False  # (needs keypoint_maps, compose accum) training decodes every frame from the
                                   # keypoints the encoder finds in that frame (detached), as Minderer et al.
                                   # train their decoder, not from the state's guess: a pixel loss scores a
                                   # small part drawn a few pixels off worse than no part, so a decoder fed the
                                   # state's uncertain keypoints learns to leave the part where it was. The
                                   # state's keypoints (kp_head, trained by the keypoint loss) drive it at run time

    def validate(self) -> None:
        if self.size not in SIZES:
            raise DbbError(f"--size must be one of {', '.join(map(str, SIZES))}, not {self.size}")
        for f in ("deter", "stoch", "hidden", "embed", "enc_depth", "dec_depth", "view_freqs"):
            if getattr(self, f) < 1:
                raise DbbError(f"RSSM {f} must be positive")
        if self.keypoint_scale > 0 and self.keypoints < 1:
            raise DbbError("RSSM keypoint_scale needs keypoints > 0")
        if self.compose not in ("copy3", "blend", "accum"):
            raise DbbError(f"RSSM compose must be copy3, blend or accum, not {self.compose!r}")
        if self.compose == "accum" and not self.skip:
            raise DbbError("RSSM compose accum warps the context frame: it needs skip")
        if self.motion_weight_of not in ("truth", "both"):
            raise DbbError(f"RSSM motion_weight_of must be truth or both, not {self.motion_weight_of!r}")
        if self.flow_snap < 0.0 or not 0.0 <= self.mask_snap < 1.0:
            raise DbbError(f"RSSM flow_snap must be >= 0 and mask_snap in [0, 1), not {self.flow_snap}, {self.mask_snap}")
        if not 0.0 <= self.warp_leak < 1.0:
            raise DbbError(f"RSSM warp_leak must be in [0, 1), not {self.warp_leak}")
        if self.warp_leak_fps < 0.0:
            raise DbbError(f"RSSM warp_leak_fps must be >= 0, not {self.warp_leak_fps}")
        if self.filter_decode not in ("posterior", "prior"):
            raise DbbError(f"RSSM filter_decode must be posterior or prior, not {self.filter_decode!r}")
        if self.decoder_view not in ("absolute", "relative", "both"):
            raise DbbError(f"RSSM decoder_view must be absolute, relative or both, not {self.decoder_view!r}")
        if self.first_step_scale < 0.0:
            raise DbbError(f"RSSM first_step_scale must be >= 0, not {self.first_step_scale}")
        if self.sharp_scale < 0.0:
            raise DbbError(f"RSSM sharp_scale must be >= 0, not {self.sharp_scale}")
        if self.sharp_where not in ("all", "moving"):
            raise DbbError(f"RSSM sharp_where must be all or moving, not {self.sharp_where!r}")
        if self.pyramid_scale < 0.0 or self.pyramid_levels < 1:
            raise DbbError(f"RSSM pyramid_scale must be >= 0 and pyramid_levels >= 1, not {self.pyramid_scale}, {self.pyramid_levels}")
        if self.pyramid_on not in ("both", "filter", "open_loop"):
            raise DbbError(f"RSSM pyramid_on must be both, filter or open_loop, not {self.pyramid_on!r}")
        if self.open_loop_temperature < 0.0:
            raise DbbError(f"RSSM open_loop_temperature must be >= 0, not {self.open_loop_temperature}")
        if self.open_loop_samples < 1:
            raise DbbError("RSSM open_loop_samples must be at least 1")
        if self.keypoints < 0:
            raise DbbError(f"RSSM keypoints must be >= 0, not {self.keypoints}")
        if self.keypoint_maps and self.keypoint_scale <= 0:
            raise DbbError("RSSM keypoint_maps needs keypoint_scale > 0 (and keypoints > 0)")
        if self.keypoint_teacher and not (self.keypoint_maps and self.compose == "accum"):
            raise DbbError("RSSM keypoint_teacher needs keypoint_maps and compose accum")
        if self.keypoint_map_std <= 0:
            raise DbbError(f"RSSM keypoint_map_std must be > 0, not {self.keypoint_map_std}")
        if not 0.0 <= self.osc_keep_min < 1.0:
            raise DbbError(f"RSSM osc_keep_min must be in [0, 1), not {self.osc_keep_min}")
        if self.osc < 0 or 2 * self.osc >= self.deter:
            raise DbbError(f"RSSM osc must be >= 0 and leave GRU units (2 x osc < deter {self.deter}), not {self.osc}")

    @classmethod
    def from_json(cls, d: dict) -> RssmConfig:
        names = {f.name for f in fields(cls)}
        # Runs written before the skip path / copy3 / filter_decode / decoder_view had none, and
        # those before the eleventh round's defaults (and first_step_scale) had the old values.
        d = {"skip": False, "compose": "blend", "filter_decode": "posterior", "decoder_view": "absolute",
             "warp_leak": 0.0, "motion_weight_of": "truth", "open_loop_scale": 1.0, "first_step_scale": 0.0, **d}
        return cls(**{k: v for k, v in d.items() if k in names})


@dataclass(frozen=True)
class TrainConfig:
    """How long and how to train. ``minutes``/``steps``: the first limit reached wins."""

    minutes: float | None = None
    steps: int | None = None
    batch: int = 8
    lr: float = 1e-3
    lr_end: float = 1.0            # the learning rate falls (cosine) to this fraction of lr by the end of the
                                   # budget (steps or minutes, whichever ends first); 1 = flat
    adam_eps: float = 1e-4
    weight_decay: float = 0.25     # > 0: AdamW's decoupled decay (each step the weights shrink by lr x this),
                                   # against memorising a short capture's windows (0 = Adam, before the twelfth round)
    ema: float = 0.995             # > 0: the run's model is the exponential moving average of the weights
                                   # with this decay per step (0.995: about the last 200 steps), kept beside
                                   # the trained ones; it smooths the late steps' noise (0 = the last weights)
    grad_clip: float = 100.0
    checkpoint_seconds: float = 60.0
    seed: int = 0
    max_bad_steps: int = 20        # consecutive non-finite steps before giving up
    horizon: int | None = None     # predicted frames per training window (1 context + horizon), cut from
                                   # consecutive training frames; None: the dataset's own windows (the
                                   # default: 30 gave less in a 15-minute budget, docs/benchmarks.md)
    augment: str = "flip,reverse,shift"  # comma-separated: "flip" mirrors half the windows left-right
                                   # (azimuth negated), "reverse" plays half of them backwards, "shift"
                                   # moves each window by a random whole-pixel offset (up to size/16,
                                   # DrQ; +0.2 to +1.2 dB on held-out windows, nineteenth round); "none"
    val_fraction: float = 0.0      # model selection: this fraction of the training frames (the last, in
                                   # time) is held out of training; every val_every steps the open loop
                                   # is scored on its windows and the best model is the one written
    val_every: int = 100
    snapshot_every: int = 0        # > 0: also save the model every this many steps into
                                   # .<RUN>.snapshots/ beside the run (to study a run's course afterwards)
    val_min_energy: float = 0.7    # selection only among models whose open loop on the held-out windows
                                   # moves at least this fraction of the truth (no frozen model wins)
    dynamics_steps: int = 0        # > 0: after each step, this many more on fresh windows that train the
                                   # transition and prior alone (latent_loss: posteriors fixed, nothing
                                   # decoded), so the dynamics get many updates for each costly one
                                   # (a non-finite one is skipped and counted)
    dynamics_horizon: int | None = None  # the latent-only steps' windows (1 context + this many frames, as
                                   # `horizon`); None: the same windows as the full steps. Nothing is
                                   # decoded there, so windows many times longer cost little (pendulum:
                                   # 60 with osc modes gives the prior the swing's period, 22nd-24th rounds;
                                   # without them 60 and 120 gave less motion, 16th round)

    def validate(self) -> None:
        bad = set(self.augment.split(",")) - {"none", "flip", "reverse", "shift"}
        if bad:
            raise DbbError(f"augment: unknown {', '.join(sorted(bad))} (flip, reverse, shift or none)")
        if not 0.0 <= self.val_fraction < 0.5:
            raise DbbError(f"val_fraction must be in [0, 0.5), not {self.val_fraction}")
        if self.val_every < 1:
            raise DbbError("val_every must be at least 1")
        if not 0.0 < self.lr_end <= 1.0:
            raise DbbError(f"lr_end must be in (0, 1], not {self.lr_end}")
        if self.weight_decay < 0.0:
            raise DbbError(f"weight_decay must be at least 0, not {self.weight_decay}")
        if not 0.0 <= self.ema < 1.0:
            raise DbbError(f"ema must be in [0, 1), not {self.ema}")
        for name in ("horizon", "dynamics_horizon"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise DbbError(f"{name} must be at least 1, not {getattr(self, name)}")


def leak_at_frame_rate(cfg: RssmConfig, fps: float | None) -> RssmConfig:
    """``cfg`` with ``warp_leak`` given per frame at ``warp_leak_fps`` rescaled to footage at ``fps``
    frames per second: the same fraction of the displacement left after one second,
    1 - (1 - leak) ** (warp_leak_fps / fps); ``warp_leak_fps`` becomes ``fps``, so applying it again
    changes nothing. Unchanged when ``warp_leak_fps`` is 0 or the frame rate is unknown.

    A leak per frame is a time constant in frames: 0.1 keeps a displaced part ~10 frames, a second
    at 10 frames/s but a third of one at 30, too short for a swing to get anywhere.
    """
    if cfg.warp_leak_fps <= 0.0 or not fps or cfg.warp_leak == 0.0:
        return cfg
    leak = 1.0 - (1.0 - cfg.warp_leak) ** (cfg.warp_leak_fps / float(fps))
    return replace(cfg, warp_leak=leak, warp_leak_fps=float(fps))


# Named bundles of settings, for footage the defaults do not suit. ``preset=NAME`` in a settings
# list stands for its pairs (later pairs override them).
PRESETS: dict[str, tuple[str, ...]] = {
    # A small part that swings in front of a still camera (the pendulum; docs/benchmarks.md, RSSM,
    # twenty-fourth round): the encoder's keypoints find the ball, oscillator modes in the state
    # keep the rhythm past the trained horizon, latent-only steps over 60 frames train that
    # rhythm, and the decoder draws from keypoint maps, trained from the keypoints of each frame.
    "swing": ("compose=accum", "warp_leak=0.1", "warp_leak_fps=10", "energy_scale=100", "sharp_scale=100",
              "keypoints=16", "keypoint_scale=100", "keypoints_frozen=true", "osc=16", "deter=96",
              "osc_keep_min=0.999", "dynamics_steps=1", "dynamics_horizon=60", "keypoint_maps=true",
              "keypoint_teacher=true"),
}


def configs_from_settings(pairs: list[str], cfg: RssmConfig | None = None,
                          tcfg: TrainConfig | None = None) -> tuple[RssmConfig, TrainConfig]:
    """Model and training settings from ``NAME=VALUE`` pairs (fields of :class:`RssmConfig` or
    :class:`TrainConfig`, e.g. ``compose=accum``, or ``preset=NAME`` for the pairs of
    :data:`PRESETS` ``[NAME]``), over ``cfg`` / ``tcfg`` (default: the defaults); values take the
    field's type ("none" for None, true/false for flags)."""
    cfg, tcfg = cfg or RssmConfig(), tcfg or TrainConfig()
    expanded: list[str] = []
    for pair in pairs:
        name, _, value = pair.partition("=")
        if name == "preset":
            if value not in PRESETS:
                raise DbbError(f"--set {pair}: no such preset (known: {', '.join(sorted(PRESETS))})")
            expanded.extend(PRESETS[value])
        else:
            expanded.append(pair)
    for pair in expanded:
        name, eq, value = pair.partition("=")
        target = cfg if name in {f.name for f in fields(RssmConfig)} else tcfg
        if not eq or name not in {f.name for f in fields(target)} or name in ("minutes", "steps"):
            raise DbbError(f"--set {pair}: expected NAME=VALUE with NAME a model or training setting "
                           f"({', '.join(f.name for f in fields(RssmConfig))}; "
                           f"{', '.join(f.name for f in fields(TrainConfig) if f.name not in ('minutes', 'steps'))})")
        cur = getattr(target, name)
        try:
            if value == "none" and not isinstance(cur, str):
                v = None
            elif isinstance(cur, bool):
                v = value.lower() == "true"
            else:
                v = type(cur)(value) if cur is not None else int(value)
        except ValueError:
            raise DbbError(f"--set {pair}: {value!r} is not a {type(cur).__name__}") from None
        if target is cfg:
            cfg = replace(cfg, **{name: v})
        else:
            tcfg = replace(tcfg, **{name: v})
    return cfg, tcfg


# --------------------------------------------------------------------------- viewpoint encoding
def view_encoding(view: torch.Tensor, freqs: int) -> torch.Tensor:
    """Positional encoding of viewpoints (..., 3) [azimuth_deg, elevation_deg, distance_m] -> (..., 4 * freqs).

    sin/cos of azimuth and elevation at octaves 1, 2, 4, ...; distance is not used (the crops
    are distance-normalized, thesis 6.1.1).
    """
    ang = view[..., :2] * (math.pi / 180.0)
    k = 2.0 ** torch.arange(freqs, dtype=view.dtype, device=view.device)
    a = ang[..., :, None] * k                                    # (..., 2, F)
    return torch.cat([torch.sin(a), torch.cos(a)], -1).flatten(-2)


def view_delta_encoding(pe: torch.Tensor, ctx_pe: torch.Tensor, freqs: int) -> torch.Tensor:
    """sin/cos of (view - context view) per angle and octave, (N, 4 * freqs), from two
    :func:`view_encoding` rows (N, 4 * freqs): sin(a - b) = sin a cos b - cos a sin b, etc.

    The change of viewpoint since the context frame is what the warp needs; an MLP can form
    these products of its inputs only approximately.
    """
    s1, c1 = pe.view(-1, 2, 2, freqs).unbind(2)
    s0, c0 = ctx_pe.view(-1, 2, 2, freqs).unbind(2)
    return torch.stack([s1 * c0 - c1 * s0, c1 * c0 + s1 * s0], 2).flatten(1)


def decoder_features(h: torch.Tensor, z: torch.Tensor, pe: torch.Tensor, ctx_pe: torch.Tensor, skip: bool,
                     decoder_view: str, freqs: int, prev_pe: torch.Tensor | None = None) -> torch.Tensor:
    """The decoder's input (N, deter + stoch + views): the states and what it is told of the
    current view ``pe`` and (skip path) the context frame's ``ctx_pe`` (see ``RssmConfig.decoder_view``);
    with ``prev_pe`` (the previous frame's view, ``compose="accum"``) also the change of view since
    that frame, which the step's flow has to follow."""
    if not skip:
        return torch.cat([h, z, pe], -1)
    if decoder_view == "relative":
        parts = [h, z, view_delta_encoding(pe, ctx_pe, freqs)]
    elif decoder_view == "both":
        parts = [h, z, pe, ctx_pe, view_delta_encoding(pe, ctx_pe, freqs)]
    else:
        parts = [h, z, pe, ctx_pe]
    if prev_pe is not None:
        parts.append(view_delta_encoding(pe, prev_pe, freqs))
    return torch.cat(parts, -1)


def identity_grid(n: int, size: int, device: torch.device | None = None) -> torch.Tensor:
    """Pixel-centre sampling grid of ``grid_sample`` (align_corners=False), (n, S, S, 2) as (x, y) in [-1, 1]."""
    lin = (torch.arange(size, dtype=torch.float32, device=device) * 2.0 + 1.0) / size - 1.0
    gy, gx = torch.meshgrid(lin, lin, indexing="ij")
    return torch.stack([gx, gy], -1)[None].expand(n, -1, -1, -1).contiguous()


def snap_flow(flow: torch.Tensor, thresh: float) -> torch.Tensor:
    """``flow`` (N, 2, S, S) with every vector shorter than ``thresh`` (same units) set to exactly
    zero in the forward pass; the gradient passes as if it were not (straight-through), so a
    snapped pixel can still learn to move. Sampling the identity grid returns the pixels exactly:
    what does not move is copied, not resampled (a 0.2 px flow softens every edge by itself)."""
    if thresh <= 0.0:
        return flow
    keep = ((flow * flow).sum(1, keepdim=True) >= thresh * thresh).to(flow.dtype)
    return flow + (flow * keep - flow).detach()


def snap_mask(mask: torch.Tensor, margin: float) -> torch.Tensor:
    """A warp share ``mask`` (N, 1, S, S) in (0, 1) set to exactly 1 where it is above 1 - ``margin``
    in the forward pass (straight-through gradient): no generated content mixed into copied pixels."""
    if margin <= 0.0:
        return mask
    return mask + (torch.where(mask > 1.0 - margin, torch.ones_like(mask), mask) - mask).detach()


def accumulated_warp(grid: torch.Tensor, flow: torch.Tensor, base: torch.Tensor, leak: float = 0.0) -> torch.Tensor:
    """Where each pixel of the next frame comes from in the context frame, (N, S, S, 2) grid_sample
    coordinates: ``grid`` the same for the current frame, ``flow`` (N, 2, S, S) the step's motion
    as a backward flow (the next frame's pixel p was at p + flow(p) in the current one), ``base``
    the identity grid (1, S, S, 2) (:func:`identity_grid`).

    The composition grid(p + flow(p)) resamples the smooth coordinate field, never the image, so
    a part that travels far over many steps stays as sharp as one resampling of the context frame,
    and a still part (flow 0) keeps its coordinates exactly. ``leak`` > 0 then shrinks the
    displacement from ``base`` by that fraction: a step's error no longer persists for ever
    (errors stay within about error / leak), and a part must be held where it is by the flow.
    """
    b = base.to(flow.dtype)
    g = F.grid_sample(grid.permute(0, 3, 1, 2), b + flow.permute(0, 2, 3, 1), mode="bilinear",
                      padding_mode="border", align_corners=False).permute(0, 2, 3, 1)
    return g if leak == 0.0 else torch.lerp(g, b, leak)


def warp_maps(maps: list[torch.Tensor], grid: torch.Tensor) -> list[torch.Tensor]:
    """The context frame's encoder maps moved to where their content is now: each map (N, C, r, r)
    resampled through ``grid`` (N, S, S, 2) averaged down to r x r (the identity grid leaves them as they are).
    ``maps`` coarsest first (:meth:`Encoder.features`); the averages are taken finest first, each
    from the last (2x2 means: the same as averaging S x S down to r, at a fraction of the cost)."""
    g = grid.permute(0, 3, 1, 2)
    out: list[torch.Tensor] = []
    for m in maps[::-1]:
        r = m.shape[-1]
        while g.shape[-1] > r:                 # sizes are powers of two (RssmConfig.validate)
            g = F.avg_pool2d(g, 2)
        out.append(F.grid_sample(m, g.permute(0, 2, 3, 1), mode="bilinear", padding_mode="border",
                                 align_corners=False))
    return out[::-1]


def keypoint_maps(kp: torch.Tensor, r: int, std: float) -> torch.Tensor:
    """Keypoints (N, 2K) as :class:`SpatialSoftmax` gives them (K x, then K y, in [-1, 1]) ->
    Gaussian maps (N, K, r, r) at the pixel centres of an r x r grid, peak 1; the std is at
    least half a cell (2 / r frame units a cell), so a coarse map still sees the point."""
    k = kp.shape[1] // 2
    s = max(std, 1.0 / r)
    c = (torch.arange(r, dtype=kp.dtype, device=kp.device) + 0.5) * (2.0 / r) - 1.0
    gx = torch.exp(-0.5 * ((c - kp[:, :k, None]) / s) ** 2)             # (N, K, r)
    gy = torch.exp(-0.5 * ((c - kp[:, k:, None]) / s) ** 2)
    return gy[:, :, :, None] * gx[:, :, None, :]


# --------------------------------------------------------------------------- networks
def _enc_channels(cfg: RssmConfig) -> list[int]:
    n = int(math.log2(cfg.size // 4))
    return [min(cfg.enc_depth * 2 ** i, 256) for i in range(n)]


def _dec_channels(cfg: RssmConfig) -> list[int]:
    """Channels at resolutions 4, 8, ..., size/2 (the last conv makes the 4 RGBA channels)."""
    n = int(math.log2(cfg.size // 4))
    return [max(8, min(128, cfg.dec_depth * 32 // (4 * 2 ** i))) for i in range(n)]


class SpatialSoftmax(nn.Module):
    """Feature map (B, C, H, W) -> keypoints (B, 2K): the expected (x, y) in [-1, 1] of each of K
    softmax distributions over the map (Finn et al. 2016, deep spatial autoencoders).

    Each channel of a 1x1 conv is standardised over the map before the softmax, so a small
    part unlike its surroundings dominates whatever its size; the sharpness is learned (one per
    keypoint, starting at 5: a 5-px ball on a plain wall then moves its keypoints by ~0.1-0.6).
    """

    def __init__(self, channels: int, k: int, size: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, k, 1)
        self.log_beta = nn.Parameter(torch.full((k,), math.log(5.0)))
        c = (torch.arange(size, dtype=torch.float32) + 0.5) * (2.0 / size) - 1.0     # pixel centres
        self.register_buffer("coords", c, persistent=False)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        logits = self.conv(f).flatten(2)
        logits = (logits - logits.mean(-1, keepdim=True)) / (logits.std(-1, keepdim=True) + 1e-5)
        p = torch.softmax(logits * self.log_beta.exp()[:, None], -1).view(f.shape[0], -1, f.shape[2], f.shape[3])
        return torch.cat([(p.sum(2) * self.coords).sum(-1), (p.sum(3) * self.coords).sum(-1)], 1)


class Encoder(nn.Module):
    """Premultiplied RGBA (B, 4, S, S) in [0, 1] -> embedding (B, embed + 2 * keypoints); also its
    feature maps."""

    def __init__(self, cfg: RssmConfig):
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 4
        for c in _enc_channels(cfg):
            layers += [nn.Conv2d(c_in, c, 4, 2, 1), nn.SiLU()]
            c_in = c
        self.convs = nn.Sequential(*layers)
        self.out = nn.Linear(c_in * 16, cfg.embed)
        # Keypoints over the first (finest) feature map; None keeps earlier runs' weights loadable.
        self.keypoints = (SpatialSoftmax(_enc_channels(cfg)[0], cfg.keypoints, cfg.size // 2)
                          if cfg.keypoints > 0 else None)
        self.maps = bool(cfg.keypoint_maps)
        self.map_std = float(cfg.keypoint_map_std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        maps = self.features(x)                  # coarsest first: the last is the finest
        kp = x.new_zeros(x.shape[0], 0) if self.keypoints is None else self.keypoints(maps[-1])
        return torch.cat([F.silu(self.out(maps[0].flatten(1))), kp], 1)

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Feature maps after each conv, coarsest first: [(B, C, 4, 4), (B, C', 8, 8), ..., (B, c, S/2, S/2)]."""
        maps: list[torch.Tensor] = []
        x = x - 0.5
        i = 0
        for layer in self.convs:
            x = layer(x)
            if i % 2 == 1:
                maps.insert(0, x)
            i += 1
        return maps

    def context(self, x: torch.Tensor) -> list[torch.Tensor]:
        """What the decoder's skip path reads of a context frame (B, 4, S, S): :meth:`features`,
        with ``keypoint_maps`` each joined by the Gaussian maps of the frame's keypoints."""
        maps = self.features(x)
        if not self.maps or self.keypoints is None:
            return maps
        kp = self.keypoints(maps[-1])
        return [torch.cat([m, keypoint_maps(kp, m.shape[-1], self.map_std)], 1) for m in maps]


class Decoder(nn.Module):
    """Features (B, deter + stoch + 4 * view_freqs [+ 4 * view_freqs of the context view with
    ``skip``]) -> premultiplied RGBA (B, 4, S, S) in [0, 1].

    Without ``skip`` the frame is generated from the features alone. With ``skip`` (the context
    frame's encoder maps ``ctx`` joined at each resolution, U-Net style) the last layer also
    gives a flow and masks. ``compose="copy3"`` (SV2P/CDNA-style): a per-pixel softmax over three
    candidates, the context frame as is, the context frame warped by the flow, and generated
    content; it starts close to copying, so static parts are copied exactly (no resampling
    blur) and only what moves is warped or drawn. ``"blend"``: one mask between the warped
    context frame and generated content. ``"accum"`` (:meth:`accum_step`): the flow is one
    step's motion, composed with the warp so far (:func:`accumulated_warp`), so parts may travel
    anywhere in the frame over many steps while the frame stays one resampling of the context
    frame; the context maps are moved along (:func:`warp_maps`), so the decoder sees where
    things are now; it starts as the context frame exactly (zero flow, mask ~95 % warp).
    With ``keypoint_maps`` each layer also reads Gaussian maps of the keypoints that ``kp_net``
    reads from the state (h, z), the first deter + stoch features.
    """

    def __init__(self, cfg: RssmConfig):
        super().__init__()
        ch = _dec_channels(cfg)
        self.c0 = ch[0]
        self.skip = bool(cfg.skip)
        self.max_flow = float(cfg.max_flow)
        self.copy3 = self.skip and cfg.compose == "copy3"
        self.accum = self.skip and cfg.compose == "accum"
        self.max_step_flow = float(cfg.max_step_flow)
        self.warp_leak = float(cfg.warp_leak)
        self.flow_snap = 2.0 * float(cfg.flow_snap) / cfg.size     # pixels -> grid_sample units
        self.mask_snap = float(cfg.mask_snap)
        # With the skip path the decoder also sees the context frame's viewpoint: warping that
        # frame to the current view needs to know where it was seen from.
        n_pe = 4 * cfg.view_freqs * ({"absolute": 2, "relative": 1, "both": 3}[cfg.decoder_view] + int(self.accum)
                                     if self.skip else 1)
        self.fc = nn.Sequential(nn.Linear(cfg.deter + cfg.stoch + n_pe, cfg.hidden), nn.SiLU(),
                                nn.Linear(cfg.hidden, ch[0] * 16))
        enc = _enc_channels(cfg)[::-1] if self.skip else [0] * len(ch)      # at 4, 8, ..., S/2
        self.n_state = cfg.deter + cfg.stoch
        self.map_std = float(cfg.keypoint_map_std)
        self.kp_net = (nn.Sequential(nn.Linear(self.n_state, cfg.hidden), nn.SiLU(),
                                     nn.Linear(cfg.hidden, 2 * cfg.keypoints)) if cfg.keypoint_maps else None)
        if cfg.keypoint_maps:             # the state's keypoints, and (skip) the context's in its maps
            enc = [c + cfg.keypoints * (1 + int(self.skip)) for c in enc]
        # RGBA, then mask logit(s) (copy3: copy, warp, generate; blend: warp), then flow x, y.
        n_out = (9 if self.copy3 else 7) if self.skip else 4
        self.ups = nn.ModuleList([nn.ConvTranspose2d(c_in + c_skip, c_out, 4, 2, 1)
                                  for c_in, c_skip, c_out in zip(ch, enc, ch[1:] + [n_out])])
        # Pixel-centre sampling grid of grid_sample (align_corners=False), (1, S, S, 2) as (x, y).
        self.register_buffer("grid", identity_grid(1, cfg.size), persistent=False)
        if self.skip:                     # start close to copying the context frame, unwarped
            with torch.no_grad():
                last = self.ups[-1]
                last.weight[:, 4:].mul_(0.1)
                last.bias[4:] = 0.0
                last.bias[4] = 3.0 if self.copy3 or self.accum else 1.0     # ~90-95 % copy at the start
                if self.accum:            # zero flow: the first steps are the context frame exactly
                    last.weight[:, 5:7] = 0.0

    def _load_from_state_dict(self, state_dict, prefix, *args, **kw):
        # Runs written before the skip path: ``convs`` was a Sequential (conv, SiLU, conv, ...).
        for k in [k for k in state_dict if k.startswith(prefix + "convs.")]:
            i, name = k[len(prefix) + 6:].split(".", 1)
            state_dict[f"{prefix}ups.{int(i) // 2}.{name}"] = state_dict.pop(k)
        super()._load_from_state_dict(state_dict, prefix, *args, **kw)

    def state_keypoints(self, feat: torch.Tensor) -> torch.Tensor:
        """``keypoint_maps``: the keypoints (N, 2K) the state (feat's first deter + stoch) puts the parts at."""
        if self.kp_net is None:
            return feat.new_zeros(feat.shape[0], 0)
        return self.kp_net(feat[:, :self.n_state])

    def heads(self, feat: torch.Tensor, ctx: list[torch.Tensor], kp: torch.Tensor) -> torch.Tensor:
        """The last layer's output (N, 4 | 7 | 9, S, S) before any compositing (see ``forward``);
        ``kp`` the state's keypoints (:meth:`state_keypoints`)."""
        x = F.silu(self.fc(feat).view(-1, self.c0, 4, 4))
        n = len(self.ups)
        i = 0
        for up in self.ups:
            if self.skip:
                x = torch.cat([x, ctx[i]], 1)
            if self.kp_net is not None:
                x = torch.cat([x, keypoint_maps(kp, x.shape[-1], self.map_std)], 1)
            x = up(x)
            if i < n - 1:
                x = F.silu(x)
            i += 1
        return x

    def accum_step(self, feat: torch.Tensor, ctx: list[torch.Tensor], ctx_pm: torch.Tensor,
                   grid: torch.Tensor, kp: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``compose="accum"``: the next frame (N, 4, S, S) premultiplied and its warp (N, S, S, 2),
        from the current frame's warp ``grid`` (the identity grid before the first step) and the
        context's maps ``ctx`` and pixels ``ctx_pm`` (as ``forward``); ``kp`` (N, 2K) the keypoints
        to draw from (``keypoint_teacher`` in training), by default the state's."""
        if kp is None:
            kp = self.state_keypoints(feat)
        x = self.heads(feat, warp_maps(ctx, grid), kp)
        s = torch.sigmoid(x[:, :5])                               # RGBA and the warp's share
        gen = torch.cat([s[:, :3] * s[:, 3:4], s[:, 3:4]], 1)
        flow = snap_flow(torch.tanh(x[:, 5:7]) * self.max_step_flow, self.flow_snap)
        grid = accumulated_warp(grid, flow, self.grid, self.warp_leak)
        warped = F.grid_sample(ctx_pm, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        return torch.lerp(gen, warped, snap_mask(s[:, 4:5], self.mask_snap)), grid

    def forward(self, feat: torch.Tensor, ctx: list[torch.Tensor], ctx_pm: torch.Tensor) -> torch.Tensor:
        """``ctx``: context maps per frame (coarsest first, as :meth:`Encoder.features`), ``ctx_pm``
        the premultiplied context frame (N, 4, S, S); both ignored without ``skip``. (``"accum"``:
        one step from the context frame, :meth:`accum_step` from the identity grid.)"""
        if self.accum:
            return self.accum_step(feat, ctx, ctx_pm, self.grid.expand(feat.shape[0], -1, -1, -1))[0]
        x = self.heads(feat, ctx, self.state_keypoints(feat))
        if not self.skip:
            rgba = torch.sigmoid(x)
            return torch.cat([rgba[:, :3] * rgba[:, 3:4], rgba[:, 3:4]], 1)
        gen = torch.sigmoid(x[:, :4])
        gen = torch.cat([gen[:, :3] * gen[:, 3:4], gen[:, 3:4]], 1)
        f0 = 7 if self.copy3 else 5
        flow = snap_flow(torch.tanh(x[:, f0:f0 + 2]) * self.max_flow, self.flow_snap)
        grid = self.grid.to(x.dtype) + flow.permute(0, 2, 3, 1)
        warped = F.grid_sample(ctx_pm, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        if self.copy3:
            m = torch.softmax(x[:, 4:7], 1)
            return m[:, 0:1] * ctx_pm + m[:, 1:2] * warped + m[:, 2:3] * gen
        mask = snap_mask(torch.sigmoid(x[:, 4:5]), self.mask_snap)
        return mask * warped + (1.0 - mask) * gen


class PhaseUp(nn.Module):
    """A ``ConvTranspose2d(c_in, c_out, 4, stride=2, padding=1)`` as one 2x2 convolution to
    4 x c_out channels, one per output phase, interleaved into the doubled grid: the same
    function with the same multiply-adds as the transposed convolution, which has no fast CPU
    kernel (measured on 1 core at 64x64: 505 us for the four layers against 743 for 3x3 subpixel
    convolutions and 902 for the transposed ones). The stepper decodes with these; training keeps
    the transposed convolutions (same weights, same results)."""

    def __init__(self, up: nn.ConvTranspose2d):
        super().__init__()
        if up.kernel_size != (4, 4) or up.stride != (2, 2) or up.padding != (1, 1) or up.groups != 1:
            raise ValueError("PhaseUp converts ConvTranspose2d(k=4, s=2, p=1) only")
        w = up.weight.detach()                                   # (c_in, c_out, 4, 4)
        c_in, c_out = w.shape[:2]
        k = w.new_zeros(c_out, 2, 2, c_in, 2, 2)                 # (c_out, row phase, col phase, c_in, 2, 2)
        # Output row 2m + a: a = 0 takes input rows m - 1 (tap 3) and m (tap 1); a = 1 takes rows
        # m (tap 2) and m + 1 (tap 0). The 2x2 convolution over the input padded by 1 sees rows
        # q - 1 and q at its output row q, so phase a reads its output at q = m + a.
        taps = ((3, 1), (2, 0))
        for a in (0, 1):
            for b in (0, 1):
                for j in (0, 1):
                    for i in (0, 1):
                        k[:, a, b, :, j, i] = w[:, :, taps[a][j], taps[b][i]].t()
        # Channels-last convolutions are faster from 32 input channels (1 core: 1.3-1.8x), slower below.
        self.channels_last = c_in >= 32
        fmt = torch.channels_last if self.channels_last else torch.contiguous_format
        self.weight = nn.Parameter(k.reshape(4 * c_out, c_in, 2, 2).contiguous(memory_format=fmt), requires_grad=False)
        bias = up.bias.detach() if up.bias is not None else w.new_zeros(c_out)
        self.bias = nn.Parameter(bias.repeat_interleave(4), requires_grad=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        y = F.conv2d(x, self.weight, self.bias, padding=1)       # (N, 4C, H + 1, W + 1), either layout
        n, c, h, w = y.shape[0], y.shape[1] // 4, y.shape[2] - 1, y.shape[3] - 1
        sn, sc, sh, sw = y.stride(0), y.stride(1), y.stride(2), y.stride(3)
        # Phase (a, b) at (m, n) is y[:, 4c + 2a + b, m + a, n + b]: a linear offset in (a, b, m, n)
        # in any layout, so one strided view gathers all four phases.
        s = y.as_strided([n, c, 2, 2, h, w], [sn, 4 * sc, 2 * sc + sh, sc + sw, sh, sw])
        return s.permute(0, 1, 4, 2, 5, 3).reshape(n, c, 2 * h, 2 * w)


def fast_decoder(dec: Decoder) -> Decoder:
    """A copy of ``dec`` for the run-time stepper, its upsampling layers recast as :class:`PhaseUp`."""
    fast = copy.deepcopy(dec)
    fast.ups = nn.ModuleList([PhaseUp(u) for u in fast.ups])
    return fast


def straight(pm: torch.Tensor) -> torch.Tensor:
    """Premultiplied RGBA (B, 4, S, S) -> straight RGBA (colour undefined where alpha is ~0)."""
    a = pm[:, 3:4]
    return torch.cat([(pm[:, :3] / a.clamp(min=1e-4)).clamp(0.0, 1.0), a], 1)


def _gauss(stats: torch.Tensor, min_std: float) -> tuple[torch.Tensor, torch.Tensor]:
    mean, raw = stats.chunk(2, -1)
    return mean, F.softplus(raw) + min_std


class OscCell(nn.Module):
    """A GRU cell beside ``n`` damped rotations, one recurrent state (B, units + 2n): [gru, re, im].

    Each mode k turns by ``theta_k`` radians a step and keeps ``exp(-exp(nu_k))`` of its length;
    the input drives the modes, the GRU reads them. Initialised near the unit circle (keeps
    0.97-0.999 a step) with periods of 6-120 steps, so a mode rings long after the trained horizon.
    ``keep_min`` floors the kept length. Same call as ``nn.GRUCell``: ``cell(x, h) -> h``."""

    def __init__(self, input_size: int, units: int, n: int, keep_min: float = 0.0):
        super().__init__()
        self.n = n
        self.keep_min = keep_min
        self.units = units
        self.cell = nn.GRUCell(input_size + 2 * n, units)
        self.drive = nn.Linear(input_size, 2 * n, bias=False)   # rings about 0
        g = torch.Generator().manual_seed(0)
        keep = 0.97 + 0.029 * torch.rand(n, generator=g)
        self.nu = nn.Parameter(torch.log(-torch.log(keep)))
        self.theta = nn.Parameter(2 * math.pi / torch.exp(torch.empty(n).uniform_(math.log(6.0), math.log(120.0), generator=g)))
        with torch.no_grad():
            self.drive.weight.mul_(0.1)

    def kept(self) -> torch.Tensor:
        """The share of each mode's length kept a step (n,)."""
        return torch.exp(-torch.exp(self.nu)).clamp(min=self.keep_min)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        g, re, im = h[:, :self.units], h[:, self.units:self.units + self.n], h[:, self.units + self.n:]
        keep = self.kept()
        c, s = keep * torch.cos(self.theta), keep * torch.sin(self.theta)
        d_re, d_im = self.drive(x).chunk(2, -1)
        re, im = c * re - s * im + d_re, s * re + c * im + d_im
        g = self.cell(torch.cat([x, re, im], -1), g)
        return torch.cat([g, re, im], -1)


class Rssm(nn.Module):
    """The model. The transition (``gru``, ``prior``) takes no viewpoint input at all."""

    def __init__(self, cfg: RssmConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.decoder = Decoder(cfg)
        self.z_in = nn.Sequential(nn.Linear(cfg.stoch, cfg.hidden), nn.SiLU())
        self.gru = (OscCell(cfg.hidden, cfg.deter - 2 * cfg.osc, cfg.osc, cfg.osc_keep_min) if cfg.osc
                    else nn.GRUCell(cfg.hidden, cfg.deter))
        self.prior = nn.Sequential(nn.Linear(cfg.deter, cfg.hidden), nn.SiLU(), nn.Linear(cfg.hidden, 2 * cfg.stoch))
        self.post = nn.Sequential(nn.Linear(cfg.deter + cfg.embed + 2 * cfg.keypoints + 4 * cfg.view_freqs, cfg.hidden), nn.SiLU(),
                                  nn.Linear(cfg.hidden, 2 * cfg.stoch))
        # Training only (keypoint_scale): the keypoints of a state's frame; None keeps old runs loadable.
        # With keypoint_maps it is the decoder's own (one head: the maps are drawn where it says).
        self.kp_head = (self.decoder.kp_net if cfg.keypoint_maps else
                        nn.Sequential(nn.Linear(cfg.deter + cfg.stoch, cfg.hidden), nn.SiLU(),
                                      nn.Linear(cfg.hidden, 2 * cfg.keypoints)) if cfg.keypoint_scale > 0 else None)
        if cfg.keypoints_frozen and self.encoder.keypoints is not None:
            self.encoder.keypoints.requires_grad_(False)

    # -- pieces shared by training and the stepper
    def transition(self, h: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Next deterministic state (B, deter) from (B, deter), (B, stoch)."""
        return self.gru(self.z_in(z), h)

    def prior_stats(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return _gauss(self.prior(h), self.cfg.min_std)

    def post_stats(self, h: torch.Tensor, emb: torch.Tensor, pe: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return _gauss(self.post(torch.cat([h, emb, pe], -1)), self.cfg.min_std)

    def decode(self, h: torch.Tensor, z: torch.Tensor, pe: torch.Tensor, ctx: list[torch.Tensor],
               ctx_pm: torch.Tensor, ctx_pe: torch.Tensor) -> torch.Tensor:
        """Premultiplied RGBA (N, 4, S, S); ``ctx``/``ctx_pm``/``ctx_pe`` of the context frame, one per row."""
        return self.decoder(decoder_features(h, z, pe, ctx_pe, self.cfg.skip, self.cfg.decoder_view,
                                             self.cfg.view_freqs, ctx_pe if self.decoder.accum else None),
                            ctx, ctx_pm)

    def decode_chain(self, h: torch.Tensor, z: torch.Tensor, pe: torch.Tensor, prev_pe: torch.Tensor,
                     ctx: list[torch.Tensor], ctx_pm: torch.Tensor, ctx_pe: torch.Tensor,
                     grid: torch.Tensor, kp: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``compose="accum"``: consecutive frames of each row, one step after another. ``h``, ``z``
        (N, T, .), ``pe`` (N, T, 4F) their views, ``prev_pe`` (N, 4F) the view of the frame before
        the first, ``grid`` (N, S, S, 2) its warp; context as :meth:`decode`; ``kp`` (N, T, 2K) the
        keypoints to draw each frame from (None: the states'). Returns premultiplied RGBA
        (N, T, 4, S, S) and the last frame's warp."""
        out = []
        for t in range(h.shape[1]):
            feat = decoder_features(h[:, t], z[:, t], pe[:, t], ctx_pe, True, self.cfg.decoder_view,
                                    self.cfg.view_freqs, prev_pe)
            x, grid = self.decoder.accum_step(feat, ctx, ctx_pm, grid, None if kp is None else kp[:, t])
            out.append(x)
            prev_pe = pe[:, t]
        return torch.stack(out, 1), grid


# --------------------------------------------------------------------------- losses
def _kl(m1, s1, m2, s2) -> torch.Tensor:
    """KL(N(m1, s1) || N(m2, s2)) summed over the last axis (nats)."""
    return (torch.log(s2 / s1) + (s1 ** 2 + (m1 - m2) ** 2) / (2 * s2 ** 2) - 0.5).sum(-1)


def premultiply(rgba: torch.Tensor) -> torch.Tensor:
    """Straight RGBA (..., 4, H, W) -> premultiplied colour and alpha, same shape."""
    return torch.cat([rgba[..., :3, :, :] * rgba[..., 3:4, :, :], rgba[..., 3:4, :, :]], -3)


def _pixel_err(pred_pm: torch.Tensor, target_pm: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Squared error per pixel (N, 4, S, S); ``weight`` (N, 1, S, S) scales each pixel's error."""
    err = (pred_pm - target_pm) ** 2
    return err if weight is None else err * weight


def _rec_loss(pred_pm: torch.Tensor, target_pm: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Squared error summed over pixels (Gaussian, unit variance), mean over frames (see :func:`_pixel_err`)."""
    return _pixel_err(pred_pm, target_pm, weight).flatten(1).sum(1).mean()


def motion_weights(x: torch.Tensor, scale: float) -> torch.Tensor:
    """Per-pixel loss weights (B, T, 1, S, S) of premultiplied frames ``x`` (B, T, 4, S, S), T >= 2.

    1 + ``scale`` * (largest channel change from the previous frame; frame 0 uses frame 1's): the
    moving parts of a toy are a small fraction of the crop, and a plain per-pixel error is
    minimised well enough by a still frame.
    """
    d = (x[:, 1:] - x[:, :-1]).abs().amax(2, keepdim=True)
    return 1.0 + scale * torch.cat([d[:, :1], d], 1)


def with_predicted_change(w: torch.Tensor | None, pred: torch.Tensor, prev: torch.Tensor, scale: float,
                          how: str) -> torch.Tensor | None:
    """The loss weights ``w`` (N, 1, S, S) of predicted frames ``pred`` (N, 4, S, S), raised with
    ``how="both"`` to 1 + ``scale`` * the prediction's largest channel change from the true previous
    frame ``prev`` (N, 4, S, S) where that is more (no gradient through the weight).

    Weights from the truth's change alone pull a prediction toward change: a part drawn moving
    where the truth stays costs no more than elsewhere, one left still where the truth moves
    costs up to 1 + scale times as much (``RssmConfig.motion_weight_of``).
    """
    if w is None or how == "truth":
        return w
    return torch.maximum(w, 1.0 + scale * (pred.detach() - prev).abs().amax(1, keepdim=True))


def energy_match(pred: torch.Tensor, truth: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Squared log ratio of motion energies (mean |frame change|) of each sequence, mean over the batch.

    ``pred``, ``truth``: premultiplied (B, T, 4, S, S), T >= 2 consecutive frames. A sampled
    open loop scored by squared error alone is free to move more or less than the truth (the
    error of a wrong motion is about that of none); this term asks it to move as much.
    """
    e_p = (pred[:, 1:] - pred[:, :-1]).abs().flatten(1).mean(1)
    e_t = (truth[:, 1:] - truth[:, :-1]).abs().flatten(1).mean(1)
    return ((torch.log(e_p + eps) - torch.log(e_t + eps)) ** 2).mean()


def motion_envelope(x: torch.Tensor, grow: int = 2) -> torch.Tensor:
    """Where each window's truth moves, (B, 1, S, S) in [0, 1], from premultiplied frames ``x``
    (B, T, 4, S, S), T >= 2: the largest channel change between consecutive frames over the
    window, grown by ``grow`` pixels (max pooling) and divided by the window's largest (0 where
    nothing changes). Any frame rate, any footage: no threshold."""
    d = (x[:, 1:] - x[:, :-1]).abs().amax(2).amax(1, keepdim=True)           # (B, 1, S, S)
    if grow > 0:
        d = F.max_pool2d(d, 2 * grow + 1, 1, grow)
    return d / d.flatten(1).amax(1).clamp(min=1e-6)[:, None, None, None]


def sharpness_match(pred: torch.Tensor, truth: torch.Tensor, where: torch.Tensor | None = None) -> torch.Tensor:
    """Squared distance between the distributions of the pixel-to-pixel differences (horizontal and
    vertical, per channel) of each frame, summed over them, mean over frames: ``pred``, ``truth``
    (N, C, S, S), each frame's differences sorted and compared rank by rank (the 1-D Wasserstein-2
    distance, times their count).

    Blind to where things are: an edge drawn in the wrong place costs nothing here, an edge left
    out, faded or smeared does. Squared error alone is least for the mean of the places a part may
    be, so a small moving part whose place is uncertain (a pendulum's ball, a toy's arm) is drawn
    faded or smeared; with this term beside it a sharp part in one place may cost less. (On the
    pendulum footage a frame with the ball 5-6 frames away scores 0.03-0.12 here, the mean of 13
    frames 0.25-0.45; a global value histogram told them apart less well, exposure flicker moves it.)

    ``where`` (N, 1, S, S) in [0, 1] (e.g. :func:`motion_envelope`): each difference is weighted by
    it (the mean of its two pixels') before sorting, so only the parts of the frame it covers are
    compared, still blind to where in them an edge is.
    """
    def diffs(x: torch.Tensor) -> torch.Tensor:
        dv, dh = x[..., 1:, :] - x[..., :-1, :], x[..., :, 1:] - x[..., :, :-1]
        if where is not None:
            dv = dv * (0.5 * (where[..., 1:, :] + where[..., :-1, :]))
            dh = dh * (0.5 * (where[..., :, 1:] + where[..., :, :-1]))
        return torch.cat([dv.flatten(2), dh.flatten(2)], 2)

    return ((diffs(pred).sort(-1).values - diffs(truth).sort(-1).values) ** 2).flatten(1).sum(1).mean()


def pyramid_err(pred: torch.Tensor, truth: torch.Tensor, levels: int) -> torch.Tensor:
    """Squared error of ``pred`` and ``truth`` (N, C, S, S) blurred at ``levels`` scales (level l:
    averaged down by 2 ** (l - 1), then a Gaussian of 2 pixels there, i.e. ~2 ** l pixels of the
    frame), each level's pixel counted for the pixels it covers, summed over levels and pixels,
    mean over frames.

    Through a warp (grid_sample) a pixel's error moves the flow only where the context frame has
    an edge within a pixel of the sampling point: a small part predicted several pixels from where
    the truth has it gets no gradient toward it at full size, only to fade it. Blurred, the two
    overlap again and the flow is pulled toward the truth (coarse to fine, as flow estimators'
    multi-scale losses); a level of 2 ** l pixels reaches ~2 ** (l + 1).
    """
    from kornia.filters import gaussian_blur2d     # training only: the run-time stepper does not need it

    total = pred.new_zeros(())
    for level in range(1, levels + 1):
        k = 2 ** (level - 1)
        if 4 * k > pred.shape[-1]:
            break
        a, b = (F.avg_pool2d(pred, k), F.avg_pool2d(truth, k)) if k > 1 else (pred, truth)
        # kornia's separable Gaussian (std 2 px, 3 std each side, edges replicated)
        d = gaussian_blur2d(a - b, (13, 13), (2.0, 2.0), border_type="replicate")
        total = total + (d * d).flatten(1).sum(1).mean() * (k * k)
    return total


def best_of(err: torch.Tensor, k: int, b: int) -> torch.Tensor:
    """Best-of-K loss: ``err`` (k * b * n, ...) per-pixel errors of k sampled copies (copy-major) of
    b windows of n frames -> mean over windows of the least (over copies) per-window error (pixels
    summed, frames averaged). With k = 1 it is the plain reconstruction loss.

    A sampled open loop scored by its error alone is pulled toward the average of the motions a
    window may take (a blur); scored by its best of k it may keep several sharp ones.
    """
    return err.flatten(1).sum(1).view(k, b, -1).mean(2).min(0).values.mean()


def _decoded(n: int, k: int, first: int, device: torch.device) -> torch.Tensor:
    """Indices of the frames to decode: all of ``first..n-1`` if at most ``k``, else ``k`` of them at
    random (sorted); a long window is decoded sparsely so its cost stays that of a short one."""
    if n - first <= k:
        return torch.arange(first, n, device=device)
    return first + torch.randperm(n - first, device=device)[:k].sort().values


def sequence_loss(model: Rssm, x: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """Training loss of a batch of sequences.

    ``x``: premultiplied RGBA (B, T+1, 4, S, S) in [0, 1], frame 0 the context;
    ``views``: (B, T+1, 3) [azimuth_deg, elevation_deg, distance_m]. Returns (loss, parts).
    """
    cfg = model.cfg
    B, T1 = x.shape[:2]
    pe = view_encoding(views, cfg.view_freqs)
    emb = model.encoder(x.flatten(0, 1)).view(B, T1, -1)
    # Context of every decoded frame: frame 0's encoder maps, pixels and viewpoint, n rows per sequence.
    ctx0 = model.encoder.context(x[:, 0]) if cfg.skip else []

    def decode(h: torch.Tensor, z: torch.Tensor, ts: torch.Tensor, reps: int = 1) -> torch.Tensor:
        """Frames ``ts`` of every sequence from states (reps * B, len(ts), .) -> (reps * B * len(ts), 4, S, S);
        ``reps`` copies of the batch, copy-major (row r * B + b is sequence b)."""
        n = len(ts)
        rep = lambda a: a.repeat((reps,) + (1,) * (a.dim() - 1)).repeat_interleave(n, 0)
        return model.decode(h.flatten(0, 1), z.flatten(0, 1), pe[:, ts].repeat(reps, 1, 1).flatten(0, 1),
                            [rep(c) for c in ctx0], rep(x[:, 0]), rep(pe[:, 0]))

    h = x.new_zeros(B, cfg.deter)
    hs, zs, zd, kl_dyn, kl_rep, post_m, post_s, prior_m = [], [], [], [], [], [], [], []
    z = None
    for t in range(T1):                                  # filtering: posterior at every step
        if z is not None:
            h = model.transition(h, z)
        pm, ps = model.prior_stats(h)
        prior_m.append(pm)
        qm, qs = model.post_stats(h, emb[:, t], pe[:, t])
        z = qm + qs * torch.randn_like(qs)
        hs.append(h)
        zs.append(z)
        # What the filtering frame is decoded from: the posterior, or (as at run time) a prior sample.
        zd.append(z if cfg.filter_decode == "posterior" else pm + ps * torch.randn_like(ps))
        post_m.append(qm)
        post_s.append(qs)
        kl_dyn.append(_kl(qm.detach(), qs.detach(), pm, ps).mean())
        kl_rep.append(_kl(qm, qs, pm.detach(), ps.detach()).mean())
    # Free nats on the representation term only (per step, batch mean): the prior always learns.
    dyn = torch.stack(kl_dyn).mean()
    rep = torch.clamp(torch.stack(kl_rep), min=cfg.free_nats).mean()
    kl = cfg.kl_balance * dyn + (1 - cfg.kl_balance) * rep
    w = motion_weights(x, cfg.motion_weight) if cfg.motion_weight > 0 else None
    accum = model.decoder.accum
    k = min(max(cfg.open_loop_from, 0), T1 - 2)
    K = cfg.open_loop_samples                            # best-of-K: K copies of the batch, copy-major
    if accum:
        # Frames follow one another (each step's warp builds on the last): the filtering frames
        # 1..T are decoded in order from the identity warp (frame 0 is the context itself), and
        # the open loop goes on from the filtering warp of frame k, as its states do.
        def chain(hh, zz, t0, t1, grid, reps=1):
            rep = lambda a: a.repeat((reps,) + (1,) * (a.dim() - 1))
            kp = rep(emb[:, t0:t1, cfg.embed:].detach()) if cfg.keypoint_teacher else None
            return model.decode_chain(hh, zz, rep(pe[:, t0:t1]), rep(pe[:, t0 - 1]), [rep(c) for c in ctx0],
                                      rep(x[:, 0]), rep(pe[:, 0]), grid, kp)

        H, Zd = torch.stack(hs, 1), torch.stack(zd, 1)
        f1, g_k = x[:, :0], model.decoder.grid.expand(B, -1, -1, -1)
        if k >= 1:
            f1, g_k = chain(H[:, 1:k + 1], Zd[:, 1:k + 1], 1, k + 1, g_k)
        f2, _ = chain(H[:, k + 1:], Zd[:, k + 1:], k + 1, T1, g_k)
        ti = torch.arange(1, T1, device=x.device)
        fr = torch.cat([f1, f2], 1).flatten(0, 1)
        fr_truth = x[:, 1:].flatten(0, 1)
        rec = _rec_loss(fr, fr_truth, with_predicted_change(
            None if w is None else w[:, 1:].flatten(0, 1), fr, x[:, :-1].flatten(0, 1), cfg.motion_weight,
            cfg.motion_weight_of))
    else:
        ti = _decoded(T1, cfg.decode_frames + 1, 0, x.device)
        fr = decode(torch.stack(hs, 1)[:, ti], torch.stack(zd, 1)[:, ti], ti)
        fr_truth = x[:, ti].flatten(0, 1)
        rec = _rec_loss(fr, fr_truth, with_predicted_change(
            None if w is None else w[:, ti].flatten(0, 1), fr, x[:, (ti - 1).clamp(min=0)].flatten(0, 1),
            cfg.motion_weight, cfg.motion_weight_of))
    # Open loop, the way it runs: prior samples only, from the filtering state of frame k.
    # k = 0 is the run-time start exactly, but one frame cannot tell which way a swing goes,
    # so a sampled rollout from it is scored against one direction and the error is least for
    # a still, averaged frame: the model learns to stop. From k = 1 the posterior has seen
    # frames 0 and 1 (the direction is in z_1) and the open loop learns sustained motion; the
    # run time samples z_1 from the prior, which the dynamics KL trains to cover those posteriors.
    ol_h, ol_z, overshoot = _open_loop(model, hs[k], zs[k], post_m, post_s, k, K)
    oi = torch.arange(k + 1, T1, device=x.device) if accum else _decoded(T1, cfg.decode_frames, k + 1, x.device)
    dh, dz, di = torch.stack(ol_h, 1)[:, oi - k - 1], torch.stack(ol_z, 1)[:, oi - k - 1], oi
    n0 = 0
    loss = cfg.rec_scale * rec + cfg.kl_scale * kl + cfg.overshoot_scale * overshoot
    parts = {"rec": rec.item(), "kl_dyn": dyn.item(), "kl_rep": torch.stack(kl_rep).mean().item(),
             "overshoot": overshoot.item()}
    # The open loop's frames are decoded only for a loss that scores them; without one (PlaNet's
    # open_loop_scale=0) the prior learns from the KL and overshooting alone, and skipping the
    # decoder there roughly halves a step's cost (more steps in the same minutes).
    pixels = (cfg.open_loop_scale > 0 or cfg.sharp_scale > 0 or cfg.energy_scale > 0
              or (cfg.pyramid_scale > 0 and cfg.pyramid_on in ("both", "open_loop")))
    ol_x = None
    if cfg.prior_first and k >= 1 and (pixels or cfg.first_step_scale > 0):
        # The run-time step 1 exactly: z_1 sampled from the prior at h_1 (the open loop from
        # frame k >= 1 never decodes it; untrained, it drew a random motion and lost ~3 dB to copying).
        # With the open loop it is one of the open loop's frames (K copies), without it scored alone.
        reps = K if pixels else 1
        h1 = hs[1].repeat(reps, 1)
        pm1, ps1 = model.prior_stats(h1)
        z1 = pm1 + cfg.open_loop_temperature * ps1 * torch.randn_like(ps1)
        if accum:                                        # from the identity warp, as at run time
            first, _ = chain(h1[:, None], z1[:, None], 1, 2, model.decoder.grid.expand(reps * B, -1, -1, -1), reps)
        elif not pixels:
            first = decode(h1[:, None], z1[:, None], torch.ones(1, dtype=torch.long, device=x.device))[:, None]
        if pixels:
            if not accum:
                dh, dz = torch.cat([h1[:, None], dh], 1), torch.cat([z1[:, None], dz], 1)
            di, n0 = torch.cat([di.new_ones(1), di]), 1
        else:
            first = first.flatten(0, 1)
            first_err = _rec_loss(first, x[:, 1], with_predicted_change(
                None if w is None else w[:, 1], first, x[:, 0], cfg.motion_weight, cfg.motion_weight_of))
            loss = loss + cfg.first_step_scale * first_err
            parts["first_step"] = first_err.item()
    if pixels:
        if accum:
            ol_x, _ = chain(dh, dz, k + 1, T1, g_k.repeat(K, 1, 1, 1), K)
            ol_x = (torch.cat([first, ol_x], 1) if n0 else ol_x).flatten(0, 1)
        else:
            ol_x = decode(dh, dz, di, K)
        copies = lambda a, i=di: a[:, i].flatten(0, 1).repeat(K, 1, 1, 1)
        w_ol = with_predicted_change(None if w is None else copies(w), ol_x, copies(x, di - 1), cfg.motion_weight,
                                     cfg.motion_weight_of)
        ol = best_of(_pixel_err(ol_x, copies(x), w_ol), K, B)
        loss = loss + cfg.open_loop_scale * ol
        parts["open_loop"] = ol.item()
        if cfg.sharp_scale > 0:
            env = None
            if cfg.sharp_where == "moving":              # each frame's window's envelope, as copies() lays them out
                env = motion_envelope(x)[:, None].expand(-1, len(di), -1, -1, -1).flatten(0, 1).repeat(K, 1, 1, 1)
            sh = sharpness_match(ol_x, copies(x), env)
            loss = loss + cfg.sharp_scale * sh
            parts["sharp"] = sh.item()
    if cfg.pyramid_scale > 0:                            # every copy, not only the best (best_of)
        py = loss.new_zeros(())
        if cfg.pyramid_on in ("both", "filter"):
            py = py + pyramid_err(fr, fr_truth, cfg.pyramid_levels)
        if ol_x is not None and cfg.pyramid_on in ("both", "open_loop"):
            py = py + pyramid_err(ol_x, copies(x), cfg.pyramid_levels)
        loss = loss + cfg.pyramid_scale * py
        parts["pyramid"] = py.item()
    if model.kp_head is not None:
        kerr = _keypoint_err(model, emb, hs, zs, ol_h, ol_z, k, prior_m)
        loss = loss + cfg.keypoint_scale * kerr
        parts["keypoints"] = kerr.item()
    if ol_x is not None and cfg.energy_scale > 0 and len(oi) > 1 and int(oi[-1] - oi[0]) == len(oi) - 1:
        # consecutive frames only
        en = energy_match(ol_x[:B * len(di)].view(B, len(di), *x.shape[2:])[:, n0:], x[:, oi])
        loss = loss + cfg.energy_scale * en
        parts["energy"] = en.item()
    parts["loss"] = loss.item()
    return loss, parts


def _open_loop(model: Rssm, h: torch.Tensor, z: torch.Tensor, post_m: list[torch.Tensor],
               post_s: list[torch.Tensor], k: int, reps: int = 1) -> tuple[list, list, torch.Tensor]:
    """The open loop from the filtering state (``h``, ``z``) (B, .) of frame ``k``: prior samples
    only, ``reps`` copies of the batch (copy-major), to the last of the posteriors ``post_m``/``post_s``
    (T+1 of (B, stoch)). Returns its states (T - k of (reps * B, .) each) and the latent
    overshooting term (the posteriors, detached, against its priors)."""
    ho, zo = h.repeat(reps, 1), z.repeat(reps, 1)
    ol_h, ol_z, over = [], [], []
    for t in range(k + 1, len(post_m)):
        ho = model.transition(ho, zo)
        pm, ps = model.prior_stats(ho)
        zo = pm + model.cfg.open_loop_temperature * ps * torch.randn_like(ps)
        ol_h.append(ho)
        ol_z.append(zo)
        over.append(_kl(post_m[t].detach().repeat(reps, 1), post_s[t].detach().repeat(reps, 1), pm, ps).mean())
    return ol_h, ol_z, torch.stack(over).mean()


def mean_step(a: torch.Tensor) -> torch.Tensor:
    """Mean absolute step of trajectories ``a`` (B, T, D) along time: (B, D)."""
    return (a[:, 1:] - a[:, :-1]).abs().mean(1)


def _keypoint_err(model: Rssm, emb: torch.Tensor, hs: list[torch.Tensor], zs: list[torch.Tensor],
                  ol_h: list[torch.Tensor], ol_z: list[torch.Tensor], k: int,
                  prior_m: list[torch.Tensor] | None = None) -> torch.Tensor:
    """``keypoint_scale``'s error: the frames' keypoints (``emb`` (B, T+1, embed + 2K), detached)
    against the head's reading of the filtering states ``hs``/``zs`` (T+1 of (B, .)); with
    ``keypoint_open_loop``, of the open loop's ``ol_h``/``ol_z`` from frame ``k`` (T - k of
    (R * B, .), R copies of the batch; with ``keypoint_energy``, also its mean step lengths); with
    ``keypoint_prior``, of the filtering steps' prior means ``prior_m`` (T+1 of (B, stoch); frame
    0's, a forecast from nothing, is left out)."""
    kp = emb[:, :, model.cfg.embed:].detach()
    kf = model.kp_head(torch.cat([torch.stack(hs, 1), torch.stack(zs, 1)], -1))
    err = ((kf - kp) ** 2).sum(-1).mean()
    if model.cfg.keypoint_prior and prior_m is not None and len(hs) > 1:
        kpr = model.kp_head(torch.cat([torch.stack(hs[1:], 1), torch.stack(prior_m[1:], 1)], -1))
        err = err + ((kpr - kp[:, 1:]) ** 2).sum(-1).mean()
    if not model.cfg.keypoint_open_loop or not ol_h:
        return err
    ko = model.kp_head(torch.cat([torch.stack(ol_h, 1), torch.stack(ol_z, 1)], -1))
    reps = ko.shape[0] // kp.shape[0]
    target = kp[:, k + 1:].repeat(reps, 1, 1)
    err = err + ((ko - target) ** 2).sum(-1).mean()
    if model.cfg.keypoint_energy > 0 and ko.shape[1] > 1:
        err = err + model.cfg.keypoint_energy * ((mean_step(ko) - mean_step(target)) ** 2).sum(-1).mean()
    return err


def latent_loss(model: Rssm, x: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """The prior's share of :func:`sequence_loss` alone, with the encoder and posterior held fixed
    and nothing decoded (``TrainConfig.dynamics_steps``): the dynamics KL along the filtering
    states, latent overshooting along the open loop and (``keypoint_scale``) the keypoints read from
    both. Same arguments as :func:`sequence_loss`; a fraction of its cost."""
    cfg = model.cfg
    B, T1 = x.shape[:2]
    pe = view_encoding(views, cfg.view_freqs)
    with torch.no_grad():
        emb = model.encoder(x.flatten(0, 1)).view(B, T1, -1)
    h, z = x.new_zeros(B, cfg.deter), None
    hs, zs, post_m, post_s, dyn, prior_m = [], [], [], [], [], []
    for t in range(T1):
        if z is not None:
            h = model.transition(h, z)
        pm, ps = model.prior_stats(h)
        prior_m.append(pm)
        with torch.no_grad():
            qm, qs = model.post_stats(h, emb[:, t], pe[:, t])
        z = qm + qs * torch.randn_like(qs)
        hs.append(h)
        zs.append(z)
        post_m.append(qm)
        post_s.append(qs)
        dyn.append(_kl(qm, qs, pm, ps).mean())
    k = min(max(cfg.open_loop_from, 0), T1 - 2)
    ol_h, ol_z, o = _open_loop(model, hs[k], zs[k], post_m, post_s, k)
    d = torch.stack(dyn).mean()
    loss = cfg.kl_scale * cfg.kl_balance * d + cfg.overshoot_scale * o
    parts = {"kl_dyn": d.item(), "overshoot": o.item()}
    if model.kp_head is not None:
        kerr = _keypoint_err(model, emb, hs, zs, ol_h, ol_z, k, prior_m)
        loss = loss + cfg.keypoint_scale * kerr
        parts["keypoints"] = kerr.item()
    return loss, parts


# --------------------------------------------------------------------------- run-time stepper
class Stepper(nn.Module):
    """Run-time API, TorchScript-exportable.

    ``start(rgba, view) -> (h, z)``: the state after seeing the first frame (straight RGBA
    (B, 4, S, S) in [0, 1], view (B, 3) = [azimuth_deg, elevation_deg, distance_m]). With the
    skip path the stepper also keeps that frame (and its encoder maps) as the context of the
    following steps, so one stepper runs one rollout (batch) at a time.
    ``step(h, z, view) -> (h, z, rgba)``: advance one frame (the transition ignores ``view``),
    sample the stochastic state (``temperature`` scales its std; 0 gives the mean) and decode
    the next straight RGBA frame as seen from ``view``.
    """

    def __init__(self, model: Rssm, temperature: float = 1.0):
        super().__init__()
        self.encoder = model.encoder
        self.decoder = fast_decoder(model.decoder)    # the same function, faster (PhaseUp)
        self.z_in = model.z_in
        self.gru = model.gru
        self.prior = model.prior
        self.post = model.post
        self.min_std = float(model.cfg.min_std)
        self.freqs = int(model.cfg.view_freqs)
        self.deter = int(model.cfg.deter)
        self.size = int(model.cfg.size)
        self.skip = bool(model.cfg.skip)
        self.decoder_view = str(model.cfg.decoder_view)
        self.accum = bool(self.decoder.accum)
        self.temperature = float(temperature)
        self.ctx = []                  # the context frame's encoder maps (skip path), set by start()
        self.ctx_pm = torch.zeros(0)
        self.warp = torch.zeros(0)     # compose "accum": the last frame's warp, set by start(), step()
        self.ctx_view = torch.zeros(0)  # the context's and (accum) the last frame's viewpoints (N, 3)
        self.prev_view = torch.zeros(0)
        self.fast_views = self.accum and self.decoder_view == "relative"
        # Radians per degree at octaves 1, 2, 4, ... (view_encoding's frequencies).
        self.register_buffer("octaves", (math.pi / 180.0) * 2.0 ** torch.arange(self.freqs, dtype=torch.float32),
                             persistent=False)

    def _pe(self, view: torch.Tensor) -> torch.Tensor:
        a = view[:, :2, None] * self.octaves.to(view.dtype)
        return torch.cat([torch.sin(a), torch.cos(a)], -1).flatten(1)

    @torch.jit.export
    def start(self, rgba: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pm = premultiply(rgba)
        emb = self.encoder(pm)
        if self.skip:
            self.ctx = self.encoder.context(pm)
            self.ctx_pm = pm
            self.ctx_view = view
            self.prev_view = view
            self.warp = self.decoder.grid.expand(rgba.shape[0], -1, -1, -1).to(rgba.dtype)
        h = torch.zeros(rgba.shape[0], self.deter, dtype=rgba.dtype, device=rgba.device)
        mean, raw = self.post(torch.cat([h, emb, self._pe(view)], -1)).chunk(2, -1)
        std = F.softplus(raw) + self.min_std
        return h, mean + self.temperature * std * torch.randn_like(std)

    def _transition(self, h: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The next state: h from the GRU, z sampled from the prior (``temperature`` times its std)."""
        h = self.gru(self.z_in(z), h)
        mean, raw = self.prior(h).chunk(2, -1)
        std = F.softplus(raw) + self.min_std
        return h, torch.addcmul(mean, std, torch.randn_like(std), value=self.temperature)

    def _decode(self, h: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        """Straight RGBA (B, 4, S, S) of state (h, z) seen from ``view``; moves the accumulated warp on."""
        if self.fast_views:
            # "accum" with relative views (the default): the view changes' encodings come straight
            # from the angles (the same values as view_delta_encoding, in fewer operations).
            n = view.shape[0]
            d = self._pe(torch.cat([view - self.ctx_view, view - self.prev_view]))
            pm, self.warp = self.decoder.accum_step(torch.cat([h, z, d[:n], d[n:]], -1), self.ctx, self.ctx_pm, self.warp)
            self.prev_view = view
            return straight(pm)
        pe = self._pe(view)
        ctx_pe = self._pe(self.ctx_view) if self.skip else pe      # without the skip path: unused
        if self.accum:
            feat = decoder_features(h, z, pe, ctx_pe, self.skip, self.decoder_view, self.freqs,
                                    self._pe(self.prev_view))
            pm, self.warp = self.decoder.accum_step(feat, self.ctx, self.ctx_pm, self.warp)
            self.prev_view = view
        else:
            feat = decoder_features(h, z, pe, ctx_pe, self.skip, self.decoder_view, self.freqs)
            pm = self.decoder(feat, self.ctx, self.ctx_pm)
        return straight(pm)

    @torch.jit.export
    def step(self, h: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        h, z = self._transition(h, z)
        return h, z, self._decode(h, z, view)

    @torch.jit.export
    def observe(self, h: torch.Tensor, z: torch.Tensor, rgba: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Filtering instead of forecasting: the next state after seeing frame ``rgba`` (straight
        RGBA (B, 4, S, S)) from ``view``, z the posterior's mean. Nothing is decoded."""
        h = self.gru(self.z_in(z), h)
        pm = premultiply(rgba)
        mean, raw = self.post(torch.cat([h, self.encoder(pm), self._pe(view)], -1)).chunk(2, -1)
        return h, mean

    @torch.jit.export
    def decode(self, h: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        """The frame of a state (e.g. from :meth:`observe`) seen from ``view`` (see :meth:`step`)."""
        return self._decode(h, z, view)

    def forward(self, h: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.step(h, z, view)


def script_stepper(model: Rssm, temperature: float = 1.0) -> torch.jit.ScriptModule:
    """The TorchScript stepper of ``model`` (on CPU, eval mode)."""
    st = Stepper(model, temperature).cpu().eval()
    st.ctx = torch.jit.Attribute([], List[torch.Tensor])     # TorchScript cannot type an empty list
    return torch.jit.script(st)


@torch.no_grad()
def rollout(stepper, first: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
    """Open-loop frames from ``first`` (B, 4, S, S) straight RGBA; ``views`` (B, T+1, 3) incl. frame 0.

    Returns straight RGBA (B, T, 4, S, S) for frames 1..T.
    """
    h, z = stepper.start(first, views[:, 0])
    out = []
    for t in range(1, views.shape[1]):
        h, z, x = stepper.step(h, z, views[:, t])
        out.append(x)
    return torch.stack(out, 1)


# --------------------------------------------------------------------------- data
@dataclass
class SequenceData:
    """Frames of a crops.json dataset in memory, and the sequence windows over them."""

    source: Path
    rgba: np.ndarray               # (N, S, S, 4) uint8 straight RGBA
    views: np.ndarray              # (N, 3) float32 [azimuth_deg, elevation_deg, distance_m]
    splits: np.ndarray             # (N,) str
    times: np.ndarray              # (N,) seconds
    windows: list[tuple[int, str]]  # (start, split)
    length: int                    # frames per window (1 context + predicted)
    meta: dict = field(default_factory=dict)

    def starts(self, split: str) -> np.ndarray:
        return np.array([s for s, sp in self.windows if sp == split], dtype=np.int64)


def load_sequences(dataset: Path, size: int = 64) -> SequenceData:
    """Read ``crops.json`` (RGBA crops, per-frame ``viewpoint``, ``split``, ``time``, ``sequences``).

    Windows come from the file's ``sequences``; a file without them gets windows from the frame
    times (:func:`dbb_capture.crops.camera.sequence_windows`, 11 frames).
    """
    src = find_dataset_file(Path(dataset))
    if src.name != "crops.json":
        raise DbbError(f"{dataset}: the RSSM trains on a preprocess dataset (crops.json), found {src.name}")
    meta = read_json(src, "dataset")
    ds = load_dataset(src)
    raw = meta["frames"]
    views, times = [], []
    for i, f in enumerate(raw):
        vp = f.get("viewpoint")
        try:
            views.append([float(vp["azimuth_deg"]), float(vp["elevation_deg"]), float(vp["distance_m"])])
        except (TypeError, KeyError, ValueError):
            raise DbbError(f"{src} frame {i}: needs viewpoint {{azimuth_deg, elevation_deg, distance_m}}") from None
        if f.get("time") is None:
            raise DbbError(f"{src} frame {i}: needs time (seconds)")
        times.append(float(f["time"]))
    splits = np.array([fr.split for fr in ds.frames])
    length = int(meta.get("sequence_length", 11))
    if "sequences" in meta:
        windows = [(int(s["start"]), str(s["split"])) for s in meta["sequences"]]
    else:
        windows = sequence_windows(np.array(times), splits, length)
    if any(s < 0 or s + length > len(raw) for s, _ in windows):
        raise DbbError(f"{src}: a sequence window runs past the last frame")
    if not any(sp == "train" for _, sp in windows):
        raise DbbError(f"{src}: no training sequences of {length} consecutive frames")
    imgs = np.empty((len(raw), size, size, 4), np.uint8)
    with progress(transient=True) as prog:
        task = prog.add_task("load crops", total=len(raw), info="")
        for i, fr in enumerate(ds.frames):
            imgs[i] = np.round(resize_rgba(load_rgba(fr), size) * 255).astype(np.uint8)
            prog.update(task, advance=1)
    return SequenceData(src, imgs, np.array(views, np.float32), splits, np.array(times), windows, length,
                        {k: v for k, v in meta.items() if k != "frames"})


def training_windows(data: SequenceData, horizon: int | None) -> tuple[np.ndarray, int]:
    """Starts and length (1 + ``horizon``) of the training windows: runs of consecutive training
    frames (no gap, no split change). Longer than the dataset's 1 + 10 windows so the transition
    learns motion that goes on; the horizon shrinks to what the training frames allow, and
    ``None`` keeps the dataset's windows."""
    if horizon is None or horizon + 1 == data.length:
        return data.starts("train"), data.length
    n_train = int((data.splits == "train").sum())
    for length in range(min(horizon + 1, n_train), data.length - 1, -1):
        # At least half as many windows as frames: a handful of long windows would be memorised.
        w = sequence_windows(data.times, data.splits, length)
        starts = np.array([s for s, sp in w if sp == "train"], dtype=np.int64)
        if len(starts) >= max(1, n_train // 2):
            return starts, length
    return data.starts("train"), data.length


def _batch(data: SequenceData, starts: np.ndarray, device: torch.device,
           length: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Premultiplied RGBA (B, L, 4, S, S) float and views (B, L, 3) of windows starting at ``starts``
    (L = ``length``, default the dataset's window length)."""
    idx = starts[:, None] + np.arange(length or data.length)[None]
    x = torch.from_numpy(data.rgba[idx]).to(device).permute(0, 1, 4, 2, 3).float() / 255.0
    return premultiply(x), torch.from_numpy(data.views[idx]).to(device)


def augment(x: torch.Tensor, views: torch.Tensor, how: str, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Training windows ``x`` (B, L, 4, S, S), ``views`` (B, L, 3), each changed with probability 1/2
    as ``how`` asks (``TrainConfig.augment``): "flip" mirrors the frames left-right and negates the
    azimuth (the mirrored toy seen from the mirrored side), "reverse" plays the window backwards.
    "shift" moves every window by a random whole-pixel offset of up to S/16 (:func:`shift_windows`).

    The toy is seen along one camera path, each viewpoint at one time: the model can learn which
    pose goes with which view and window instead of how the toy moves (2-5 dB better on training
    windows than on held-out ones, docs/benchmarks.md); mirrored and reversed windows are motions
    it has not seen.
    """
    kinds = set(how.split(","))
    B = x.shape[0]
    if "flip" in kinds:
        f = torch.from_numpy(rng.random(B) < 0.5).to(x.device)
        x = torch.where(f[:, None, None, None, None], x.flip(-1), x)
        views = torch.where(f[:, None, None], views * views.new_tensor([-1.0, 1.0, 1.0]), views)
    if "reverse" in kinds:
        r = torch.from_numpy(rng.random(B) < 0.5).to(x.device)
        x = torch.where(r[:, None, None, None, None], x.flip(1), x)
        views = torch.where(r[:, None, None], views.flip(1), views)
    if "shift" in kinds:
        x = shift_windows(x, rng.integers(-(x.shape[-1] // 16), x.shape[-1] // 16 + 1, size=(B, 2)))
    return x, views


def shift_windows(x: torch.Tensor, offsets: np.ndarray) -> torch.Tensor:
    """Windows ``x`` (B, L, C, S, S) each moved by whole pixels ``offsets`` (B, 2) = (dx, dy), the
    same for every frame of a window (its motion is kept), edges repeated (DrQ's random shift).

    The crops put the toy at one place in the frame; a model that only ever sees it there can key
    its motion to pixel positions it will not meet at new viewpoints, where the crop sits a pixel
    or two off."""
    B, L, C, S, _ = x.shape
    k = int(np.abs(offsets).max()) if len(offsets) else 0
    if k == 0:
        return x
    pad = F.pad(x.reshape(B, L * C, S, S), (k, k, k, k), mode="replicate")
    out = [pad[b, :, k - dy:k - dy + S, k - dx:k - dx + S] for b, (dx, dy) in enumerate(offsets.tolist())]
    return torch.stack(out).reshape(B, L, C, S, S)


# --------------------------------------------------------------------------- model selection
def validation_split(data: SequenceData, starts: np.ndarray, length: int,
                     fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Training window starts (those ending before the held-out tail) and validation window starts
    (the dataset's training windows inside the last ``fraction`` of the training frames, in time).

    The test split is the capture's last 20 %: new viewpoints at new times. The tail of the
    training split is the nearest thing to it the training data has; no training window may
    touch it, or the selection would score memorised frames.
    """
    train = np.flatnonzero(data.splits == "train")
    order = train[np.argsort(data.times[train], kind="stable")]
    cut_t = data.times[order[int(len(order) * (1.0 - fraction))]]
    val = np.array([s for s in data.starts("train") if data.times[s] >= cut_t], dtype=np.int64)
    keep = np.array([s for s in starts if data.times[s + length - 1] < cut_t], dtype=np.int64)
    if len(val) == 0 or len(keep) == 0:
        raise DbbError(f"val_fraction {fraction}: too few training frames for held-out windows "
                       f"({len(keep)} training / {len(val)} validation windows)")
    return keep, val


@torch.no_grad()
def validate(model: Rssm, data: SequenceData, starts: np.ndarray, seed: int = 0, max_windows: int = 24) -> dict:
    """Open-loop score of ``model`` on the windows at ``starts``, run as at run time (the stepper,
    sampled at temperature 1, fixed seed): ``gain`` = mean PSNR (dB, premultiplied RGBA) minus
    that of copying the first frame; ``energy_ratio`` = mean |frame change| of the predictions over
    the truth's. Leaves the global random state as it was."""
    if len(starts) > max_windows:
        starts = starts[np.linspace(0, len(starts) - 1, max_windows).round().astype(int)]
    x, views = _batch(data, starts, torch.device("cpu"))                 # premultiplied (W, L, 4, S, S)
    first = torch.from_numpy(data.rgba[starts]).permute(0, 3, 1, 2).float() / 255.0
    was_training = model.training
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        pred = premultiply(rollout(Stepper(model.eval()), first, views.cpu()))
    model.train(was_training)
    x, pred = x.numpy(), pred.numpy()
    truth = x[:, 1:]

    def mean_psnr(p: np.ndarray) -> float:
        return float(np.mean([psnr(a, b) for a, b in zip(p.reshape(-1, *p.shape[2:]), truth.reshape(-1, *p.shape[2:]))]))

    # Time first for motion_energy; the predictions' first change is from the context frame.
    e_pred = motion_energy(np.concatenate([x[:, :1], pred], 1).swapaxes(0, 1))
    e_true = motion_energy(x.swapaxes(0, 1))
    return {"gain": mean_psnr(pred) - mean_psnr(np.broadcast_to(x[:, :1], truth.shape)),
            "energy_ratio": e_pred / max(e_true, 1e-9)}


@dataclass
class Selection:
    """The best model so far on the held-out tail (``TrainConfig.val_fraction``) and the scores."""

    step: int = -1
    gain: float = -math.inf
    energy_ratio: float = 0.0
    qualified: bool = False          # its open loop moved at least val_min_energy of the truth
    state_dict: dict | None = None
    history: list[dict] = field(default_factory=list)   # {step, gain, energy_ratio} per validation

    def offer(self, step: int, score: dict, model: Rssm, min_energy: float) -> None:
        """Keep ``model`` if it beats the best: any model that moves enough beats one that does not."""
        self.history.append({"step": step, **{k: round(v, 4) for k, v in score.items()}})
        q = score["energy_ratio"] >= min_energy
        if (q, score["gain"]) > (self.qualified, self.gain):
            self.step, self.gain, self.energy_ratio, self.qualified = step, score["gain"], score["energy_ratio"], q
            self.state_dict = {k: v.detach().clone().cpu() for k, v in model.state_dict().items()}

    def summary(self) -> dict:
        return {"step": self.step, "gain_vs_copy_first_db": round(self.gain, 3),
                "energy_ratio": round(self.energy_ratio, 3), "moves_enough": self.qualified,
                "validations": self.history}


# --------------------------------------------------------------------------- training
@dataclass
class TrainState:
    model: Rssm
    opt: torch.optim.Optimizer
    step: int = 0
    seconds: float = 0.0
    bad_steps: int = 0                      # non-finite losses or gradients skipped, in total
    history: list[dict] = field(default_factory=list)
    selection: Selection | None = None      # model selection on held-out training windows (val_fraction)
    ema: dict | None = None                 # the weights' moving average (TrainConfig.ema), as a state dict
    ema_updates: int = 0
    train_config: dict | None = None        # the TrainConfig it was trained with (asdict), for --resume

    def save(self, path: Path) -> None:
        tmp = Path(path).with_suffix(".tmp")
        torch.save({"config": asdict(self.model.cfg), "model": self.model.state_dict(),
                    "opt": self.opt.state_dict(), "step": self.step, "seconds": self.seconds,
                    "bad_steps": self.bad_steps, "history": self.history,
                    "selection": None if self.selection is None else asdict(self.selection),
                    "ema": self.ema, "ema_updates": self.ema_updates, "train_config": self.train_config}, tmp)
        tmp.replace(path)

    def update_ema(self, decay: float) -> None:
        """Move the average toward the current weights. Bias-corrected (as Adam's moments): after
        n updates it is sum_i decay^(n-i) w_i / sum_i decay^(n-i), the weights seen so far and
        never the initial ones, so a short run's average is as good as a long one's."""
        sd = self.model.state_dict()
        self.ema_updates += 1
        if self.ema is None:
            self.ema = {k: v.detach().clone() for k, v in sd.items()}
            return
        share = (1.0 - decay) / (1.0 - decay ** self.ema_updates)
        with torch.no_grad():
            for k, v in sd.items():
                if v.is_floating_point():
                    self.ema[k].lerp_(v, share)
                else:
                    self.ema[k].copy_(v)

    def run_model(self) -> Rssm:
        """The model a run writes, on the CPU in eval mode: the selected one (``val_fraction``),
        else the weights' average (``ema``), else the last weights."""
        model = self.model.cpu().eval()
        best = self.selection.state_dict if self.selection is not None else None
        sd = best if best is not None else self.ema
        if sd is not None:
            model = copy.deepcopy(model)
            model.load_state_dict(sd)
        return model

    @classmethod
    def load(cls, path: Path, tcfg: TrainConfig, device: torch.device) -> TrainState:
        ck = _read_checkpoint(path, device)
        try:
            model = Rssm(RssmConfig.from_json(ck["config"])).to(device)
            model.load_state_dict(ck["model"])
        except (KeyError, RuntimeError) as e:
            raise DbbError(f"cannot read RSSM checkpoint {path}: {e}") from None
        st = cls(model, _optimizer(model, tcfg), ck["step"], ck["seconds"], ck.get("bad_steps", 0), ck["history"])
        st.opt.load_state_dict(ck["opt"])
        if ck.get("selection"):
            st.selection = Selection(**ck["selection"])
        st.ema, st.ema_updates = ck.get("ema"), ck.get("ema_updates", 0)
        st.train_config = ck.get("train_config")
        return st


def resume_configs(out: Path) -> tuple[RssmConfig, TrainConfig]:
    """The model and training settings of the run ``out``'s last checkpoint, as the base that a
    resumed run's own settings go over (so ``--resume`` keeps ``--preset``/``--set`` given at the
    start). Checkpoints written before training settings were stored give the training defaults."""
    path = resume_checkpoint(Path(out))
    ck = _read_checkpoint(path, torch.device("cpu"))
    if "config" not in ck:
        raise DbbError(f"cannot read RSSM checkpoint {path}: it has no model config")
    cfg = RssmConfig.from_json(ck["config"])
    names = {f.name for f in fields(TrainConfig)}
    stored = {k: v for k, v in (ck.get("train_config") or {}).items() if k in names}
    return cfg, TrainConfig(**stored)


def _read_checkpoint(path: Path, device: torch.device) -> dict:
    try:
        return torch.load(path, map_location=device, weights_only=False)
    except (OSError, RuntimeError) as e:
        raise DbbError(f"cannot read RSSM checkpoint {path}: {e}") from None


def _optimizer(model: Rssm, tcfg: TrainConfig) -> torch.optim.Optimizer:
    if tcfg.weight_decay > 0.0:
        return torch.optim.AdamW(model.parameters(), lr=tcfg.lr, eps=tcfg.adam_eps, weight_decay=tcfg.weight_decay)
    return torch.optim.Adam(model.parameters(), lr=tcfg.lr, eps=tcfg.adam_eps)


def lr_at(tcfg: TrainConfig, fraction: float) -> float:
    """Learning rate at ``fraction`` (0..1) of the budget: cosine from ``lr`` to ``lr * lr_end``."""
    return tcfg.lr * (tcfg.lr_end + (1.0 - tcfg.lr_end) * 0.5 * (1.0 + math.cos(math.pi * fraction)))


def train(state: TrainState, data: SequenceData, tcfg: TrainConfig, ckpt: Path | None = None,
          on_step=None) -> TrainState:
    """Train until ``tcfg.minutes`` (wall clock, over all sessions) or ``tcfg.steps`` is reached.

    A step whose loss or gradient is not finite is skipped (optimiser untouched) and counted;
    ``max_bad_steps`` in a row end training with a :class:`DbbError`.
    """
    starts, length = training_windows(data, tcfg.horizon)
    val = None
    if tcfg.val_fraction > 0:
        starts, val = validation_split(data, starts, length, tcfg.val_fraction)
        if state.selection is None:
            state.selection = Selection()
    rng = np.random.default_rng(tcfg.seed + state.step)
    state.train_config = asdict(tcfg)
    state.model.train()
    try:
        _train_loop(state, data, tcfg, ckpt, on_step, starts, length, rng, val)
    except KeyboardInterrupt:
        if ckpt is not None:             # an interrupted run resumes from here (--resume)
            state.save(ckpt)
        raise
    if ckpt is not None:
        state.save(ckpt)
    return state


def _train_loop(state: TrainState, data: SequenceData, tcfg: TrainConfig, ckpt: Path | None, on_step,
                starts: np.ndarray, length: int, rng: np.random.Generator, val: np.ndarray | None = None) -> None:
    model, device = state.model, next(state.model.parameters()).device
    last_ckpt = time.perf_counter()
    t_prev = time.perf_counter()
    in_a_row = 0
    lat_starts, lat_length = starts, length
    if tcfg.dynamics_steps and tcfg.dynamics_horizon is not None:
        lat_starts, lat_length = training_windows(data, tcfg.dynamics_horizon)
        if val is not None:              # the held-out frames stay out of these windows too
            lat_starts = validation_split(data, lat_starts, lat_length, tcfg.val_fraction)[0]

    def draw(pool: np.ndarray = starts, n: int = length) -> tuple[torch.Tensor, torch.Tensor]:
        pick = pool[rng.integers(0, len(pool), tcfg.batch)]
        return augment(*_batch(data, pick, device, n), tcfg.augment, rng)

    while not _done(state, tcfg):
        x, v = draw()
        loss, parts = sequence_loss(model, x, v)
        state.opt.zero_grad(set_to_none=True)
        ok = bool(torch.isfinite(loss))
        if ok:
            loss.backward()
            gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), tcfg.grad_clip)
            ok = bool(torch.isfinite(gnorm))
        if ok:
            if tcfg.lr_end < 1.0:        # a function of the budget's fraction, so --resume continues it
                for g in state.opt.param_groups:
                    g["lr"] = lr_at(tcfg, _fraction(state, tcfg))
            state.opt.step()
            for _ in range(tcfg.dynamics_steps):
                dl = latent_loss(model, *draw(lat_starts, lat_length))[0]
                state.opt.zero_grad(set_to_none=True)
                good = bool(torch.isfinite(dl))
                if good:
                    dl.backward()
                    good = bool(torch.isfinite(torch.nn.utils.clip_grad_norm_(model.parameters(), tcfg.grad_clip)))
                if good:
                    state.opt.step()
                else:
                    state.bad_steps += 1
            if tcfg.ema > 0.0:
                state.update_ema(tcfg.ema)
            in_a_row = 0
        else:
            state.bad_steps += 1
            in_a_row += 1
            if in_a_row >= tcfg.max_bad_steps:
                raise DbbError(f"training diverged: {in_a_row} non-finite steps in a row at step {state.step} "
                               "(last good checkpoint kept; try a lower learning rate)")
        now = time.perf_counter()
        state.seconds += now - t_prev
        t_prev = now
        state.step += 1
        if ok and (state.step % 10 == 0 or state.step == 1 or _done(state, tcfg)):
            state.history.append({"step": state.step, "seconds": round(state.seconds, 2),
                                  **{k: round(v, 4) for k, v in parts.items()}})
        if val is not None and (state.step % tcfg.val_every == 0 or _done(state, tcfg)):
            # Validation time counts against the budget (it is part of training).
            state.selection.offer(state.step, validate(state.model, data, val, tcfg.seed), state.model,
                                  tcfg.val_min_energy)
            now = time.perf_counter()
            state.seconds += now - t_prev
            t_prev = now
        if on_step is not None:
            on_step(state, parts if ok else None)
        if ckpt is not None and tcfg.snapshot_every > 0 and state.step % tcfg.snapshot_every == 0:
            snaps = ckpt.parent.parent / (ckpt.parent.name.removesuffix(".work") + ".snapshots")
            snaps.mkdir(exist_ok=True)
            torch.save({"config": asdict(model.cfg), "state_dict": state.ema if state.ema is not None
                        else model.state_dict()}, snaps / f"{state.step:06d}.pt")
        if ckpt is not None and now - last_ckpt > tcfg.checkpoint_seconds:
            state.save(ckpt)
            last_ckpt = now


def _done(state: TrainState, tcfg: TrainConfig) -> bool:
    if tcfg.steps is not None and state.step >= tcfg.steps:
        return True
    return tcfg.minutes is not None and state.seconds >= 60 * tcfg.minutes


def _fraction(state: TrainState, tcfg: TrainConfig) -> float:
    f = 0.0
    if tcfg.steps:
        f = max(f, state.step / tcfg.steps)
    if tcfg.minutes:
        f = max(f, state.seconds / (60 * tcfg.minutes))
    return min(f, 1.0)


def motion_energy(frames: np.ndarray) -> float:
    """Mean absolute frame-to-frame change of premultiplied RGBA frames (T, ..., S, S)."""
    return float(np.mean(np.abs(np.diff(frames.astype(np.float64), axis=0)))) if len(frames) > 1 else 0.0


def motion_coherence(frames: np.ndarray) -> float | None:
    """Mean cosine between successive frame changes of frames (T, S, S, C), T >= 3.

    Near 1 for smooth motion (a swing changes the same pixels the same way from one step to the
    next), near 0 or below for jitter (changes that come and go at random); ``None`` if still.
    """
    d = np.diff(frames.astype(np.float64), axis=0).reshape(len(frames) - 1, -1)
    n = np.linalg.norm(d, axis=1)
    ok = (n[:-1] > 1e-9) & (n[1:] > 1e-9)
    if not ok.any():
        return None
    return float(np.mean(np.sum(d[:-1] * d[1:], 1)[ok] / (n[:-1] * n[1:])[ok]))


def _pm_np(rgba_u8_or_float: np.ndarray) -> np.ndarray:
    """Straight RGBA (..., S, S, 4) uint8 or float -> premultiplied float32 (..., S, S, 4)."""
    x = rgba_u8_or_float.astype(np.float32)
    if rgba_u8_or_float.dtype == np.uint8:
        x /= 255.0
    return np.concatenate([x[..., :3] * x[..., 3:4], x[..., 3:4]], -1)


def _unit(views: np.ndarray) -> np.ndarray:
    a, e = np.radians(views[:, 0]), np.radians(views[:, 1])
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)


def nearest_training_frames(data: SequenceData, views: np.ndarray) -> np.ndarray:
    """Index of the training frame whose viewing direction is closest to each of ``views`` (M, 3)."""
    train = np.flatnonzero(data.splits == "train")
    if len(train) == 0:
        raise DbbError("no training frames for the 'near' baseline")
    cos = _unit(views) @ _unit(data.views[train]).T
    return train[np.argmax(cos, 1)]


@dataclass
class EvalReport:
    """Open-loop quality on held-out sequences and long-rollout motion (see ``to_json``)."""

    split: str
    windows: int
    steps: int
    psnr: dict[str, list[float]]          # method -> mean PSNR per predicted step (dB)
    ssim: dict[str, list[float]]
    motion: dict                          # motion-energy figures of the still-viewpoint rollouts
    notes: list[str]

    def mean(self, metric: str, method: str) -> float:
        return float(np.mean(getattr(self, metric)[method]))

    def to_json(self) -> dict:
        r = lambda xs: [round(float(v), 4) for v in xs]
        return {"split": self.split, "windows": self.windows, "steps": self.steps,
                "metric_space": "premultiplied RGBA in [0, 1]",
                "psnr_db": {k: r(v) for k, v in self.psnr.items()},
                "ssim": {k: r(v) for k, v in self.ssim.items()},
                "mean_psnr_db": {k: round(self.mean("psnr", k), 3) for k in self.psnr},
                "mean_ssim": {k: round(self.mean("ssim", k), 4) for k in self.ssim},
                "psnr_gain_db": {"vs_copy_first": round(self.mean("psnr", "model") - self.mean("psnr", "copy_first"), 3),
                                 "vs_near": round(self.mean("psnr", "model") - self.mean("psnr", "near"), 3)},
                "motion": self.motion, "notes": self.notes}


def evaluate(stepper, data: SequenceData, max_windows: int = 64, rollout_steps: int = 150,
             still_truth: np.ndarray | None = None, still_start: tuple[np.ndarray, np.ndarray] | None = None,
             seed: int = 0) -> tuple[EvalReport, dict]:
    """Per-step PSNR/SSIM of open-loop predictions vs "near" and copy-first-frame; motion energy.

    ``stepper``: a :class:`Stepper` (eager or TorchScript). The model column samples the
    stochastic state (as at run time); ``model_mean`` uses temperature 0 where the stepper
    allows it. Motion: ``rollout_steps`` steps at a still viewpoint from the first frame of a
    few held-out windows; truth energy is that of ``still_truth`` (T, S, S, 4) straight RGBA
    uint8 rendered at the same still viewpoint when given (synthetic data; ``still_start`` =
    (first frame (S, S, 4) uint8, view (3,)) is then the start), otherwise that of the
    dataset's own consecutive frames (which include the camera's motion). Returns the report
    and arrays for the figures.
    """
    notes = []
    split = "test"
    starts = data.starts("test")
    if len(starts) == 0:
        split, starts = "train", data.starts("train")
        notes.append("no test sequences in the dataset: evaluated on training sequences")
    if len(starts) > max_windows:
        starts = starts[np.linspace(0, len(starts) - 1, max_windows).round().astype(int)]
    L = data.length
    idx = starts[:, None] + np.arange(L)[None]
    truth = _pm_np(data.rgba[idx])                                   # (W, L, S, S, 4)
    views = data.views[idx]
    torch.manual_seed(seed)
    first = torch.from_numpy(data.rgba[idx[:, 0]]).permute(0, 3, 1, 2).float() / 255.0
    vt = torch.from_numpy(views)
    preds = {"model": rollout(stepper, first, vt)}
    mean_stepper = _with_temperature(stepper, 0.0)
    if mean_stepper is not None:
        preds["model_mean"] = rollout(mean_stepper, first, vt)
    methods: dict[str, np.ndarray] = {k: _pm_np(v.permute(0, 1, 3, 4, 2).numpy()) for k, v in preds.items()}
    near = nearest_training_frames(data, views[:, 1:].reshape(-1, 3)).reshape(len(starts), L - 1)
    methods["near"] = _pm_np(data.rgba[near])
    methods["copy_first"] = np.repeat(truth[:, :1], L - 1, 1)
    ps = {k: [float(np.mean([psnr(m[w, t], truth[w, t + 1]) for w in range(len(starts))])) for t in range(L - 1)]
          for k, m in methods.items()}
    ss = {k: [float(np.mean([ssim(m[w, t], truth[w, t + 1]) for w in range(len(starts))])) for t in range(L - 1)]
          for k, m in methods.items()}
    # Long rollouts at a still viewpoint.
    truth_src = "rendered at the still viewpoint"
    if still_truth is None and fixed_camera(data) and len(data.rgba) > rollout_steps:
        # A fixed camera's footage is its own still-viewpoint truth: start at the first test
        # frame when enough frames follow it, otherwise as late as possible.
        k = min(int(starts[0]) if split == "test" else 0, len(data.rgba) - rollout_steps - 1)
        still_start, still_truth = (data.rgba[k], data.views[k]), data.rgba[k + 1:k + 1 + rollout_steps]
        truth_src = f"the footage itself, frames {k + 1}-{k + rollout_steps} (fixed camera)"
    if still_start is not None:
        f0 = torch.from_numpy(still_start[0][None]).permute(0, 3, 1, 2).float() / 255.0
        v0 = torch.from_numpy(np.asarray(still_start[1], np.float32)[None])
    else:
        pick = idx[np.linspace(0, len(starts) - 1, min(4, len(starts))).round().astype(int), 0]
        f0 = torch.from_numpy(data.rgba[pick]).permute(0, 3, 1, 2).float() / 255.0
        v0 = torch.from_numpy(data.views[pick])
    still_views = v0[:, None].expand(-1, rollout_steps + 1, -1).contiguous()
    torch.manual_seed(seed + 1)
    long = _pm_np(rollout(stepper, f0, still_views).permute(0, 1, 3, 4, 2).numpy())   # (K, T, S, S, 4)
    pred_e = [motion_energy(long[:, t:t + 2].swapaxes(0, 1)) for t in range(rollout_steps - 1)]
    if still_truth is not None:
        tr = _pm_np(still_truth)
        truth_e = motion_energy(tr)
        truth_curve = [motion_energy(tr[t:t + 2]) for t in range(len(tr) - 1)]
    else:
        diffs = [motion_energy(_pm_np(data.rgba[s:s + L])) for s, _ in data.windows]
        truth_e = float(np.mean(diffs))
        truth_curve = None
        truth_src = "dataset sequences (includes camera motion)"
        notes.append("motion-energy truth from the dataset's moving-camera sequences, not a still viewpoint")
    pred_mean = float(np.mean(pred_e))
    coh = [c for c in (motion_coherence(r) for r in long) if c is not None]
    truth_coh = motion_coherence(tr) if still_truth is not None else None
    half = len(pred_e) // 2
    motion = {"steps": rollout_steps, "rollouts": int(f0.shape[0]), "pred_energy": round(pred_mean, 6),
              "truth_energy": round(truth_e, 6), "truth_source": truth_src,
              "ratio": round(pred_mean / truth_e, 4) if truth_e > 0 else None,
              "ratio_first_half": round(float(np.mean(pred_e[:half])) / truth_e, 4) if truth_e > 0 else None,
              "ratio_second_half": round(float(np.mean(pred_e[half:])) / truth_e, 4) if truth_e > 0 else None,
              # Smooth motion or jitter: mean cosine of successive frame changes (see motion_coherence).
              "coherence": round(float(np.mean(coh)), 4) if coh else None,
              "truth_coherence": None if truth_coh is None else round(truth_coh, 4)}
    report = EvalReport(split, len(starts), L - 1, ps, ss, motion, notes)
    figs = {"truth": truth, "methods": methods, "long": long, "pred_curve": pred_e, "truth_curve": truth_curve,
            "truth_energy": truth_e, "still_truth": None if still_truth is None else _pm_np(still_truth)}
    return report, figs


def fixed_camera(data: SequenceData) -> bool:
    """Whether every frame has the same viewpoint (preprocess's fixed-camera mode)."""
    return bool(np.ptp(data.views[:, :2], 0).max() < 1e-3)


def _with_temperature(stepper, temperature: float):
    """The same stepper with another sampling temperature (eager :class:`Stepper` only)."""
    if isinstance(stepper, Stepper):
        s = Stepper.__new__(Stepper)
        s.__dict__.update(stepper.__dict__)
        s.temperature = temperature
        return s
    return None


@dataclass
class Calibration:
    """The run-time temperature fitted to the footage (:func:`calibrate_temperature`).

    Energies are mean absolute changes per step of premultiplied RGBA frames (as
    :func:`motion_energy`), over ``steps``-step runs from the training frames ``starts``.
    """

    temperature: float
    target: float | None                  # the footage's own motion, as the model sees it (a fixed
                                          # camera's: as the footage has it)
    energy: dict[float, float]            # still-view open-loop energy at each temperature tried
    starts: list[int]
    steps: int
    note: str | None = None

    def to_json(self) -> dict:
        return {"temperature": round(self.temperature, 4),
                "target_energy": None if self.target is None else round(self.target, 6),
                "energy_by_temperature": {f"{t:g}": round(e, 6) for t, e in self.energy.items()},
                "starts": self.starts, "steps": self.steps, "note": self.note}


# Temperatures the calibration tries (the fit interpolates between them and stays inside them).
CALIBRATION_TEMPERATURES = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0)


def long_training_runs(data: SequenceData, steps: int, count: int) -> tuple[np.ndarray, int]:
    """Up to ``count`` evenly spread starts of runs of 1 + ``steps`` consecutive training frames,
    and that length; shorter runs (down to the dataset's window) when the footage has none."""
    for length in range(min(steps + 1, len(data.times)), data.length - 1, -1):
        starts = np.array([s for s, sp in sequence_windows(data.times, data.splits, length) if sp == "train"],
                          dtype=np.int64)
        if len(starts):
            pick = np.linspace(0, len(starts) - 1, min(count, len(starts))).round().astype(int)
            return starts[np.unique(pick)], length
    return np.zeros(0, np.int64), 0


@torch.no_grad()
def still_view_target(model: Rssm, data: SequenceData, starts: np.ndarray, length: int) -> float:
    """Energy per step of the footage's own motion as the model sees it: the posterior follows
    the real frames (:meth:`Stepper.observe`, its mean), and each state is decoded from the
    first frame's viewpoint, held still. The transition takes no viewpoint, so what changes
    is the object; the decoder's blur is in it, as in the open loop it is compared with.
    A fixed camera's footage is itself seen from a still viewpoint: its own change is the
    target there (frames 1 to L-1, as the open loop's)."""
    idx = starts[:, None] + np.arange(length)[None]
    x = torch.from_numpy(data.rgba[idx]).permute(0, 1, 4, 2, 3).float() / 255.0     # (B, L, 4, S, S)
    if fixed_camera(data):
        return motion_energy(premultiply(x[:, 1:].transpose(0, 1)).numpy())
    st = _with_temperature(Stepper(model.cpu().eval()), 0.0)
    v = torch.from_numpy(data.views[idx])
    h, z = st.start(x[:, 0], v[:, 0])
    frames = []
    for t in range(1, length):
        h, z = st.observe(h, z, x[:, t], v[:, t])
        frames.append(st.decode(h, z, v[:, 0]))
    return motion_energy(premultiply(torch.stack(frames)).numpy())


@torch.no_grad()
def still_view_energy(model: Rssm, data: SequenceData, starts: np.ndarray, length: int, temperature: float,
                      samples: int = 2, seed: int = 0) -> float:
    """Energy per step of ``samples`` open-loop rollouts at ``temperature`` from each of the
    frames ``starts``, each at its own viewpoint held still for ``length - 1`` steps."""
    first = torch.from_numpy(data.rgba[starts]).permute(0, 3, 1, 2).float().repeat(samples, 1, 1, 1) / 255.0
    views = torch.from_numpy(data.views[starts])[:, None].expand(-1, length, -1).repeat(samples, 1, 1)
    torch.manual_seed(seed)
    frames = rollout(Stepper(model.cpu().eval(), temperature), first, views.contiguous())     # (B, T, 4, S, S)
    return motion_energy(premultiply(frames.transpose(0, 1)).numpy())


def calibrate_temperature(model: Rssm, data: SequenceData, steps: int = 150, count: int = 4, samples: int = 2,
                          temperatures: tuple[float, ...] = CALIBRATION_TEMPERATURES, seed: int = 0) -> Calibration:
    """The sampling temperature at which the open loop, at a still viewpoint, moves as much as
    the footage's own motion as the model sees it (:func:`still_view_target`).

    The stochastic state carries the object's motion that the deterministic path does not: at
    temperature 0 the rollouts settle, and their energy grows with the temperature. How much
    it grows differs between captures and runs (1.6x the truth's at 1 on one capture, 0.7x on
    another, docs/benchmarks.md), so no fixed temperature fits them all. The energies at
    ``temperatures`` are interpolated to meet the target; outside them the nearest one is kept
    (noted). Footage without a run of consecutive training frames gets :data:`RUN_TEMPERATURE`.
    """
    starts, length = long_training_runs(data, steps, count)
    if len(starts) == 0:
        return Calibration(RUN_TEMPERATURE, None, {}, [], 0,
                           f"no run of {data.length} consecutive training frames: temperature {RUN_TEMPERATURE:g} kept")
    energy = {}
    with progress(transient=True) as prog:
        task = prog.add_task("fit temperature", total=len(temperatures) + 1, info="")
        target = still_view_target(model, data, starts, length)
        for t in temperatures:
            prog.update(task, advance=1, info=f"temperature {t:g}")
            energy[float(t)] = still_view_energy(model, data, starts, length, t, samples, seed)
        prog.update(task, advance=1)
    ts = np.array(sorted(energy))
    es = np.maximum.accumulate(np.array([energy[t] for t in ts]))     # interp needs it non-decreasing
    note = None
    if target <= es[0]:
        temp, note = float(ts[0]), f"the open loop moves more than the footage even at temperature {ts[0]:g}"
    elif target >= es[-1]:
        temp, note = float(ts[-1]), f"the open loop moves less than the footage even at temperature {ts[-1]:g}"
    else:
        temp = float(np.interp(target, es, ts))
    return Calibration(temp, target, energy, [int(s) for s in starts], length - 1, note)


def write_figures(report: EvalReport, figs: dict, history: list[dict], folder: Path) -> None:
    """``plots.png`` (per-step PSNR/SSIM, motion energy, losses), ``strip.png``, ``rollout.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    steps = np.arange(1, report.steps + 1)
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    for k in report.psnr:
        axes[0, 0].plot(steps, report.psnr[k], marker="o", label=k)
        axes[0, 1].plot(steps, report.ssim[k], marker="o", label=k)
    axes[0, 0].set(xlabel="open-loop step", ylabel="PSNR (dB)", title=f"PSNR, {report.split} split")
    axes[0, 1].set(xlabel="open-loop step", ylabel="SSIM", title=f"SSIM, {report.windows} windows")
    axes[0, 0].legend()
    ax = axes[1, 0]
    ax.plot(np.arange(1, len(figs["pred_curve"]) + 1), figs["pred_curve"], label="prediction")
    if figs["truth_curve"] is not None:
        ax.plot(np.arange(1, len(figs["truth_curve"]) + 1), figs["truth_curve"], label="truth")
    else:
        ax.axhline(figs["truth_energy"], color="k", ls="--", label="truth (dataset mean)")
    ax.set(xlabel="step", ylabel="mean |frame change|",
           title=f"motion energy at a still viewpoint, ratio {report.motion['ratio']}")
    ax.legend()
    ax = axes[1, 1]
    if history:
        s = [h["step"] for h in history]
        for k in ("rec", "open_loop", "kl_dyn", "kl_rep", "overshoot"):
            if k in history[-1]:                     # "open_loop" only when a loss scores it
                ax.plot(s, [max(h.get(k, 0.0), 1e-3) for h in history], label=k)
        ax.set(yscale="log")
        ax.legend()
    ax.set(xlabel="step", title="training losses")
    fig.tight_layout()
    fig.savefig(folder / "plots.png", dpi=90)
    plt.close(fig)

    # Strip: one held-out window, rows truth / model / near, on a grey checker (alpha visible).
    truth, m = figs["truth"], figs["methods"]
    rows = [truth[0, 1:], m["model"][0], m["near"][0]]
    cv2.imwrite(str(folder / "strip.png"), _grid(rows))
    long = figs["long"][0][::10]
    rows = [long] + ([figs["still_truth"][1::10][:len(long)]] if figs["still_truth"] is not None else [])
    cv2.imwrite(str(folder / "rollout.png"), _grid(rows))


def _grid(rows: list[np.ndarray]) -> np.ndarray:
    """Rows of premultiplied RGBA frames (n, S, S, 4) over a checkerboard -> BGR uint8 image."""
    S = rows[0].shape[1]
    n = max(len(r) for r in rows)
    yy, xx = np.mgrid[:S, :S]
    bg = np.where(((yy // 8) + (xx // 8)) % 2 == 0, 0.55, 0.75)[..., None]
    out = np.ones((len(rows) * (S + 2), n * (S + 2), 3))
    for i, r in enumerate(rows):
        for j, f in enumerate(r):
            out[i * (S + 2):i * (S + 2) + S, j * (S + 2):j * (S + 2) + S] = f[..., :3] + (1 - f[..., 3:4]) * bg
    return np.round(out[..., ::-1].clip(0, 1) * 255).astype(np.uint8)


# --------------------------------------------------------------------------- run folder
def train_run(dataset: Path, out: Path, cfg: RssmConfig, tcfg: TrainConfig, resume: bool = False,
              overwrite: bool = False, quiet: bool = False, temperature: float | None = None) -> dict:
    """Train on ``dataset`` and write the run folder ``out`` atomically; returns run.json.

    ``temperature``: the stepper's sampling temperature (scales the prior's std at run time;
    None: fitted to the footage, :func:`calibrate_temperature`).
    """
    out = Path(out)
    check_run_output(out, overwrite, resume)
    tcfg = replace(tcfg, minutes=training_minutes(tcfg.minutes, tcfg.steps, default=15.0))
    device = pick_device()
    work = run_work_dir(out)
    ckpt = work / "checkpoint.pt"
    state = None
    if resume:
        state = TrainState.load(resume_checkpoint(out), tcfg, device)
        cfg = state.model.cfg
    cfg.validate()
    tcfg.validate()
    data = load_sequences(dataset, cfg.size)
    torch.manual_seed(tcfg.seed)
    if state is None:
        cfg = leak_at_frame_rate(cfg, _fps(data))
        model = Rssm(cfg).to(device)
        state = TrainState(model, _optimizer(model, tcfg))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with progress() as prog:
        task = prog.add_task("train rssm", total=100, info="")

        def on_step(st: TrainState, parts: dict | None) -> None:
            if quiet:
                return
            info = ("non-finite step skipped" if parts is None else
                    f"step {st.step}  rec {parts['rec']:.1f}  "
                    + (f"open-loop {parts['open_loop']:.1f}  " if "open_loop" in parts else "")
                    + f"kl {parts['kl_dyn']:.2f}  over {parts['overshoot']:.2f}")
            prog.update(task, completed=100 * _fraction(st, tcfg), info=info)

        state = train(state, data, tcfg, ckpt, on_step)
        prog.update(task, completed=100)
    meta = write_run(out, state, data, dataset, tcfg, ckpt, wall=time.perf_counter() - t0, temperature=temperature)
    shutil.rmtree(work, ignore_errors=True)
    return meta


def write_run(out: Path, state: TrainState, data: SequenceData, dataset: Path, tcfg: TrainConfig,
              ckpt: Path, wall: float, temperature: float | None = None) -> dict:
    """The run folder of a trained state; ``temperature`` None: calibrated (run.json says how)."""
    model = state.run_model()           # checkpoint.pt keeps the last weights (for --resume)
    sel = state.selection
    cfg = model.cfg
    cal = calibrate_temperature(model, data) if temperature is None else None
    temperature = cal.temperature if cal is not None else float(temperature)
    with atomic_dir(out, overwrite=True) as tmp:
        shutil.copyfile(ckpt, tmp / "checkpoint.pt")
        torch.save({"config": asdict(cfg), "state_dict": model.state_dict()}, tmp / "model.pt")
        script_stepper(model, temperature).save(str(tmp / "stepper.ts"))
        report = run_eval(model, data, tmp / "report", state.history, temperature=temperature)
        meta = {
            "format": RUN_FORMAT, "version": 1, "kind": "dynamic",
            "dataset": str(Path(dataset).resolve()), "dataset_file": data.source.name,
            "object": data.meta.get("object"), "up": data.meta.get("up"),
            "crop": {"size": data.meta.get("crop_size"), "fill": data.meta.get("crop_fill")},
            "model": {"file": "model.pt", "type": "rssm", "config": asdict(cfg)},
            "stepper": {"file": "stepper.ts", "format": "TorchScript",
                        "api": {"start": "(rgba (B,4,S,S) straight RGBA 0..1, view (B,3)) -> (h, z)",
                                "step": "(h, z, view (B,3)) -> (h, z, rgba (B,4,S,S) straight RGBA 0..1)"},
                        "view": "[azimuth_deg, elevation_deg, distance_m] of the camera from the object centre "
                                "(crops.json viewpoint)",
                        "frame_size": cfg.size, "fps": _fps(data), "temperature": temperature,
                        "temperature_calibration": None if cal is None else cal.to_json()},
            "checkpoint": "checkpoint.pt",
            "selection": None if sel is None else sel.summary(),
            "training": {"steps": state.step, "seconds": round(state.seconds, 1),
                         "wall_seconds_this_session": round(wall, 1), "budget_minutes": tcfg.minutes,
                         "budget_steps": tcfg.steps, "batch": tcfg.batch, "lr": tcfg.lr,
                         "weights": "selected" if sel is not None and sel.state_dict is not None
                         else "moving average" if state.ema is not None else "last",
                         "non_finite_steps_skipped": state.bad_steps,
                         "train_sequences": len(data.starts("train")),
                         "test_sequences": len(data.starts("test")),
                         "final": state.history[-1] if state.history else None},
            "eval": report.to_json(),
            "report": "report/",
        }
        write_json(tmp / "run.json", meta)
    return meta


def _fps(data: SequenceData) -> float | None:
    if len(data.times) < 2:
        return None
    return round(1.0 / float(np.median(np.diff(data.times))), 4)


def run_eval(model: Rssm, data: SequenceData, folder: Path, history: list[dict],
             temperature: float = RUN_TEMPERATURE, **kw) -> EvalReport:
    """Evaluate ``model`` (sampling at ``temperature``) on ``data``; ``eval.json`` and figures into ``folder``."""
    report, figs = evaluate(Stepper(model.cpu().eval(), temperature), data, **kw)
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "eval.json", report.to_json())
    write_figures(report, figs, history, folder)
    return report


def load_model(run: Path) -> Rssm:
    """The trained model of a run folder (``model.pt``)."""
    meta = read_json(Path(run) / "run.json", "run description")
    if meta.get("format") != RUN_FORMAT:
        raise DbbError(f"{run} is not an RSSM run (run.json format {meta.get('format')!r})")
    try:
        ck = torch.load(Path(run) / meta["model"]["file"], map_location="cpu", weights_only=False)
        model = Rssm(RssmConfig.from_json(ck["config"]))
        model.load_state_dict(ck["state_dict"])
    except (OSError, KeyError, RuntimeError) as e:
        raise DbbError(f"cannot read the RSSM model of {run}: {e}") from None
    return model.eval()


def eval_run(run: Path, dataset: Path | None = None, temperature: float | None = None,
             calibrate: bool = False) -> EvalReport:
    """Re-run the evaluation of a run folder (on its own dataset unless ``dataset`` is given).

    Rewrites ``report/`` and the ``eval`` entry of ``run.json`` in place; a new ``temperature``
    (or ``calibrate``: fit it again, :func:`calibrate_temperature`) also rewrites ``stepper.ts``
    and the stepper's temperature in ``run.json``.
    """
    run = Path(run)
    model = load_model(run)
    meta = read_json(run / "run.json", "run description")
    ds = Path(dataset) if dataset is not None else Path(meta["dataset"])
    data = load_sequences(ds, model.cfg.size)
    ck = run / meta.get("checkpoint", "checkpoint.pt")
    history = torch.load(ck, map_location="cpu", weights_only=False)["history"] if ck.is_file() else []
    tmp = run / ".report.partial"
    shutil.rmtree(tmp, ignore_errors=True)
    if calibrate:
        cal = calibrate_temperature(model, data)
        temperature = cal.temperature
        meta["stepper"]["temperature_calibration"] = cal.to_json()
    elif temperature is None:
        temperature = float(meta["stepper"].get("temperature", 1.0))
    elif temperature != meta["stepper"].get("temperature", 1.0):
        meta["stepper"]["temperature_calibration"] = None      # set by hand
    report = run_eval(model, data, tmp, history, temperature=temperature)
    if temperature != meta["stepper"].get("temperature", 1.0):
        ts = run / ".stepper.ts.partial"
        script_stepper(model, temperature).save(str(ts))
        ts.replace(run / meta["stepper"]["file"])
        meta["stepper"]["temperature"] = temperature
    shutil.rmtree(run / "report", ignore_errors=True)
    tmp.replace(run / "report")
    meta["eval"] = report.to_json()
    write_json(run / "run.json", meta)
    return report


# --------------------------------------------------------------------------- synthetic ground truth
@dataclass(frozen=True)
class SyntheticCrops:
    """A crops.json dataset rendered straight from a synthetic dynamic object (no preprocess)."""

    root: Path
    still_first: np.ndarray         # (S, S, 4) uint8: first frame of the still-viewpoint truth
    still_view: np.ndarray          # (3,) its viewpoint [azimuth_deg, elevation_deg, distance_m]
    still_truth: np.ndarray         # (steps, S, S, 4) uint8: the following frames, same viewpoint


def synthetic_crops(out: Path, seconds: float = 60.0, fps: float = 10.0, size: int = 64, seed: int = 0,
                    still_steps: int = 150, samples: int = 2) -> SyntheticCrops:
    """Render a dynamic toy along a handheld camera path into ``out/crops/`` + ``out/crops.json``.

    Exactly what the preprocess crop stage writes, with perfect mattes; the last 20 % of the
    time is the test split. Also renders ``still_steps`` frames after the first test frame
    at that frame's (now still) viewpoint: the truth of the motion-energy ratio.
    """
    from ..crops.camera import CropRecord, crop_camera, crops_json, split_by_time
    from ..synth.scene import UP, SynthConfig, camera_path, make_scene, render_object_rgba

    cfg = SynthConfig(kind="dynamic", seconds=seconds, fps=fps, seed=seed, background_seconds=None)
    rng = np.random.default_rng(seed)
    scene = make_scene(cfg, rng)
    times = np.arange(round(seconds * fps)) / fps
    poses = camera_path(cfg, scene, times, rng)
    intr = cfg.intrinsics()
    center, radius = scene.obj.bounding_sphere(times[:: max(1, len(times) // 200)])
    radius *= 1.05
    splits = split_by_time(times)
    out = Path(out)
    (out / "crops").mkdir(parents=True, exist_ok=True)
    records = []
    cams = []
    with progress(transient=True) as prog:
        task = prog.add_task("render crops", total=len(times), info="")
        for i, (t, c2w) in enumerate(zip(times, poses)):
            cam = crop_camera(c2w, intr, center, radius, UP, size, 0.9)
            rgba = render_object_rgba(scene.obj, cam.intr, cam.c2w, float(t), samples)
            cv2.imwrite(str(out / "crops" / f"{i:05d}.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
            records.append(CropRecord(f"crops/{i:05d}.png", cam, i, float(t), str(splits[i])))
            cams.append(cam)
            prog.update(task, advance=1)
        write_json(out / "crops.json", crops_json(records, center, radius, UP, size, 0.9))
        k = int(np.flatnonzero(splits == "test")[0]) if (splits == "test").any() else 0
        cam = cams[k]
        still = []
        task = prog.add_task("render still truth", total=still_steps + 1, info="")
        for j in range(still_steps + 1):
            still.append(render_object_rgba(scene.obj, cam.intr, cam.c2w, float(times[k] + j / fps), samples))
            prog.update(task, advance=1)
    v = cam.viewpoint
    return SyntheticCrops(out, still[0], np.array([v.azimuth_deg, v.elevation_deg, v.distance_m], np.float32),
                          np.stack(still[1:]))
