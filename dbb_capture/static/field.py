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
convention of svox/PlenOctrees, so baking is a straight copy (see :mod:`.bake`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F

from ..core.errors import DbbError
from ..core.row_table import RowTable
from ..datasets.records import ObjectVolume
from ..geometry.cameras import Intrinsics
from ..geometry.sh import sh_basis

RES_LIMIT = 512     # finest lattice per axis


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
    # (docs/decisions.md, ``res_max``).
    res_max: int | None = None
    max_points: int = 6_000_000     # never upsample past this many active points (memory, time)
    step_cells: float = 0.5         # sample spacing along rays
    batch_rays: int = 4096
    lr_density: float = 10.0        # density lives per normalized unit: ~300 for one opaque 256^3 cell
    lr_sh: float = 0.3
    lr_final_ratio: float = 0.1     # learning rates decay exponentially to this fraction
    tv_density: float = 1e-5        # total-variation weights (mean squared neighbour difference)
    tv_sh: float = 1e-3             # Plenoxels weights SH smoothness 100x density (docs/decisions.md, ``tv_sh``)
    tv_points: int = 8192           # lattice points sampled per step for TV
    prune_alpha: float = 1e-3       # drop points whose one-cell opacity stays below this
    weight_eps: float = 1e-4        # colour is evaluated only where a sample's weight exceeds this
    init_alpha: float = 1e-4        # opacity of one step at the start (nearly empty)
    # Fraction of the budget at which each new stage starts; stages past the last one listed are
    # not reached.
    upsample_at: tuple[float, ...] = (0.15, 0.3, 0.45, 0.6)
    # From this fraction of the budget on (final stage only), samples read their nearest lattice
    # point instead of interpolating: piecewise constant, exactly what the baked tree renders,
    # so the last steps fine-tune the tree itself (PlenOctrees' tree fine-tuning). 1: never.
    nearest_from: float = 0.8
    # Progressive SH (as 3D Gaussian Splatting adds bands over training): until this fraction of
    # the budget the colour uses SH degree at most 1, and the higher bands join from here on.
    # Degree 1 steps faster (fewer coefficients to interpolate, scatter and update) and
    # extrapolates colour to views the training never saw better; the higher bands then fit the
    # view dependence that is left, at the schedule's low learning rates (docs/decisions.md,
    # ``sh_full_from``). 0: all bands from the start.
    sh_full_from: float = 0.8
    # Datasets that keep each crop's observed pixels and the room predicted behind them
    # (preprocess crops): render over the predicted room and compare with what the camera saw,
    # so alpha comes from multi-view consistency instead of from the matte. The matte (random
    # background, as for other datasets) stays a prior on a share ``matte_prior`` of the rays
    # where the observed colour is within ``decisive_diff`` (max over RGB, [0, 1]) of the room's,
    # fading out linearly up to that difference. False: the matte alone; None: by the dataset's
    # kind (:meth:`for_dataset`: on for preprocess crops). A table-coloured part that a view's
    # matte misses renders like the room there and costs nothing in that view, while the views
    # that see it against another colour keep it (docs/decisions.md, ``observed_loss``).
    observed_loss: bool | None = None
    matte_prior: float = 0.5
    decisive_diff: float = 0.6
    # ... and where the matte sees any of the object (alpha at least this) it decides: over one
    # room per ray, colour and alpha trade off (a * c + (1 - a) * B fits many pairs), which left
    # the object see-through from new angles (at 0.99), and at the outline the observed colour
    # carries the footage's blur, which widened the outline. So the observed pixels speak where
    # the matte says "room": against its misses. Above 1: never.
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

    def for_dataset(self, kind: str) -> FieldConfig:
        """Settings left to the dataset (None) decided by its ``kind``: carving (0.1), robust
        training (from half the budget) and the observed loss for preprocess crops ("crops"),
        whose mattes carry errors that the views outvote (docs/decisions.md, ``carve_share``,
        ``robust_from``); off where the alpha is the truth or absent (Blender, nerfstudio,
        instant-ngp)."""
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


def lattice_for_views(cams: list[tuple[np.ndarray, Intrinsics]], volume: ObjectVolume, mode: str,
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


def lattice_lin(i: torch.Tensor, res: int) -> torch.Tensor:
    """Linear index of integer lattice coordinates (..., 3) of a ``res``^3 lattice."""
    return (i[..., 0] * res + i[..., 1]) * res + i[..., 2]


_CORNERS = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])


class VoxelField:
    """The field: ``index`` (res^3 lattice -> row or -1), ``density`` (N+1, 1), ``sh`` (N+1, 3*B).

    Row N is a sentinel for inactive lattice points: very negative raw density, zero colour.
    New fields with other active points or on another lattice come from :mod:`.structure`.
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
        """Whether training and rendering run the numba kernel (:mod:`.kernels`): object mode
        on the CPU; CUDA and scene mode take the PyTorch path."""
        return self.device.type == "cpu" and self.cfg.mode == "object"

    # ---- queries --------------------------------------------------------------------------
    def corners(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows (M, 8) and trilinear weights (M, 8) for lattice-space points (M, 3)."""
        u = self.to_lattice(x).clamp(0, self.res - 1)
        if self.nearest:
            # The nearest point alone: its row 8 times at weight 1/8 keeps the (M, 8) shapes.
            rows = self.index[lattice_lin(u.round().long(), self.res)].long()
            rows = torch.where(rows < 0, torch.full_like(rows, self.n_active), rows)
            return rows[:, None].expand(-1, 8), torch.full((x.shape[0], 8), 0.125, device=x.device)
        i0 = u.floor().clamp(max=self.res - 2)
        f = u - i0
        i0 = i0.long()
        c = _CORNERS.to(x.device)
        lin = lattice_lin(i0[:, None, :] + c[None], self.res)
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
        rows, w = self.corners(x)
        sig = self.sigma_from(rows, w)
        return sig, (self.rgb_from(rows, w, d) if d is not None else None)

    def raw_at(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Interpolated raw density (M,) and SH coefficients (M, 3*B) at lattice-space points."""
        rows, w = self.corners(x)
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

    @torch.no_grad()
    def point_alpha(self) -> torch.Tensor:
        """Opacity of one cell at each active point (N,), from its own raw density."""
        sig = F.softplus(self.density.data[:-1, 0] + self.act_shift)
        return 1 - torch.exp(-sig * self.cell)

    def reset_sentinel(self) -> None:
        self.density.data[-1] = self.SENTINEL_RAW
        self.sh.data[-1] = 0

    # ---- persistence ----------------------------------------------------------------------
    def state(self) -> dict:
        return {"config": asdict(self.cfg), "volume": self.volume.to_json(), "res": self.res,
                "nearest": self.nearest, "active": self.active.cpu(), "density": self.density.data[:-1].cpu(),
                "sh": self.sh.data[:-1].cpu()}

    @classmethod
    def from_state(cls, st: dict, device: torch.device) -> VoxelField:
        """The field :meth:`state` saved (a checkpoint of this version: :class:`.train.TrainState`)."""
        v = st["volume"]
        vol = ObjectVolume(tuple(v["center"]), float(v["radius"]), bool(v["estimated"]))
        return cls(FieldConfig(**st["config"]), vol, st["res"], device, st["active"], st["density"], st["sh"],
                   bool(st["nearest"]))
