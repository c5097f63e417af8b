"""Training the RSSM: the state of a run (model, optimiser, history, the weights' moving average),
its checkpoint, and the loop."""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..core.errors import DbbError
from .config import RssmConfig, TrainConfig
from .data import SequenceData, augment, batch, training_windows
from .losses import latent_loss, sequence_loss
from .model import Rssm

CHECKPOINT_FORMAT = "dbb-rssm-checkpoint"
CHECKPOINT_STEPS = 500      # a checkpoint at least this often, besides every checkpoint_seconds and on a stop
CHECKPOINT_VERSION = 2


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
        """The state saved at ``path``, its optimiser built for ``tcfg`` and then restored."""
        ck = read_checkpoint(path, device)
        try:
            model = Rssm(RssmConfig.from_json(ck["config"])).to(device)
            model.load_state_dict(ck["model"])
        except (KeyError, RuntimeError) as e:
            raise DbbError(f"cannot read RSSM checkpoint {path}: {e}") from None
        st = cls(model, optimizer(model, tcfg), ck["step"], ck["seconds"], ck["bad_steps"], ck["history"],
                 ck["ema"], ck["ema_updates"], ck["train_config"])
        st.opt.load_state_dict(ck["opt"])
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


def read_checkpoint(path: Path, device: torch.device) -> dict:
    """A checkpoint's contents; one written by an older version is refused (train again)."""
    try:
        ck = torch.load(path, map_location=device, weights_only=False)
    except Exception as e:              # a damaged file fails in many ways inside the unpickler
        raise DbbError(f"cannot read RSSM checkpoint {path}: {type(e).__name__}: {e}") from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise DbbError(f"{path} is an RSSM checkpoint of an older version: train the run again")
    if ck.get("version") != CHECKPOINT_VERSION:
        raise DbbError(f"{path} is an RSSM checkpoint of version {ck.get('version')} (this version reads "
                       f"{CHECKPOINT_VERSION}): train the run again")
    return ck


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
    ``max_bad_steps`` in a row end training with a :class:`DbbError`.
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

    def draw(self, pool: tuple[np.ndarray, int]) -> tuple[torch.Tensor, torch.Tensor]:
        starts, length = pool
        pick = starts[self.rng.integers(0, len(starts), self.tcfg.batch)]
        return augment(*batch(self.data, pick, self.device, length), self.tcfg.augment, self.rng)


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
