"""Structure changes of a voxel field: fewer active points (prune, carve), a finer lattice (upsample).

Each returns a new :class:`~.field.VoxelField` (fresh optimizer state) and leaves its input alone.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .field import VoxelField
from .rays import Silhouettes, carve_mask


@torch.no_grad()
def pruned(field: VoxelField, alpha_min: float) -> VoxelField:
    """``field`` without the points whose one-cell opacity is below ``alpha_min``.

    Kept: points above the threshold and their 26 neighbours (trilinear interpolation
    near a surface reads them).
    """
    keep = field.point_alpha() >= alpha_min
    if not bool(keep.any()):
        return field    # nothing learned yet: pruning would leave no field to train
    res = field.res
    mask = torch.zeros(res ** 3, device=field.device)
    mask[field.active[keep]] = 1
    mask = F.max_pool3d(mask.view(1, 1, *(res,) * 3), 3, 1, 1).view(-1) > 0
    rows = field.index[mask.nonzero()[:, 0]].long()
    rows = rows[rows >= 0]
    return VoxelField(field.cfg, field.volume, res, field.device, field.active[rows],
                      field.density.data[rows], field.sh.data[rows], field.nearest)


@torch.no_grad()
def carved(field: VoxelField, views: Silhouettes, share: float, min_views: int = 3,
           empty_alpha: float = 0.1) -> VoxelField:
    """``field`` without the active points the views carve away (:func:`~.rays.carve_mask`)."""
    pts = (field.lattice_points(field.active).cpu().numpy().astype(np.float64) * field.radius
           + np.asarray(field.volume.center, np.float64))
    keep = torch.from_numpy(~carve_mask(views, pts, field.cell * field.radius, share, min_views, empty_alpha))
    keep = keep.to(field.device)
    if bool(keep.all()):
        return field
    return VoxelField(field.cfg, field.volume, field.res, field.device, field.active[keep],
                      field.density.data[:-1][keep], field.sh.data[:-1][keep], field.nearest)


@torch.no_grad()
def upsampled(field: VoxelField, res: int) -> VoxelField:
    """The same field on a finer lattice (``res`` points per axis), active near active points."""
    occ = torch.zeros(field.res ** 3, device=field.device)
    occ[field.active] = 1
    occ = F.max_pool3d(occ.view(1, 1, *(field.res,) * 3), 3, 1, 1)
    # Fine point -> coarse point it lies in (nearest): the dilated coarse mask picks it.
    fine = F.interpolate(occ, size=(res,) * 3, mode="nearest").view(-1) > 0
    lin = fine.nonzero()[:, 0]
    x = field.lattice_points(lin, res)
    raws, coefs = [], []
    for s in range(0, lin.numel(), 1 << 20):
        r, c = field.raw_at(x[s:s + (1 << 20)])
        raws.append(r)
        coefs.append(c)
    return VoxelField(field.cfg, field.volume, res, field.device, lin,
                      torch.cat(raws) if raws else None, torch.cat(coefs) if coefs else None)
