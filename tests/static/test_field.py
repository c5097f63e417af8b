"""The voxel field: its settings, the lattice size by the views, contraction, queries, state."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from dbb_capture.core.errors import DbbError
from dbb_capture.datasets.records import ObjectVolume
from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.transforms import look_at
from dbb_capture.static.field import (
    FieldConfig,
    VoxelField,
    contract,
    lattice_for_views,
)


def test_contraction_is_identity_inside_and_bounded():
    x = torch.tensor([[0.3, -0.2, 0.5], [3.0, 0.0, 0.0], [0.0, -1e6, 0.0]])
    y = contract(x)
    assert torch.allclose(y[0], x[0])
    assert y[1, 0].item() == pytest.approx(2 - 1 / 3)
    assert y[2].norm().item() == pytest.approx(2.0, abs=1e-5)


def test_matte_treatments_follow_the_dataset_kind_unless_set():
    """Preprocess crops get carving, robust training and the observed loss; datasets whose alpha
    is the truth do not; a value given explicitly (even "off") is kept."""
    crops = FieldConfig().for_dataset("crops")
    assert (crops.carve_share, crops.robust_from, crops.observed_loss) == (0.1, 0.5, True)
    for kind in ("blender", "transforms"):
        other = FieldConfig().for_dataset(kind)
        assert (other.carve_share, other.robust_from, other.observed_loss) == (0.0, 1.0, False)
    kept = FieldConfig(carve_share=0.0, robust_from=1.0, observed_loss=False).for_dataset("crops")
    assert (kept.carve_share, kept.robust_from, kept.observed_loss) == (0.0, 1.0, False)


def test_settings_are_checked():
    for bad in ({"mode": "sky"}, {"sh_degree": 4}, {"res_max": None}, {"res_start": 4}, {"res_max": 16}):
        with pytest.raises(DbbError):
            (replace(FieldConfig(res_max=32), **bad)).validate()
    FieldConfig(res_max=32).validate()


def test_lattice_follows_the_pixels_across_the_object():
    """One cell per pixel: a sphere of radius 1 seen from 4 units by a 100 px focal length spans
    2 * 100 * tan(asin(1/4)) = 51.6 px -> 64^3; nearer or sharper views raise it, to 512 at most;
    scene mode (lattice over twice the sphere) doubles it; a downscale shrinks it."""
    vol = ObjectVolume((0.0, 0.0, 0.0), 1.0)
    cam = lambda dist: look_at(np.array([0.0, -dist, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    intr = lambda f: Intrinsics(128, 128, f, f, 64.0, 64.0)
    assert lattice_for_views([(cam(4.0), intr(100.0))], vol, "object") == 64
    assert lattice_for_views([(cam(4.0), intr(100.0)), (cam(2.0), intr(100.0))], vol, "object") == 128
    assert lattice_for_views([(cam(4.0), intr(100.0))], vol, "scene") == 128
    assert lattice_for_views([(cam(4.0), intr(100.0))], vol, "object", downscale=2.0) == 32
    assert lattice_for_views([(cam(1.5), intr(2000.0))], vol, "object") == 512
    assert lattice_for_views([(cam(40.0), intr(100.0))], vol, "object", start=16) == 16


def _random_field(res: int = 8, seed: int = 0) -> VoxelField:
    g = torch.Generator().manual_seed(seed)
    cfg = FieldConfig(res_start=res, res_max=res, sh_degree=1)
    active = torch.randperm(res ** 3, generator=g)[: res ** 3 // 2].sort().values
    return VoxelField(cfg, ObjectVolume((0.5, 0.0, -0.5), 2.0), res, torch.device("cpu"), active,
                      torch.randn(active.numel(), 1, generator=g), torch.randn(active.numel(), 12, generator=g))


def test_queries_interpolate_active_points_and_read_the_sentinel_elsewhere():
    """At a lattice point the trilinear query reads that point's row alone; inactive points
    read the sentinel (very negative raw density, no colour); the nearest lookup reads the
    nearest point's row; world points normalize to the lattice space."""
    f = _random_field()
    lin = torch.arange(f.res ** 3)
    x = f.lattice_points(lin)
    raw, coef = f.raw_at(x)
    rows = f.index.long()
    want = torch.where(rows >= 0, f.density.data[rows.clamp_min(0), 0], torch.tensor(f.SENTINEL_RAW))
    assert torch.allclose(raw, want, atol=1e-4)
    assert torch.allclose(coef[rows < 0], torch.zeros(1), atol=1e-4)
    f.nearest = True
    near, _ = f.raw_at(x + 0.3 * f.cell)                    # still nearest to the same point
    assert torch.allclose(near, want, atol=1e-4)
    p = torch.tensor([[0.5, 0.0, -0.5], [2.5, 0.0, -0.5]])
    assert torch.allclose(f.normalize(p), torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    sig, rgb = f.query(x[:5], torch.nn.functional.normalize(torch.ones(5, 3), dim=-1))
    assert sig.shape == (5,) and (sig >= 0).all() and rgb.shape == (5, 3) and ((rgb >= 0) & (rgb <= 1)).all()


def test_state_round_trip():
    f = _random_field(seed=1)
    f.nearest = True
    g = VoxelField.from_state(f.state(), torch.device("cpu"))
    assert g.cfg == f.cfg and g.volume == f.volume and g.res == f.res and g.nearest
    assert torch.equal(g.active, f.active) and torch.equal(g.index, f.index)
    assert torch.equal(g.density.data, f.density.data) and torch.equal(g.sh.data, f.sh.data)
