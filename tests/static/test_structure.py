"""Structure changes: pruning keeps what is seen and its neighbours, carving drops what the views
see through, upsampling keeps the interpolated field."""

from __future__ import annotations

import numpy as np
import torch
from conftest import synthetic_object_frames

from dbb_capture.datasets.records import ObjectVolume
from dbb_capture.static.field import FieldConfig, VoxelField
from dbb_capture.static.rays import build_ray_bank, carve_mask
from dbb_capture.static.structure import carved, pruned, upsampled

from .synthetic import TINY


def _blob(res: int = 16) -> VoxelField:
    """A dense field whose points within 0.3 of the centre are opaque, the rest empty."""
    cfg = FieldConfig(res_start=res, res_max=2 * res, sh_degree=1)
    f = VoxelField(cfg, ObjectVolume((0.0, 0.0, 0.0), 1.0), res, torch.device("cpu"))
    x = f.lattice_points(f.active)
    f.density.data[:-1, 0] = torch.where(x.norm(dim=-1) < 0.3, 30.0, -30.0)
    f.sh.data[:-1] = torch.randn(f.n_active, 12, generator=torch.Generator().manual_seed(0))
    return f


def test_pruning_keeps_the_opaque_points_and_their_neighbours():
    f = _blob()
    p = pruned(f, 1e-3)
    seen = f.point_alpha() >= 1e-3
    assert 0 < p.n_active < f.n_active
    assert set(f.active[seen].tolist()) <= set(p.active.tolist())
    ijk = lambda lin: torch.stack([lin // 256, (lin // 16) % 16, lin % 16], -1)
    kept, core = ijk(p.active), ijk(f.active[seen])
    # Every kept point is within one cell (26-neighbourhood) of an opaque one.
    assert ((kept[:, None] - core[None]).abs().amax(-1) <= 1).any(1).all()
    rows = f.index[p.active].long()
    assert torch.equal(p.density.data[:-1], f.density.data[rows]) and torch.equal(p.sh.data[:-1], f.sh.data[rows])
    empty = VoxelField(f.cfg, f.volume, 16, torch.device("cpu"))
    assert pruned(empty, 1e-3) is empty                         # nothing learned yet: nothing to prune


def test_upsampling_keeps_the_field_between_lattice_points():
    f = pruned(_blob(), 1e-3)
    up = upsampled(f, 32)
    assert up.res == 32 and up.n_active > f.n_active
    x = up.lattice_points(up.active)
    raw, coef = f.raw_at(x)
    assert torch.allclose(up.density.data[:-1, 0], raw) and torch.allclose(up.sh.data[:-1], coef)


def test_carving_a_field_drops_exactly_the_carved_points(tmp_path):
    frames, vol = synthetic_object_frames(tmp_path, n=24, size=32)
    bank = build_ray_bank([f for f in frames if f.split == "train"], 1, vol)
    res = 32
    field = VoxelField(TINY, vol, res, torch.device("cpu"))
    pts = field.lattice_points(field.active).numpy().astype(np.float64) * vol.radius + np.asarray(vol.center)
    cut = carve_mask(bank.views, pts, field.cell * vol.radius, 0.2)
    assert 0 < cut.sum() < len(cut)
    c = carved(field, bank.views, 0.2)
    assert c.n_active == int((~cut).sum())
    assert torch.equal(c.active, field.active[torch.from_numpy(~cut)])
    assert carved(field, bank.views, 0.2, min_views=len(bank.views.alphas) + 1) is field
