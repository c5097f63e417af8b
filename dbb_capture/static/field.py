"""A sparse voxel radiance field (density + spherical-harmonic colour), optimized directly.

Plenoxels/DVGO style, in plain PyTorch: values live on the points of a regular lattice
inside the object's bounding cube; a query interpolates the 8 surrounding lattice points
trilinearly. Only *active* lattice points own parameters (``index`` maps the dense lattice
to rows of compact tables), so pruned empty space costs neither memory nor time, and the
dense ``occupancy`` of active points lets rays skip empty space.

Coordinates. ``object`` mode: normalized ``x = (p - center) / radius``; the lattice spans
the cube [-1, 1]^3 around the object sphere. ``scene`` mode (unbounded, e.g. a clean
plate): the same, then contracted (mip-NeRF 360): ``|x| <= 1`` unchanged, beyond it
``(2 - 1/|x|) x/|x|``, so the lattice spans [-2, 2]^3 and holds everything to infinity.

Units. Density ``sigma`` is per normalized unit (one object radius); world density is
``sigma / radius``. Colour is ``sigmoid(sum_b c_b Y_b(d))`` with the SH basis and sign
convention of svox/PlenOctrees, so baking is a straight copy (see :mod:`.octree`).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from ..datasets.records import Frame, ObjectVolume, load_rgb, load_rgba
from ..geometry.rays import pixel_rays
from ..geometry.cameras import scaled_intrinsics
from ..core.errors import DbbError
from ..core.metrics import psnr_from_mse
from ..core.row_table import RowTable
from ..geometry.cameras import Intrinsics
from ..geometry.sh import sh_basis


def contract(x: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360 contraction of normalized points (..., 3) into the ball of radius 2."""
    n = x.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return torch.where(n <= 1, x, (2 - 1 / n) * (x / n))


@dataclass
class FieldConfig:
    """How to build and train a field. Lengths in lattice cells unless stated."""

    mode: str = "object"            # "object" (bounded, RGBA) or "scene" (unbounded, contracted)
    sh_degree: int = 2
    res_start: int = 32             # lattice points per axis at the first stage
    # Coarse to fine doubles up to this. None: by the training views (:func:`lattice_for_views`),
    # one cell per pixel across the object: a finer lattice than the pixels only gives the
    # optimizer more freedom to fit each view's noise and the footage's blur at the outline
    # (docs/benchmarks.md, issue 4, seventh session: 128 px crops, 10 min, 640x480 capture,
    # held out on white 30.81 dB at 128^3 against 29.05 at 256^3).
    res_max: int | None = None
    max_points: int = 6_000_000     # never upsample past this many active points (memory, time)
    step_cells: float = 0.5         # sample spacing along rays
    batch_rays: int = 4096
    lr_density: float = 10.0        # density lives per normalized unit: ~300 for one opaque 256^3 cell
    lr_sh: float = 0.3
    lr_final_ratio: float = 0.1     # learning rates decay exponentially to this fraction
    tv_density: float = 1e-5        # total-variation weights (mean squared neighbour difference)
    tv_sh: float = 1e-3             # Plenoxels weights SH smoothness 100x density: +0.15 dB held out on lego
    tv_points: int = 8192           # lattice points sampled per step for TV
    prune_alpha: float = 1e-3       # drop points whose one-cell opacity stays below this
    weight_eps: float = 1e-4        # colour is evaluated only where a sample's weight exceeds this
    init_alpha: float = 1e-4        # opacity of one step at the start (nearly empty)
    # Fraction of the budget at which each new stage starts; stages past the last one listed are
    # not reached (checkpoints from before 512^3 was reachable list three).
    upsample_at: tuple[float, ...] = (0.15, 0.3, 0.45, 0.6)
    # From this fraction of the budget on (final stage only), samples read their nearest lattice
    # point instead of interpolating: piecewise constant, exactly what the baked tree renders,
    # so the last steps fine-tune the tree itself (PlenOctrees' tree fine-tuning). 1: never.
    nearest_from: float = 0.8
    # Progressive SH (as 3D Gaussian Splatting adds bands over training): until this fraction of
    # the budget the colour uses SH degree at most 1, and the higher bands join from here on.
    # Degree 1 steps faster (fewer coefficients to interpolate, scatter and update) and
    # extrapolates colour to views the training never saw better; the higher bands then fit the
    # view dependence that is left, at the schedule's low learning rates (docs/benchmarks.md,
    # issue 4, eleventh session: 640x480 static capture, 10 min, +0.25 dB black, +0.14-0.17
    # white, 28 % more steps). 0: all bands from the start.
    sh_full_from: float = 0.8
    # Weight of the opacity prior log(A + e) + log(1 - A + e) on each ray's opacity A (Neural
    # Volumes' beta prior), mean over rays: pushes rays to empty or opaque, against the fringe
    # haze that noisy mattes leave. 0: off.
    beta_alpha: float = 0.0
    # Datasets that keep each crop's observed pixels and the room predicted behind them
    # (preprocess crops): render over the predicted room and compare with what the camera saw,
    # so alpha comes from multi-view consistency instead of from the matte. The matte (random
    # background, as for other datasets) stays a prior on a share ``matte_prior`` of the rays
    # where the observed colour is within ``decisive_diff`` (max over RGB, [0, 1]) of the room's,
    # fading out linearly up to that difference. False: the matte alone; None: by the dataset's
    # kind (:meth:`for_dataset`: on for preprocess crops). A table-coloured part that a view's
    # matte misses renders like the room there and costs nothing in that view, while the views
    # that see it against another colour keep it (docs/benchmarks.md, issue 4, seventh session:
    # +1.1 dB on white at 2000 steps on the 640x480 capture, -0.1 at 1920x1440).
    observed_loss: bool | None = None
    matte_prior: float = 0.5
    decisive_diff: float = 0.6
    # ... and where the matte sees any of the object (alpha at least this) it decides: over one
    # room per ray, colour and alpha trade off (a * c + (1 - a) * B fits many pairs), which left
    # the object see-through from new angles (at 0.99), and at the outline the observed colour
    # carries the footage's blur, which widened the outline (at 0.99: -0.8 dB on white at
    # 1920x1440; at 0.02: -0.1). So the observed pixels speak where the matte says "room":
    # against its misses. Above 1: never.
    matte_opaque: float = 0.02
    # Robust training (iteratively reweighted least squares, as RobustNeRF / NeRF-W let views
    # outvote their outliers): from this fraction of the budget on, each ray's squared error is
    # weighted by ``1 / (1 + e / robust_scale^2)``, ``e`` the running mean of that ray's own
    # error (premultiplied colour and alpha against its target, independent of the random
    # background) over its earlier visits. A matte's false object or hole that other views
    # contradict keeps a large error and loses its say; what the views agree on fits and keeps
    # weight 1. ``robust_scale`` is in colour units (0..1). 1: off (plain L2); None: by the
    # dataset's kind (:meth:`for_dataset`).
    robust_from: float | None = None
    robust_scale: float = 0.1
    # Carving (space carving / a visual hull with a tolerance): at every lattice stage, points
    # that at least this share of the training views that see them (and at least
    # ``carve_min_views``) see as clearly empty (alpha under ``carve_alpha`` within a pixel and
    # the point's footprint of it) are left out of the field. A matte's false object that other
    # views see through cannot be learned as geometry; a hole that few views share is kept.
    # 0: off; None: by the dataset's kind. Needs the views' alpha (object mode); datasets
    # without alpha are not carved.
    carve_share: float | None = None
    carve_min_views: int = 3
    carve_alpha: float = 0.1
    seed: int = 0

    def for_dataset(self, kind: str) -> "FieldConfig":
        """Settings left to the dataset (None) decided by its ``kind``: carving (0.1), robust
        training (from half the budget) and the observed loss for preprocess crops ("crops"),
        whose mattes carry errors that the views outvote (docs/benchmarks.md, issue 4: +0.7 dB
        at 2000 steps on the 640x480 sample for the first two); off where the alpha is the truth
        or absent (Blender, nerfstudio, instant-ngp)."""
        crops = kind == "crops"
        pick = lambda v, on, off: (on if crops else off) if v is None else v
        return replace(self, robust_from=pick(self.robust_from, 0.5, 1.0), carve_share=pick(self.carve_share, 0.1, 0.0),
                       observed_loss=pick(self.observed_loss, True, False))

    @property
    def n_basis(self) -> int:
        return (self.sh_degree + 1) ** 2

    def validate(self) -> None:
        if self.mode not in ("object", "scene"):
            raise DbbError(f"field mode must be object or scene, not {self.mode!r}")
        if not 0 <= self.sh_degree <= 3:
            raise DbbError("SH degree must be 0..3")
        if self.res_max is None:
            raise DbbError("the lattice size is not decided yet (res_max None: see lattice_for_views)")
        if self.res_start < 8 or self.res_max < self.res_start:
            raise DbbError("need 8 <= res_start <= res_max")


def _lattice_lin(i: torch.Tensor, res: int) -> torch.Tensor:
    """Linear index of integer lattice coordinates (..., 3)."""
    return (i[..., 0] * res + i[..., 1]) * res + i[..., 2]


_CORNERS = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])


class VoxelField:
    """The field: ``index`` (res^3 lattice -> row or -1), ``density`` (N+1, 1), ``sh`` (N+1, 3*B).

    Row N is a sentinel for inactive lattice points: very negative raw density, zero colour.
    """

    SENTINEL_RAW = -20.0

    def __init__(self, cfg: FieldConfig, volume: ObjectVolume, res: int, device: torch.device,
                 active: torch.Tensor | None = None, density: torch.Tensor | None = None,
                 sh: torch.Tensor | None = None, nearest: bool = False):
        cfg.validate()
        self.cfg = cfg
        self.volume = volume
        self.device = device
        self.center = torch.tensor(volume.center, dtype=torch.float32, device=device)
        self.radius = float(volume.radius)
        self.span = 1.0 if cfg.mode == "object" else 2.0       # lattice covers [-span, span]^3
        self.res = int(res)
        if active is None:
            active = torch.arange(self.res ** 3, device=device)
        active = active.to(device=device, dtype=torch.long)
        n = active.numel()
        # int32: at 512^3 the dense map alone is half a gigabyte.
        self.index = torch.full((self.res ** 3,), -1, dtype=torch.int32, device=device)
        self.index[active] = torch.arange(n, device=device, dtype=torch.int32)
        self.active = active
        if density is None:
            density = torch.zeros(n, 1, device=device)
        if sh is None:
            sh = torch.zeros(n, 3 * cfg.n_basis, device=device)
        self.density = RowTable(torch.cat(
            [density.to(device).float().reshape(n, 1), torch.full((1, 1), self.SENTINEL_RAW, device=device)]))
        self.sh = RowTable(torch.cat(
            [sh.to(device).float().reshape(n, 3 * cfg.n_basis), torch.zeros(1, 3 * cfg.n_basis, device=device)]))
        self._occ_cache: torch.Tensor | None = None
        self.nearest = nearest  # queries read the nearest lattice point (see FieldConfig.nearest_from)
        self.sh_active = cfg.sh_degree  # SH bands in use (see FieldConfig.sh_full_from)

    # ---- geometry -------------------------------------------------------------------------
    @property
    def cell(self) -> float:
        """Lattice spacing in normalized units."""
        return 2 * self.span / self.res

    @property
    def step(self) -> float:
        return self.cfg.step_cells * self.cell

    @property
    def act_shift(self) -> float:
        """Raw-density offset making one step's opacity ``init_alpha`` at the start resolution."""
        step0 = self.cfg.step_cells * 2 * self.span / self.cfg.res_start
        s = -math.log(1 - self.cfg.init_alpha) / step0
        return math.log(math.expm1(s))

    def normalize(self, p: torch.Tensor) -> torch.Tensor:
        """World points (..., 3) -> lattice-space points (object: [-1,1]^3, scene: contracted)."""
        x = (p - self.center) / self.radius
        return contract(x) if self.cfg.mode == "scene" else x

    def to_lattice(self, x: torch.Tensor) -> torch.Tensor:
        """Lattice-space points (..., 3) -> continuous lattice coordinates (point i at i)."""
        return (x + self.span) / self.cell - 0.5

    def lattice_points(self, lin: torch.Tensor, res: int | None = None) -> torch.Tensor:
        """Lattice-space position (M, 3) of linear lattice indices (M,) (of a ``res`` lattice)."""
        r = res or self.res
        ijk = torch.stack([lin // (r * r), (lin // r) % r, lin % r], -1).float()
        return (ijk + 0.5) * (2 * self.span / r) - self.span

    @property
    def n_active(self) -> int:
        return int(self.active.numel())

    @property
    def cpu_kernel(self) -> bool:
        """Whether training and rendering run the numba kernel (:mod:`.fields_cpu`): object mode
        on the CPU; CUDA and scene mode take the PyTorch path."""
        return self.device.type == "cpu" and self.cfg.mode == "object"

    # ---- queries --------------------------------------------------------------------------
    def _corners(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows (M, 8) and trilinear weights (M, 8) for lattice-space points (M, 3)."""
        u = self.to_lattice(x).clamp(0, self.res - 1)
        if self.nearest:
            # The nearest point alone: its row 8 times at weight 1/8 keeps the (M, 8) shapes.
            rows = self.index[_lattice_lin(u.round().long(), self.res)].long()
            rows = torch.where(rows < 0, torch.full_like(rows, self.n_active), rows)
            return rows[:, None].expand(-1, 8), torch.full((x.shape[0], 8), 0.125, device=x.device)
        i0 = u.floor().clamp(max=self.res - 2)
        f = u - i0
        i0 = i0.long()
        c = _CORNERS.to(x.device)
        lin = _lattice_lin(i0[:, None, :] + c[None], self.res)
        rows = self.index[lin].long()
        rows = torch.where(rows < 0, torch.full_like(rows, self.n_active), rows)
        fc = torch.where(c[None].bool(), f[:, None, :], 1 - f[:, None, :])
        return rows, fc.prod(-1)

    def sigma_from(self, rows: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """Density (M,) per normalized unit, post-activation (DVGO: interpolate, then softplus)."""
        raw = torch.bmm(w[:, None, :], self.density.gather(rows))[:, 0, 0]
        return F.softplus(raw + self.act_shift)

    def rgb_from(self, rows: torch.Tensor, w: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Colour (M, 3) in [0, 1] seen along unit world directions ``d`` (M, 3)."""
        coef = torch.bmm(w[:, None, :], self.sh.gather(rows))[:, 0]
        coef = coef.view(-1, 3, self.cfg.n_basis)
        basis = sh_basis(self.cfg.sh_degree, d)
        if self.sh_active < self.cfg.sh_degree:
            basis = basis * (torch.arange(basis.shape[-1], device=basis.device) < (self.sh_active + 1) ** 2)
        return torch.sigmoid((coef * basis[:, None, :]).sum(-1))

    def query(self, x: torch.Tensor, d: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Density (M,) and, given directions (M, 3), colour (M, 3) at lattice-space points (M, 3)."""
        rows, w = self._corners(x)
        sig = self.sigma_from(rows, w)
        return sig, (self.rgb_from(rows, w, d) if d is not None else None)

    def raw_at(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Interpolated raw density (M,) and SH coefficients (M, 3*B) at lattice-space points."""
        rows, w = self._corners(x)
        raw = (self.density.data[rows][..., 0] * w).sum(-1)
        coef = (self.sh.data[rows] * w[..., None]).sum(1)
        return raw, coef

    def occupancy(self) -> torch.Tensor:
        """Dense bool lattice (res^3,): points near an active one (dilated by one cell)."""
        if self._occ_cache is None:
            occ = torch.zeros(self.res ** 3, device=self.device)
            occ[self.active] = 1
            occ = F.max_pool3d(occ.view(1, 1, self.res, self.res, self.res), 3, 1, 1)
            self._occ_cache = occ.view(-1) > 0
        return self._occ_cache

    # ---- structure changes ----------------------------------------------------------------
    @torch.no_grad()
    def point_alpha(self) -> torch.Tensor:
        """Opacity of one cell at each active point (N,), from its own raw density."""
        sig = F.softplus(self.density.data[:-1, 0] + self.act_shift)
        return 1 - torch.exp(-sig * self.cell)

    @torch.no_grad()
    def pruned(self, alpha_min: float) -> "VoxelField":
        """A field without the points whose one-cell opacity is below ``alpha_min``.

        Kept: points above the threshold and their 26 neighbours (trilinear interpolation
        near a surface reads them).
        """
        keep = self.point_alpha() >= alpha_min
        if not bool(keep.any()):
            return self    # nothing learned yet: pruning would leave no field to train
        mask = torch.zeros(self.res ** 3, device=self.device)
        mask[self.active[keep]] = 1
        mask = F.max_pool3d(mask.view(1, 1, *(self.res,) * 3), 3, 1, 1).view(-1) > 0
        rows = self.index[mask.nonzero()[:, 0]].long()
        rows = rows[rows >= 0]
        return VoxelField(self.cfg, self.volume, self.res, self.device, self.active[rows],
                          self.density.data[rows], self.sh.data[rows], self.nearest)

    @torch.no_grad()
    def carved(self, views: "Silhouettes", share: float, min_views: int = 3, empty_alpha: float = 0.1) -> "VoxelField":
        """The field without the active points the views carve away (:func:`carve_mask`)."""
        pts = (self.lattice_points(self.active).cpu().numpy().astype(np.float64) * self.radius
               + np.asarray(self.volume.center, np.float64))
        keep = torch.from_numpy(~carve_mask(views, pts, self.cell * self.radius, share, min_views, empty_alpha))
        keep = keep.to(self.device)
        if bool(keep.all()):
            return self
        return VoxelField(self.cfg, self.volume, self.res, self.device, self.active[keep],
                          self.density.data[:-1][keep], self.sh.data[:-1][keep], self.nearest)

    @torch.no_grad()
    def upsampled(self, res: int) -> "VoxelField":
        """The same field on a finer lattice (``res`` points per axis), active near active points."""
        occ = torch.zeros(self.res ** 3, device=self.device)
        occ[self.active] = 1
        occ = F.max_pool3d(occ.view(1, 1, *(self.res,) * 3), 3, 1, 1)
        # Fine point -> coarse point it lies in (nearest): the dilated coarse mask picks it.
        fine = F.interpolate(occ, size=(res,) * 3, mode="nearest").view(-1) > 0
        lin = fine.nonzero()[:, 0]
        x = self.lattice_points(lin, res)
        raws, coefs = [], []
        for s in range(0, lin.numel(), 1 << 20):
            r, c = self.raw_at(x[s:s + (1 << 20)])
            raws.append(r)
            coefs.append(c)
        return VoxelField(self.cfg, self.volume, res, self.device, lin,
                          torch.cat(raws) if raws else None, torch.cat(coefs) if coefs else None)

    def reset_sentinel(self) -> None:
        self.density.data[-1] = self.SENTINEL_RAW
        self.sh.data[-1] = 0

    # ---- persistence ----------------------------------------------------------------------
    def state(self) -> dict:
        return {"config": asdict(self.cfg), "volume": self.volume.to_json(), "res": self.res,
                "nearest": self.nearest, "active": self.active.cpu(), "density": self.density.data[:-1].cpu(),
                "sh": self.sh.data[:-1].cpu()}

    @classmethod
    def from_state(cls, st: dict, device: torch.device) -> "VoxelField":
        cfgd = dict(st["config"])
        cfgd["upsample_at"] = tuple(cfgd.get("upsample_at", ()))
        cfgd.setdefault("sh_full_from", 0.0)     # checkpoints from before progressive SH: all bands
        cfg = FieldConfig(**cfgd)
        v = st["volume"]
        vol = ObjectVolume(tuple(v["center"]), float(v["radius"]), bool(v.get("estimated", False)))
        return cls(cfg, vol, st["res"], device, st["active"], st["density"], st["sh"],
                   bool(st.get("nearest", False)))


# ---- rays -------------------------------------------------------------------------------------

def _sphere_hits(o: torch.Tensor, d: torch.Tensor, r: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances (B,) of rays with the sphere of radius ``r`` at the origin.

    Rays that miss get entry = exit = the distance of closest approach (clamped at 0).
    """
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - r * r
    disc = b * b - c
    s = disc.clamp_min(0).sqrt()
    t0 = (-b - s).clamp_min(0)
    t1 = (-b + s).clamp_min(0)
    miss = disc <= 0
    tc = (-b).clamp_min(0)
    return torch.where(miss, tc, t0), torch.where(miss, tc, t1)


def _object_samples(field: VoxelField, o: torch.Tensor, d: torch.Tensor, jitter: torch.Tensor):
    """Sample distances (B, S), validity (B, S) and spacing (B, S) inside the unit sphere."""
    t0, t1 = _sphere_hits(o, d, 1.0)
    step = field.step
    S = max(1, int(math.ceil(float((t1 - t0).max()) / step)))
    k = torch.arange(S, device=o.device, dtype=o.dtype)
    t = t0[:, None] + (k[None] + jitter[:, None]) * step
    valid = t < t1[:, None]
    return t, valid, torch.full_like(t, step)


def _scene_samples(field: VoxelField, o: torch.Tensor, d: torch.Tensor, jitter: torch.Tensor,
                   far: float = 1e4):
    """Samples for the contracted scene: even inside the unit sphere, even in contracted
    radius outside it (before and after), so the lattice sees about one sample per half cell."""
    step = field.step
    t0, t1 = _sphere_hits(o, d, 1.0)
    S_in = max(1, int(math.ceil(float((t1 - t0).max()) / step)))
    # Outside, offsets u from the sphere so that 2 - 1/(1+u) advances by one step each.
    s = (torch.arange(int(math.ceil(1 / step)), device=o.device, dtype=o.dtype)[None]
         + jitter[:, None]) * step
    u = 1 / (1 - s).clamp_min(1e-4) - 1
    k = torch.arange(S_in, device=o.device, dtype=o.dtype)
    t_in = t0[:, None] + (k[None] + jitter[:, None]) * step
    t_pre = (t0[:, None] - u.flip(-1))
    t_post = t1[:, None] + u
    t = torch.cat([t_pre, t_in, t_post], -1)
    valid = torch.cat([t_pre > 0, t_in < t1[:, None], t_post < far], -1)
    # Spacing measured in lattice space, where the density lives.
    x = contract(o[:, None] + t[..., None] * d[:, None])
    gap = (x[:, 1:] - x[:, :-1]).norm(dim=-1)
    delta = torch.cat([gap, gap[:, -1:]], -1)
    return t, valid, delta


@dataclass
class RayOutput:
    rgb: torch.Tensor        # (B, 3) composited on the given background
    alpha: torch.Tensor      # (B,) accumulated opacity = 1 - transmittance
    depth: torch.Tensor      # (B,) expected distance (world units), 0 where empty


def render_rays(field: VoxelField, origins: torch.Tensor, dirs: torch.Tensor,
                background: torch.Tensor | None = None, jitter: bool = False) -> RayOutput:
    """Volume-render world rays: origins (B, 3), unit directions (B, 3), background (B, 3) or None (black).

    Samples in empty lattice space are skipped; colour is evaluated only where a sample's
    weight exceeds ``weight_eps``. Differentiable with respect to the field.
    """
    dev = origins.device
    B = origins.shape[0]
    o = (origins - field.center) / field.radius
    j = torch.rand(B, device=dev) if jitter else torch.full((B,), 0.5, device=dev)
    sampler = _object_samples if field.cfg.mode == "object" else _scene_samples
    t, valid, delta = sampler(field, o, dirs, j)
    x = o[:, None] + t[..., None] * dirs[:, None]
    if field.cfg.mode == "scene":
        x = contract(x)
    u = field.to_lattice(x).round().long().clamp(0, field.res - 1)
    valid &= field.occupancy()[_lattice_lin(u, field.res)]
    idx = valid.nonzero()
    bi, si = idx[:, 0], idx[:, 1]
    rows, w = field._corners(x[bi, si])
    if torch.is_grad_enabled():
        # Pass 1 without autograd: drop samples hidden behind opaque matter (a suffix of each
        # ray), so the differentiable pass only pays for what can still be seen.
        with torch.no_grad():
            raw = torch.bmm(w[:, None, :], field.density.data[rows])[:, 0, 0]
            tau0 = torch.zeros_like(t).index_put((bi, si), F.softplus(raw + field.act_shift) * delta[bi, si])
            seen = (torch.cumsum(tau0, -1) - tau0)[bi, si] < -math.log(field.cfg.weight_eps)
        bi, si, rows, w = bi[seen], si[seen], rows[seen], w[seen]
    sig = field.sigma_from(rows, w)
    tau = torch.zeros_like(t).index_put((bi, si), sig * delta[bi, si])
    # Transmittance before each sample: exp of minus the optical depth accumulated so far.
    T = torch.exp(-(torch.cumsum(tau, -1) - tau))
    wgt = (T * (1 - torch.exp(-tau)))[bi, si]
    keep = wgt > field.cfg.weight_eps
    rgb_s = field.rgb_from(rows[keep], w[keep], dirs[bi[keep]])
    rgb = torch.zeros(B, 3, device=dev).index_add(0, bi[keep], wgt[keep, None] * rgb_s)
    acc = torch.zeros(B, device=dev).index_add(0, bi, wgt)
    dep = torch.zeros(B, device=dev).index_add(0, bi, wgt * t[bi, si]) * field.radius
    if background is not None:
        rgb = rgb + (1 - acc)[:, None] * background
    return RayOutput(rgb, acc, dep)


@torch.no_grad()
def render_image(field: VoxelField, origins: torch.Tensor, dirs: torch.Tensor,
                 background: tuple[float, float, float] | None = None, chunk: int = 8192) -> np.ndarray:
    """Straight RGBA (H, W, 4) float32 of rays (H, W, 3) — or RGB on ``background`` if given."""
    H, W = origins.shape[:2]
    o = origins.reshape(-1, 3).to(field.device)
    d = dirs.reshape(-1, 3).to(field.device)
    out = []
    for s in range(0, o.shape[0], chunk):
        if field.cpu_kernel:
            n = o[s:s + chunk].shape[0]
            res = torch.from_numpy(_cpu_rays(field, o[s:s + chunk], d[s:s + chunk], torch.zeros(n, 3), None,
                                             torch.full((n,), 0.5)))
            r = RayOutput(res[:, :3], res[:, 3], torch.zeros(n))
        else:
            r = render_rays(field, o[s:s + chunk], d[s:s + chunk])
        a = r.alpha.clamp(0, 1)
        if background is None:
            rgb = r.rgb / a.clamp_min(1e-6)[:, None]
            out.append(torch.cat([rgb.clamp(0, 1), a[:, None]], -1))
        else:
            bg = torch.tensor(background, device=o.device, dtype=torch.float32)
            out.append((r.rgb + (1 - a)[:, None] * bg).clamp(0, 1))
    return torch.cat(out).reshape(H, W, -1).cpu().numpy()


# ---- training ---------------------------------------------------------------------------------

RAY_RUN = 32     # CPU training draws rays in runs of this many consecutive bank entries
BETA_EPS = 0.01  # keeps the opacity prior's log finite at A = 0 and 1


def opacity_prior(alpha: torch.Tensor) -> torch.Tensor:
    """Mean of log(A + e) + log(1 - A + e) over ray opacities ``alpha`` (B,): lowest at 0 and 1."""
    a = alpha.clamp(0, 1)
    return (torch.log(a + BETA_EPS) + torch.log(1 - a + BETA_EPS)).mean()


@dataclass
class RayBank:
    """Every training pixel as a ray: origins, unit directions (N, 3) world; straight RGBA (N, 4);
    for preprocess crops also the observed RGB and the predicted room's RGB (N, 3), else None;
    for robust training each ray's running squared error (N,) (NaN until first rendered)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    rgba: torch.Tensor
    observed: torch.Tensor | None = None
    room: torch.Tensor | None = None
    error: torch.Tensor | None = None
    views: "Silhouettes | None" = None

    @property
    def n(self) -> int:
        return int(self.origins.shape[0])

    def record_errors(self, pick: torch.Tensor, rgb: torch.Tensor, alpha: torch.Tensor, bg: torch.Tensor,
                      keep: float = 0.5) -> None:
        """Fold the rays ``pick`` (B,) as just rendered into their running error (:attr:`error`):
        ``rgb`` (B, 3) composited over ``bg`` (B, 3), ``alpha`` (B,). The error is the squared
        premultiplied-colour difference (summed over RGB) plus the squared alpha difference to
        the ray's straight RGBA target, so the random background does not enter it; it replaces
        ``1 - keep`` of the previous value."""
        if self.error is None:
            self.error = torch.full((self.n,), float("nan"))
        t = self.rgba[pick]
        pm = rgb - (1 - alpha[:, None]) * bg
        e = ((pm - t[:, :3] * t[:, 3:]) ** 2).sum(-1) + (alpha - t[:, 3]) ** 2
        old = self.error[pick]
        self.error[pick] = torch.where(old.isnan(), e, keep * old + (1 - keep) * e)


@dataclass
class Silhouettes:
    """The training views' alpha (each (h, w) uint8, 255 = opaque) and cameras (OpenCV c2w (4, 4),
    intrinsics at the alpha's size): what :func:`carve_mask` asks which points the views see empty."""

    alphas: list[np.ndarray]
    cameras: list[tuple[np.ndarray, "Intrinsics"]]


def carve_mask(views: Silhouettes, points: np.ndarray, cell: float, share: float, min_views: int = 3,
               empty_alpha: float = 0.1) -> np.ndarray:
    """Which world points (M, 3) the views carve away: (M,) bool, True where at least ``share``
    of the views that see the point (it projects inside the image, in front of the camera), and
    at least ``min_views`` of them, find alpha below ``empty_alpha`` everywhere within one pixel
    plus half the point's footprint (a cube of side ``cell`` world units) of where it projects.
    So a point is only carved where views clearly see through it: pose and resampling errors of
    a pixel, and holes that fewer views than ``share`` have, keep it."""
    import cv2

    from ..geometry.transforms import invert_rigid
    from ..geometry.cameras import project_points

    seen = np.zeros(len(points), np.int32)
    empty = np.zeros(len(points), np.int32)
    for a, (c2w, intr) in zip(views.alphas, views.cameras):
        w2c = invert_rigid(c2w)
        z = points @ w2c[:3, :3].T[:, 2] + w2c[2, 3]
        front = z > 1e-6
        if not front.any():
            continue
        # Dilate by the footprint of a cell at the view's median depth (plus one pixel).
        r = 1 + int(math.ceil(0.5 * cell * 0.5 * (intr.fx + intr.fy) / float(np.median(z[front]))))
        wide = cv2.dilate(a, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        uv = project_points(points[front], c2w, intr)
        iu, iv = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        inside = (iu >= 0) & (iu < a.shape[1]) & (iv >= 0) & (iv < a.shape[0])
        idx = np.nonzero(front)[0][inside]
        seen[idx] += 1
        empty[idx] += wide[iv[inside], iu[inside]] < 255 * empty_alpha
    return (empty >= min_views) & (empty >= share * seen)


def robust_weights(error: torch.Tensor, scale: float) -> torch.Tensor:
    """IRLS weights (B,) of the Cauchy loss for rays with running squared errors ``error`` (B,):
    ``1 / (1 + error / scale^2)``; rays not yet rendered (NaN) weigh 1."""
    w = 1.0 / (1.0 + error / (scale * scale))
    return torch.where(error.isnan(), torch.ones_like(w), w)


def frame_tensors(frame: Frame, downscale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origins, dirs, rgba) of one frame at 1/downscale size, each (h, w, C) float32."""
    rgba = load_rgba(frame, downscale)
    o, d = pixel_rays(scaled_intrinsics(frame.intr, downscale), frame.c2w)
    return o, d, rgba


def build_ray_bank(frames: list[Frame], downscale: float, volume: ObjectVolume | None = None,
                   mode: str = "object", observed: bool = True) -> RayBank:
    """All pixels of ``frames``; in object mode, rays that miss the object sphere are dropped
    (they only ever see the background, which the random-background loss already covers), and
    the views' alpha is kept for carving (:attr:`RayBank.views`). With ``observed``, frames that
    name their observed crop and predicted room (preprocess crops) add them to the bank
    (:attr:`FieldConfig.observed_loss` uses them)."""
    # Frames without them (a crop past the frame's border) get NaN rows: the matte alone.
    has_room = [f.observed_path is not None and f.background_path is not None for f in frames]
    with_room = observed and mode == "object" and any(has_room)
    os_, ds, cs, seen, rooms, alphas = [], [], [], [], [], []
    for f, known in zip(frames, has_room):
        o, d, c = frame_tensors(f, downscale)
        alphas.append(np.round(c[..., 3] * 255).astype(np.uint8))
        o, d, c = o.reshape(-1, 3), d.reshape(-1, 3), c.reshape(-1, 4)
        hit = np.ones(len(o), bool)
        if mode == "object" and volume is not None:
            oc = o - np.asarray(volume.center, np.float32)
            b = (oc * d).sum(-1)
            hit = b * b - ((oc * oc).sum(-1) - volume.radius ** 2) > 0
        os_.append(o[hit])
        ds.append(d[hit])
        cs.append(c[hit])
        if with_room:
            unknown = np.full((int(hit.sum()), 3), np.nan, np.float32)
            seen.append(load_rgb(f.observed_path, f.intr, downscale).reshape(-1, 3)[hit] if known else unknown)
            rooms.append(load_rgb(f.background_path, f.intr, downscale).reshape(-1, 3)[hit] if known else unknown)
    if not os_ or sum(len(o) for o in os_) == 0:
        raise DbbError("no training rays: no frame sees the object volume")
    def cat(xs: list[np.ndarray]) -> torch.Tensor | None:
        return torch.from_numpy(np.concatenate(xs)) if xs else None

    views = None
    if mode == "object":
        views = Silhouettes(alphas, [(f.c2w, scaled_intrinsics(f.intr, downscale)) for f in frames])
    return RayBank(cat(os_), cat(ds), cat(cs), cat(seen), cat(rooms), views=views)


def ray_targets(rgba: torch.Tensor, bg: torch.Tensor, observed: torch.Tensor | None, room: torch.Tensor | None,
                cfg: FieldConfig, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Background and target colour (B, 3) of each training ray.

    ``rgba`` (B, 4) straight RGBA (a matte's alpha for crops), ``bg`` (B, 3) random colours:
    the target is ``rgba`` composited over ``bg``. With ``observed`` / ``room`` (B, 3) (see
    :attr:`FieldConfig.observed_loss`), a ray instead renders over the predicted room and is
    compared with the observed pixel, except with probability ``matte_prior * (1 - diff /
    decisive_diff)`` (clipped at 0), ``diff`` the largest RGB difference observed - room: where
    colour cannot tell object from room, the matte decides; so it does where its alpha is at least
    ``matte_opaque``. Rays with NaN ``observed`` take the matte.
    """
    target = rgba[:, :3] * rgba[:, 3:] + (1 - rgba[:, 3:]) * bg
    if observed is None or room is None or not cfg.observed_loss:
        return bg, target
    diff = (observed - room).abs().amax(-1)
    p_matte = cfg.matte_prior * (1 - diff / max(cfg.decisive_diff, 1e-6)).clamp(0, 1)
    p_matte = torch.where(rgba[:, 3] >= cfg.matte_opaque, torch.ones_like(p_matte), p_matte)
    use_seen = (torch.rand(diff.shape[0], generator=gen) >= p_matte.cpu()).to(rgba.device) & diff.isfinite()
    use_seen = use_seen[:, None]
    return torch.where(use_seen, room, bg), torch.where(use_seen, observed, target)


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
    history: list[dict] = field(default_factory=list)   # {"step", "seconds", "loss", "psnr", "res"}

    def save(self, path: Path) -> None:
        st = {"field": self.field.state(), "step": self.step, "seconds": self.seconds,
              "stage": self.stage, "history": self.history}
        tmp = Path(path).with_name(Path(path).name + f".tmp{os.getpid()}")
        torch.save(st, tmp)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: Path, device: torch.device) -> "TrainState":
        try:
            st = torch.load(path, map_location="cpu", weights_only=False)
        except (OSError, RuntimeError, EOFError) as e:
            raise DbbError(f"cannot read checkpoint {path}: {e}") from None
        return cls(VoxelField.from_state(st["field"], device), st["step"], st["seconds"],
                   st["stage"], list(st["history"]))


RES_LIMIT = 512


def lattice_for_views(cams: list[tuple[np.ndarray, "Intrinsics"]], volume: ObjectVolume, mode: str,
                      downscale: float = 1.0, start: int = 32) -> int:
    """Finest lattice per axis for views ``cams`` ((4, 4) camera-to-world, OpenCV axes;
    intrinsics) of the sphere ``volume``: the next power of two at or above the most pixels any
    view (shrunk by ``downscale``) spans across the sphere, from ``start`` to 512. In scene mode
    the lattice covers twice the sphere (contracted space), so twice that."""
    c = np.asarray(volume.center, np.float64)
    px = 0.0
    for c2w, intr in cams:
        s = min(volume.radius / max(float(np.linalg.norm(c2w[:3, 3] - c)), 1e-9), 0.999)
        px = max(px, 2 * max(intr.fx, intr.fy) / downscale * math.tan(math.asin(s)))
    need = px * (2 if mode == "scene" else 1)
    res = start
    while res < need and res < RES_LIMIT:
        res *= 2
    return min(res, RES_LIMIT)


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
        nrows = field.index[_lattice_lin(nb.clamp(max=r - 1), r)].long()
        ok &= nrows >= 0
        a, b = pick[ok], nrows[ok]
        dens.append(field.density.gather(a) - field.density.gather(b))
        shs.append(field.sh.gather(a) - field.sh.gather(b))
    d = torch.cat(dens)
    s = torch.cat(shs)
    return (d ** 2).mean() if d.numel() else d.sum(), (s ** 2).mean() if s.numel() else s.sum()


def _cpu_rays(field: VoxelField, origins: torch.Tensor, dirs: torch.Tensor, bg: torch.Tensor,
              target: torch.Tensor | None, jitter: torch.Tensor, beta: float = 0.0,
              ray_w: torch.Tensor | None = None) -> np.ndarray:
    """Run the numba kernel (:mod:`.fields_cpu`) on world rays (B, 3); (B, 5) RGB, alpha, sq. error.
    ``ray_w`` (B,): each ray's weight in the gradient (None: 1)."""
    from .kernels import render_rays_cpu     # numba; imported late (it imports this module)

    if not field.cpu_kernel:
        raise ValueError("the CPU kernel covers object mode on the CPU only")
    o = ((origins - field.center) / field.radius).float().contiguous().numpy()
    B = o.shape[0]
    out = np.zeros((B, 5), np.float32)
    tgt = target if target is not None else bg
    w = np.ones(B, np.float32) if ray_w is None else ray_w.float().contiguous().numpy()
    render_rays_cpu(o, dirs.float().contiguous().numpy(), jitter.float().contiguous().numpy(),
                    bg.float().contiguous().numpy(), tgt.float().contiguous().numpy(), w,
                    field.index.numpy(), field.occupancy().numpy(), field.res,
                    field.density.data.numpy()[:, 0], field.sh.data.numpy(), field.density.grad.numpy()[:, 0],
                    field.sh.grad.numpy(), field.density.touched.numpy(), field.sh.touched.numpy(),
                    field.act_shift, field.step, field.cfg.sh_degree, field.sh_active, field.cfg.weight_eps,
                    1.0 / (3 * B),
                    target is not None, field.nearest, beta / B, out)
    return out


def cpu_photometric_step(field: VoxelField, origins: torch.Tensor, dirs: torch.Tensor, bg: torch.Tensor,
                         target: torch.Tensor, jitter: torch.Tensor, beta: float = 0.0,
                         ray_w: torch.Tensor | None = None) -> tuple[torch.Tensor, np.ndarray]:
    """The photometric loss of :func:`render_rays` + MSE, on CPU without autograd: renders the
    rays (B, 3) world origins / unit directions over ``bg`` (B, 3), compares with ``target``
    (B, 3) and adds the gradient of the mean squared error (each ray's term weighted by
    ``ray_w`` (B,) when given), plus ``beta`` times :func:`opacity_prior`, into the field's
    gradient buffers (as ``backward`` would). ``jitter`` (B,) in [0, 1) offsets the samples.
    Returns the unweighted MSE (0-d) and the rays as rendered (B, 4): RGB over ``bg``, alpha."""
    out = _cpu_rays(field, origins, dirs, bg, target, jitter, beta, ray_w)
    return torch.tensor(float(out[:, 4].sum()) / (3 * out.shape[0])), out[:, :4]


def cpu_tv_step(field: VoxelField, n: int, gen: torch.Generator) -> tuple[float, float]:
    """:func:`tv_loss` on CPU without autograd: adds ``tv_density`` / ``tv_sh`` times its
    gradient into the field's buffers; returns the two means."""
    from .kernels import tv_grad

    if field.n_active == 0:
        return 0.0, 0.0
    pick = torch.randint(0, field.n_active, (min(n, field.n_active),), generator=gen)
    return tv_grad(pick.numpy(), field.active.numpy(), field.index.numpy(), field.res,
                   field.density.data.numpy()[:, 0], field.sh.data.numpy(), field.density.grad.numpy()[:, 0],
                   field.sh.grad.numpy(), field.density.touched.numpy(), field.sh.touched.numpy(),
                   field.cfg.tv_density, field.cfg.tv_sh)


def new_field(cfg: FieldConfig, volume: ObjectVolume, device: torch.device) -> VoxelField:
    """A fresh, nearly empty field over the whole lattice at the first resolution."""
    return VoxelField(cfg, volume, cfg.res_start, device)


def train(state: TrainState, bank: RayBank, budget: Budget,
          on_step: Callable[[TrainState, float], None] | None = None,
          checkpoint: Path | None = None, checkpoint_every_s: float = 120.0) -> TrainState:
    """Optimize ``state.field`` on the rays of ``bank`` until ``budget`` is spent.

    Each step renders ``batch_rays`` random rays over random background colours (so alpha is
    learned as true transparency: the target is ``rgb * a + (1 - a) * bg``; for crops that keep
    their observed pixels, over the predicted room instead: :func:`ray_targets`), adds TV, and
    takes a sparse Adam step. The coarse-to-fine schedule follows the *fraction of the budget*
    spent, so a shorter budget runs the same stages faster. Checkpoints go to ``checkpoint``.
    """
    cfg = state.field.cfg
    dev = state.field.device
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed + state.step)
    torch.manual_seed(cfg.seed + state.step)
    ress = stage_resolutions(cfg)
    bounds = list(cfg.upsample_at[: len(ress) - 1])
    t_start = time.perf_counter() - state.seconds
    last_ckpt = time.perf_counter()
    ema = None
    robust = cfg.robust_from is not None and cfg.robust_from < 1.0

    def carve(f: VoxelField) -> VoxelField:
        if not cfg.carve_share or bank.views is None or cfg.mode != "object":
            return f
        return f.carved(bank.views, cfg.carve_share, cfg.carve_min_views, cfg.carve_alpha)

    while True:
        seconds = time.perf_counter() - t_start
        frac = budget.fraction(state.step, seconds)
        if frac >= 1.0:
            break
        # Coarse to fine: prune, then move to the next lattice when its budget share starts.
        if state.stage < len(bounds) and frac >= bounds[state.stage]:
            f = state.field.pruned(cfg.prune_alpha)
            nxt = ress[state.stage + 1]
            if f.n_active * (nxt / f.res) ** 3 <= cfg.max_points:
                f = f.upsampled(nxt)
            state.field = carve(f)
            state.stage += 1
        elif state.step == 0:
            state.field = carve(state.field)
        fld = state.field
        if state.stage == len(bounds) and frac >= cfg.nearest_from:
            fld.nearest = True
        fld.sh_active = cfg.sh_degree if frac >= cfg.sh_full_from else min(cfg.sh_degree, 1)
        lr_scale = cfg.lr_final_ratio ** frac
        fast = fld.cpu_kernel
        if fast:
            # Runs of neighbouring pixels: their rays read the same lattice rows back to back
            # (cache hits in the CPU kernel); the runs themselves are drawn at random.
            run = min(RAY_RUN, bank.n)
            starts = torch.randint(0, bank.n - run + 1, (max(1, cfg.batch_rays // run),), generator=gen)
            pick = (starts[:, None] + torch.arange(run)).reshape(-1)
        else:
            pick = torch.randint(0, bank.n, (cfg.batch_rays,), generator=gen)
        o = bank.origins[pick].to(dev)
        d = bank.dirs[pick].to(dev)
        c = bank.rgba[pick].to(dev)
        bg = torch.rand(pick.numel(), 3, generator=gen).to(dev)   # runs may round the batch down
        seen, room = (None, None) if bank.observed is None else (bank.observed[pick].to(dev), bank.room[pick].to(dev))
        bg, target = ray_targets(c, bg, seen, room, cfg, gen)
        ray_w = None
        if robust and frac >= cfg.robust_from and bank.error is not None:
            ray_w = robust_weights(bank.error[pick], cfg.robust_scale).to(dev)
        if fast:
            # Closed-form forward and backward in numba: gradients land in the tables' buffers.
            mse, seen_rays = cpu_photometric_step(fld, o, d, bg, target, torch.rand(o.shape[0], generator=gen),
                                                  cfg.beta_alpha, ray_w)
            tvd, tvs = cpu_tv_step(fld, cfg.tv_points, gen) if cfg.tv_density > 0 or cfg.tv_sh > 0 else (0, 0)
            loss = mse + cfg.tv_density * tvd + cfg.tv_sh * tvs
            seen_rays = torch.from_numpy(seen_rays)
        else:
            out = render_rays(fld, o, d, bg, jitter=True)
            se = ((out.rgb - target) ** 2).mean(-1)
            mse = se.mean()
            loss = mse if ray_w is None else (se * ray_w).mean()
            loss = loss + cfg.beta_alpha * opacity_prior(out.alpha) if cfg.beta_alpha > 0 else loss
            seen_rays = torch.cat([out.rgb, out.alpha[:, None]], -1).detach().cpu()
            if cfg.tv_density > 0 or cfg.tv_sh > 0:
                tvd, tvs = tv_loss(fld, cfg.tv_points, gen)
                loss = loss + cfg.tv_density * tvd + cfg.tv_sh * tvs
            loss.backward()
        if robust:
            bank.record_errors(pick, seen_rays[:, :3], seen_rays[:, 3], bg.cpu())
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
        if checkpoint is not None and time.perf_counter() - last_ckpt > checkpoint_every_s:
            state.save(checkpoint)
            last_ckpt = time.perf_counter()
    # Leave the field pruned: what gets baked and saved holds no empty lattice points.
    state.field = state.field.pruned(cfg.prune_alpha)
    if checkpoint is not None:
        state.save(checkpoint)
    return state


