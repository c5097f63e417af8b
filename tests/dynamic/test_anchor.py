"""The view anchor's atlas: its grid, looking views up (bilinear, azimuth wrapping round, elevation
held at the ends) and its renders of a PlenOctree through the crop cameras."""

from __future__ import annotations

import numpy as np
import torch

from dbb_capture.crops.camera import facing_camera
from dbb_capture.dynamic.anchor import AtlasGrid, ViewAtlas, atlas_grid, render_atlas
from dbb_capture.geometry.viewpoint import Viewpoint, eye_at
from dbb_capture.octree.tree import PlenOctree, build_tree


def _atlas() -> ViewAtlas:
    # Entry (e, a) is filled with the value 10 * e + a: a lookup's value says where it read.
    grid = AtlasGrid(30.0, 12, -30.0, 3, 0.5)
    vals = (10 * torch.arange(3)[:, None] + torch.arange(12)[None]).to(torch.uint8)
    return ViewAtlas(vals[:, :, None, None, None].expand(3, 12, 4, 2, 2).contiguous(), grid)


def test_lookup_is_bilinear_in_the_angles_wraps_in_azimuth_and_holds_elevation():
    atlas = _atlas()
    views = torch.tensor([[0.0, -30.0, 0.5],      # node (0, 0)
                          [60.0, 30.0, 0.5],      # node (2, 2)
                          [15.0, -30.0, 0.5],     # halfway between azimuths 0 and 1
                          [345.0, 0.0, 0.5],      # between azimuth 11 and 0 (wrapped), row 1
                          [-15.0, 0.0, 0.5],      # the same view, a negative azimuth
                          [30.0, 85.0, 0.5],      # above the grid: its top row
                          [30.0, 15.0, 0.5]])     # halfway between rows 1 and 2
    got = atlas(views)[:, 0, 0, 0] * 255
    want = torch.tensor([0.0, 22.0, 0.5, 15.5, 15.5, 21.0, 16.0])
    assert got.shape == (7,) and torch.allclose(got, want, atol=1e-4)
    rebuilt = ViewAtlas.from_state(atlas.state())
    assert torch.equal(rebuilt(views), atlas(views))


def test_grid_spans_the_footage_and_coarsens_to_stay_small():
    views = np.array([[0.0, 10.0, 0.6], [90.0, 40.0, 0.8], [200.0, 25.0, 0.7]])
    g = atlas_grid(views, 64)
    assert g.step_deg == 5.0 and g.n_az == 72 and g.el0_deg == 0.0
    assert g.el0_deg + (g.n_el - 1) * g.step_deg == 50.0 and g.distance_m == 0.7
    big = atlas_grid(views, 256, max_bytes=8 * 2 ** 20)
    assert big.step_deg > 5.0 and big.n_az * big.n_el * 4 * 256 * 256 <= 8 * 2 ** 20
    steep = atlas_grid(np.array([[0.0, 80.0, 0.5], [0.0, -80.0, 0.5]]), 32)
    assert steep.el0_deg == -85.0 and steep.el0_deg + (steep.n_el - 1) * steep.step_deg <= 85.0
    # Footage up to 74 deg (a capture from above): the top row at 84, none past the limit, and
    # every row's crop camera exists.
    high = atlas_grid(np.array([[0.0, 18.9, 0.6], [40.0, 74.3, 0.6]]), 64)
    rows = high.views()[:, 0, 1]
    assert abs(rows[-1] - 84.3) < 1e-6 and rows[0] <= 8.9 and rows.max() <= 85.0
    for el in rows:
        facing_camera(eye_at(Viewpoint(0.0, float(el), 0.6), np.zeros(3), np.array([0.0, 0.0, -1.0])),
                      np.zeros(3), 0.1, np.array([0.0, 0.0, -1.0]), 64, 0.9)


def _sphere_tree(radius: float, depth: int = 4) -> PlenOctree:
    """A PlenOctree of an opaque grey ball of ``radius`` m at the origin (SH degree 0) in a 1 m cube."""
    n = 1 << (depth + 1)
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    inside = np.linalg.norm((idx + 0.5) / n - 0.5, axis=1) < radius
    cells = idx[inside]
    vals = np.concatenate([np.zeros((len(cells), 3)), np.full((len(cells), 1), 500.0)], 1).astype(np.float32)
    data, child, pd = build_tree(cells, vals, depth)
    return PlenOctree(data.astype(np.float16), child, pd, np.ones(3, np.float32), np.full(3, 0.5, np.float32),
                      depth, "SH1")


def test_renders_through_the_crop_cameras_fill_the_frame_as_the_crops_do():
    r = 0.3
    tree = _sphere_tree(r)
    grid = AtlasGrid(45.0, 8, 0.0, 2, 2.0)
    images = render_atlas(tree, grid, np.zeros(3), r, np.array([0.0, 0.0, 1.0]), 32, 0.8, quiet=True)
    assert images.shape == (2, 8, 4, 32, 32) and images.dtype == np.uint8
    alpha = images[:, :, 3].astype(np.float64) / 255
    # The ball's silhouette is the object sphere's: a disc of diameter fill x size, in every view.
    disc = alpha.sum((-1, -2))
    assert np.allclose(disc, np.pi * (0.8 * 32 / 2) ** 2, rtol=0.15)
    assert np.ptp(disc) / disc.mean() < 0.05
