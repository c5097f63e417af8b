"""Training the RSSM: the state of a run (model, optimiser, history, the weights' moving average),
its checkpoint, and the loop."""

from __future__ import annotations

import copy
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ..core import checkpoint
from ..core.errors import DbbError, InputError
from ..core.fields import number, shown, type_name
from .config import RssmConfig, TrainConfig
from .data import SequenceData, anchor_batch, augment, batch, training_windows
from .losses import latent_loss, sequence_loss
from .model import Rssm

CHECKPOINT_FORMAT = "dbb-rssm-checkpoint"
CHECKPOINT_STEPS = 500      # a checkpoint at least this often, besides every checkpoint_seconds and on a stop
CHECKPOINT_VERSION = 3


def optimizer(model: Rssm, tcfg: TrainConfig) -> torch.optim.Optimizer:
    """AdamW with ``weight_decay`` > 0, else Adam."""
    if tcfg.weight_decay > 0.0:
        return torch.optim.AdamW(model.parameters(), lr=tcfg.lr, eps=tcfg.adam_eps, weight_decay=tcfg.weight_decay)
    return torch.optim.Adam(model.parameters(), lr=tcfg.lr, eps=tcfg.adam_eps)


@dataclass
class TrainState:
    """A run's training state; ``checkpoint.pt`` holds it (:meth:`save`, :meth:`load`)."""

    model: Rssm
    opt: torch.optim.Optimizer
    step: int = 0
    seconds: float = 0.0
    bad_steps: int = 0                      # non-finite losses or gradients skipped, in total
    history: list[dict] = field(default_factory=list)
    ema: dict | None = None                 # the weights' moving average (TrainConfig.ema), as a state dict
    ema_updates: int = 0
    train_config: dict | None = None        # the TrainConfig it was trained with (asdict), for a resumed run

    @classmethod
    def new(cls, model: Rssm, tcfg: TrainConfig) -> TrainState:
        """The state before the first step of ``model``, with its optimiser."""
        return cls(model, optimizer(model, tcfg))

    def save(self, path: Path) -> None:
        tmp = Path(path).with_suffix(".tmp")
        torch.save({"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
                    "config": asdict(self.model.cfg), "model": self.model.state_dict(),
                    "opt": self.opt.state_dict(), "step": self.step, "seconds": self.seconds,
                    "bad_steps": self.bad_steps, "history": self.history,
                    "ema": self.ema, "ema_updates": self.ema_updates, "train_config": self.train_config}, tmp)
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path, tcfg: TrainConfig, device: torch.device) -> TrainState:
        """The state saved at ``path``, its optimiser built for ``tcfg`` and then restored; every
        entry checked first (:func:`read_checkpoint`, :func:`checkpoint.state_dict`)."""
        ck = read_checkpoint(path)
        where = str(path)
        with torch.device("meta"):      # the shapes the config implies, without allocating them
            like = Rssm(ck.config).state_dict()
        weights = checkpoint.state_dict(ck.model, like, "model", where)
        ema = None if ck.ema is None else checkpoint.state_dict(ck.ema, like, "ema", where)
        model = Rssm(ck.config).to(device)
        model.load_state_dict(weights)
        st = cls(model, optimizer(model, tcfg), ck.step, ck.seconds, ck.bad_steps, ck.history,
                 None if ema is None else {k: v.to(device) for k, v in ema.items()}, ck.ema_updates,
                 asdict(ck.train_config))
        load_optimizer(st.opt, ck.opt, where)
        return st

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
        """The model a run writes, on the CPU in eval mode: the weights' average (``ema``), else the last weights."""
        model = self.model.cpu().eval()
        if self.ema is not None:
            model = copy.deepcopy(model)
            model.load_state_dict(self.ema)
        return model


@dataclass(frozen=True)
class Checkpoint:
    """A checkpoint's entries as :func:`read_checkpoint` checked them (tensors on the CPU);
    ``model``, ``ema`` and ``opt`` are checked against the model by :meth:`TrainState.load`."""

    config: RssmConfig
    train_config: TrainConfig
    step: int
    seconds: float
    bad_steps: int
    history: list[dict]
    ema_updates: int
    model: dict
    ema: dict | None
    opt: dict


def read_checkpoint(path: Path) -> Checkpoint:
    """A checkpoint's entries, each of the type and range it must have; one written by an older
    version is refused (train again)."""
    ck = checkpoint.load(path, "RSSM checkpoint")
    if ck.get("format") != CHECKPOINT_FORMAT:
        raise InputError(f"{path} is an RSSM checkpoint of an older version: train the run again")
    if ck.get("version") != CHECKPOINT_VERSION:
        which = f"of version {shown(ck['version'])}" if "version" in ck else "without a version"
        raise InputError(f"{path} is an RSSM checkpoint {which} (this version reads {CHECKPOINT_VERSION}): "
                         "train the run again")
    where = str(path)
    cfg = checkpoint.config(checkpoint.part(ck, "config", where), RssmConfig, "config", where)
    tcfg = checkpoint.config(checkpoint.part(ck, "train_config", where), TrainConfig, "train_config", where)
    step, seconds = checkpoint.progress(ck, where)
    count = lambda name: int(number(checkpoint.part(ck, name, where), name, where, low=0, integer=True))
    model, opt, ema = (checkpoint.part(ck, k, where) for k in ("model", "opt", "ema"))
    for name, value in (("model", model), ("opt", opt), ("ema", ema)):
        if not isinstance(value, dict) and not (name == "ema" and value is None):
            raise InputError(f"{where}: {name} must be a dict, not {type_name(value)} ({shown(value)})")
    return Checkpoint(replace(cfg, loss_scales=dict(cfg.loss_scales)), tcfg, step, seconds, count("bad_steps"),
                      checkpoint.history(checkpoint.part(ck, "history", where), "history", where),
                      count("ema_updates"), model, ema, opt)


def load_optimizer(opt: torch.optim.Optimizer, saved: dict, where: str) -> None:
    """Restore ``opt`` from the checkpoint's ``opt`` entry (``saved``): its parameter groups of
    finite settings, and for each parameter finite moments of its shape, squared ones not negative
    (a NaN moment would turn the first step's weights into NaN)."""
    groups, state = checkpoint.part(saved, "opt.param_groups", where), checkpoint.part(saved, "opt.state", where)
    if not isinstance(groups, list) or len(groups) != len(opt.param_groups) or not all(isinstance(g, dict) for g in groups):
        raise InputError(f"{where}: opt.param_groups must be a list of {len(opt.param_groups)} dict, "
                         f"not {type_name(groups)} ({shown(groups)})")
    if not isinstance(state, dict):
        raise InputError(f"{where}: opt.state must be a dict, not {type_name(state)} ({shown(state)})")
    params = [p for g in opt.param_groups for p in g["params"]]
    for g, group in enumerate(groups):
        for k, v in group.items():
            if isinstance(v, float) and not math.isfinite(v):
                raise InputError(f"{where}: opt.param_groups[{g}].{k} must be a finite number, not {shown(v)}")
    for i, moments in state.items():
        if not isinstance(i, int) or not 0 <= i < len(params) or not isinstance(moments, dict):
            raise InputError(f"{where}: opt.state must map parameters 0..{len(params) - 1} to their moments, "
                             f"not {shown(i)} to {type_name(moments)}")
        for k, v in moments.items():
            shape = () if k == "step" else tuple(params[i].shape)
            t = checkpoint.tensor(v, f"opt.state[{i}].{k}", where, shape)
            # A step count and a mean of squared gradients are never negative; Adam divides by the
            # latter's square root, so a negative one turns the weights into NaN at the first step.
            if (k == "step" or k.endswith("exp_avg_sq")) and t.numel() and float(t.min()) < 0:
                raise InputError(f"{where}: opt.state[{i}].{k} must not be negative, and holds {float(t.min()):g}")
    try:
        opt.load_state_dict(saved)
    except (ValueError, KeyError, TypeError, RuntimeError) as e:
        raise InputError(f"{where}: opt is not this model's optimiser state: {e}") from None


def budget_fraction(state: TrainState, tcfg: TrainConfig) -> float:
    """How much of the budget (steps or minutes, whichever ends first) is spent, 0..1."""
    f = 0.0
    if tcfg.steps:
        f = max(f, state.step / tcfg.steps)
    if tcfg.minutes:
        f = max(f, state.seconds / (60 * tcfg.minutes))
    return min(f, 1.0)


def _done(state: TrainState, tcfg: TrainConfig) -> bool:
    if tcfg.steps is not None and state.step >= tcfg.steps:
        return True
    return tcfg.minutes is not None and state.seconds >= 60 * tcfg.minutes


def train(state: TrainState, data: SequenceData, tcfg: TrainConfig, ckpt: Path | None = None,
          on_step=None) -> TrainState:
    """Train until ``tcfg.minutes`` (time spent in training steps, over all resumptions) or
    ``tcfg.steps`` is reached; ``on_step(state, parts or None)`` after each step.

    A step whose loss or gradient is not finite is skipped (optimiser untouched) and counted;
    ``max_bad_steps`` in a row end training with a :class:`DbbError`, and so do weights that are
    not finite at the end (a model that renders NaN is not written).
    """
    state.train_config = asdict(tcfg)
    state.model.train()
    if ckpt is not None and not ckpt.is_file():     # resumable from the start, even after a SIGKILL
        state.save(ckpt)
    try:
        _train_loop(state, data, tcfg, ckpt, on_step)
    except KeyboardInterrupt:
        if ckpt is not None:             # an interrupted run resumes from here
            state.save(ckpt)
        raise
    bad = [name for name, w in state.model.named_parameters() if not bool(torch.isfinite(w).all())]
    if bad:
        raise DbbError(f"training diverged: {len(bad)} weight tensors ({', '.join(bad[:2])} ...) are not finite "
                       f"at step {state.step} (try a lower learning rate)")
    if ckpt is not None:
        state.save(ckpt)
    return state


class _Windows:
    """Random training batches: the dataset's training windows for the full steps, and those of
    ``dynamics_horizon`` for the latent-only steps; one generator, seeded by the step (so a resumed
    run draws new ones)."""

    def __init__(self, data: SequenceData, tcfg: TrainConfig, step: int, device: torch.device):
        self.data, self.tcfg, self.device = data, tcfg, device
        self.rng = np.random.default_rng(tcfg.seed + step)
        self.full = data.starts("train"), data.length
        self.latent = training_windows(data, tcfg.dynamics_horizon) if tcfg.dynamics_steps else self.full

    def draw(self, pool: tuple[np.ndarray, int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Frames, views and (with a view anchor) its renders of a batch of windows, augmented."""
        starts, length = pool
        pick = starts[self.rng.integers(0, len(starts), self.tcfg.batch)]
        return augment(*batch(self.data, pick, self.device, length), self.tcfg.augment, self.rng,
                       anchor_batch(self.data, pick, self.device, length))


def _apply(state: TrainState, loss: torch.Tensor, grad_clip: float) -> bool:
    """One optimiser step on ``loss``, unless it or its gradient is not finite; whether it was taken."""
    state.opt.zero_grad(set_to_none=True)
    if not bool(torch.isfinite(loss)):
        return False
    loss.backward()
    if not bool(torch.isfinite(torch.nn.utils.clip_grad_norm_(state.model.parameters(), grad_clip))):
        return False
    state.opt.step()
    return True


def _train_loop(state: TrainState, data: SequenceData, tcfg: TrainConfig, ckpt: Path | None, on_step) -> None:
    model = state.model
    windows = _Windows(data, tcfg, state.step, next(model.parameters()).device)
    last_ckpt = t_prev = time.perf_counter()
    last_step = state.step
    in_a_row = 0
    while not _done(state, tcfg):
        loss, parts = sequence_loss(model, *windows.draw(windows.full))
        ok = _apply(state, loss, tcfg.grad_clip)
        if ok:
            for _ in range(tcfg.dynamics_steps):
                if not _apply(state, latent_loss(model, *windows.draw(windows.latent))[0], tcfg.grad_clip):
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
        if on_step is not None:
            on_step(state, parts if ok else None)
        if ckpt is not None and (now - last_ckpt > tcfg.checkpoint_seconds
                                 or state.step - last_step >= CHECKPOINT_STEPS):
            state.save(ckpt)
            last_ckpt, last_step = now, state.step
