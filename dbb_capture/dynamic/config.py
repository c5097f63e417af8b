"""The RSSM's settings: model and loss (:class:`RssmConfig`), training (:class:`TrainConfig`), the
``NAME=VALUE`` settings that set them and the presets (``presets/NAME.toml``) that bundle them.

Why each default is what it is: ``docs/decisions.md`` (one row per lever, by setting name).
Imports nothing heavy: the command line reads the preset names from here.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from ..core.errors import DbbError

if sys.version_info >= (3, 11):
    import tomllib
else:                                   # Python 3.10: the same parser as a package
    import tomli as tomllib

SIZES = (32, 64, 128, 256)
PRESETS_DIR = Path(__file__).with_name("presets")

# The weights of the loss terms (:func:`dbb_capture.dynamic.losses.loss_terms` returns them unscaled),
# in the order they are summed. A term whose weight is 0 is not computed.
LOSS_SCALES: dict[str, float] = {
    "rec": 1.0,          # the filtering reconstruction: frames 1..T decoded from the posterior states
    "kl": 1.0,           # the KL terms (kl_balance of the dynamics term, the rest of the representation term)
    "overshoot": 1.0,    # latent overshooting: the open loop's priors against the filtering posteriors
    "first_step": 1.0,   # the run-time first step (frame 1 from a prior sample at h_1), scored on its own
    "sharp": 0.0,        # the open loop's sharpness matched to the truth's (losses.sharpness_match)
    "keypoints": 0.0,    # the state predicts its frame's keypoints (needs keypoints > 0)
    "keypoint_spread": 0.0,  # the open loop's keypoints spread over time as the frames' do (needs keypoints)
    "energy": 0.0,       # the open loop's motion energy matched to the truth's (losses.energy_match)
}


@dataclass(frozen=True)
class RssmConfig:
    """Model and loss settings. Sizes in pixels, KL in nats; ``loss_scales`` as :data:`LOSS_SCALES`
    (a new mapping through :func:`dataclasses.replace`, never changed in place)."""

    size: int = 64                 # square RGBA frames, a power of two in SIZES
    deter: int = 64                # deterministic GRU state
    stoch: int = 64                # Gaussian stochastic state
    hidden: int = 256              # MLP width
    embed: int = 256               # encoder output
    enc_depth: int = 8             # channels of the first encoder conv (doubling, capped at 256)
    dec_depth: int = 8             # decoder channels at 32 px (halving per doubling, >= 8)
    view_freqs: int = 4            # positional-encoding octaves of azimuth and elevation
    min_std: float = 0.1           # std = softplus(x) + min_std (PlaNet)
    free_nats: float = 1.0         # floor of the representation KL (batch mean per step); the dynamics KL has none
    kl_balance: float = 0.8        # weight of the dynamics (prior-training) KL term; 1 - this of the representation term
    max_step_flow: float = 0.25    # largest flow of one step, in image half-widths
    warp_leak: float = 0.1         # each step the accumulated warp's displacement shrinks by this fraction
                                   # (toward the context frame's layout), so its errors stay bounded
    warp_leak_fps: float = 0.0     # > 0: warp_leak is the leak of one frame at this frame rate; training
                                   # rescales it to the dataset's rate, the same fraction per second
                                   # (leak_at_frame_rate; 0.1 at 10 fps is 0.035 at 30 fps)
    motion_weight: float = 10.0    # extra weight of changing pixels in the reconstruction losses: the
                                   # truth's change from its previous frame, or the prediction's where more
    keypoints: int = 0             # > 0: this many spatial-softmax keypoints join the encoder's embedding
                                   # (SpatialSoftmax): the flattened conv stack all but ignores a part a few
                                   # pixels wide (a 5-px ball moves its embedding by ~1e-5), a keypoint follows it
    keypoints_frozen: bool = False  # the keypoint layer and the encoder conv it reads keep their initial
                                   # weights (learned, the softmax spreads and the features drift until
                                   # the keypoints no longer follow the part)
    keypoint_maps: bool = False    # (needs loss_scales.keypoints) the decoder draws from keypoints: Gaussian
                                   # maps of the keypoints its state predicts (kp_head) and of the context
                                   # frame's join its layers (Minderer et al. 2019), so a small part can be
                                   # drawn where the state puts it, far from where the context frame shows it
    keypoint_map_std: float = 0.08  # those maps' std in [-1, 1] frame units (0.08: 2.6 px at 64 px);
                                   # at least half a cell at each coarser layer
    keypoint_teacher: bool = False  # (needs keypoint_maps) training decodes every frame from the keypoints
                                   # the encoder finds in that frame (detached), as Minderer et al. train their
                                   # decoder, not from the state's guess: a pixel loss scores a small part drawn
                                   # a few pixels off worse than no part, so a decoder fed the state's uncertain
                                   # keypoints learns to leave the part where it was. The state's keypoints
                                   # (kp_head, trained by the keypoint loss) drive it at run time
    keypoint_horizon: int | None = None  # the open loop's first this many steps score the state's
                                   # keypoints against the frames' one by one (None: every step); beyond it
                                   # the phase of a swing is unknown, the mean of its places scores best there
                                   # and a prior trained to it settles (loss_scales.keypoint_spread keeps the
                                   # swing's size)
    osc: int = 0                   # > 0: this many damped rotations (complex modes, LRU-style) take 2 x osc
                                   # of the deter units beside the GRU (OscCell): a state that rings at its
                                   # own frequency keeps a swing going after the trained horizon, where a
                                   # GRU's forecast settles
    osc_keep_min: float = 0.0      # floor of each mode's kept length a step (e.g. 0.999: rings ~1000 steps);
                                   # trained freely the modes learn to damp within 10-50 steps
    anchor: bool = True            # the decoder reads a PlenOctree of the capture, fitted to its crops
                                   # (dynamic/anchor.py), at the drawn view: how the object looks from a
                                   # view comes from a 3D model, the RSSM supplies what moves
    loss_scales: dict[str, float] = field(default_factory=lambda: dict(LOSS_SCALES))

    def scale(self, term: str) -> float:
        """The weight of loss term ``term`` (a name of :data:`LOSS_SCALES`)."""
        return float(self.loss_scales[term])

    def validate(self) -> None:
        if self.size not in SIZES:
            raise DbbError(f"RSSM frame size ({{=size}}) must be one of {', '.join(map(str, SIZES))}, not {self.size}")
        for f in ("deter", "stoch", "hidden", "embed", "enc_depth", "dec_depth", "view_freqs"):
            if getattr(self, f) < 1:
                raise DbbError(f"RSSM {{={f}}} must be positive")
        if set(self.loss_scales) != set(LOSS_SCALES):
            raise DbbError(f"RSSM loss_scales must name {', '.join(LOSS_SCALES)}, not {', '.join(self.loss_scales)}")
        bad = [k for k, v in self.loss_scales.items() if not v >= 0.0]
        if bad:
            raise DbbError(f"RSSM loss_scales.{bad[0]} must be >= 0, not {self.loss_scales[bad[0]]}")
        if self.max_step_flow <= 0.0:
            raise DbbError(f"RSSM {{=max_step_flow}} must be > 0, not {self.max_step_flow}")
        if not 0.0 <= self.warp_leak < 1.0:
            raise DbbError(f"RSSM {{=warp_leak}} must be in [0, 1), not {self.warp_leak}")
        if self.warp_leak_fps < 0.0:
            raise DbbError(f"RSSM {{=warp_leak_fps}} must be >= 0, not {self.warp_leak_fps}")
        if self.keypoints < 0:
            raise DbbError(f"RSSM {{=keypoints}} must be >= 0, not {self.keypoints}")
        if self.scale("keypoints") > 0 and self.keypoints < 1:
            raise DbbError("RSSM loss_scales.keypoints needs {=keypoints} > 0")
        if self.keypoint_maps and self.scale("keypoints") <= 0:
            raise DbbError("RSSM {=keypoint_maps} needs loss_scales.keypoints > 0 (and {=keypoints} > 0)")
        if self.scale("keypoint_spread") > 0 and self.scale("keypoints") <= 0:
            raise DbbError("RSSM loss_scales.keypoint_spread needs loss_scales.keypoints > 0")
        if self.keypoint_horizon is not None and self.keypoint_horizon < 1:
            raise DbbError(f"RSSM {{=keypoint_horizon}} must be at least 1, not {self.keypoint_horizon}")
        if self.keypoint_teacher and not self.keypoint_maps:
            raise DbbError("RSSM {=keypoint_teacher} needs {=keypoint_maps}")
        if self.keypoint_map_std <= 0:
            raise DbbError(f"RSSM {{=keypoint_map_std}} must be > 0, not {self.keypoint_map_std}")
        if not 0.0 <= self.osc_keep_min < 1.0:
            raise DbbError(f"RSSM {{=osc_keep_min}} must be in [0, 1), not {self.osc_keep_min}")
        if self.osc < 0 or 2 * self.osc >= self.deter:
            raise DbbError(f"RSSM {{=osc}} must be >= 0 and leave GRU units (2 x {{=osc}} < {{=deter}} {self.deter}), not {self.osc}")

    @classmethod
    def from_json(cls, d: Mapping) -> RssmConfig:
        """The config :func:`dataclasses.asdict` wrote (run.json, model.pt, checkpoints)."""
        try:
            cfg = cls(**d)
        except TypeError as e:
            raise DbbError(f"not an RSSM model config of this version: {e}") from None
        # A term added since the model was written was off for it (every new term is 0 by default).
        return replace(cfg, loss_scales={**LOSS_SCALES, **cfg.loss_scales})


@dataclass(frozen=True)
class TrainConfig:
    """How long and how to train. ``minutes``/``steps``: the first limit reached wins."""

    minutes: float | None = None
    steps: int | None = None
    batch: int = 8
    seed: int = 0
    lr: float = 1e-3
    adam_eps: float = 1e-4
    weight_decay: float = 0.25     # > 0: AdamW's decoupled decay (each step the weights shrink by lr x this),
                                   # against memorising a short capture's windows (0: Adam)
    ema: float = 0.995             # > 0: the run's model is the exponential moving average of the weights
                                   # with this decay per step (0.995: about the last 200 steps), kept beside
                                   # the trained ones; it smooths the late steps' noise (0 = the last weights)
    grad_clip: float = 100.0
    checkpoint_seconds: float = 60.0
    max_bad_steps: int = 20        # consecutive non-finite steps before giving up
    augment: str = "flip,reverse,shift"  # comma-separated: "flip" mirrors half the windows left-right
                                   # (azimuth negated), "reverse" plays half of them backwards, "shift"
                                   # moves each window by a random whole-pixel offset (up to size/16, DrQ); "none"
    dynamics_steps: int = 0        # > 0: after each step, this many more on fresh windows that train the
                                   # transition and prior alone (latent_loss: posteriors fixed, nothing
                                   # decoded), so the dynamics get many updates for each costly one
                                   # (a non-finite one is skipped and counted)
    anchor_share: float = 0.2      # the share of a minutes budget spent fitting the view anchor (with a
                                   # steps budget it trains as many steps as the RSSM)
    dynamics_horizon: int | None = None  # the latent-only steps' windows: 1 context + this many frames, cut
                                   # from consecutive training frames; None: the dataset's windows. Nothing
                                   # is decoded there, so windows many times longer cost little

    def validate(self) -> None:
        bad = set(self.augment.split(",")) - {"none", "flip", "reverse", "shift"}
        if bad:
            raise DbbError(f"augment: unknown {', '.join(sorted(bad))} (flip, reverse, shift or none)")
        if self.batch < 1:
            raise DbbError(f"{{=batch}} must be at least 1, not {self.batch}")
        if self.weight_decay < 0.0:
            raise DbbError(f"weight_decay must be at least 0, not {self.weight_decay}")
        if not 0.0 <= self.ema < 1.0:
            raise DbbError(f"ema must be in [0, 1), not {self.ema}")
        if self.dynamics_steps < 0:
            raise DbbError(f"dynamics_steps must be at least 0, not {self.dynamics_steps}")
        if not 0.0 < self.anchor_share < 1.0:
            raise DbbError(f"anchor_share must be above 0 and below 1, not {self.anchor_share}")
        if self.dynamics_horizon is not None and self.dynamics_horizon < 1:
            raise DbbError(f"dynamics_horizon must be at least 1, not {self.dynamics_horizon}")


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


def model_changes(run: RssmConfig, asked: RssmConfig) -> list[str]:
    """The model settings in which ``asked`` differs from a run's own ``run`` (its checkpoint's),
    as "name value (the run's value)"; a resumed run keeps its model, so any is a contradiction.
    ``asked``'s leak per frame is first rescaled to the run's frame rate, as training did (floats
    agree to 1e-9: the rescaling's own rounding is no difference)."""
    asked = leak_at_frame_rate(asked, run.warp_leak_fps)
    pairs = [(f.name, getattr(asked, f.name), getattr(run, f.name)) for f in fields(RssmConfig) if f.name != "loss_scales"]
    pairs += [(f"loss_scales.{k}", asked.loss_scales.get(k), run.loss_scales.get(k))
              for k in {**run.loss_scales, **asked.loss_scales}]

    def same(a, r) -> bool:
        return math.isclose(a, r, rel_tol=1e-9) if isinstance(a, float) and isinstance(r, float) else a == r
    def word(v) -> str:
        return f"{v:.6g}" if isinstance(v, float) else str(v)
    return [f"{name} {word(a)} (the run's {word(r)})" for name, a, r in pairs if not same(a, r)]


# --------------------------------------------------------------------------- settings by name
# Fields with a command-line option of their own (or none: loss_scales is set term by term).
_NOT_SETTINGS = {"size", "loss_scales", "minutes", "steps", "batch", "seed"}


def setting_names() -> list[str]:
    """Every name :func:`apply_settings` accepts: model fields, ``loss_scales.TERM``, training fields."""
    model = [f.name for f in fields(RssmConfig) if f.name not in _NOT_SETTINGS]
    train = [f.name for f in fields(TrainConfig) if f.name not in _NOT_SETTINGS]
    return model + [f"loss_scales.{k}" for k in LOSS_SCALES] + train


_OPTIONAL = {"dynamics_horizon", "keypoint_horizon"}  # settings that may be None ("none")
_KINDS = {bool: "true or false", int: "a whole number", float: "a number", str: "text"}


def _value(name: str, value: object, current: object) -> object:
    """``value`` (text, or a TOML value) as the type of the setting's ``current`` value."""
    kind = int if current is None else type(current)        # int | None settings are None by default
    if isinstance(value, str) and kind is not str:
        text = value.strip().lower()
        if text == "none" and name in _OPTIONAL:
            return None
        try:
            if kind is bool:
                if text not in ("true", "false"):
                    raise ValueError(text)
                return text == "true"
            return kind(text)
        except ValueError:
            raise DbbError(f"{name}: {value!r} is not {_KINDS[kind]}") from None
    if kind is float and type(value) is int:
        return float(value)
    if type(value) is not kind:
        raise DbbError(f"{name}: {value!r} is not {_KINDS[kind]}")
    return value


def apply_settings(settings: Mapping[str, object], cfg: RssmConfig | None = None,
                   tcfg: TrainConfig | None = None) -> tuple[RssmConfig, TrainConfig]:
    """``cfg`` / ``tcfg`` (default: the defaults) with ``settings`` ({name: value}, names of
    :func:`setting_names`; values as text, "none" for no value, true/false for flags, or already typed)."""
    cfg, tcfg = cfg or RssmConfig(), tcfg or TrainConfig()
    model_names = {f.name for f in fields(RssmConfig)} - _NOT_SETTINGS
    train_names = {f.name for f in fields(TrainConfig)} - _NOT_SETTINGS
    for name, value in settings.items():
        if name.startswith("loss_scales.") and name[12:] in LOSS_SCALES:
            term = name[12:]
            scales = {**cfg.loss_scales, term: _value(name, value, float(cfg.loss_scales[term]))}
            cfg = replace(cfg, loss_scales=scales)
        elif name in model_names:
            cfg = replace(cfg, **{name: _value(name, value, getattr(cfg, name))})
        elif name in train_names:
            tcfg = replace(tcfg, **{name: _value(name, value, getattr(tcfg, name))})
        else:
            raise DbbError(f"{name}: no such setting (settings: {', '.join(setting_names())})")
    return cfg, tcfg


def configs_from_settings(pairs: list[str], cfg: RssmConfig | None = None,
                          tcfg: TrainConfig | None = None) -> tuple[RssmConfig, TrainConfig]:
    """:func:`apply_settings` of ``NAME=VALUE`` pairs, in order (a later pair wins)."""
    settings: dict[str, str] = {}
    for pair in pairs:
        name, eq, value = pair.partition("=")
        if not eq or not name:
            raise DbbError(f"{pair}: expected NAME=VALUE")
        settings.pop(name, None)
        settings[name] = value
    return apply_settings(settings, cfg, tcfg)


# --------------------------------------------------------------------------- presets
def preset_names() -> list[str]:
    """The presets in :data:`PRESETS_DIR` (``NAME.toml``)."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.toml"))


def read_preset(name: str) -> dict[str, object]:
    """The settings of preset ``name``: its file's top-level keys are setting names, and its
    ``[loss_scales]`` table gives ``loss_scales.TERM`` settings."""
    path = PRESETS_DIR / f"{name}.toml"
    if name not in preset_names():
        raise DbbError(f"no preset named {name!r} (presets: {', '.join(preset_names())})")
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise DbbError(f"preset {path} is not valid TOML: {e}") from None
    out: dict[str, object] = {}
    for key, value in doc.items():
        if isinstance(value, dict):
            out.update({f"{key}.{k}": v for k, v in value.items()})
        else:
            out[key] = value
    return out


def apply_preset(name: str, cfg: RssmConfig | None = None,
                 tcfg: TrainConfig | None = None) -> tuple[RssmConfig, TrainConfig]:
    """``cfg`` / ``tcfg`` with the settings of preset ``name`` (:func:`read_preset`)."""
    settings = read_preset(name)
    try:
        return apply_settings(settings, cfg, tcfg)
    except DbbError as e:
        raise DbbError(f"preset {name}: {e}") from None
