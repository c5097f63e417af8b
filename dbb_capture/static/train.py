"""Training the voxel field: the budget, the coarse-to-fine schedule, one step per path, the loop.

A step draws a batch of training rays (:func:`draw_batch`), then takes the numba path
(:func:`kernel_step`: closed-form forward and backward, object mode on the CPU) or the PyTorch
one (:func:`torch_step`: autograd, CUDA and scene mode); both add TV and leave the gradients in
the field's tables for the lazy Adam step.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from ..core import checkpoint as saved
from ..core.errors import InputError
from ..core.fields import flag, number, numbers, shown
from ..core.metrics import psnr_from_mse
from ..datasets.records import ObjectVolume
from .field import FieldConfig, VoxelField, lattice_lin
from .kernels import RAY_RUN, photometric_step, tv_step
from .rays import RayBank, ray_targets, robust_weights
from .render import render_rays
from .structure import carved, pruned, upsampled

CHECKPOINT_VERSION = 2   # checkpoints of other versions are refused (their settings differ)


@dataclass
class Budget:
    """When to stop: after ``steps`` steps, or ``minutes`` of wall-clock training, whichever first."""

    minutes: float | None = None
    steps: int | None = None

    def fraction(self, step: int, seconds: float) -> float:
        fs = [step / self.steps] if self.steps else []
        if self.minutes:
            fs.append(seconds / (60 * self.minutes))
        return min(1.0, max(fs)) if fs else 1.0


@dataclass
class TrainState:
    """Where training is: the field, the step, seconds spent, and the loss/PSNR history."""

    field: VoxelField
    step: int = 0
    seconds: float = 0.0
    stage: int = 0
    history: list[dict] = field(default_factory=list)   # {"step", "seconds", "loss", "psnr", "res", "points"}

    def save(self, path: Path) -> None:
        st = {"version": CHECKPOINT_VERSION, "field": self.field.state(), "step": self.step,
              "seconds": self.seconds, "stage": self.stage, "history": self.history}
        tmp = Path(path).with_name(Path(path).name + f".tmp{os.getpid()}")
        torch.save(st, tmp)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: Path, device: torch.device) -> TrainState:
        """The state :meth:`save` wrote, every entry checked (:func:`checked_field`); a checkpoint
        of another version is refused."""
        st = saved.load(path, "checkpoint")
        where = str(path)
        version = st.get("version")
        if version != CHECKPOINT_VERSION:
            raise InputError(f"checkpoint {path} is of another version of the static trainer "
                             f"({shown(version) if 'version' in st else 1}, this one reads {CHECKPOINT_VERSION}): "
                             "train the run again")
        step, seconds = saved.progress(st, where)
        fld = checked_field(saved.part(st, "field", where), where)
        stages = len(stage_resolutions(fld.cfg))
        stage = number(saved.part(st, "stage", where), "stage", where, low=0, high=stages - 1, integer=True)
        history = saved.history(saved.part(st, "history", where), "history", where)
        return cls(VoxelField.from_state(fld.state, device), step, seconds, int(stage), list(history))


@dataclass(frozen=True)
class CheckedField:
    """A checkpoint's ``field`` entry, checked: its settings and the state to build it from."""

    cfg: FieldConfig
    state: dict


def checked_field(st: object, where: str) -> CheckedField:
    """The ``field`` entry of the checkpoint ``where``: settings this version knows, a sphere of
    positive radius, a lattice of one of its stages' sizes, and N distinct active lattice points
    with tables of N rows (density (N, 1), SH (N, 3 B)) of finite values; else one line naming the
    entry. Checked here so that a damaged field is refused before a resumed run trains on it."""
    cfg = saved.config(saved.part(st, "field.config", where), FieldConfig, "field.config", where)
    vol = saved.part(st, "field.volume", where)
    center = numbers(saved.part(vol, "field.volume.center", where), "field.volume.center", where, (3,))
    radius = number(saved.part(vol, "field.volume.radius", where), "field.volume.radius", where,
                    low=0, low_open=True)
    estimated = flag(saved.part(vol, "field.volume.estimated", where), "field.volume.estimated", where)
    ress = stage_resolutions(cfg)
    res = saved.part(st, "field.res", where)
    if isinstance(res, bool) or res not in ress:
        raise InputError(f"{where}: field.res must be one of its stages' lattice sizes "
                         f"({', '.join(map(str, ress))}), not {shown(res)}")
    nearest = flag(saved.part(st, "field.nearest", where), "field.nearest", where)
    active = saved.tensor(saved.part(st, "field.active", where), "field.active", where, (None,), floating=False)
    n = active.numel()
    if n and (int(active.min()) < 0 or int(active.max()) >= res ** 3):
        raise InputError(f"{where}: field.active must hold lattice points 0..{res ** 3 - 1} of its {res}^3 lattice, "
                         f"not {int(active.min())}..{int(active.max())}")
    if torch.unique(active).numel() != n:
        raise InputError(f"{where}: field.active must not hold a lattice point twice")
    density = saved.tensor(saved.part(st, "field.density", where), "field.density", where, (n, 1))
    sh = saved.tensor(saved.part(st, "field.sh", where), "field.sh", where, (n, 3 * cfg.n_basis))
    return CheckedField(cfg, {"config": asdict(cfg), "res": int(res), "nearest": nearest, "active": active,
                              "density": density, "sh": sh,
                              "volume": ObjectVolume(tuple(center), radius, estimated).to_json()})


def new_field(cfg: FieldConfig, volume: ObjectVolume, device: torch.device) -> VoxelField:
    """A fresh, nearly empty field over the whole lattice at the first resolution."""
    return VoxelField(cfg, volume, cfg.res_start, device)


def stage_resolutions(cfg: FieldConfig) -> list[int]:
    """Lattice sizes of the coarse-to-fine stages: res_start doubling up to res_max."""
    out = [cfg.res_start]
    while out[-1] * 2 <= cfg.res_max:
        out.append(out[-1] * 2)
    if out[-1] < cfg.res_max:
        out.append(cfg.res_max)
    return out


def tv_loss(field: VoxelField, n: int, gen: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean squared difference to the +x, +y, +z neighbours over ``n`` random active points:
    (density term, SH term). Inactive neighbours are not counted."""
    N = field.n_active
    if N == 0:
        z = field.density.gather(torch.zeros(0, dtype=torch.long, device=field.device)).sum()
        return z, z
    pick = torch.randint(0, N, (min(n, N),), device=field.device, generator=gen)
    lin = field.active[pick]
    r = field.res
    ijk = torch.stack([lin // (r * r), (lin // r) % r, lin % r], -1)
    dens, shs = [], []
    for axis in range(3):
        nb = ijk.clone()
        nb[:, axis] += 1
        ok = nb[:, axis] < r
        nrows = field.index[lattice_lin(nb.clamp(max=r - 1), r)].long()
        ok &= nrows >= 0
        a, b = pick[ok], nrows[ok]
        dens.append(field.density.gather(a) - field.density.gather(b))
        shs.append(field.sh.gather(a) - field.sh.gather(b))
    d = torch.cat(dens)
    s = torch.cat(shs)
    return (d ** 2).mean() if d.numel() else d.sum(), (s ** 2).mean() if s.numel() else s.sum()


def advance_schedule(state: TrainState, bank: RayBank, frac: float) -> None:
    """Bring ``state`` to the budget fraction ``frac``: prune and move to the next lattice when
    its stage starts (carving the new field), the nearest-point lookup in the final stage from
    ``nearest_from``, the higher SH bands from ``sh_full_from``."""
    cfg = state.field.cfg
    ress = stage_resolutions(cfg)
    starts = list(cfg.upsample_at[: len(ress) - 1])

    def carve(f: VoxelField) -> VoxelField:
        if not cfg.carve_share or bank.views is None or cfg.mode != "object":
            return f
        return carved(f, bank.views, cfg.carve_share, cfg.carve_min_views, cfg.carve_alpha)

    if state.stage < len(starts) and frac >= starts[state.stage]:
        f = pruned(state.field, cfg.prune_alpha)
        nxt = ress[state.stage + 1]
        if f.n_active * (nxt / f.res) ** 3 <= cfg.max_points:
            f = upsampled(f, nxt)
        state.field = carve(f)
        state.stage += 1
    elif state.step == 0:
        state.field = carve(state.field)
    fld = state.field
    if state.stage == len(starts) and frac >= cfg.nearest_from:
        fld.nearest = True
    fld.sh_active = cfg.sh_degree if frac >= cfg.sh_full_from else min(cfg.sh_degree, 1)


@dataclass
class Batch:
    """One step's training rays: bank rows ``pick`` (B,); on the field's device world origins and
    unit directions, backgrounds and targets (B, 3), robust weights (B,) or None (plain L2)."""

    pick: torch.Tensor
    origins: torch.Tensor
    dirs: torch.Tensor
    bg: torch.Tensor
    target: torch.Tensor
    ray_w: torch.Tensor | None


def draw_batch(bank: RayBank, fld: VoxelField, frac: float, robust: bool, gen: torch.Generator) -> Batch:
    """``batch_rays`` random rays of ``bank`` over random background colours (so alpha is
    learned as true transparency: the target is ``rgb * a + (1 - a) * bg``; for crops that keep
    their observed pixels, over the predicted room instead: :func:`.rays.ray_targets`), weighted
    from ``robust_from`` on when ``robust``."""
    cfg, dev = fld.cfg, fld.device
    if fld.cpu_kernel:
        # Runs of neighbouring pixels: their rays read the same lattice rows back to back
        # (cache hits in the CPU kernel); the runs themselves are drawn at random.
        run = min(RAY_RUN, bank.n)
        starts = torch.randint(0, bank.n - run + 1, (max(1, cfg.batch_rays // run),), generator=gen)
        pick = (starts[:, None] + torch.arange(run)).reshape(-1)
    else:
        pick = torch.randint(0, bank.n, (cfg.batch_rays,), generator=gen)
    c = bank.rgba[pick].to(dev)
    bg = torch.rand(pick.numel(), 3, generator=gen).to(dev)   # runs may round the batch down
    seen, room = (None, None) if bank.observed is None else (bank.observed[pick].to(dev), bank.room[pick].to(dev))
    bg, target = ray_targets(c, bg, seen, room, cfg, gen)
    ray_w = None
    if robust and frac >= cfg.robust_from and bank.error is not None:
        ray_w = robust_weights(bank.error[pick], cfg.robust_scale).to(dev)
    return Batch(pick, bank.origins[pick].to(dev), bank.dirs[pick].to(dev), bg, target, ray_w)


def kernel_step(fld: VoxelField, b: Batch, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The numba path: closed-form forward and backward, gradients straight into the tables'
    buffers. Returns the MSE and the loss (0-d) and the rays as rendered (B, 4) on the CPU."""
    cfg = fld.cfg
    mse, seen_rays = photometric_step(fld, b.origins, b.dirs, b.bg, b.target,
                                      torch.rand(b.origins.shape[0], generator=gen), b.ray_w)
    tvd, tvs = tv_step(fld, cfg.tv_points, gen) if cfg.tv_density > 0 or cfg.tv_sh > 0 else (0, 0)
    loss = mse + cfg.tv_density * tvd + cfg.tv_sh * tvs
    return mse, loss, torch.from_numpy(seen_rays)


def torch_step(fld: VoxelField, b: Batch, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The PyTorch path: :func:`.render.render_rays` (samples jittered from torch's global
    generator) and autograd. Returns as :func:`kernel_step`."""
    cfg = fld.cfg
    out = render_rays(fld, b.origins, b.dirs, b.bg, jitter=True)
    se = ((out.rgb - b.target) ** 2).mean(-1)
    mse = se.mean()
    loss = mse if b.ray_w is None else (se * b.ray_w).mean()
    seen_rays = torch.cat([out.rgb, out.alpha[:, None]], -1).detach().cpu()
    if cfg.tv_density > 0 or cfg.tv_sh > 0:
        tvd, tvs = tv_loss(fld, cfg.tv_points, gen)
        loss = loss + cfg.tv_density * tvd + cfg.tv_sh * tvs
    loss.backward()
    return mse, loss, seen_rays


def train(state: TrainState, bank: RayBank, budget: Budget,
          on_step: Callable[[TrainState, float], None] | None = None,
          checkpoint: Path | None = None, checkpoint_every_s: float = 120.0,
          checkpoint_every_steps: int = 5000) -> TrainState:
    """Optimize ``state.field`` on the rays of ``bank`` until ``budget`` is spent.

    Each step draws a batch (:func:`draw_batch`), renders it with TV (:func:`kernel_step` or
    :func:`torch_step`) and takes a sparse Adam step. The coarse-to-fine schedule follows the
    *fraction of the budget* spent, so a shorter budget runs the same stages faster.
    ``on_step(state, running train PSNR)`` follows every step; checkpoints go to ``checkpoint``
    every ``checkpoint_every_s`` seconds or ``checkpoint_every_steps`` steps, whichever comes
    first (a large field takes seconds to write), and on Ctrl-C or SIGTERM; the first one before
    the first step, so a run killed outright (SIGKILL, power loss) can still be resumed. The field
    is left pruned: what gets baked and saved holds no empty lattice points.
    """
    cfg = state.field.cfg
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed + state.step)
    torch.manual_seed(cfg.seed + state.step)
    if checkpoint is not None and not checkpoint.is_file():
        state.save(checkpoint)
    t_start = time.perf_counter() - state.seconds
    try:
        _loop(state, bank, budget, on_step, checkpoint, checkpoint_every_s, checkpoint_every_steps, gen, t_start)
    except KeyboardInterrupt:
        if checkpoint is not None:          # --resume continues from here
            state.save(checkpoint)
        raise
    state.field = pruned(state.field, cfg.prune_alpha)
    if checkpoint is not None:
        state.save(checkpoint)
    return state


def _loop(state: TrainState, bank: RayBank, budget: Budget, on_step, checkpoint: Path | None,
          every_s: float, every_steps: int, gen: torch.Generator, t_start: float) -> None:
    cfg = state.field.cfg
    last_ckpt, last_step = time.perf_counter(), state.step
    ema = None
    robust = cfg.robust_from is not None and cfg.robust_from < 1.0
    while True:
        frac = budget.fraction(state.step, time.perf_counter() - t_start)
        if frac >= 1.0:
            break
        advance_schedule(state, bank, frac)
        fld = state.field
        lr_scale = cfg.lr_final_ratio ** frac
        batch = draw_batch(bank, fld, frac, robust, gen)
        mse, loss, seen_rays = (kernel_step if fld.cpu_kernel else torch_step)(fld, batch, gen)
        if robust:
            bank.record_errors(batch.pick, seen_rays[:, :3], seen_rays[:, 3], batch.bg.cpu())
        fld.density.adam_step(cfg.lr_density * lr_scale)
        fld.sh.adam_step(cfg.lr_sh * lr_scale)
        fld.reset_sentinel()
        state.step += 1
        m = float(mse.detach())
        ema = m if ema is None else 0.9 * ema + 0.1 * m
        state.seconds = time.perf_counter() - t_start
        if state.step % 10 == 0 or state.step == 1:
            state.history.append({"step": state.step, "seconds": round(state.seconds, 2),
                                  "loss": float(loss.detach()), "psnr": psnr_from_mse(ema), "res": fld.res,
                                  "points": fld.n_active})
        if on_step is not None:
            on_step(state, psnr_from_mse(ema))
        if checkpoint is not None and (time.perf_counter() - last_ckpt > every_s
                                       or state.step - last_step >= every_steps):
            state.save(checkpoint)
            last_ckpt, last_step = time.perf_counter(), state.step
